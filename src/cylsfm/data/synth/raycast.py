"""Ray casting against vertical prisms and the ground plane.

Everything is a vertical prism standing on the ground, so a ray only has to be tested against the objects
whose horizontal footprint covers its azimuth: objects are binned by the azimuth interval their footprint
spans as seen from the camera, and each ray tests the candidates of its bin, nearest footprint first.
"""

from __future__ import annotations

import numpy as np

from .prisms import BOX, CYLINDER, PRISM_FIELDS, Prisms

__all__ = ["MAX_RANGE", "cast", "footprint_distance", "intersect"]

#: Objects whose footprint is farther than this (metres, horizontally) are not drawn.
MAX_RANGE = 160.0
_NBINS = 2048  # azimuth bins (a power of two)
_BIN_SCALE = _NBINS / (2 * np.pi)  # bins per radian


def _azimuth_intervals(p: Prisms, ox: float, oz: float) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth interval [lo, hi] (radians, hi >= lo, possibly beyond +-pi) of each footprint seen from (ox, oz)."""
    box = p.kind == BOX
    cx = np.where(box, 0.5 * (p.a[:, 0] + p.a[:, 1]), p.a[:, 0])
    cz = np.where(box, 0.5 * (p.a[:, 2] + p.a[:, 3]), p.a[:, 1])
    centre = np.arctan2(cx - ox, cz - oz)
    # boxes: the extreme corner azimuths relative to the centre direction
    corners_x = p.a[:, [0, 1, 0, 1]]
    corners_z = p.a[:, [2, 2, 3, 3]]
    ang = np.arctan2(corners_x - ox, corners_z - oz) - centre[:, None]
    ang = (ang + np.pi) % (2 * np.pi) - np.pi
    lo_box, hi_box = ang.min(1), ang.max(1)
    inside = box & (ox >= p.a[:, 0]) & (ox <= p.a[:, 1]) & (oz >= p.a[:, 2]) & (oz <= p.a[:, 3])
    # cylinders: centre +- asin(r / distance)
    dist = np.hypot(cx - ox, cz - oz)
    half = np.arcsin(np.clip(p.a[:, 2] / np.maximum(dist, 1e-9), 0, 1))
    inside |= ~box & (dist <= p.a[:, 2])
    lo = np.where(box, lo_box, -half) + centre
    hi = np.where(box, hi_box, half) + centre
    lo = np.where(inside, -np.pi, lo)
    hi = np.where(inside, np.pi, hi)
    return lo, hi


def footprint_distance(p: Prisms, ox: float, oz: float) -> np.ndarray:
    """Horizontal distance [N] (metres) from (ox, oz) to each prism's footprint (0 inside it)."""
    box = p.kind == BOX
    dx = np.maximum(np.maximum(p.a[:, 0] - ox, ox - p.a[:, 1]), 0)
    dz = np.maximum(np.maximum(p.a[:, 2] - oz, oz - p.a[:, 3]), 0)
    d_box = np.hypot(dx, dz)
    d_cyl = np.maximum(np.hypot(p.a[:, 0] - ox, p.a[:, 1] - oz) - p.a[:, 2], 0)
    return np.where(box, d_box, d_cyl)


def cast(p: Prisms, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit of rays ``origin + t dirs`` ([P,3]) with the prisms and the ground plane y = 0.

    Returns ``(t [P] (inf: sky), object index [P] (-1: ground or sky), face [P])``; face 0/1: box side with
    normal along x/z, 2: top, 3: cylinder side.

    Candidates are found per azimuth bin (the objects whose footprint covers the ray's azimuth) and tested
    in rounds, nearest footprint first. A ray leaves the rounds as soon as no remaining candidate can beat
    its best hit: their footprints start farther away than that hit, or they are all too low for a ray
    climbing at its slope.
    """
    ox, oy, oz = origin
    P = len(dirs)
    dirs = dirs.astype(np.float32)
    rho = np.hypot(dirs[:, 0], dirs[:, 2])  # horizontal length of each direction
    with np.errstate(divide="ignore", invalid="ignore"):
        t_best = np.where(dirs[:, 1] > 1e-9, np.float32(-oy) / dirs[:, 1], np.float32(np.inf))  # the ground
        slope = dirs[:, 1] / rho
    obj = np.full(P, -1, np.int64)
    face = np.full(P, 2, np.int8)
    dist = footprint_distance(p, ox, oz)
    idx = np.nonzero(dist < MAX_RANGE)[0]
    if len(idx) == 0:
        return t_best, obj, face
    sub = p.take(idx)
    cast_sub = Prisms(
        *(
            getattr(sub, f).astype(np.float32) if f in ("a", "y_top", "y_bot") else getattr(sub, f)
            for f in PRISM_FIELDS
        )
    )
    near = dist[idx]
    with np.errstate(divide="ignore"):
        sigma = np.where(near > 1e-9, (sub.y_top - oy) / near, -np.inf)  # climb needed to pass over its top
    table, near_t, sig_t = _bin_table(sub, near, sigma, ox, oz)
    phi = np.arctan2(dirs[:, 0], dirs[:, 2])
    pix_bin = np.floor((phi + np.float32(np.pi)) * np.float32(_BIN_SCALE)).astype(np.int32) & (_NBINS - 1)
    act = np.arange(P)
    for r in range(table.shape[1]):
        b = pix_bin[act]
        c = table[b, r]
        # (the climb test holds for rays that do not descend: a descending ray can still drop onto a
        # low roof behind the footprint's nearest point)
        climb = (slope[act] > 0) | (slope[act] >= sig_t[b, r])
        keep = (c >= 0) & (near_t[b, r] < t_best[act] * rho[act]) & climb
        act, c = act[keep], c[keep]
        if len(act) == 0:
            break
        t_hit, f_hit = intersect(cast_sub, c, origin.astype(np.float32), dirs[act])
        better = t_hit < t_best[act]
        win = act[better]
        t_best[win] = t_hit[better]
        obj[win] = idx[c[better]]
        face[win] = f_hit[better]
    return t_best, obj, face


def _bin_table(
    p: Prisms, near: np.ndarray, sigma: np.ndarray, ox: float, oz: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The candidates of every azimuth bin, nearest footprint first, as seen from (ox, oz).

    ``near`` [N] is each footprint's distance and ``sigma`` [N] the climb (dy per horizontal metre) a ray
    needs to pass over its top. Returns ``(table, near_t, sig_t)``, each [bins, K+1]: the prism indices
    (-1 ends every list), their footprint distances (inf past the end), and the lowest climb among each
    candidate and the ones after it.
    """
    lo, hi = _azimuth_intervals(p, ox, oz)
    # one spare bin on each side, so that a ray whose azimuth is rounded into a neighbouring bin still
    # finds the object
    b_lo = np.floor((lo + np.pi) * _BIN_SCALE).astype(np.int64) - 1
    b_hi = np.floor((hi + np.pi) * _BIN_SCALE).astype(np.int64) + 1
    span = np.minimum(b_hi - b_lo + 1, _NBINS)
    cand = np.repeat(np.arange(len(p)), span)
    cand_bin = (
        np.repeat(b_lo, span) + np.arange(len(cand)) - np.repeat(np.cumsum(span) - span, span)
    ) % _NBINS
    order = np.lexsort((near[cand], cand_bin))  # by bin, then nearest first
    cand, cand_bin = cand[order], cand_bin[order]
    counts = np.bincount(cand_bin, minlength=_NBINS)
    rank = np.arange(len(cand)) - np.repeat(np.cumsum(counts) - counts, counts)
    k_max = int(counts.max())
    table = np.full((_NBINS, k_max + 1), -1, np.int64)  # a -1 column ends every list
    table[cand_bin, rank] = cand
    near_t = np.full((_NBINS, k_max + 1), np.inf)
    near_t[cand_bin, rank] = near[cand]
    sig_t = np.full((_NBINS, k_max + 1), np.inf)
    sig_t[cand_bin, rank] = sigma[cand]
    sig_t = np.minimum.accumulate(sig_t[:, ::-1], axis=1)[:, ::-1]  # lowest climb among the rest
    return table, near_t, sig_t


def intersect(p: Prisms, k: np.ndarray, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray-prism intersections for pairs (prism k[i], ray d[i]) -> (t [n] or inf, face [n]).

    Slab tests in float32; a zero direction component divides to +-inf, which the slab logic handles
    (``fmin``/``fmax`` ignore the NaN of a ray lying exactly in a slab's plane).
    """
    n = len(k)
    t = np.full(n, np.inf, np.float32)
    face = np.zeros(n, np.int8)
    ox, oy, oz = o
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for kind in (BOX, CYLINDER):
            sel = np.nonzero(p.kind[k] == kind)[0]
            if len(sel) == 0:
                continue
            kk = k[sel]
            dx, dy, dz = d[sel, 0], d[sel, 1], d[sel, 2]
            a = p.a[kk]
            inv_y = 1 / dy
            ty1 = (p.y_top[kk] - oy) * inv_y
            ty2 = (p.y_bot[kk] - oy) * inv_y
            ty_in, ty_out = np.fmin(ty1, ty2), np.fmax(ty1, ty2)
            if kind == BOX:
                side_in, side_out, side_face = _box_sides(a, ox, oz, dx, dz)
            else:
                side_in, side_out, side_face = _cylinder_side(a, ox, oz, dx, dz)
            t_in = np.fmax(side_in, ty_in)
            hit = (t_in <= np.fmin(side_out, ty_out)) & (t_in > 1e-5)
            t[sel] = np.where(hit, t_in, np.inf)
            face[sel] = np.where(ty_in > side_in, 2, side_face)
    return t, face


def _box_sides(a, ox, oz, dx, dz) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Entry and exit ``t`` [n] of rays through the x and z slabs of boxes ``a`` [n,4], and the entry face
    (0: the side whose normal is along x, 1: along z)."""
    inv_x, inv_z = 1 / dx, 1 / dz
    tx1 = (a[:, 0] - ox) * inv_x
    tx2 = (a[:, 1] - ox) * inv_x
    tz1 = (a[:, 2] - oz) * inv_z
    tz2 = (a[:, 3] - oz) * inv_z
    tx_in, tz_in = np.fmin(tx1, tx2), np.fmin(tz1, tz2)
    side_in = np.fmax(tx_in, tz_in)
    side_out = np.fmin(np.fmax(tx1, tx2), np.fmax(tz1, tz2))
    side_face = np.where(tx_in > tz_in, 0, 1).astype(np.int8)
    return side_in, side_out, side_face


def _cylinder_side(a, ox, oz, dx, dz) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Entry and exit ``t`` [n] of rays through the infinite cylinders ``a`` [n,4] (cx, cz, r, 0):
    ``|o_xz + t d_xz - c|^2 = r^2`` (inf / -inf for a miss), and the face (3)."""
    ex, ez = ox - a[:, 0], oz - a[:, 1]
    qa = dx * dx + dz * dz
    qb = ex * dx + ez * dz
    qc = ex * ex + ez * ez - a[:, 2] * a[:, 2]
    disc = qb * qb - qa * qc
    root = np.sqrt(np.maximum(disc, 0))
    side_in = np.where(disc >= 0, (-qb - root) / qa, np.inf)
    side_out = np.where(disc >= 0, (-qb + root) / qa, -np.inf)
    side_face = np.full(len(a), 3, np.int8)
    return side_in, side_out, side_face
