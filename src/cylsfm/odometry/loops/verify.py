"""Loop closure, verification: whether a candidate pair of frames is the same place, by geometry.

The visual compass's yaw between the two panoramas (in closed form, looked for within the heading the
odometry can have lost: a straight street looks much the same ahead and behind, a crossing four ways
round, but the odometry knows which way the camera faces) and direct photometric alignment with the
frames' depth, started from translations around the first frame out to its median depth
(:func:`~cylsfm.geometry.align.align`: a street driven back on the other side of the road is several
metres across), in both directions (the second frame's depth aligned back to the first). A revisit passes
when the two directions agree (their composition is near the identity) and most textured pixels fit (the
inlier fraction of :func:`~cylsfm.geometry.photometric.photometric_inliers`, both ways, insensitive to
where the other frame samples a texture within a pixel).

The relative pose of a loop ``T_{i->j}`` (``p_j = T p_i``) is in frame ``i``'s depth unit; the ratio of
the two frames' depth units is measured by the depths themselves (frame ``i``'s points moved into frame
``j`` against frame ``j``'s depth where they land), so that the pose graph
(:mod:`~cylsfm.odometry.loops.graph`) corrects the drift of the monocular scale as well.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ...geometry import Camera, compass_yaw, invert, sample_image, transform_points, yaw_matrix
from ...geometry.align import align
from ...geometry.photometric import photometric_inliers
from .loop import Loop, Reason, odometry_yaw, rotation_deg
from .settings import LoopSettings

__all__ = ["depth_ratio", "verify_loops"]


def _starts(yaw: Tensor, reach: Tensor) -> Tensor:
    """Starting poses ``[B,17,4,4]``: the compass's rotation, with no translation and with 16 around the
    first camera (8 directions, at a third of ``reach`` ``[B]`` and at ``reach``: a street driven back on
    the other side of the road is several metres across)."""
    b = yaw.shape[0]
    rot = yaw_matrix(yaw, dtype=torch.float64)
    out = torch.eye(4, dtype=torch.float64, device=yaw.device).repeat(b, 17, 1, 1)
    out[:, :, :3, :3] = rot[:, None]
    k = 1
    for r in (1 / 3, 1.0):
        for a in range(8):
            ang = 2 * math.pi * a / 8
            offset = torch.tensor([math.sin(ang), 0.0, math.cos(ang)], dtype=torch.float64, device=yaw.device)
            # p_j = R p_i + t: a camera j at c (in i's frame) has t = -R c
            out[:, k, :3, 3] = -(rot @ (offset * r)[None, :, None].expand(b, 3, 1))[..., 0] * reach[:, None]
            k += 1
    return out


def _median_depth(depth: Tensor) -> Tensor:
    """``[B,1,H,W]`` -> ``[B]`` median of the known (> 0) depths."""
    d = torch.where(depth > 0, depth, torch.full_like(depth, float("nan"))).flatten(1)
    return torch.nan_to_num(torch.nanmedian(d, dim=1).values, nan=1.0).double()


def depth_ratio(depth_i: Tensor, depth_j: Tensor, pose: Tensor, camera: Camera) -> Tensor:
    """Frame ``j``'s depth unit per frame ``i``'s ``[B]``: the median, over frame ``i``'s points moved by
    ``pose`` ``T_{i->j}`` ``[B,4,4]`` into frame ``j``, of frame ``j``'s depth where they land over their
    depth (``1.0`` where none lands)."""
    points = transform_points(pose.float(), camera.unproject(depth_i.clamp(min=1e-6)))
    uv = camera.project(points)
    sampled, valid = sample_image(depth_j, uv, camera.wraps)
    own = camera.depth_of(points)
    ok = valid & (depth_i > 0) & (sampled > 0) & camera.projectable(points) & (own > 1e-6)
    r = torch.where(ok, sampled / own.clamp(min=1e-6), torch.full_like(own, float("nan"))).flatten(1)
    return torch.nan_to_num(torch.nanmedian(r, dim=1).values, nan=1.0).double()


def verify_loops(
    pairs: list[tuple[int, int, float]],
    image_of,
    depth_of,
    camera: Camera,
    settings: LoopSettings,
    mask: Tensor | None = None,
    batch: int = 8,
    c2w: np.ndarray | None = None,
) -> list[Loop]:
    """Verify candidate pairs (see the module docstring).

    Args:
        pairs: ``(i, j, relative distance)`` from :func:`loop_candidates`.
        image_of, depth_of: frame index -> its network-size image ``[3,H,W]`` / depth ``[1,H,W]``.
        camera: the camera of those images (a full panorama).
        mask: ``[1,1,H,W]``: 1 where the scene is seen; ``None``: every pixel.
        c2w: the odometry's camera-to-world poses ``[M,4,4]``: with them, the compass looks for the yaw
            only within the odometry's plausible heading drift of its yaw (:class:`LoopSettings`);
            ``None``: any yaw.

    Returns:
        One :class:`Loop` per pair, accepted or not.
    """
    out = []
    for n in range(0, len(pairs), batch):
        chunk = pairs[n : n + batch]
        img_i = torch.stack([image_of(i) for i, _, _ in chunk]).float()
        img_j = torch.stack([image_of(j) for _, j, _ in chunk]).float()
        dep_i = torch.stack([depth_of(i) for i, _, _ in chunk]).float()
        dep_j = torch.stack([depth_of(j) for _, j, _ in chunk]).float()
        if c2w is None:
            yaw = compass_yaw(img_i, img_j, mask)
        else:
            near = torch.tensor([odometry_yaw(c2w, i, j) for i, j, _ in chunk], dtype=torch.float64)
            within = torch.tensor([settings.yaw_allowance(i, j) for i, j, _ in chunk], dtype=torch.float64)
            yaw = compass_yaw(img_i, img_j, mask, near=near, within=within)
        reach_i, reach_j = _median_depth(dep_i), _median_depth(dep_j)
        fwd = align(img_i, img_j, dep_i, _starts(yaw, reach_i), camera, config=settings.align, mask=mask)
        # a revisit turned round sees every texture from elsewhere: inliers insensitive to sampling
        turned = yaw.abs() > math.radians(settings.turned_deg)
        need = [settings.min_inliers_turned if t else settings.min_inliers for t in turned.tolist()]
        inl_f = photometric_inliers(img_i, img_j, dep_i, fwd.poses, camera, spread=turned.float(), mask=mask)
        ratio = depth_ratio(dep_i, dep_j, fwd.poses, camera)
        # the way back only for the pairs that fit one way (most candidates do not: half the work)
        go = [b for b in range(len(chunk)) if float(inl_f[b]) >= need[b]]
        back_poses, inl_b = {}, {}
        if go:
            sel = torch.tensor(go)
            start = torch.cat((invert(fwd.poses[sel])[:, None], _starts(-yaw[sel], reach_j[sel])), 1)
            back = align(img_j[sel], img_i[sel], dep_j[sel], start, camera, config=settings.align, mask=mask)
            inl = photometric_inliers(
                img_j[sel], img_i[sel], dep_j[sel], back.poses, camera, spread=turned[sel].float(), mask=mask
            )
            for n_b, b in enumerate(go):
                back_poses[b], inl_b[b] = back.poses[n_b].numpy(), float(inl[n_b])
        for b, (i, j, dist) in enumerate(chunk):
            t_f = fwd.poses[b].numpy()
            if b not in back_poses:
                nan = (math.nan, math.nan)
                out.append(Loop(i, j, t_f, float(ratio[b]), float(inl_f[b]), nan, dist, Reason.FEW_INLIERS))
                continue
            t_b = back_poses[b].copy()
            t_b[:3, 3] /= float(ratio[b])  # the way back is in j's unit: to i's before composing
            e = t_b @ t_f
            rot = rotation_deg(e[:3, :3])
            trans = float(np.linalg.norm(e[:3, 3]) / float(reach_i[b]))
            inliers = min(float(inl_f[b]), inl_b[b])
            agree = rot <= settings.max_rotation_deg and trans <= settings.max_translation
            reason = Reason.ACCEPTED if inliers >= need[b] else Reason.FEW_INLIERS
            reason = reason if agree else Reason.DISAGREE
            out.append(Loop(i, j, t_f, float(ratio[b]), inliers, (rot, trans), dist, reason))
    return out
