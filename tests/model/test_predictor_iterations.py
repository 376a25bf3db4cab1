"""The pose network applied again to the source warped by its own pose (``Predictor.pose_iterations``)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from torch import nn

from cylsfm.errors import CylsfmError
from cylsfm.geometry import CylindricalCamera, compass_yaw, inverse_warp, invert, pose_vec_to_mat
from cylsfm.model import Predictor
from cylsfm.model.build import LoadedModels
from cylsfm.model.config import preset
from cylsfm.model.predictor import DEFAULT_POSE_ITERATIONS
from helpers import PoseStub, untrained_checkpoint

W, H = 128, 32


class _HalfCompassNet(PoseStub):
    """A pair pose network that reads half of the yaw between the target and each source (the visual
    compass's, no translation): a network that under-reads the motion, each pass by half."""

    def forward(self, target: torch.Tensor, sources: torch.Tensor):
        b, s = sources.shape[:2]
        yaw = compass_yaw(target[:, None].expand_as(sources).flatten(0, 1), sources.flatten(0, 1))
        vec = torch.zeros(b, s, 6)
        vec[..., 4] = 0.5 * yaw.view(b, s)
        return vec, None


class _FlatDisp(nn.Module):
    def forward(self, x: torch.Tensor):
        return [torch.ones(x.shape[0], 1, *x.shape[-2:])]


def _predictor(iterations: int | None) -> Predictor:
    cfg = preset("default")
    cfg.data.width, cfg.data.height = W, H
    models = LoadedModels(_FlatDisp(), _HalfCompassNet(), cfg, 0, Path("stub"))  # type: ignore[arg-type]
    return Predictor(models, pose_iterations=iterations)


def _panorama() -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    coarse = torch.rand(1, 3, 8, 16, generator=g)
    return torch.nn.functional.interpolate(coarse, size=(H, W), mode="bicubic", align_corners=False).clamp(
        0, 1
    )


@pytest.mark.parametrize(("iterations", "fraction"), [(0, 0.5), (1, 0.75), (3, 0.9375)])
def test_each_pass_reads_what_the_warp_left(iterations: int, fraction: float) -> None:
    """A camera turned by 8 columns (22.5 degrees): a network that reads half of any yaw gets
    1 - 2^-(n+1) of it after n further passes over its own warp."""
    tgt = _panorama()
    src = torch.roll(tgt, 8, -1)[:, None].repeat(1, 2, 1, 1, 1)
    pose = _predictor(iterations).poses(tgt, src, CylindricalCamera.full(W, H))
    true = float(compass_yaw(tgt, src[:, 0]))
    assert abs(true) == pytest.approx(2 * math.pi * 8 / W, rel=0.02)
    yaw = math.atan2(float(pose[0, 0, 0, 2]), float(pose[0, 0, 0, 0]))
    assert yaw == pytest.approx(fraction * true, rel=0.02)


def test_iterations_are_checked_and_default_by_network() -> None:
    assert _predictor(None).pose_iterations == DEFAULT_POSE_ITERATIONS
    with pytest.raises(CylsfmError, match=">= 0"):
        _predictor(-1)
    one_pass = _HalfCompassNet()
    one_pass.pairs = False  # the paper's network: its slot prior would be added at every pass
    cfg = preset("default")
    models = LoadedModels(_FlatDisp(), one_pass, cfg, 0, Path("stub"))  # type: ignore[arg-type]
    assert Predictor(models).pose_iterations == 0
    with pytest.raises(CylsfmError, match="frame pairs"):
        Predictor(models, pose_iterations=2)


def test_standing_camera_stays_still_through_the_passes(tmp_path: Path) -> None:
    """The default recipe's pair network, untrained: identical frames give zero motion in every pass."""
    predictor = Predictor.from_checkpoint(untrained_checkpoint(tmp_path, W, H), "cpu")
    assert predictor.pose_iterations == DEFAULT_POSE_ITERATIONS
    tgt = _panorama()
    pose = predictor.poses(tgt, tgt[:, None].repeat(1, 2, 1, 1, 1), CylindricalCamera.full(W, H))
    torch.testing.assert_close(pose, torch.eye(4, dtype=pose.dtype).expand_as(pose), atol=1e-5, rtol=0)


# ---------------------------------------------------------------------------------------------------
# A translation with non-flat depth: the order of composition and depth (not disparity) in the warp matter.
# The frames are rendered by casting rays into a rectangular room (vertical walls, no occlusion) whose
# walls carry a smooth pattern of the world coordinates; the target camera is the world frame.
ROOM = ((0, -3.0), (0, 2.0), (2, -2.5), (2, 4.0))  # walls x = -3, x = 2, z = -2.5, z = 4 (metres)
CAMERA = CylindricalCamera.full(W, H)
MOTIONS = (  # T_tgt_to_src of the two sources: turned and moved (the turn turns the translation's frame)
    (0.3, 0.05, 0.4, 25.0),
    (-0.25, 0.0, 0.3, -20.0),
)


def _motion(tx: float, ty: float, tz: float, yaw_deg: float) -> torch.Tensor:
    return pose_vec_to_mat(torch.tensor([tx, ty, tz, 0.0, math.radians(yaw_deg), 0.0], dtype=torch.float64))


def _render_room(c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(image [1,3,H,W], cylindrical depth [1,1,H,W])`` of the room seen by a camera at ``c2w``."""
    u = torch.arange(W, dtype=torch.float64)
    v = torch.arange(H, dtype=torch.float64)
    theta = ((u - CAMERA.cx) / CAMERA.fx)[None].expand(H, W)
    h = ((v - CAMERA.cy) / CAMERA.fy)[:, None].expand(H, W)
    ray = torch.stack([theta.sin(), h, theta.cos()], -1) @ c2w[:3, :3].T  # horizontal unit length: s = d
    origin = c2w[:3, 3]
    dist = torch.full((H, W), math.inf, dtype=torch.float64)
    for axis, at in ROOM:
        s = (at - origin[axis]) / ray[..., axis]
        dist = torch.where(s > 0, torch.minimum(dist, s), dist)
    p = origin + dist[..., None] * ray
    x, y, z = p.unbind(-1)
    image = torch.stack(
        [
            0.5 + 0.2 * torch.sin(1.7 * x + 2.1 * y) + 0.15 * torch.cos(1.3 * z),
            0.5 + 0.2 * torch.cos(1.1 * z - 1.9 * y) + 0.15 * torch.sin(1.5 * x + 0.8 * z),
            0.5 + 0.2 * torch.sin(0.9 * x - 1.4 * z + 2.6 * y),
        ]
    )
    return image[None].float(), dist[None, None].float()


def _read(target: torch.Tensor, source: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """The motion ``T_tgt_to_src`` as a pose vector under which the source, warped with the target's
    ``depth``, best reproduces the target (what the view synthesis loss trains a pose network to give), by
    damped Gauss-Newton; rows near the top and bottom, where a warp may have left the source, are not used."""
    mask = torch.zeros_like(depth, dtype=torch.bool)
    mask[..., 5:-5, :] = True
    tgt, src, depth = target.double(), source.double(), depth.double()

    def residual(vec: torch.Tensor) -> torch.Tensor:
        warped, valid = inverse_warp(src, depth, pose_vec_to_mat(vec)[None], CAMERA)
        return ((warped - tgt) * (valid & mask)).flatten()

    vec, damping = torch.zeros(6, dtype=torch.float64), 1e-3
    for _ in range(40):
        r = residual(vec)
        jac = torch.stack(
            [(residual(vec + e) - residual(vec - e)) / 2e-6 for e in 1e-6 * torch.eye(6).double()], 1
        )
        a = jac.T @ jac
        step = -torch.linalg.solve(a + damping * torch.diag(a.diag()), jac.T @ r)
        if residual(vec + step).square().sum() < r.square().sum():
            vec, damping = vec + step, max(damping / 3, 1e-6)
            if float(step.abs().max()) < 1e-7:
                break
        else:
            damping *= 5
    return vec


class _TurnFirstNet(PoseStub):
    """A pair pose network that reads the motion exactly from the images, but only the turn while the
    frames are turned by more than 5 degrees: its first pass reads the turn and no translation, the further
    passes read what the warp by the pose so far left."""

    pairs = True

    def __init__(self, depth: torch.Tensor) -> None:
        super().__init__()
        self.depth = depth

    def forward(self, target: torch.Tensor, sources: torch.Tensor):
        vec = torch.zeros(*sources.shape[:2], 6)
        for i in range(sources.shape[0]):
            for k in range(sources.shape[1]):
                read = _read(target[i : i + 1], sources[i, k : k + 1], self.depth)
                if math.degrees(float(read[3:].norm())) > 5.0:
                    read[:3] = 0.0
                vec[i, k] = read.float()
        return vec, None


class _DepthDisp(nn.Module):
    """The disparity of the target's true depth (the Predictor turns it into depth)."""

    def __init__(self, depth: torch.Tensor) -> None:
        super().__init__()
        self.depth = depth

    def forward(self, x: torch.Tensor):
        return [(1.0 / self.depth).expand(x.shape[0], -1, -1, -1)]


@pytest.mark.parametrize("iterations", [1, 2])
def test_passes_compose_a_turn_and_a_translation_over_non_flat_depth(iterations: int) -> None:
    """A room 2 to 5 m around the camera, two sources turned by 25 and -20 degrees and moved by 0.3-0.5 m.

    The first pass reads only the turns. The source warped by a turn alone is what the turned camera sees,
    so the next pass reads the translation left, as seen from there (``T_cur^-1 T_true``, rotated by the
    turn): composed after the current pose (``T_cur @ step``) it gives the true motion, and a pass after
    that, warping with the target's depth, reads nothing more. Composed the other way round the translation
    comes out turned by the yaw (about 0.2 m off); warped with disparity for depth, the second pass reads
    a motion that is not there."""
    target, depth = _render_room(torch.eye(4, dtype=torch.float64))
    assert float(depth.min()) == pytest.approx(2.0, abs=0.01) and float(depth.max()) > 4.5  # far from flat
    truth = torch.stack([_motion(*m) for m in MOTIONS])
    sources = torch.cat([_render_room(invert(t))[0] for t in truth])[None]
    cfg = preset("default")
    cfg.data.width, cfg.data.height = W, H
    models = LoadedModels(_DepthDisp(depth), _TurnFirstNet(depth), cfg, 0, Path("stub"))  # type: ignore[arg-type]
    first = Predictor(models, pose_iterations=0).poses(target, sources, CAMERA)[0]
    assert float(first[:, :3, 3].abs().max()) < 1e-6  # the first pass: the turns and no translation
    torch.testing.assert_close(first[:, :3, :3], truth[:, :3, :3], atol=2e-3, rtol=0)
    pose = Predictor(models, pose_iterations=iterations).poses(target, sources, CAMERA)[0]
    torch.testing.assert_close(pose[:, :3, :3], truth[:, :3, :3], atol=2e-3, rtol=0)
    torch.testing.assert_close(pose[:, :3, 3], truth[:, :3, 3], atol=5e-3, rtol=0)
