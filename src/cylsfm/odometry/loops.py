"""Loop closure, part one: the places a ride comes back to, found and verified.

1. **Candidates.** Every frame has a heading-invariant descriptor
   (:func:`~cylsfm.geometry.place.place_descriptor`). Distances between frames far apart in time are
   averaged along short sequences (the frames around each, matched in the same order for a revisit in
   the same direction and in reverse order for one in the opposite direction), which tells a street
   passed before from one that merely looks like it far better than one frame does. Each query frame
   keeps its few nearest earlier frames (at least ``min_gap`` frames back); the pairs are ranked by their
   distance relative to the query's median, and the best ones are verified.
2. **Verification** by geometry: the visual compass's yaw between the two panoramas (in closed form,
   looked for within the heading the odometry can have lost: a straight street looks much the same ahead
   and behind, a crossing four ways round, but the odometry knows which way the camera faces) and direct
   photometric alignment with the network's depth, started from translations around the first frame out
   to its median depth (:func:`~cylsfm.geometry.align.align`: a street driven back on the other side of
   the road is several metres across), in both directions (the second frame's depth aligned back to the
   first). A revisit is accepted when the two directions agree (their composition is near the identity)
   and most textured pixels fit (the inlier fraction of
   :func:`~cylsfm.geometry.photometric.photometric_inliers`, both ways, insensitive to where the other frame
   samples a texture within a pixel). Streets that only look alike are told apart by the odometry: a
   revisit must lie within its plausible drift (position and heading) and agree with its neighbours.

The relative pose of an accepted loop ``T_{i->j}`` (``p_j = T p_i``) is in frame ``i``'s depth unit; the
ratio of the two frames' depth units is measured by the depths themselves (frame ``i``'s points moved
into frame ``j`` against frame ``j``'s depth where they land), so that the pose graph
(:mod:`~cylsfm.odometry.posegraph`) corrects the drift of the monocular scale as well.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from ..errors import InputError
from ..evaluate.motion import yaw_angle
from ..geometry import Camera, compass_yaw, invert, sample_image, transform_points, yaw_matrix
from ..geometry.align import AlignConfig, align
from ..geometry.photometric import photometric_inliers
from ..geometry.place import place_distance

__all__ = [
    "Loop",
    "LoopSettings",
    "check_loops",
    "loop_candidates",
    "loop_rows",
    "loops_from_rows",
    "verify_loops",
]


@dataclass(frozen=True)
class LoopSettings:
    """How loops are looked for and accepted.

    Attributes:
        min_gap: the two frames of a loop are at least this many frames apart.
        window: sequence matching over ``2 * window + 1`` frames around each.
        per_query: the nearest earlier frames each query frame keeps (apart by at least ``window``).
        max_pairs: pairs verified at most in a ride.
        min_inliers: the smallest inlier fraction (both ways, :func:`~cylsfm.geometry.photometric.photometric_inliers`)
            of an accepted loop seen in much the same direction (a texture seen again at the same scale).
        turned_deg, min_inliers_turned: a revisit whose yaw is more than ``turned_deg`` degrees sees each
            texture from elsewhere (a street driven back on the other side of the road): its inliers are
            counted insensitive to sampling within a pixel, and at least ``min_inliers_turned`` must fit.
        max_rotation_deg, max_translation: the largest disagreement of the two directions' poses:
            rotation (degrees) and translation (as a fraction of the first frame's median depth).
        max_drift: a loop may move the second frame, relative to the first, by at most this fraction of
            the distance the odometry travelled between them (plus a tenth of the median depth): the
            drift odometry can plausibly have; a loop that asks for more is a place that only looks alike.
        yaw_drift_deg, yaw_drift_per_frame_deg, yaw_drift_max_deg: the heading the odometry can plausibly
            have lost between the two frames: ``yaw_drift_deg`` plus ``yaw_drift_per_frame_deg`` per frame
            between them, at most ``yaw_drift_max_deg`` (degrees; below 90, so that a street seen the
            other way round is never taken for the same view). The visual compass looks for the yaw only
            that close to the odometry's, and a loop that turns farther from it is rejected: a straight
            street looks much the same ahead and behind, and a crossing four ways round, but the odometry
            knows which way the camera faces.
        support: an accepted loop needs at least this many verified loops (itself included) nearby (both
            frames within ``span`` frames of its own) that agree with it through the odometry between
            them; a revisit is seen by several consecutive frames, a lookalike rarely agrees with itself.
            The others may be accepted loops or pairs seen the same way round that fit less well (at
            least ``min_inliers_support`` of their pixels, within the odometry's drift) but whose own
            alignment found the pose the loop predicts: a ride that ends where it started sees its start
            only from its last few frames, each a little farther back than the last.
        min_inliers_support: see ``support``.
        span: frames; see ``support``.
        align: the alignment's settings.
    """

    min_gap: int = 50
    window: int = 5
    per_query: int = 2
    max_pairs: int = 64
    min_inliers: float = 0.5
    turned_deg: float = 90.0
    min_inliers_turned: float = 0.6
    max_rotation_deg: float = 3.0
    max_translation: float = 0.1
    max_drift: float = 0.15
    yaw_drift_deg: float = 30.0
    yaw_drift_per_frame_deg: float = 0.1
    yaw_drift_max_deg: float = 80.0
    support: int = 2
    min_inliers_support: float = 0.3
    span: int = 20
    align: AlignConfig = field(default_factory=lambda: AlignConfig(levels=4, iterations=8))

    def __post_init__(self) -> None:
        if self.min_gap < 2 or self.window < 0 or self.per_query < 1 or self.max_pairs < 0:
            raise InputError(
                "loops: min_gap must be at least 2, window at least 0, per_query at least 1, max_pairs at "
                f"least 0; got {self.min_gap}, {self.window}, {self.per_query}, {self.max_pairs}"
            )
        if (
            self.yaw_drift_deg < 0
            or self.yaw_drift_per_frame_deg < 0
            or not 0 <= self.yaw_drift_max_deg <= 180
        ):
            raise InputError(
                "loops: yaw_drift_deg and yaw_drift_per_frame_deg must be >= 0 and yaw_drift_max_deg in "
                f"[0, 180], got {self.yaw_drift_deg}, {self.yaw_drift_per_frame_deg}, {self.yaw_drift_max_deg}"
            )
        fractions = (self.min_inliers, self.min_inliers_turned, self.min_inliers_support)
        if not all(0 <= f <= 1 for f in fractions):
            raise InputError(
                "loops: min_inliers, min_inliers_turned and min_inliers_support must be in [0, 1], got "
                + ", ".join(f"{f:g}" for f in fractions)
            )


@dataclass
class Loop:
    """A verified pair of frames ``i < j`` at the same place.

    Attributes:
        i, j: the frames.
        pose: ``T_{i->j}`` ``[4,4]`` (float64, ``p_j = T p_i``), translation in frame ``i``'s depth unit.
        ratio: frame ``j``'s depth unit per frame ``i``'s (the scale between the two).
        inliers: the smaller of the two directions' inlier fractions.
        disagreement: ``(degrees, fraction of the median depth)`` between the two directions.
        distance: the sequence-matched descriptor distance relative to the query's median.
        accepted: whether it passed the verification and the checks against the odometry.
        why: why it was not accepted (``""``: accepted).
    """

    i: int
    j: int
    pose: np.ndarray
    ratio: float
    inliers: float
    disagreement: tuple[float, float]
    distance: float
    accepted: bool
    why: str = ""


def sequence_distances(desc: Tensor, window: int, rows: tuple[int, int] | None = None) -> np.ndarray:
    """Descriptor distances ``[R,N]`` averaged over ``2 * window + 1`` frames: for each pair the smaller
    of the same-order average (``d(i+t, j+t)``) and the reverse-order one (``d(i+t, j-t)``), over the
    frames that exist.

    Args:
        desc: the frames' descriptors ``[N,D]``.
        window: frames on each side.
        rows: the query frames ``[a, b)`` whose rows are wanted (``R = b - a``); ``None``: all (``R = N``).
            Only ``R + 2 * window`` rows of plain distances are held at once, so a long ride is searched
            a block of rows at a time.
    """
    n = desc.shape[0]
    a, b = (0, n) if rows is None else rows
    lo, hi = max(0, a - window), min(n, b + window)
    d = np.full((b - a + 2 * window, n + 2 * window), np.nan)  # rows a-w .. b+w, columns -w .. n+w
    d[lo - a + window : hi - a + window, window : window + n] = (
        place_distance(desc[lo:hi], desc).double().numpy()
    )
    if window == 0:
        return d[:, :n]
    best = np.full((b - a, n), np.inf)
    for sign in (1, -1):
        total, count = np.zeros_like(best), np.zeros_like(best)
        for t in range(-window, window + 1):
            part = d[window + t : window + t + b - a, window + sign * t : window + sign * t + n]
            total += np.nan_to_num(part)
            count += ~np.isnan(part)
        best = np.minimum(best, total / np.maximum(count, 1))
    return best


def loop_candidates(
    desc: Tensor,
    settings: LoopSettings,
    c2w: np.ndarray | None = None,
    reach: np.ndarray | None = None,
) -> list[tuple[int, int, float]]:
    """Pairs ``(i, j, relative distance)`` (``i <= j - min_gap``) to verify, best first, at most
    ``max_pairs`` (see the module docstring).

    Args:
        desc: the frames' descriptors ``[N,D]``.
        settings: the search's settings.
        c2w, reach: the odometry's poses ``[N,4,4]`` and the frames' median depths ``[N]``: with them, only
            the earlier frames within the odometry's plausible drift of the query
            (:attr:`LoopSettings.max_drift`) are considered.
    """
    n = desc.shape[0]
    if n <= settings.min_gap:
        return []
    block, dist, first = 256, np.empty((0, n)), 0  # query rows [first, first + len(dist)) held
    gated = c2w is not None and reach is not None
    if gated:
        pos = c2w[:, :3, 3]
        travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    pairs = []
    for j in range(settings.min_gap, n):
        if j >= first + len(dist):
            first = j
            dist = sequence_distances(desc, settings.window, (j, min(n, j + block)))
        m = j - settings.min_gap + 1
        earlier = dist[j - first, :m]
        median = float(np.median(earlier))  # the query's typical distance, over every earlier frame
        plausible = np.ones(m, dtype=bool)
        if gated:  # one row at a time: no N x N matrices of positions
            apart = np.linalg.norm(pos[:m] - pos[j], axis=-1)
            plausible = apart <= settings.max_drift * (travelled[j] - travelled[:m]) + 0.1 * reach[:m]
        taken: list[int] = []
        for i in np.argsort(earlier, kind="stable"):
            if not plausible[i]:
                continue
            if all(abs(int(i) - t) > settings.window for t in taken):
                taken.append(int(i))
                pairs.append((int(i), j, float(earlier[i]) / max(median, 1e-12)))
            if len(taken) == settings.per_query:
                break
    pairs.sort(key=lambda p: p[2])
    return pairs[: settings.max_pairs]


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
            near = torch.tensor([_odometry_yaw(c2w, i, j) for i, j, _ in chunk], dtype=torch.float64)
            within = torch.tensor([_yaw_allowance(settings, i, j) for i, j, _ in chunk], dtype=torch.float64)
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
                out.append(Loop(i, j, t_f, float(ratio[b]), float(inl_f[b]), (math.nan, math.nan), dist, False,
                                "few inliers"))  # fmt: skip
                continue
            t_b = back_poses[b].copy()
            t_b[:3, 3] /= float(ratio[b])  # the way back is in j's unit: to i's before composing
            e = t_b @ t_f
            rot = _rotation_deg(e[:3, :3])
            trans = float(np.linalg.norm(e[:3, 3]) / float(reach_i[b]))
            inliers = min(float(inl_f[b]), inl_b[b])
            agree = rot <= settings.max_rotation_deg and trans <= settings.max_translation
            ok = agree and inliers >= need[b]
            why = "" if ok else ("the two ways disagree" if not agree else "few inliers")
            out.append(Loop(i, j, t_f, float(ratio[b]), inliers, (rot, trans), dist, ok, why))
    return out


def _odometry_yaw(c2w: np.ndarray, i: int, j: int) -> float:
    """The yaw (radians) of the odometry's ``T_{i->j}`` (as :func:`~cylsfm.geometry.compass_yaw`'s)."""
    return float(yaw_angle(invert(c2w[j]) @ c2w[i]))


def _yaw_allowance(settings: LoopSettings, i: int, j: int) -> float:
    """The heading drift (radians) the odometry can plausibly have between frames ``i`` and ``j``."""
    drift = settings.yaw_drift_deg + settings.yaw_drift_per_frame_deg * abs(j - i)
    return math.radians(min(settings.yaw_drift_max_deg, drift))


def _rotation_deg(r: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(r)) - 1) / 2))))


def check_loops(loops: list[Loop], c2w: np.ndarray, reach: np.ndarray, settings: LoopSettings) -> list[Loop]:
    """The verified loops checked against the odometry (see :class:`LoopSettings`: ``max_drift``,
    ``support``): those that fail are no longer accepted (their ``why`` says which check).

    Args:
        loops: from :func:`verify_loops`.
        c2w: the odometry's camera-to-world poses ``[M,4,4]`` (its own unit).
        reach: each frame's median depth ``[M]`` (the same unit).
    """
    pos = c2w[:, :3, 3]
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    supporters = []
    for lp in loops:
        weak = (
            not lp.accepted
            and lp.why == "few inliers"
            and lp.inliers >= settings.min_inliers_support
            and abs(float(yaw_angle(lp.pose))) <= math.radians(settings.turned_deg)
        )
        if not (lp.accepted or weak):
            continue
        why = _beyond_drift(lp, c2w, reach, travelled[lp.j] - travelled[lp.i], settings)
        if why and lp.accepted:
            lp.accepted, lp.why = False, why
        if not why:
            supporters.append(lp)
    kept = [lp for lp in loops if lp.accepted]
    for a in kept:
        agree = sum(
            1
            for b in supporters
            if abs(a.i - b.i) <= settings.span
            and abs(a.j - b.j) <= settings.span
            and _agree(a, b, c2w, reach)
        )
        if agree < settings.support:
            a.accepted, a.why = False, "no other loop agrees"
    return loops


def _beyond_drift(
    lp: Loop, c2w: np.ndarray, reach: np.ndarray, travelled: float, settings: LoopSettings
) -> str:
    """Why loop ``lp`` asks for more than the odometry's plausible drift (``""``: it does not);
    ``travelled``: the odometry's way between its two frames."""
    odo = invert(c2w[lp.j]) @ c2w[lp.i]  # the odometry's T_{i->j}
    centre_loop = -lp.pose[:3, :3].T @ lp.pose[:3, 3]  # camera j in frame i
    centre_odo = -odo[:3, :3].T @ odo[:3, 3]
    if np.linalg.norm(centre_loop - centre_odo) > settings.max_drift * travelled + 0.1 * reach[lp.i]:
        return "farther than the odometry's drift"
    turn = float(yaw_angle(lp.pose)) - _odometry_yaw(c2w, lp.i, lp.j)
    if abs(math.remainder(turn, 2 * math.pi)) > _yaw_allowance(settings, lp.i, lp.j):
        return "turned farther than the odometry's drift"
    return ""


def _agree(a: Loop, b: Loop, c2w: np.ndarray, reach: np.ndarray) -> bool:
    """Whether loop ``b``'s pose is what loop ``a``'s predicts through the odometry between their frames
    (``T_{ib->jb} ≈ T_{ja->jb} T_{ia->ja} T_{ib->ia}``): within 3 degrees and a tenth of the median depth
    plus a tenth of the odometry's way between them."""
    if a is b:
        return True

    def odo(x: int, y: int) -> np.ndarray:  # the odometry's T_{x->y}
        return invert(c2w[y]) @ c2w[x]

    pred = odo(a.j, b.j) @ a.pose @ odo(b.i, a.i)
    way = np.linalg.norm(odo(a.j, b.j)[:3, 3]) + np.linalg.norm(odo(b.i, a.i)[:3, 3])
    rot = _rotation_deg(pred[:3, :3].T @ b.pose[:3, :3])
    return rot <= 3.0 and np.linalg.norm(pred[:3, 3] - b.pose[:3, 3]) <= 0.1 * (reach[b.i] + way)


def loop_rows(loops: list[Loop]) -> np.ndarray:
    """Loops as rows of 24 numbers ``[K,24]`` (``i, j, ratio, inliers, disagreement (2), distance,
    accepted, pose (16)``): how the odometry's state keeps them."""
    rows = [
        [
            lp.i,
            lp.j,
            lp.ratio,
            lp.inliers,
            *lp.disagreement,
            lp.distance,
            float(lp.accepted),
            *lp.pose.ravel(),
        ]
        for lp in loops
    ]
    return np.asarray(rows, dtype=np.float64).reshape(-1, 24)


def loops_from_rows(rows: np.ndarray, why: list[str]) -> list[Loop]:
    """The inverse of :func:`loop_rows` (``why``: each loop's reason, ``""`` when accepted)."""
    return [
        Loop(int(r[0]), int(r[1]), r[8:].reshape(4, 4).copy(), float(r[2]), float(r[3]), (float(r[4]), float(r[5])),
             float(r[6]), bool(r[7]), w)
        for r, w in zip(rows, why, strict=True)
    ]  # fmt: skip
