"""Every parser of an untrusted file, fed arbitrary content: the project's own error naming the file (or a
valid result), never a traceback from deep inside, never a path outside the dataset's root."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cylsfm.data.io import read_tum
from cylsfm.data.prepare.rig import load_rig
from cylsfm.data.splits import read_split
from cylsfm.errors import CylsfmError
from cylsfm.geometry import CylindricalCamera, load_camera
from cylsfm.model.config import load_config
from cylsfm.odometry.state import State

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-(10**6), 10**6), st.floats(allow_nan=True), st.text(max_size=12)
)
json_values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=5),
)
CAMERA_KEYS = ["model", "width", "height", "fx", "fy", "cx", "cy", "hfov_deg", "vfov_h"]
camera_like = st.dictionaries(st.sampled_from(CAMERA_KEYS), scalars, max_size=len(CAMERA_KEYS))
GOOD_CAMERA = {
    "model": "cylindrical",
    "width": 64,
    "height": 16,
    "fx": 10.2,
    "cx": 32.0,
    "fy": 8.0,
    "cy": 7.5,
}
# a valid camera with one or two entries spoiled (or not): NaN, infinities, zero, negative, fractional sizes
spoilt = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 0.0, -0.0, 1e-300, 1e300, 2.5]),
    st.integers(-3, 3),
    st.none(),
    st.text(max_size=3),
)
near_camera = st.tuples(
    st.sampled_from(["cylindrical", "pinhole", "equirectangular"]),
    st.dictionaries(st.sampled_from(CAMERA_KEYS[1:7]), spoilt, max_size=2),
).map(lambda m: {**GOOD_CAMERA, "model": m[0], **m[1]})
junk = st.one_of(st.binary(max_size=200), st.text(max_size=200).map(str.encode))


def _write(path: Path, content: bytes | str) -> Path:
    path.write_bytes(content if isinstance(content, bytes) else content.encode("utf-8", "surrogatepass"))
    return path


def _named(exc: CylsfmError, path: Path) -> None:
    assert str(path) in str(exc) or path.name in str(exc), str(exc)


def _reads_or_names(read, path: Path, *args, **kwargs):
    """``read(path, ...)``'s result, or ``None`` after checking that its error is the project's, naming
    ``path``; any other exception fails the test."""
    try:
        return read(path, *args, **kwargs)
    except CylsfmError as exc:
        _named(exc, path)
        return None


def _valid_camera(camera) -> None:
    """What a camera that was read must be: a known model, a size of positive integers, finite intrinsics
    with positive focal lengths, and the same camera again when written and read back."""
    from cylsfm.geometry import Camera

    assert camera.model in ("cylindrical", "pinhole", "equirectangular"), camera
    assert isinstance(camera.width, int) and isinstance(camera.height, int), camera
    assert camera.width >= 1 and camera.height >= 1, camera
    for name in ("fx", "fy", "cx", "cy"):
        assert math.isfinite(float(getattr(camera, name))), f"{name} of {camera}"
    assert float(camera.fx) > 0 and float(camera.fy) > 0, camera
    assert Camera.from_dict(camera.to_dict()) == camera


def test_every_spoilt_entry_of_a_camera_is_refused_or_harmless(tmp_path):
    """Each model's valid camera with each entry in turn made NaN, infinite, zero, negative, fractional,
    tiny or huge (JSON allows NaN and Infinity): an error naming the file, or a camera that is valid."""
    import itertools

    values = [math.nan, math.inf, -math.inf, 0, -1, -0.0, 2.5, 1e-300, 1e300]
    for model, key, value in itertools.product(
        ["cylindrical", "pinhole", "equirectangular"], CAMERA_KEYS[1:7], values
    ):
        path = _write(tmp_path / "camera.json", json.dumps({**GOOD_CAMERA, "model": model, key: value}))
        camera = _reads_or_names(load_camera, path)
        if camera is not None:
            _valid_camera(camera)


@FUZZ
@given(
    content=st.one_of(
        junk, json_values.map(json.dumps), camera_like.map(json.dumps), near_camera.map(json.dumps)
    )
)
def test_camera_json(tmp_path, content):
    path = _write(tmp_path / "camera.json", content)
    camera = _reads_or_names(load_camera, path)
    if camera is not None:
        _valid_camera(camera)


@FUZZ
@given(
    content=st.one_of(
        junk,
        st.lists(st.lists(st.one_of(st.floats(), st.integers(), st.just("x")), max_size=9), max_size=5).map(
            lambda rows: "\n".join(" ".join(str(v) for v in r) for r in rows)
        ),
    )
)
def test_poses_txt(tmp_path, content):
    path = _write(tmp_path / "poses.txt", content)
    try:
        times, c2w = read_tum(path)
    except CylsfmError as exc:
        _named(exc, path)
    else:
        assert np.isfinite(c2w).all() and len(times) == len(c2w)


@FUZZ
@given(
    lines=st.lists(
        st.one_of(
            st.text(max_size=30),
            st.sampled_from(
                ["seq_a 000", "seq_a 001", "../seq_a 000", "/etc passwd", "seq_a ../../x", "seq_a\t000"]
            ),
        ),
        max_size=6,
    )
)
def test_split_files_never_leave_the_root(tmp_path, lines):
    root = tmp_path / "data"
    (root / "seq_a" / "images").mkdir(parents=True, exist_ok=True)
    CylindricalCamera.full(16, 8).to_json(root / "seq_a" / "camera.json")
    for stem in ("000", "001"):
        (root / "seq_a" / "images" / f"{stem}.png").touch()
    path = _write(tmp_path / "split.txt", "\n".join(lines))
    try:
        entries = read_split(path, root)
    except CylsfmError as exc:
        _named(exc, path)
    else:
        for seq, frame in entries:
            assert (root / seq / "images").resolve().is_relative_to(root.resolve()) and "/" not in frame


@FUZZ
@given(
    content=st.one_of(
        junk,
        json_values.map(json.dumps),
        st.sampled_from(["preset: default\nmodel: [1, 2]\n", "0:\n", "data: {1: 2}\n"]),
    )
)
def test_config_yaml(tmp_path, content):
    path = _write(tmp_path / "config.yaml", content)
    for saved in (False, True):
        try:
            load_config(path, saved=saved)
        except CylsfmError as exc:
            _named(exc, path)


@FUZZ
@given(content=st.one_of(junk, json_values.map(json.dumps)))
def test_rig_json(tmp_path, content):
    path = _write(tmp_path / "rig.json", content)
    rig = _reads_or_names(load_rig, path)
    if rig is not None:
        views, frames, _ = rig
        assert views and len({len(f.images) for f in frames} | {len(views)}) == 1
        for frame in frames:
            assert math.isfinite(frame.time)
            assert frame.pose is None or (frame.pose.shape == (4, 4) and np.isfinite(frame.pose).all())
            for file in [*frame.images, *(frame.depths or [])]:
                assert Path(file).resolve().is_relative_to(tmp_path.resolve()), file


@FUZZ
@given(content=st.one_of(junk, st.binary(max_size=60).map(lambda b: b"PK\x03\x04" + b)))
def test_odometry_state_is_started_over_when_unreadable(tmp_path, content):
    path = _write(tmp_path / ".odometry-state.npz", content)
    assert State.load(path, "key") is None


@pytest.mark.parametrize("name", ["camera.json", "poses.txt", "rig.json", "config.yaml"])
def test_a_missing_file_is_named(tmp_path, name):
    reader = {
        "camera.json": load_camera,
        "poses.txt": read_tum,
        "rig.json": load_rig,
        "config.yaml": load_config,
    }
    with pytest.raises(CylsfmError) as info:
        reader[name](tmp_path / name)
    _named(info.value, tmp_path / name)


@FUZZ
@given(content=st.one_of(junk, json_values.map(json.dumps)))
def test_prepare_json(tmp_path, content):
    from cylsfm.data.prepare.sequence import PREPARE_FILE, PreparedSequence

    seq = tmp_path / "seq"
    seq.mkdir(exist_ok=True)
    path = _write(seq / PREPARE_FILE, content)
    try:
        PreparedSequence(seq, CylindricalCamera.full(16, 8), {"size": [16, 8]}, overwrite=False)
    except CylsfmError as exc:
        _named(exc, path)
