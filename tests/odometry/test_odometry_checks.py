"""``cylsfm odometry``'s options checked by their values, through the command line: metres from the camera
height the right way round, keyframes aligned to the frames they name, and a direction of travel given with
``--mount-yaw`` that turns the motion the pose network reads."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from cylsfm.cli import main
from cylsfm.data.format import SequenceWriter
from cylsfm.data.io import load_image, read_tum
from cylsfm.data.synth.room import make_pose, render_room
from cylsfm.geometry import CylindricalCamera
from cylsfm.model import Predictor
from cylsfm.model.build import LoadedModels
from cylsfm.model.config import preset
from cylsfm.odometry import track
from helpers import PoseStub

W, H, N = 128, 32, 10
#: The camera's height over the room's floor (the floor is at y = 1.6, the camera at y = 0.1).
HEIGHT = 1.5
#: The depth the refinement is given in the camera-height test is in units of this many metres.
UNIT = 2.5


def _pose(i: int) -> torch.Tensor:
    """Frame ``i`` of the ride: driving 0.32 m a frame and turning 3 degrees."""
    return make_pose(0.8 - 0.12 * i, 0.1, -2.0 + 0.3 * i, yaw_deg=-8.0 + 3.0 * i)


def _rgb(image: torch.Tensor) -> np.ndarray:
    return (image[0].permute(1, 2, 0).clamp(0, 1) * 255).round().byte().numpy()


@pytest.fixture(scope="module")
def ride(tmp_path_factory) -> dict:
    """The ride as a dataset in metres (``metres/ride``, with poses) and its depth in units of ``UNIT``
    metres (``units/ride``: a depth of unknown scale, as a network's)."""
    root = tmp_path_factory.mktemp("checks")
    cam = CylindricalCamera.full(W, H)
    metres, units = (
        SequenceWriter(root / "metres" / "ride", cam),
        SequenceWriter(root / "units" / "ride", cam),
    )
    poses = []
    for i in range(N):
        image, depth = render_room(cam, _pose(i), supersample=2)
        metres.add_frame(_rgb(image), depth[0, 0].numpy())
        units.add_frame(_rgb(image), depth[0, 0].numpy() / UNIT)
        poses.append(_pose(i).numpy())
    times = np.arange(N) * 0.2
    seq = metres.finish(np.stack(poses), timestamps=times)
    units.finish(np.stack(poses), timestamps=times)
    return {"seq": seq, "metres": root / "metres", "units": root / "units", "poses": np.stack(poses)}


def _run(ckpt, *args) -> int:
    return main(["odometry", "--checkpoint", str(ckpt), "--device", "cpu", "--no-progress", *map(str, args)])


def _relative(c2w: np.ndarray) -> np.ndarray:
    """Camera-to-world poses ``[M,4,4]`` in the frame of the first."""
    return np.linalg.inv(c2w[0]) @ c2w


def _step_lengths(c2w: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=1)


def test_camera_height_scales_to_true_metres(ckpt, ride, tmp_path):
    """Refined with a depth in units of 2.5 m and told the camera's true height, the trajectory's steps
    are the true steps in metres (an inverted scale would make them 2.5^2 times too short)."""
    out = tmp_path / "o"
    args = ["--out", out, "--refine", "--depth-from", ride["units"], "--camera-height", HEIGHT]
    assert _run(ckpt, ride["seq"], *args) == 0
    summary = json.loads((out / "odometry.json").read_text())
    assert summary["unit"] == "metres"
    assert summary["metres_per_unit"] == pytest.approx(UNIT, rel=0.03)  # 1.5 m over a ground 0.6 units below
    _, c2w = read_tum(out / "trajectory.txt")
    true = _step_lengths(ride["poses"])
    np.testing.assert_allclose(_step_lengths(c2w), true, rtol=0.05)
    assert _step_lengths(c2w).sum() == pytest.approx(true.sum(), rel=0.02)
    np.testing.assert_allclose(_relative(c2w)[:, :3, 3], _relative(ride["poses"])[:, :3, 3], atol=0.03)


def test_keyframes_align_each_frame_to_its_keyframe(ckpt, ride, tmp_path, monkeypatch):
    """With ``--keyframes 3`` frames 1-3 are aligned to frame 0, 4-6 to frame 3, 7-9 to frame 6, and the
    steps taken back out of those alignments are the ride's."""
    files = sorted((ride["seq"] / "images").iterdir())
    frames = torch.stack(
        [torch.from_numpy(np.array(load_image(f))).permute(2, 0, 1).float() / 255 for f in files]
    )

    def which(batch: torch.Tensor) -> list[int]:
        diff = (batch[:, None] - frames[None]).abs().flatten(2).amax(-1)  # [B, N]
        assert float(diff.min(1).values.max()) < 1e-5, "an image the ride does not have"
        return diff.argmin(1).tolist()

    pairs: list[tuple[int, int]] = []
    align = track.align

    def recording(tgt, src, *args, **kwargs):
        pairs.extend(zip(which(tgt), which(src), strict=True))
        return align(tgt, src, *args, **kwargs)

    monkeypatch.setattr(track, "align", recording)
    out = tmp_path / "k"
    args = ["--out", out, "--refine", "--depth-from", ride["metres"], "--keyframes", 3, "--mount-yaw", 0]
    assert _run(ckpt, ride["seq"], *args) == 0
    assert sorted(pairs, key=lambda p: p[1]) == [(3 * ((j - 1) // 3), j) for j in range(1, N)]
    _, c2w = read_tum(out / "trajectory.txt")
    est, true = _relative(c2w), _relative(ride["poses"])
    np.testing.assert_allclose(_step_lengths(c2w), _step_lengths(ride["poses"]), rtol=0.05)
    np.testing.assert_allclose(est[:, :3, 3], true[:, :3, 3], atol=0.03)
    yaw = np.degrees(np.arctan2(est[:, 0, 2], est[:, 2, 2]))
    np.testing.assert_allclose(yaw, 3.0 * np.arange(N), atol=0.3)


# ---------------------------------------------------------------------------------------------------
# --mount-yaw: a pose network that has only ever seen cameras facing their motion reads every step as
# straight ahead of whatever it is shown; told that the travel lies at azimuth +90 (a camera mounted
# turned left), odometry turns the frames for it and the steps back, so the travel comes out along +x.
STEP = 0.3


class _StraightAhead(PoseStub):
    """Reads ``STEP`` straight ahead (+z) per frame between the target and each source, whatever the
    frames: ``T_tgt_to_src`` of a source ``o`` frames later moves the scene ``o`` steps towards the camera."""

    pairs = False

    def forward(self, target: torch.Tensor, sources: torch.Tensor):
        b, s = sources.shape[:2]
        offsets = [o for o in range(-(s // 2), s // 2 + 1) if o != 0]
        vec = torch.zeros(b, s, 6)
        vec[..., 2] = -STEP * torch.tensor(offsets, dtype=torch.float32)
        return vec, None


class _FlatDisp(nn.Module):
    def forward(self, x: torch.Tensor):
        return [torch.ones(x.shape[0], 1, *x.shape[-2:])]


@pytest.fixture
def straight_ahead(monkeypatch):
    cfg = preset("default")
    cfg.data.width, cfg.data.height = W, H
    models = LoadedModels(_FlatDisp(), _StraightAhead(), cfg, 0, Path("stub"))  # type: ignore[arg-type]

    def load(cls, path, device="auto", pose_iterations=None, amp=True):
        return cls(models, "cpu", pose_iterations, amp)

    monkeypatch.setattr(Predictor, "from_checkpoint", classmethod(load))


@pytest.fixture(scope="module")
def sideways(tmp_path_factory) -> tuple[Path, np.ndarray]:
    """A camera looking along the world's -x while it drives along +z: it travels along its own +x."""
    cam = CylindricalCamera.full(W, H)
    writer = SequenceWriter(tmp_path_factory.mktemp("sideways") / "ride", cam)
    poses = np.stack([make_pose(0.5, 0.1, -2.0 + STEP * i, yaw_deg=-90.0).numpy() for i in range(6)])
    for c2w in poses:
        writer.add_frame(_rgb(render_room(cam, torch.from_numpy(c2w), supersample=1)[0]))
    return writer.finish(poses, timestamps=np.arange(6) * 0.2), poses


@pytest.mark.parametrize("mount", [0.0, 90.0, -90.0])
def test_mount_yaw_turns_the_motion_read(ckpt, sideways, straight_ahead, tmp_path, mount):
    seq, poses = sideways
    assert _run(ckpt, seq, "--out", tmp_path / "o", "--mount-yaw", mount) == 0
    _, c2w = read_tum(tmp_path / "o" / "trajectory.txt")
    travel = _relative(c2w)[-1, :3, 3]  # in the first camera's frame
    azimuth = math.degrees(math.atan2(travel[0], travel[2]))
    assert azimuth == pytest.approx(mount, abs=1.0) and abs(travel[1]) < 1e-6
    assert np.linalg.norm(travel) == pytest.approx(STEP * 5, rel=1e-4)
    if mount == 90.0:  # the truth: this camera travels along its own +x
        np.testing.assert_allclose(travel, _relative(poses)[-1, :3, 3], atol=1e-3)
