"""Shading: the colour of every ray's hit point (sky, ground, facades, cars, trees), lit by a sun.

Textures are filtered over the pixel's footprint on the surface (the pixel's angle times the distance,
stretched at grazing angles), so distant detail averages out instead of aliasing. Light is a sun
(Lambert) plus a sky ambient, a little darker near the ground. Colours are float32 RGB in [0, 1].
"""

from __future__ import annotations

import numpy as np

from .prisms import CAR_GLASS, CAR_UNDER, CROWN, FACADE, POLE, TRUNK, Prisms
from .textures import band, hash01, pulse, smoothstep
from .town import StreetScene

__all__ = ["SUN", "shade"]

#: Unit vector towards the sun (world frame, y down).
SUN = np.array([0.45, -0.8, 0.4]) / np.linalg.norm([0.45, -0.8, 0.4])


def shade(
    scene: StreetScene,
    p: Prisms,
    pts: np.ndarray,
    dirs: np.ndarray,
    t: np.ndarray,
    obj: np.ndarray,
    face: np.ndarray,
    pixel_angle: float,
) -> np.ndarray:
    """Colour [P,3] float32 in [0, 1] of the hit points ``pts`` [P,3] (sky where ``t`` [P] is inf).

    ``dirs`` [P,3] are the rays, ``obj`` and ``face`` [P] what they hit (see
    :func:`~cylsfm.data.synth.raycast.cast`), ``pixel_angle`` the angle (radians) of a pixel.
    """
    f32 = np.float32
    P = len(t)
    out = np.zeros((P, 3), f32)
    sky = ~np.isfinite(t)
    length = np.linalg.norm(dirs, axis=1)
    unit = dirs / length[:, None]
    # ---- sky: a gradient and soft clouds, functions of the direction only (at infinity)
    if sky.any():
        d = unit[sky]
        up = np.clip(-d[:, 1], 0, 1)
        base = np.array([0.78, 0.86, 0.95], f32) + up[:, None] * np.array([-0.43, -0.31, -0.10], f32)
        k = f32(40) / (f32(0.25) + up)
        cloud = scene.sky_tile.sample(d[:, 0] * k, d[:, 2] * k, 1.0, k * f32(pixel_angle))
        cloud = smoothstep(0.5, 0.75, cloud)[:, None]
        out[sky] = base * (1 - f32(0.7) * cloud) + f32(0.68) * cloud
    dist = np.where(sky, 0, t * length).astype(f32)
    cone = f32(pixel_angle) * dist
    ground = np.nonzero(~sky & (obj < 0))[0]
    if len(ground):
        cos = np.abs(unit[ground, 1])
        fp = cone[ground] / np.sqrt(np.maximum(cos, f32(0.02)))
        light = f32(0.55 + 0.55 * -SUN[1])
        out[ground] = _ground_colour(scene, pts[ground, 0], pts[ground, 2], fp) * light
    objs = np.nonzero(~sky & (obj >= 0))[0]
    if len(objs):
        out[objs] = _object_colour(scene, p, pts[objs], obj[objs], face[objs], unit[objs], cone[objs])
    return np.clip(out, 0, 1)


def _object_colour(
    scene: StreetScene,
    p: Prisms,
    pts: np.ndarray,
    k: np.ndarray,
    f: np.ndarray,
    unit: np.ndarray,
    cone: np.ndarray,
) -> np.ndarray:
    """Lit colour [n,3] of object surface points [n,3] on prisms ``k`` and faces ``f``."""
    f32 = np.float32
    tiles = scene.tiles
    px, py, pz = pts[:, 0], pts[:, 1], pts[:, 2]
    mat = p.material[k]
    base = p.colour[k].astype(f32)
    # surface coordinates (su along the surface, sv up) and the normal
    top = f == 2
    cyl = f == 3
    su = np.where(f == 0, pz, px)
    sv = np.where(top, pz, -py)
    nx = np.where(f == 0, np.sign(px - f32(0.5) * (p.a[k, 0] + p.a[k, 1])), 0).astype(f32)
    nz = np.where(f == 1, np.sign(pz - f32(0.5) * (p.a[k, 2] + p.a[k, 3])), 0).astype(f32)
    ny = np.where(top, np.where(py < 0.5 * (p.y_top[k] + p.y_bot[k]), -1, 1), 0).astype(f32)
    if cyl.any():
        ang = np.arctan2(px[cyl] - p.a[k[cyl], 0], pz[cyl] - p.a[k[cyl], 1]).astype(f32)
        nx[cyl] = np.sin(ang)
        nz[cyl] = np.cos(ang)
        su[cyl] = ang * p.a[k[cyl], 2]
    cos = np.abs(nx * unit[:, 0] + ny * unit[:, 1] + nz * unit[:, 2])
    fp = cone / np.sqrt(np.maximum(cos, f32(0.02)))  # footprint on the surface, metres
    fine = tiles["fine"].sample(su, sv, 40.0, fp)
    coarse = tiles["coarse"].sample(su, sv, 6.0, fp)
    # most materials: base colour times a scalar texture
    col = base * (f32(0.85) + f32(0.3) * fine)[:, None]
    fac = np.nonzero((mat == FACADE) & ~top)[0]
    if len(fac):
        col[fac] = _facade_colour(
            base[fac], p.param[k[fac]].astype(f32), su[fac], sv[fac], fine[fac], coarse[fac], fp[fac]
        )
    for m, lo, amp, tex in (
        (CAR_UNDER, 0.3, 1.5, fine),
        (CAR_GLASS, 0.7, 0.6, coarse),
        (POLE, 0.8, 0.4, fine),
    ):
        sel = mat == m
        col[sel] = base[sel] * (f32(lo) + f32(amp) * tex[sel])[:, None]
    roof = np.nonzero((mat == FACADE) & top)[0]
    col[roof] = ((0.45 + 0.2 * coarse[roof]) * (0.6 + 0.8 * fine[roof]))[:, None] * np.array(
        [0.9, 0.88, 0.85], f32
    )
    trunk = np.nonzero(mat == TRUNK)[0]
    bark = tiles["fine"].sample(su[trunk] * f32(0.5), sv[trunk] * f32(3), 40.0, fp[trunk] * f32(3))
    col[trunk] = base[trunk] * (0.6 + 0.8 * bark)[:, None]
    crown = np.nonzero(mat == CROWN)[0]
    leaves = tiles["leaves"].sample(su[crown], sv[crown], 12.0, fp[crown])
    col[crown] = base[crown] * ((0.45 + 1.1 * leaves) * (0.85 + 0.3 * coarse[crown]))[:, None]
    # sun (Lambert) + sky ambient, a little darker near the ground
    sun = SUN.astype(f32)
    lam = np.clip(nx * sun[0] + ny * sun[1] + nz * sun[2], 0, 1)
    light = (f32(0.55) + f32(0.1) * np.clip(-ny, 0, 1) + f32(0.55) * lam) * (
        f32(0.85) + f32(0.15) * smoothstep(0.0, 2.5, -py)
    )
    return col * light[:, None]


def _facade_colour(base, par, su, sv, fine, coarse, fp) -> np.ndarray:
    """Facade colour [n,3]: plaster, brick or concrete wall with a grid of windows and a plinth.

    Every pattern is box-filtered over the footprint ``fp`` (metres), so it fades to its average with
    distance instead of aliasing.
    """
    f32 = np.float32
    floor_h, pitch, style, seed = par[:, 0], par[:, 1], par[:, 2], par[:, 3]
    tone = (0.8 + 0.25 * coarse) * (0.85 + 0.3 * fine)
    # bricks: courses of 0.085 m, bricks 0.25 m long (staggered), with light mortar joints
    brick = style == 1
    course = f32(0.085)
    row = np.floor(sv / course)
    shift = f32(0.125) * (row % 2)
    detail = 1 - smoothstep(0.03, 0.1, fp)  # per-brick variation fades once bricks are sub-pixel
    tint = 1 + (0.3 * hash01(np.floor((su + shift) / f32(0.25)), row, seed) - 0.15).astype(f32) * detail
    mortar = 1 - (1 - pulse(sv, course, 0.0, 0.1, fp)) * (1 - pulse(su + shift, f32(0.25), 0.0, 0.06, fp))
    tone = np.where(brick, tone * tint, tone)
    # concrete panels: a coarse grid of dark joints
    joints = 1 - (1 - pulse(su, f32(1.5), 0.0, 0.015, fp)) * (1 - pulse(sv, f32(1.2), 0.0, 0.02, fp))
    tone = np.where(style == 2, tone * (1 - 0.4 * joints), tone)
    tone = tone * (1 - 0.3 * band(sv, -1.0, 0.6, fp))  # a darker plinth
    col = base * tone[:, None]
    mortar = np.where(brick, mortar, 0)[:, None]
    col = col * (1 - mortar) + mortar * np.array([0.52, 0.51, 0.48], f32)
    # windows on a grid of floors and bays (none below 0.9 m): frame, then glass inside it
    above = band(sv, 0.9, 1e4, fp)
    win = pulse(su, pitch, 0.22, 0.78, fp) * pulse(sv, floor_h, 0.30, 0.82, fp) * above
    pane = pulse(su, pitch, 0.26, 0.74, fp) * pulse(sv, floor_h, 0.34, 0.78, fp) * above
    lit = hash01(np.floor(su / pitch), np.floor(sv / floor_h), seed).astype(f32)
    lit = lit + (f32(0.5) - lit) * smoothstep(0.3, 1.0, fp / pitch)  # windows blend once sub-pixel
    cv = sv / floor_h - np.floor(sv / floor_h)
    glass = (np.array([0.15, 0.18, 0.22], f32) + lit[:, None] * np.array([0.25, 0.25, 0.3], f32)) * (
        0.8 + 0.4 * fine
    )[:, None] + (f32(0.25) * (np.clip(cv, 0.3, 0.82) - f32(0.3)) * (1 - smoothstep(0.5, 1.5, fp)))[:, None]
    frame = (win - pane)[:, None]
    return col * (1 - win)[:, None] + f32(0.85) * frame + glass * pane[:, None]


_GROUND_COLOURS = np.array(
    [
        [1.0, 1.0, 1.02],  # 0 asphalt
        [0.95, 0.93, 0.9],  # 1 paving
        [0.35, 0.55, 0.22],  # 2 grass
        [0.75, 0.7, 0.62],  # 3 gravel
    ],
    np.float32,
)


def _ground_colour(scene: StreetScene, x: np.ndarray, z: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Unlit ground colour [n,3] at world points (x, z) with footprint ``fp`` (metres): roads with
    markings, sidewalks with paving, parks. Markings and joints are box-filtered over the footprint."""
    f32 = np.float32
    cfg = scene.config
    rw, sw = f32(cfg.road_half_width), f32(cfg.sidewalk_width)
    tiles = scene.tiles
    # lateral offsets from the nearest street centre lines in both directions
    xs, zs = scene.xs.astype(f32), scene.zs.astype(f32)
    ix = np.clip(np.searchsorted(xs, x), 1, len(xs) - 1)
    dx = np.where(np.abs(x - xs[ix - 1]) < np.abs(x - xs[ix]), x - xs[ix - 1], x - xs[ix])
    iz = np.clip(np.searchsorted(zs, z), 1, len(zs) - 1)
    dz = np.where(np.abs(z - zs[iz - 1]) < np.abs(z - zs[iz]), z - zs[iz - 1], z - zs[iz])
    adx, adz = np.abs(dx), np.abs(dz)
    on_z, on_x = adx < rw, adz < rw
    road = on_z | on_x
    walk = ~road & ((adx < rw + sw) | (adz < rw + sw))
    asphalt = tiles["asphalt"].sample(x, z, 30.0, fp)
    fine = tiles["fine"].sample(x, z, 60.0, fp)
    kind = np.full(len(x), 3, np.int8)
    tone = f32(0.45) + f32(0.3) * asphalt
    r = np.nonzero(road)[0]
    if len(r):
        paint = _road_markings(rw, fp[r], x[r], z[r], dx[r], dz[r], on_z[r], on_x[r])
        coarse = tiles["coarse"].sample(x[r], z[r], 2.0, fp[r])
        asph = f32(0.22) + f32(0.25) * asphalt[r] + f32(0.08) * coarse
        tone[r] = asph * (1 - paint) + (f32(0.78) + f32(0.15) * fine[r]) * paint
        kind[r] = 0
    # sidewalks: 0.5 m paving slabs with dark joints, and a kerb stone
    w = np.nonzero(walk)[0]
    if len(w):
        tone[w] = _sidewalk_tone(rw, fp[w], x[w], z[w], adx[w], adz[w], fine[w])
        kind[w] = 1
    # inside the blocks: grass in parks, gravel elsewhere
    inner = np.nonzero(~road & ~walk)[0]
    if len(inner) and scene.park_blocks.any():
        bi = np.clip(np.searchsorted(scene.xs, x[inner]) - 1, 0, len(scene.xs) - 2)
        bj = np.clip(np.searchsorted(scene.zs, z[inner]) - 1, 0, len(scene.zs) - 2)
        park = inner[scene.park_blocks[bi, bj]]
        kind[park] = 2
        tone[park] = f32(0.35) + f32(0.5) * tiles["leaves"].sample(x[park], z[park], 25.0, fp[park])
    return _GROUND_COLOURS[kind] * tone[:, None]


def _road_markings(rw, fr, xr, zr, dxr, dzr, oz, ox) -> np.ndarray:
    """Paint coverage [n] in [0, 1] at road points: dashed centre lines, solid edge lines and zebra
    crossings before the intersections. ``dxr``/``dzr`` are the offsets from the nearest centre lines,
    ``oz``/``ox`` whether the point is on a street along z / x, ``fr`` the footprint (metres)."""
    f32 = np.float32
    axr, azr = np.abs(dxr), np.abs(dzr)
    cross = oz & ox
    centre_z = np.where(oz & ~cross, band(dxr, -0.08, 0.08, fr) * pulse(zr, f32(6), 0.0, 0.5, fr), 0)
    centre_x = np.where(ox & ~cross, band(dzr, -0.08, 0.08, fr) * pulse(xr, f32(6), 0.0, 0.5, fr), 0)
    edge_z = np.where(oz & ~ox, band(axr, rw - 0.42, rw - 0.28, fr), 0)
    edge_x = np.where(ox & ~oz, band(azr, rw - 0.42, rw - 0.28, fr), 0)
    zebra_z = np.where(oz, band(azr, rw + 0.5, rw + 3.5, fr) * pulse(dxr, f32(1.2), 0.0, 0.5, fr), 0)
    zebra_x = np.where(ox, band(axr, rw + 0.5, rw + 3.5, fr) * pulse(dzr, f32(1.2), 0.0, 0.5, fr), 0)
    return np.clip(centre_z + centre_x + edge_z + edge_x + zebra_z + zebra_x, 0, 1)


def _sidewalk_tone(rw, fw, su, sv, adx, adz, fine) -> np.ndarray:
    """Grey level [n] of sidewalk points: 0.5 m paving slabs with dark joints, and a kerb stone."""
    f32 = np.float32
    joint = 1 - (1 - pulse(su, f32(0.5), 0.0, 0.04, fw)) * (1 - pulse(sv, f32(0.5), 0.0, 0.04, fw))
    detail = 1 - smoothstep(0.15, 0.5, fw)
    slab = 0.61 + (0.12 * hash01(np.floor(su / 0.5), np.floor(sv / 0.5), 7) - 0.06).astype(f32) * detail
    slab = slab + 0.15 * (fine - 0.5)
    slab = slab * (1 - joint) + f32(0.38) * joint
    kerb = np.clip(band(adx, rw - 0.18, rw + 0.18, fw) + band(adz, rw - 0.18, rw + 0.18, fw), 0, 1)
    return slab * (1 - kerb) + (f32(0.7) + f32(0.1) * fine) * kerb
