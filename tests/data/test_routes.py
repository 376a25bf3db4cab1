"""The synthetic rides that come back (around a block, a figure eight, out and back) and the ones that never
do (a staircase through a town whose buildings look alike): their geometry, and the same town for every
route with ``town_frames``."""

from __future__ import annotations

import numpy as np
import pytest

from cylsfm.data.synth import StreetScene, SynthConfig
from cylsfm.data.synth.prisms import FACADE, PRISM_FIELDS
from cylsfm.errors import InputError
from cylsfm.evaluate.motion import yaw_angle
from cylsfm.geometry import invert

SEED = 12345


def _ride(route: str, frames: int, **kw) -> np.ndarray:
    return StreetScene.generate(SEED, SynthConfig(frames=frames, route=route, town_frames=150, **kw)).c2w


def _steps(c2w: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=1)


@pytest.mark.parametrize(("route", "frames"), [("block", 300), ("eight", 600)])
def test_closed_routes_end_where_they_start(route, frames):
    c2w = _ride(route, frames)
    assert c2w.shape == (frames, 4, 4)
    assert np.linalg.norm(c2w[-1, :3, 3] - c2w[0, :3, 3]) < 0.05
    steps = _steps(c2w)
    assert 0.6 < steps.min() and steps.max() < 1.6  # ridden at about the ride's speed, never standing
    # the heading comes back too (up to the yaw wobble)
    yaw = np.degrees(yaw_angle(invert(c2w[0]) @ c2w[-1]))
    assert abs((yaw + 180) % 360 - 180) < 10


def test_the_eight_passes_its_middle_street_twice_in_the_same_direction():
    c2w = _ride("eight", 600)
    pos = c2w[:, :3, 3]
    n = len(pos)
    same = []
    for j in range(n // 2 + 50, n):
        d = np.linalg.norm(pos[: j - 100] - pos[j], axis=1)
        i = int(np.argmin(d))
        if d[i] < 2.0:
            same.append(abs(np.degrees(yaw_angle(invert(c2w[i]) @ c2w[j]))))
    assert len(same) > 20 and np.median(same) < 10


def test_back_returns_on_the_other_side_of_the_road_facing_the_other_way():
    c2w = _ride("back", 450)
    pos = c2w[:, :3, 3]
    n = len(pos)
    opposite = 0
    for j in range(n // 2 + 60, n):
        d = np.linalg.norm(pos[: n // 2 - 30] - pos[j], axis=1)
        i = int(np.argmin(d))
        if d[i] < 9.0:  # the lanes are 8 m apart
            opposite += abs(abs(np.degrees(yaw_angle(invert(c2w[i]) @ c2w[j]))) - 180) < 15
    assert opposite > 50


def test_stairs_never_pass_a_place_twice():
    pos = _ride("stairs", 400)[:, :3, 3]
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    far_in_time = np.abs(np.arange(len(pos))[:, None] - np.arange(len(pos))[None]) > 50
    assert d[far_in_time].min() > 20.0


def test_every_route_rides_through_the_same_town_and_alike_towns_share_one_facade():
    town = StreetScene.generate(SEED, SynthConfig(frames=150))
    for route in ("block", "stairs"):
        other = StreetScene.generate(SEED, SynthConfig(frames=300, route=route, town_frames=150))
        np.testing.assert_array_equal(other.xs, town.xs)
        for name in PRISM_FIELDS:
            np.testing.assert_array_equal(getattr(other.static, name), getattr(town.static, name))
    alike = StreetScene.generate(SEED, SynthConfig(frames=300, route="stairs", town_frames=150, alike=True))
    facades = alike.static.material == FACADE
    assert facades.sum() > 20
    assert len(np.unique(alike.static.colour[facades], axis=0)) == 1
    assert len(np.unique(alike.static.param[facades][:, :3], axis=0)) == 1
    np.testing.assert_array_equal(alike.static.a, other.static.a)  # the same layout as the plain town
    assert len(np.unique(town.static.colour[town.static.material == FACADE], axis=0)) > 5


def test_a_route_the_town_cannot_fit_is_refused():
    with pytest.raises(InputError, match="frames"):
        _ride("eight", 100)
    with pytest.raises(InputError, match="route must be one of"):
        _ride("spiral", 300)
