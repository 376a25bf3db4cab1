"""The documentation tells the truth: every command block of README.md and docs/usage.md runs as written.

Each document's ```sh and ```python blocks run in document order, in one temporary directory per
document, so later blocks use what earlier ones made (data, runs). ``cylsfm ...`` commands run in this
process through :func:`cylsfm.cli.main` (the console script's entry point) and must exit with 0; Python
blocks are executed. A command that stops working, or a new kind of command in a block that this test
does not know, fails the test.

To stay fast the documented sizes are scaled down by a fixed, stated substitution:

* :data:`SUBSTITUTIONS`: text replaced in every command and Python block, in order (16 rides of 150
  frames at 256x64 -> 3 rides of 8 frames at 128x32, an hour's budget -> 1 step, 20 minutes of demo ->
  the demo's shortest training, 512x128 tensors of the library example -> 256x64);
* :data:`ADDED`: arguments given to a subcommand when the documented command does not set them (a tiny
  training size and budget, no data-loader processes, a tiny demo);
* :data:`SKIPPED`: commands that are not run, each with its reason.

The user's own files that the documents assume (``pano.jpg``, ``video.mp4``, ``frames/``, ``ride.mp4``,
``ride_equirect.mp4``, ``my360video.mp4``, the ``headcam`` dataset and ``helmet.png``, stand-ins of the
paper's Headcam videos and SYNTHIA-Seqs, a rig of pinhole views) are made by :func:`_user_files`.
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image

from cylsfm.cli import main
from cylsfm.data.synth import generate_dataset
from cylsfm.geometry import PinholeCamera
from synthia_standin import write_synthia_standin

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = ["README.md", "docs/usage.md"]

#: ``(documented text, text run)``, applied in order to every command and Python block.
SUBSTITUTIONS = [
    ("--sequences 16", "--sequences 3"),
    ("--frames 150", "--frames 8"),
    ("--width 256 --height 64", "--width 128 --height 32"),
    ("--split 12,1,3", "--split 1,1,1"),
    ("--size 256x64", "--size 128x32"),
    ("--resume --minutes 60", "--resume --max-steps 2"),
    ("--minutes 60", "--max-steps 1"),
    ("--minutes 20", "--minutes 0.01"),
    ("--minutes 120", "--max-steps 1"),
    ("--size 512x128", "--size 128x32"),
    ("512, 128)", "256, 64)"),
    ("128, 512)", "64, 256)"),
]

#: Per subcommand: ``flag -> arguments`` added when the command does not give the flag (a resumed run
#: keeps its own size and batch size: they are not added to it).
ADDED = {
    "train": {
        "--size": ["--size", "128x32"],
        "--batch-size": ["--batch-size", "2"],
        "--max-steps": ["--max-steps", "1"],
        "--workers": ["--workers", "0"],
    },
    "demo": {
        "--size": ["--size", "128x32"],
        "--sequences": ["--sequences", "3"],
        "--test-sequences": ["--test-sequences", "1"],
        "--frames": ["--frames", "8"],
    },
}

#: Command prefixes that are not run, and why.
SKIPPED = {
    "make demo": "sets up a virtual environment and runs the 20-minute demo (`cylsfm demo` runs below)",
    "python3 -m venv": "creates the virtual environment of the set-up (what the Makefile does first)",
    ".venv/bin/pip install": "downloads and installs packages (torch's CPU build, the extras) into the virtual "
    "environment",
    "make test": "runs this very test suite",
    "make format": "rewrites the checkout's sources",
    "make bench": "a benchmark of several minutes",
    "experiments/run.sh": "generates the full benchmark and trains for the given budget (minutes)",
    "cylsfm odometry ride.mp4 --checkpoint runs/improved --out ride_metres/": "metres need a depth that shows "
    "the ground, which a model trained for one step has not; tested in tests/odometry/test_odometry.py",
    "cylsfm predict --checkpoint runs/improved ride.mp4 --out depth_m/ --camera-height 1.6": "metres need a "
    "depth that shows the ground, which a model trained for one step has not; tested in tests/test_predict.py",
    "torchrun": "starts one process per device; data-parallel training is tested in tests/train/test_train_loop.py",
    ".venv/bin/python": "installs a CUDA build of torch into the virtual environment, or asks it for CUDA",
    "cylsfm train --data data/synth --out runs/gpu": "needs a CUDA device",
    "ns-train": "nerfstudio's trainer, installed on its own; what it reads is tested in tests/export/test_colmap.py",
}

FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)


def blocks(document: str) -> list[tuple[str, str]]:
    """The ``(language, text)`` of every fenced ``sh`` and ``python`` block of a document, in order."""
    text = (ROOT / document).read_text()
    return [(lang, body) for lang, body in FENCE.findall(text) if lang in ("sh", "python")]


def substitute(text: str) -> str:
    for old, new in SUBSTITUTIONS:
        text = text.replace(old, new)
    return text


def commands(block: str) -> list[list[str]]:
    """The commands of a shell block: one a line (``\\`` continues a line), comments dropped."""
    joined = block.replace("\\\n", " ")
    return [argv for line in joined.splitlines() if (argv := shlex.split(line, comments=True))]


def with_added(argv: list[str]) -> list[str]:
    """``cylsfm SUB ...`` with the arguments of :data:`ADDED` it does not give."""
    added = []
    for flag, args in ADDED.get(argv[1], {}).items():
        if flag in argv or (flag in ("--size", "--batch-size") and "--resume" in argv):
            continue
        added += args
    return argv + added


def skip_reason(argv: list[str]) -> str | None:
    line = " ".join(argv)
    return next((why for prefix, why in SKIPPED.items() if line.startswith(prefix)), None)


def _png(path: Path, width: int, height: int, seed: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 256, (height, width, 3), dtype=np.uint8)).save(path)


def _mp4(path: Path, width: int, height: int, frames: int = 3, rate: int = 10) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=rate)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        for _ in range(frames):
            arr = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
            for packet in stream.encode(av.VideoFrame.from_ndarray(arr, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)


def _user_files(root: Path) -> None:
    """The files a user brings: panoramas of the model's aspect ratio (4:1), 2:1 equirectangular footage,
    a head-camera dataset (tiny synthetic rides with their split) and its helmet mask."""
    _png(root / "pano.jpg", 256, 64, 0)
    for i in range(2):
        _png(root / "frames" / f"{i:06d}.png", 256, 64, i + 1)
    _mp4(root / "video.mp4", 256, 64)
    _mp4(root / "ride.mp4", 256, 64)
    _mp4(root / "ride_equirect.mp4", 128, 64, frames=8)
    _mp4(root / "my360video.mp4", 128, 64, frames=8)
    generate_dataset(root / "headcam", sequences=2, frames=8, width=128, height=32, seed=3, workers=1,
                     progress=False, splits=True, split_fractions=(0.5, 0.0, 0.5))  # fmt: skip
    mask = np.full((32, 128), 255, dtype=np.uint8)
    mask[24:] = 0  # the helmet at the bottom
    Image.fromarray(mask).save(root / "helmet.png")
    _paper_datasets(root)


def _paper_datasets(root: Path) -> None:
    """Stand-ins of the Headcam videos (30 fps, two days) and its lists, SYNTHIA-Seqs, and a rig of views."""
    for day in ("2018-10-02", "2018-10-03"):
        _mp4(root / "Headcam" / f"{day}.mkv", 128, 64, frames=13, rate=30)
    (root / "excluded.txt").write_text("2018-10-02 1\n2018-10-03 0\n")
    helmet = np.full((64, 128), 255, dtype=np.uint8)
    helmet[52:] = 0
    Image.fromarray(helmet).save(root / "helmet_equirect.png")
    write_synthia_standin(root / "SYNTHIA", frames=(0, 1, 2), sides=("left", "right"))
    views = []
    for name, yaw in (("front", 0), ("right", 90), ("back", 180), ("left", 270)):
        for i in range(2):
            _png(root / "rig" / name / f"{i:04d}.png", 64, 48, 10 * yaw + i)
        views.append({"name": name, "images": name, "camera": "pinhole.json", "yaw": yaw})
    PinholeCamera.from_fov(64, 48, 100.0).to_json(root / "rig" / "pinhole.json")
    (root / "rig" / "rig.json").write_text(json.dumps({"views": views}))


def run_document(document: str, where: Path, capsys) -> tuple[int, list[tuple[str, str]]]:
    """Run every block of ``document`` in ``where``; returns the number of commands and blocks run and
    the commands skipped, each with the reason :data:`SKIPPED` gives."""
    ran, skipped = 0, []
    for lang, body in blocks(document):
        body = substitute(body)
        if lang == "python":
            exec(compile(body, f"{document} (python block)", "exec"), {"__name__": "__doc_block__"})
            ran += 1
            continue
        for argv in commands(body):
            if (why := skip_reason(argv)) is not None:
                skipped.append((" ".join(argv), why))
                continue
            assert argv[0] == "cylsfm", (
                f"{document}: unknown command {argv[0]!r}; run it or add it to SKIPPED"
            )
            argv = with_added(argv)
            try:
                status = main(argv[1:])
            except SystemExit as exc:  # argparse: an unknown flag or a bad value
                status = exc.code
            err = capsys.readouterr().err
            assert status == 0, f"{document}: `{' '.join(argv)}` exited with {status}: {err.strip()[-2000:]}"
            ran += 1
    return ran, skipped


@pytest.mark.parametrize("document", DOCUMENTS)
def test_documented_commands_run(document, tmp_path, monkeypatch, capsys):
    _user_files(tmp_path)
    monkeypatch.chdir(tmp_path)
    ran, skipped = run_document(document, tmp_path, capsys)
    assert ran >= 5, f"{document}: only {ran} commands ran"
    unexplained = [command for command, why in skipped if not why.strip()]
    assert not unexplained, f"{document}: commands skipped without a reason: {unexplained}"
    if document == "README.md":  # the video-to-splat recipe, up to the model the splat trainer reads
        _check_splat_model(tmp_path / "my_splat")


def _check_splat_model(out: Path) -> None:
    """What a splat trainer reads: a COLMAP model (read back by pycolmap) whose images are the files of
    ``images/`` and of nerfstudio's ``transforms.json``, and points for the splats' start."""
    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    frames = json.loads((out / "transforms.json").read_text())["frames"]
    names = {image.name for image in rec.images.values()}
    assert len(names) == len(frames) > 0 and rec.num_points3D() > 0
    assert names == {f["file_path"].removeprefix("images/") for f in frames}
    assert all((out / "images" / name).is_file() for name in names)


def _shown_commands() -> list[str]:
    """Every shell command of the documents, as the runner reads it (substituted, one a line)."""
    return [
        " ".join(argv)
        for document in DOCUMENTS
        for lang, body in blocks(document)
        if lang == "sh"
        for argv in commands(substitute(body))
    ]


def test_every_skip_names_a_documented_command():
    """:data:`SKIPPED` names only commands that the documents show, each with its reason: an entry left
    behind when its command was removed or reworded would hide nothing today, and would later hide a new
    command that starts the same way without anyone having decided that it need not run."""
    shown = _shown_commands()
    for prefix, why in SKIPPED.items():
        assert why.strip(), f"SKIPPED[{prefix!r}] gives no reason"
        assert any(line.startswith(prefix) for line in shown), (
            f"SKIPPED names {prefix!r}, which no document shows"
        )


def test_substitution_and_parsing():
    """The parts of the runner on their own: line continuation, comments, the added arguments."""
    assert commands("cylsfm a \\\n  --b 1   # note\n\n# only a comment\ncylsfm c") == [
        ["cylsfm", "a", "--b", "1"],
        ["cylsfm", "c"],
    ]
    assert with_added(["cylsfm", "train", "--out", "r", "--resume", "--max-steps", "2"]) == [
        "cylsfm", "train", "--out", "r", "--resume", "--max-steps", "2", "--workers", "0",
    ]  # fmt: skip
    assert substitute("--minutes 60 --resume --minutes 60") == "--max-steps 1 --resume --max-steps 2"
    assert skip_reason(["make", "test"]) and skip_reason(["cylsfm", "train"]) is None
