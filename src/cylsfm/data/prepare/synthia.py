"""``cylsfm prepare synthia``: SYNTHIA-Seqs' four 90-degree views per frame stitched into 360-degree
cylinders, with cylindrical depth and poses, static frames left out by the ground-truth poses.

The layout read (the published one as far as it is known; anything else fails naming the file)::

    ROOT/SYNTHIA-SEQS-02-SPRING/RGB/Stereo_Left/Omni_F/000000.png        (Omni_F, _R, _B, _L)
    ROOT/SYNTHIA-SEQS-02-SPRING/Depth/Stereo_Left/Omni_F/000000.png      16-bit, centimetres along z
    ROOT/SYNTHIA-SEQS-02-SPRING/CameraParams/intrinsics.txt              focal, cx, cy, baseline
    ROOT/SYNTHIA-SEQS-02-SPRING/CameraParams/Stereo_Left/Omni_F/000000.txt   16 floats, column-major 4x4

Each (sequence, season, stereo side) becomes one output sequence ``02-SPRING-left``. The views face front,
right, back and left (yaw 0, 90, 180, 270 degrees). The rig's pose is the front view's camera-to-world
matrix, turned into our axes (x right, y down, z forward) by a convention that is uncertain for this
dataset (:data:`CONVENTIONS`; ``auto``: the one under which the stitched frames and their depth best
predict each other, checked on frame pairs across the sequence).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ...errors import CylsfmError
from ...geometry import CylindricalCamera, PinholeCamera, inverse_warp
from ..io import image_size, load_image, read_text
from ..stitch import Stitcher, View, view_rotation
from .rig import RigFrame, drop_static, read_view_depth, write_rig
from .sequence import PREPARE_FILE, PreparedSequence

__all__ = ["CONVENTIONS", "SynthiaOptions", "pose_convention", "prepare_synthia"]

VIEWS = (("Omni_F", 0.0), ("Omni_R", 90.0), ("Omni_B", 180.0), ("Omni_L", 270.0))
SIDES = {"left": "Stereo_Left", "right": "Stereo_Right"}
#: The file's axes -> ours: ``S``, applied as ``S M S`` to the (inverted, for ``-inv``) matrix ``M``.
CONVENTIONS: dict[str, np.ndarray] = {
    "y-up": np.diag([1.0, -1.0, 1.0]),  # Unity-like: y up, left-handed
    "none": np.eye(3),
    "yz-flip": np.diag([1.0, -1.0, -1.0]),
    "x-flip": np.diag([-1.0, 1.0, 1.0]),
}
_FOLDER = re.compile(r"^SYNTHIA-SEQS-(\d+)-([A-Z_]+)$", re.IGNORECASE)
FPS = 5.0
DEPTH_SCALE, DEPTH_INVALID = 0.01, 65535


@dataclass(frozen=True)
class SynthiaOptions:
    """What :func:`prepare_synthia` prepares and how (defaults: the paper's 512x128 panoramas).

    Attributes:
        sequences, seasons, sides: which folders (``None``: every one found; sides ``left``/``right``).
        size, vfov_h: the panorama (default band ``|h| <= 0.5``: what all four views see).
        convention: pose axes, a key of :data:`CONVENTIONS` (``-inv`` appended: the files hold
            world-to-camera matrices), or ``auto``.
        static_motion, static_turn_deg: a frame that moved less than this since the last kept one is left
            out (0: keep all).
        depth: write cylindrical depth.
    """

    sequences: tuple[str, ...] | None = None
    seasons: tuple[str, ...] | None = None
    sides: tuple[str, ...] = ("left", "right")
    size: tuple[int, int] = (512, 128)
    vfov_h: float = 0.5
    convention: str = "auto"
    static_motion: float = 0.1
    static_turn_deg: float = 1.0
    depth: bool = True
    exclude: frozenset[str] = field(default_factory=frozenset)


def _folders(root: Path, options: SynthiaOptions) -> list[tuple[Path, str, str]]:
    if not root.is_dir():
        raise CylsfmError(f"{root}: folder not found")
    found = []
    for d in sorted(root.iterdir()):
        m = _FOLDER.match(d.name)
        if not d.is_dir() or m is None:
            continue
        seq, season = m.group(1), m.group(2).upper()
        if options.sequences is not None and seq not in {s.zfill(2) for s in options.sequences}:
            continue
        if options.seasons is not None and season not in {s.upper() for s in options.seasons}:
            continue
        found.append((d, seq, season))
    if not found:
        raise CylsfmError(
            f"{root}: no SYNTHIA-SEQS-NN-SEASON folder (of the sequences and seasons asked for) found"
        )
    return found


def read_intrinsics(path: Path) -> tuple[float, float, float]:
    """``(focal, cx, cy)`` from ``CameraParams/intrinsics.txt`` (numbers one a line; blank lines allowed)."""
    numbers = []
    for line in read_text(path, "intrinsics file").split():
        try:
            numbers.append(float(line))
        except ValueError:
            raise CylsfmError(f"{path}: expected numbers (focal, cx, cy, baseline), found {line!r}") from None
    if len(numbers) < 3 or numbers[0] <= 0:
        raise CylsfmError(f"{path}: expected the focal length, cx and cy (and the baseline), got {numbers}")
    return numbers[0], numbers[1], numbers[2]


def read_extrinsics(path: Path) -> np.ndarray:
    """The 4x4 matrix of a ``CameraParams`` frame file (16 floats, column-major)."""
    try:
        values = [float(v) for v in read_text(path, "camera file").split()]
    except ValueError:
        raise CylsfmError(f"{path}: expected 16 numbers") from None
    if len(values) != 16 or not np.isfinite(values).all():
        raise CylsfmError(
            f"{path}: expected 16 finite numbers (a column-major 4x4 matrix), got {len(values)}"
        )
    return np.array(values).reshape(4, 4).T


def pose_convention(matrix: np.ndarray, convention: str) -> np.ndarray:
    """Camera-to-world in our axes from a file's matrix under ``convention`` (see :data:`CONVENTIONS`)."""
    name, inverse = (convention[:-4], True) if convention.endswith("-inv") else (convention, False)
    if name not in CONVENTIONS:
        raise CylsfmError(f"unknown pose convention {convention!r}; one of {', '.join(_all_conventions())}")
    s = np.eye(4)
    s[:3, :3] = CONVENTIONS[name]
    m = np.linalg.inv(matrix) if inverse else matrix
    return s @ m @ s


def _all_conventions() -> list[str]:
    return [c + suffix for c in CONVENTIONS for suffix in ("", "-inv")]


def _side_frames(folder: Path, side: str) -> tuple[list[View], list[RigFrame]]:
    sub = SIDES[side]
    f, cx, cy = read_intrinsics(folder / "CameraParams" / "intrinsics.txt")
    front = folder / "RGB" / sub / VIEWS[0][0]
    if not front.is_dir():
        raise CylsfmError(f"{front}: folder not found (expected RGB/{sub}/Omni_F, _R, _B, _L)")
    names = sorted(p.stem for p in front.glob("*.png"))
    if not names:
        raise CylsfmError(f"{front}: no frames (000000.png ...)")
    w, h = image_size(front / f"{names[0]}.png")
    camera = PinholeCamera(width=w, height=h, fx=f, cx=cx, fy=f, cy=cy)
    views = [View(v, camera, view_rotation(yaw)) for v, yaw in VIEWS]
    frames = []
    for i, n in enumerate(names):
        images = [folder / "RGB" / sub / v / f"{n}.png" for v, _ in VIEWS]
        depths = [folder / "Depth" / sub / v / f"{n}.png" for v, _ in VIEWS]
        for p in [*images, *depths]:
            if not p.is_file():
                raise CylsfmError(f"{p}: missing (every frame needs all four views' image and depth)")
        pose = read_extrinsics(folder / "CameraParams" / sub / VIEWS[0][0] / f"{n}.txt")
        frames.append(RigFrame(n, images, depths, time=i / FPS, pose=pose))
    return views, frames


def _choose_convention(
    views: list[View], frames: list[RigFrame], pairs: int = 4
) -> tuple[str, dict[str, float]]:
    """The convention under which the frames' stitched depth and poses best predict the next frames.

    For ``pairs`` frame pairs (``i``, ``i + 2``) spread over the sequence, each convention's relative pose
    warps frame ``i + 2`` into frame ``i`` with frame ``i``'s depth (at 256x32); the mean photometric error
    over the pairs decides. Returns ``(convention, {convention: error})``.
    """
    camera = CylindricalCamera.full(256, 32, 0.5)
    stitcher = Stitcher(views, camera)
    idx = np.linspace(0, max(0, len(frames) - 3), num=min(pairs, max(1, len(frames) - 2))).round().astype(int)
    errors = dict.fromkeys(_all_conventions(), 0.0)
    for i in sorted(set(idx.tolist())):
        a, b = frames[i], frames[min(i + 2, len(frames) - 1)]
        img_a = _tensor(stitcher.colour([load_image(p) for p in a.images]))
        img_b = _tensor(stitcher.colour([load_image(p) for p in b.images]))
        assert a.depths is not None
        depth = stitcher.depth([read_view_depth(p, DEPTH_SCALE, DEPTH_INVALID) for p in a.depths])
        d = torch.from_numpy(depth)[None, None]
        for c in errors:
            pa, pb = (torch.from_numpy(pose_convention(f.pose, c)) for f in (a, b))  # type: ignore[arg-type]
            rel = (torch.linalg.inv(pb) @ pa).float()[None]
            warped, valid = inverse_warp(img_b, d, rel, camera)
            valid = valid & (d > 0)
            errors[c] += float(((warped - img_a).abs() * valid).sum() / valid.sum().clamp(min=1) / 3)
    best = min(errors, key=errors.__getitem__)
    return best, errors


def _auto_convention(
    path: Path, folder: Path, side: str, views: list[View], frames: list[RigFrame], overwrite: bool
) -> tuple[str, dict[str, float] | None]:
    """The convention a finished preparation into ``path`` chose, else :func:`_choose_convention`'s."""
    convention, errors = ("auto", None) if overwrite else _chosen_before(path, folder, side)
    return (convention, errors) if convention != "auto" else _choose_convention(views, frames)


def _chosen_before(path: Path, folder: Path, side: str) -> tuple[str, dict[str, float] | None]:
    """The convention a finished preparation of ``folder``'s ``side`` into ``path`` chose (``"auto"``: none)."""
    try:
        record = json.loads((path / PREPARE_FILE).read_text(encoding="utf-8"))
        settings = record["settings"]
        same = settings["source"] == str(folder.resolve()) and settings["side"] == side
        if record.get("finished") and same and record.get("convention") in _all_conventions():
            return record["convention"], record.get("convention_errors")
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return "auto", None


def _tensor(image: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255


@dataclass
class SynthiaReport:
    """One output sequence of :func:`prepare_synthia`."""

    sequence: Path
    frames: int
    dropped_static: int
    convention: str
    errors: dict[str, float] | None = None

    def line(self) -> str:
        how = f"poses as {self.convention}"
        if self.errors:
            ranked = sorted(self.errors.items(), key=lambda kv: kv[1])[:2]
            how += f" (chosen: photometric error {ranked[0][1]:.4f}, next {ranked[1][0]} {ranked[1][1]:.4f})"
        return f"{self.sequence}: {self.frames} frames, {self.dropped_static} left out as static; {how}"


def prepare_synthia(
    root: str | os.PathLike[str],
    out: str | os.PathLike[str],
    options: SynthiaOptions | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> list[SynthiaReport]:
    """Prepare SYNTHIA-Seqs folders under ``root`` as sequences ``OUT/NN-SEASON-SIDE``.

    Raises:
        CylsfmError: naming the file or folder: no matching folder, a missing view, image or depth, an
            unreadable intrinsics or camera file, an unknown convention or side.
    """
    from ...runtime import progress_bar

    options = options or SynthiaOptions()
    if options.convention != "auto" and options.convention not in _all_conventions():
        raise CylsfmError(
            f"unknown pose convention {options.convention!r}; auto or one of {_all_conventions()}"
        )
    for side in options.sides:
        if side not in SIDES:
            raise CylsfmError(f"unknown stereo side {side!r}; left or right")
    camera = CylindricalCamera.full(int(options.size[0]), int(options.size[1]), float(options.vfov_h))
    reports = []
    for folder, seq, season in _folders(Path(root), options):
        for side in options.sides:
            views, frames = _side_frames(folder, side)
            frames = [f for f in frames if f.name not in options.exclude]
            if len(frames) < 2:
                raise CylsfmError(f"{folder} ({side}): fewer than two frames left to prepare")
            convention, errors = options.convention, None
            if convention == "auto":
                target = Path(out) / f"{seq}-{season}-{side}"
                convention, errors = _auto_convention(target, folder, side, views, frames, overwrite)
            for f in frames:
                f.pose = pose_convention(f.pose, convention)  # type: ignore[arg-type]
            frames, dropped = drop_static(frames, options.static_motion, options.static_turn_deg)
            if not options.depth:
                for f in frames:
                    f.depths = None
            settings: dict[str, Any] = {
                "source": str(folder.resolve()),
                "side": side,
                "camera": camera.to_dict(),
                "convention": convention,
                "static": [options.static_motion, options.static_turn_deg],
                "depth": options.depth,
                "exclude": sorted(options.exclude),
            }
            name = f"{seq}-{season}-{side}"
            out_seq = PreparedSequence(Path(out) / name, camera, settings, overwrite)
            if not out_seq.finished:
                with progress_bar(total=len(frames), desc=name, unit="frame", enabled=progress) as bar:
                    write_rig(out_seq, Stitcher(views, camera), frames, DEPTH_SCALE, DEPTH_INVALID, bar)
                out_seq.note(convention=convention, convention_errors=errors, dropped_static=dropped)
            reports.append(SynthiaReport(out_seq.path, len(out_seq.done), dropped, convention, errors))
    return reports
