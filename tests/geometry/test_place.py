"""The place descriptor: exactly invariant to the heading (a roll by any number of columns), different for
different places, the mask's pixels left out, and its inputs checked."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cylsfm.errors import InputError, ShapeError
from cylsfm.geometry import place_descriptor, place_distance, roll_columns


@settings(max_examples=40, deadline=None)
@given(shift=st.integers(min_value=-200, max_value=200), seed=st.integers(0, 2**16))
def test_a_panorama_and_its_roll_have_the_same_descriptor(shift, seed):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(2, 3, 32, 96, generator=g)
    rolled = roll_columns(x, shift, axis=-1)
    a, b = place_descriptor(x), place_descriptor(rolled)
    assert torch.allclose(a, b, atol=1e-5)
    assert float(place_distance(a, b).diagonal().abs().max()) < 1e-5


def test_different_places_differ_and_the_distance_is_one_minus_the_cosine():
    g = torch.Generator().manual_seed(0)
    x = torch.nn.functional.interpolate(torch.rand(3, 3, 4, 12, generator=g), size=(32, 96), mode="bilinear")
    x[1] = x[0] * 0.5 + 0.25  # the same view, darker contrast: nearly the same place
    d = place_descriptor(x)
    assert torch.allclose(d.norm(dim=1), torch.ones(3), atol=1e-5)
    dist = place_distance(d, d)
    assert dist.shape == (3, 3)
    assert float(dist[0, 1]) < 0.05 < float(dist[0, 2])
    assert torch.allclose(dist, 1 - d @ d.T)


def test_the_masked_pixels_are_left_out():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(1, 3, 32, 96, generator=g)
    mask = torch.ones(1, 1, 32, 96)
    mask[..., 24:, 10:40] = 0  # a helmet fixed to the camera
    other = x.clone()
    other[..., 24:, 10:40] = torch.rand(1, 3, 8, 30, generator=g)  # another occluder texture
    assert torch.allclose(place_descriptor(x, mask), place_descriptor(other, mask), atol=1e-6)
    assert not torch.allclose(place_descriptor(x), place_descriptor(other), atol=1e-3)


def test_bad_inputs_are_named():
    with pytest.raises(ShapeError):
        place_descriptor(torch.rand(3, 32, 96))
    with pytest.raises(InputError):
        place_descriptor(torch.rand(1, 3, 4, 96), bands=8)
    with pytest.raises(InputError):
        place_descriptor(torch.rand(1, 3, 32, 16), frequencies=16)
    with pytest.raises(ShapeError):
        place_descriptor(torch.rand(1, 3, 32, 96), torch.ones(1, 1, 16, 96))
