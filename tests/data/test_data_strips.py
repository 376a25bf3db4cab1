import math

import numpy as np
import pytest
import torch
from PIL import Image

from cylsfm import CylindricalCamera
from cylsfm.data import DatasetError, StripDataset, camera_of
from cylsfm.errors import InputError

FW, FH = 32, 8


def write_strip(root, sub, fid, n=3, seed=0, fx=None, suffix=".png", width=None):
    rng = np.random.default_rng(seed)
    frames = [rng.integers(0, 256, (FH, FW, 3), dtype=np.uint8) for _ in range(n)]
    strip = np.concatenate(frames, axis=1)
    if width is not None:
        strip = strip[:, :width]
    (root / sub).mkdir(parents=True, exist_ok=True)
    Image.fromarray(strip).save(root / sub / f"{fid}{suffix}")
    fx = FW / (2 * math.pi) if fx is None else fx
    (root / sub / f"{fid}_cam.txt").write_text(f"{fx},0.,{FW / 2},0.,3.5,{(FH - 1) / 2},0.,0.,1.\n")
    return frames


def test_strip_is_read_correctly(tmp_path):
    a = write_strip(tmp_path, "drive_01", "0000000005", seed=1)
    b = write_strip(tmp_path, "drive_01", "0000000006", seed=2)
    (tmp_path / "train.txt").write_text("drive_01 0000000005\n# comment\n\ndrive_01 0000000006\n")
    ds = StripDataset(tmp_path, "train", seq_length=3)
    assert len(ds) == 2
    for i, frames in enumerate((a, b)):
        s = ds[i]
        as_float = [torch.from_numpy(f).permute(2, 0, 1).float() / 255 for f in frames]
        assert torch.equal(s["target"], as_float[1])
        assert torch.equal(s["sources"][0], as_float[0]) and torch.equal(s["sources"][1], as_float[2])
        assert s["size"] == (FW, FH) and s["camera_model"] == "cylindrical"
        assert s["sequence"] == "drive_01" and s["frame"] == f"000000000{5 + i}" and s["index"] == i
        assert set(s) == {
            "target",
            "sources",
            "intrinsics",
            "camera_model",
            "size",
            "sequence",
            "frame",
            "index",
        }
    cam = camera_of(ds[0])
    expected = CylindricalCamera(
        width=FW, height=FH, fx=FW / (2 * math.pi), cx=FW / 2, fy=3.5, cy=(FH - 1) / 2
    )
    assert cam.wraps
    for name in ("fx", "cx", "fy", "cy"):
        assert getattr(cam, name) == pytest.approx(getattr(expected, name), rel=1e-6)
    half = camera_of(ds[0], scale=1)
    assert half.size == (FW // 2, FH // 2) and half.cx == pytest.approx(expected.resized(16, 4).cx)


def test_strip_seq_length_5_and_resize(tmp_path):
    frames = write_strip(tmp_path, "s", "f1", n=5)
    (tmp_path / "val.txt").write_text("s f1\n")
    s = StripDataset(tmp_path, "val", seq_length=5, size=(FW // 2, FH // 2))[0]
    assert s["sources"].shape == (4, 3, FH // 2, FW // 2)
    expect = frames[2].astype(np.float64).reshape(FH // 2, 2, FW // 2, 2, 3).mean((1, 3)) / 255
    got = s["target"].permute(1, 2, 0).numpy()
    assert np.abs(got - expect).max() <= 1 / 255 + 1e-6
    # the source order is the strip's order
    first = frames[0].astype(np.float64).reshape(FH // 2, 2, FW // 2, 2, 3).mean((1, 3)) / 255
    assert np.abs(s["sources"][0].permute(1, 2, 0).numpy() - first).max() <= 1 / 255 + 1e-6
    assert camera_of(s).wraps


def test_jpg_strips_and_pinhole(tmp_path):
    write_strip(tmp_path, "s", "f1", fx=20.0, suffix=".jpg")
    (tmp_path / "train.txt").write_text("s f1\n")
    ds = StripDataset(tmp_path, camera_model="pinhole")
    cam = camera_of(ds[0])
    assert cam.model == "pinhole" and cam.fx == pytest.approx(20.0) and not cam.wraps
    with pytest.raises(InputError, match="size"):
        StripDataset(tmp_path, camera_model="pinhole", size=(0, 4))
    with pytest.raises(InputError, match="camera model"):
        StripDataset(tmp_path, camera_model="fisheye")
    with pytest.raises(InputError, match="plain name"):
        StripDataset(tmp_path, split="../train")


def test_bad_strips(tmp_path):
    write_strip(tmp_path, "s", "odd", width=3 * FW - 1)
    (tmp_path / "train.txt").write_text("s odd\n")
    with pytest.raises(DatasetError, match="not a multiple") as info:
        StripDataset(tmp_path)
    assert "odd.png" in str(info.value)
    write_strip(tmp_path, "s", "ok")
    for line in ("../s ok", "/etc ok", "s/.. ok", "s ../ok"):
        (tmp_path / "train.txt").write_text(line + "\n")
        with pytest.raises(DatasetError, match="leave the dataset root") as info:
            StripDataset(tmp_path)
        assert "train.txt:1" in str(info.value)
    (tmp_path / "train.txt").write_text("s ok\ns missing\n")
    with pytest.raises(DatasetError, match="not found") as info:
        StripDataset(tmp_path)
    assert "missing" in str(info.value) and "train.txt:2" in str(info.value)
    (tmp_path / "s" / "ok_cam.txt").unlink()
    (tmp_path / "train.txt").write_text("s ok\n")
    with pytest.raises(DatasetError, match=r"ok_cam\.txt: intrinsics file not found"):
        StripDataset(tmp_path)
    (tmp_path / "s" / "ok_cam.txt").write_bytes(b"\xff\xfe1,0,2\n")
    with pytest.raises(DatasetError, match=r"ok_cam\.txt: cannot read"):
        StripDataset(tmp_path)
    (tmp_path / "s" / "ok_cam.txt").write_text("1,2,3\n")
    with pytest.raises(DatasetError, match=r"ok_cam\.txt.*9"):
        StripDataset(tmp_path)
    with pytest.raises(DatasetError, match=r"val\.txt"):
        StripDataset(tmp_path, "val")
