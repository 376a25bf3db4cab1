import math
import os

import numpy as np
import pytest
import torch
from PIL import Image

from cylsfm import CylindricalCamera, PinholeCamera
from cylsfm.data import (
    DatasetError,
    DatasetWarning,
    SequenceWriter,
    atomic_write_bytes,
    load_depth,
    load_image,
    load_mask,
    read_tum,
    save_depth,
    scan_dataset,
    write_tum,
)
from cylsfm.data.synth.room import make_pose
from cylsfm.errors import InputError

W, H = 64, 16


def frames(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(n)]


def write_seq(path, n=4, depth=True, poses=True, mask=False, camera=None, seed=0):
    camera = camera or CylindricalCamera.full(W, H)
    w = SequenceWriter(path, camera)
    imgs = frames(n, seed)
    depths = [np.full((H, W), 1.0 + i, dtype=np.float32) for i in range(n)]
    for img, d in zip(imgs, depths, strict=True):
        w.add_frame(img, d if depth else None)
    c2w = np.stack([make_pose(0.1 * i, 0, 0.2 * i, yaw_deg=5 * i).numpy() for i in range(n)])
    m = np.zeros((H, W), dtype=bool)
    m[: H // 2] = True
    w.finish(c2w if poses else None, mask=m if mask else None)
    return imgs, depths, c2w, m


# ----------------------------------------------------------------------------------------- round trip
def test_round_trip_of_a_sequence(tmp_path):
    imgs, depths, c2w, m = write_seq(tmp_path / "seq_b", n=5, mask=True)
    write_seq(tmp_path / "seq_a", n=3, depth=False, poses=False)
    seqs = scan_dataset(tmp_path)
    assert [s.name for s in seqs] == ["seq_a", "seq_b"]
    a, b = seqs
    assert a.depths is None and a.poses is None and a.mask is None and a.timestamps is None
    assert b.camera == CylindricalCamera.full(W, H) and b.camera.wraps
    assert b.stems == [f"{i:06d}" for i in range(5)]
    assert len(b) == 5 and b.bad == {}
    for i in range(5):
        assert np.array_equal(load_image(b.images[i]), imgs[i])
        d = load_depth(b.depths[i])
        assert d.dtype == np.float32 and np.array_equal(d, depths[i])
    assert b.poses.shape == (5, 4, 4) and np.allclose(b.poses, c2w, atol=1e-12)
    assert np.array_equal(b.timestamps, np.arange(5.0))
    assert np.array_equal(load_mask(b.mask), m.astype(np.float32))
    # no temporary files were left behind
    assert not [p for p in (tmp_path / "seq_b").rglob(".*")]


def test_single_sequence_root(tmp_path):
    write_seq(tmp_path / "only")
    seqs = scan_dataset(tmp_path / "only")
    assert len(seqs) == 1 and seqs[0].name == "only" and len(seqs[0]) == 4


def test_partial_depth_is_per_frame_optional(tmp_path):
    w = SequenceWriter(tmp_path / "s", PinholeCamera.from_fov(W, H, 90))
    for i, img in enumerate(frames(3)):
        w.add_frame(img, np.ones((H, W), np.float32) if i != 1 else None)
    w.finish()
    (seq,) = scan_dataset(tmp_path)
    assert seq.camera.model == "pinhole"
    assert seq.depths[0] is not None and seq.depths[1] is None and seq.depths[2] is not None


def test_writer_writes_camera_last_and_refuses_to_overwrite(tmp_path):
    w = SequenceWriter(tmp_path / "s", CylindricalCamera.full(W, H))
    w.add_frame(frames(1)[0])
    assert not (tmp_path / "s" / "camera.json").exists()
    with pytest.raises(InputError, match=r"uint8 \[16,64,3\]"):
        w.add_frame(np.zeros((H, W + 1, 3), np.uint8))
    with pytest.raises(InputError, match="uint8"):
        w.add_frame(np.zeros((H, W, 3), np.float32))
    w.finish()
    assert (tmp_path / "s" / "camera.json").exists()
    with pytest.raises(DatasetError, match="already holds a sequence"):
        SequenceWriter(tmp_path / "s", CylindricalCamera.full(W, H))
    w2 = SequenceWriter(tmp_path / "s", CylindricalCamera.full(W, H), overwrite=True)
    for img in frames(2, seed=3):
        w2.add_frame(img)
    w2.finish()
    (seq,) = scan_dataset(tmp_path)
    assert len(seq) == 2


def test_mask_in_zero_one_is_stored_white(tmp_path):
    w = SequenceWriter(tmp_path / "s", CylindricalCamera.full(W, H))
    w.add_frame(frames(1)[0])
    m = np.zeros((H, W), np.uint8)
    m[:, :10] = 1
    w.finish(mask=m)
    assert np.asarray(Image.open(tmp_path / "s" / "mask.png")).max() == 255
    assert np.array_equal(load_mask(tmp_path / "s" / "mask.png"), m.astype(np.float32))


# ----------------------------------------------------------------------------------------- TUM
def test_tum_round_trip_with_comments(tmp_path):
    rng = np.random.default_rng(1)
    c2w = []
    for _ in range(6):
        q = rng.normal(size=4)
        t = rng.normal(size=3)
        from cylsfm.geometry import tum_to_mat

        c2w.append(tum_to_mat(torch.tensor([*t, *q], dtype=torch.float64)).numpy())
    c2w = np.stack(c2w)
    times = np.linspace(0.0, 1.0, 6) + 1e9
    path = tmp_path / "poses.txt"
    write_tum(path, times, c2w)
    text = path.read_text()
    path.write_text("# header\n\n" + text.replace("\n", "\n\n", 2))
    t2, c2 = read_tum(path)
    assert np.array_equal(t2, times)
    assert np.allclose(c2, c2w, atol=1e-12)


@pytest.mark.parametrize(
    "line, problem",
    [
        ("0 1 2 3 0 0 0", "expected 8 values"),
        ("0 1 2 3 0 0 0 1 5", "expected 8 values"),
        ("0 1 2 x 0 0 0 1", "not a number"),
        ("0 1 2 nan 0 0 0 1", "non-finite"),
        ("0 1 2 inf 0 0 0 1", "non-finite"),
        ("0 1 2 3 0 0 0 0", "zero quaternion"),
    ],
)
def test_bad_tum_lines_name_file_and_line(tmp_path, line, problem):
    path = tmp_path / "poses.txt"
    path.write_text("# comment\n0 0 0 0 0 0 0 1\n" + line + "\n")
    with pytest.raises(DatasetError, match=problem) as info:
        read_tum(path)
    assert f"{path}:3:" in str(info.value)


def test_write_tum_rejects_non_rigid(tmp_path):
    bad = np.eye(4)[None].repeat(2, 0)
    bad[1, 0, 0] = 2
    with pytest.raises(InputError, match="rigid"):
        write_tum(tmp_path / "p.txt", [0, 1], bad)
    assert not (tmp_path / "p.txt").exists()


# ----------------------------------------------------------------------------------------- files
def test_unreadable_pose_file_names_the_file(tmp_path):
    with pytest.raises(DatasetError, match=r"nope\.txt: pose file not found"):
        read_tum(tmp_path / "nope.txt")
    (tmp_path / "dir.txt").mkdir()
    with pytest.raises(DatasetError, match=r"dir\.txt: cannot read"):
        read_tum(tmp_path / "dir.txt")
    (tmp_path / "latin.txt").write_bytes(b"0 0 0 0 0 0 0 1 # caf\xe9\n")
    with pytest.raises(DatasetError, match=r"latin\.txt: cannot read"):
        read_tum(tmp_path / "latin.txt")


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    path = tmp_path / "f.bin"
    atomic_write_bytes(path, b"old")
    with pytest.raises(TypeError):
        atomic_write_bytes(path, "not bytes")  # type: ignore[arg-type]
    assert path.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["f.bin"]


def test_load_image_converts_modes(tmp_path):
    grey = np.arange(W * H, dtype=np.uint8).reshape(H, W)
    Image.fromarray(grey).save(tmp_path / "g.png")
    out = load_image(tmp_path / "g.png")
    assert out.shape == (H, W, 3) and out.dtype == np.uint8 and np.array_equal(out[..., 1], grey)
    rgba = np.dstack([frames(1)[0], np.full((H, W), 7, np.uint8)])
    Image.fromarray(rgba).save(tmp_path / "a.png")
    assert np.array_equal(load_image(tmp_path / "a.png"), rgba[..., :3])
    Image.fromarray(grey.astype(np.uint16) * 257).save(tmp_path / "g16.png")
    assert np.array_equal(load_image(tmp_path / "g16.png")[..., 0], grey)
    # area resampling
    img = frames(1)[0]
    Image.fromarray(img).save(tmp_path / "c.png")
    half = load_image(tmp_path / "c.png", size=(W // 2, H // 2))
    expect = img.astype(np.float64).reshape(H // 2, 2, W // 2, 2, 3).mean((1, 3))
    assert half.shape == (H // 2, W // 2, 3) and np.abs(half - expect).max() <= 1


def test_load_image_errors_name_the_file(tmp_path):
    with pytest.raises(DatasetError, match="not found") as info:
        load_image(tmp_path / "missing.png")
    assert "missing.png" in str(info.value)
    (tmp_path / "garbage.png").write_bytes(b"this is not a png")
    with pytest.raises(DatasetError, match=r"garbage\.png"):
        load_image(tmp_path / "garbage.png")
    Image.fromarray(frames(1)[0]).save(tmp_path / "trunc.png")
    data = (tmp_path / "trunc.png").read_bytes()
    (tmp_path / "trunc.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=r"trunc\.png"):
        load_image(tmp_path / "trunc.png")


def test_load_depth_checks(tmp_path):
    np.save(tmp_path / "int.npy", np.full((H, W), 3, dtype=np.uint16))
    d = load_depth(tmp_path / "int.npy")
    assert d.dtype == np.float32 and (d == 3).all()
    cases = {
        "ndim.npy": (np.ones((1, H, W), np.float32), "2-D"),
        "nan.npy": (np.where(np.eye(H, W) > 0, np.nan, 1).astype(np.float32), "non-finite"),
        "inf.npy": (np.full((H, W), np.inf, np.float64), "non-finite"),
        "neg.npy": (-np.ones((H, W), np.float32), "negative"),
    }
    for name, (arr, problem) in cases.items():
        np.save(tmp_path / name, arr)
        with pytest.raises(DatasetError, match=problem) as info:
            load_depth(tmp_path / name)
        assert name in str(info.value)
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DatasetError, match=r"obj\.npy"):
        load_depth(tmp_path / "obj.npy")
    with pytest.raises(DatasetError, match=r"nothere\.npy"):
        load_depth(tmp_path / "nothere.npy")
    with pytest.raises(InputError, match="negative"):
        save_depth(tmp_path / "x.npy", -np.ones((H, W)))
    # nearest-neighbour resize keeps unknown (0) pixels exact
    arr = np.zeros((H, W), np.float32)
    arr[:, 1::2] = 5
    np.save(tmp_path / "alt.npy", arr)
    small = load_depth(tmp_path / "alt.npy", size=(W // 2, H // 2))
    assert small.shape == (H // 2, W // 2) and set(np.unique(small)) <= {0.0, 5.0}


def test_load_mask_threshold(tmp_path):
    grey = np.array([[0, 127, 128, 255]], dtype=np.uint8)
    Image.fromarray(grey).save(tmp_path / "m.png")
    assert load_mask(tmp_path / "m.png").tolist() == [[0.0, 0.0, 1.0, 1.0]]


# ----------------------------------------------------------------------------------------- scanning
def test_missing_camera_json(tmp_path):
    write_seq(tmp_path / "good")
    (tmp_path / "bad" / "images").mkdir(parents=True)
    with pytest.raises(DatasetError, match=r"missing camera\.json") as info:
        scan_dataset(tmp_path)
    assert str(tmp_path / "bad" / "camera.json") in str(info.value)


def test_no_sequences_and_bad_camera(tmp_path):
    with pytest.raises(DatasetError, match="no sequences"):
        scan_dataset(tmp_path)
    write_seq(tmp_path / "s")
    (tmp_path / "s" / "camera.json").write_text('{"model": "cylindrical", "width": 64}')
    with pytest.raises(DatasetError, match=r"camera\.json"):
        scan_dataset(tmp_path)


def test_wrong_image_size_names_image_and_sizes(tmp_path):
    write_seq(tmp_path / "s")
    Image.fromarray(np.zeros((H, W + 2, 3), np.uint8)).save(tmp_path / "s" / "images" / "000002.png")
    with pytest.raises(DatasetError) as info:
        scan_dataset(tmp_path)
    msg = str(info.value)
    assert "000002.png" in msg and f"{W + 2}x{H}" in msg and f"{W}x{H}" in msg


def test_corrupt_image_header_and_empty_images(tmp_path):
    write_seq(tmp_path / "s")
    (tmp_path / "s" / "images" / "000001.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(DatasetError, match=r"000001\.png"):
        scan_dataset(tmp_path)
    write_seq(tmp_path / "other" / "t")
    for p in (tmp_path / "other" / "t" / "images").iterdir():
        p.unlink()
    with pytest.raises(DatasetError, match="no images") as info:
        scan_dataset(tmp_path / "other")
    assert str(tmp_path / "other" / "t" / "images") in str(info.value)


def test_pose_count_mismatch(tmp_path):
    write_seq(tmp_path / "s", n=4)
    lines = (tmp_path / "s" / "poses.txt").read_text().splitlines()
    (tmp_path / "s" / "poses.txt").write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(DatasetError, match="3 poses but 4 frames") as info:
        scan_dataset(tmp_path)
    assert "poses.txt" in str(info.value)


def test_depth_problems_found_by_header(tmp_path):
    write_seq(tmp_path / "s")
    np.save(tmp_path / "s" / "depth" / "000001.npy", np.ones((H, W + 1), np.float32))
    with pytest.raises(DatasetError, match=r"000001\.npy"):
        scan_dataset(tmp_path)
    np.save(tmp_path / "s" / "depth" / "000001.npy", np.ones((H, W), np.float32))
    np.save(tmp_path / "s" / "depth" / "000099.npy", np.ones((H, W), np.float32))
    with pytest.raises(DatasetError, match=r"000099\.npy.*without a matching image"):
        scan_dataset(tmp_path)


def test_mask_of_wrong_size(tmp_path):
    write_seq(tmp_path / "s")
    Image.fromarray(np.zeros((H, W // 2), np.uint8)).save(tmp_path / "s" / "mask.png")
    with pytest.raises(DatasetError, match=r"mask\.png"):
        scan_dataset(tmp_path)


def test_skip_bad_drops_frames_with_bad_headers(tmp_path):
    write_seq(tmp_path / "s", n=5)
    Image.fromarray(np.zeros((H + 1, W, 3), np.uint8)).save(tmp_path / "s" / "images" / "000001.png")
    (tmp_path / "s" / "images" / "000003.png").write_bytes(b"junk")
    with pytest.warns(DatasetWarning) as record:
        (seq,) = scan_dataset(tmp_path, skip_bad=True)
    text = " ".join(str(r.message) for r in record)
    assert "000001.png" in text and "000003.png" in text
    assert sorted(seq.bad) == [1, 3] and len(seq) == 5


def test_symlinks_leaving_the_root_are_rejected(tmp_path):
    outside = tmp_path / "outside"
    write_seq(outside / "seq")
    root = tmp_path / "root"
    write_seq(root / "inner")
    link = root / "inner" / "images" / "000009.png"
    link.symlink_to(outside / "seq" / "images" / "000000.png")
    with pytest.raises(DatasetError, match="outside the dataset root") as info:
        scan_dataset(root)
    assert "000009.png" in str(info.value)
    link.unlink()
    (root / "linked").symlink_to(outside / "seq", target_is_directory=True)
    with pytest.raises(DatasetError, match="outside the dataset root"):
        scan_dataset(root)
    (root / "linked").unlink()
    # a link that stays inside is fine
    (root / "inner" / "images" / "000009.png").symlink_to(root / "inner" / "images" / "000000.png")
    (root / "inner" / "poses.txt").unlink()
    (seq,) = scan_dataset(root)
    assert len(seq) == 5


def test_full_panorama_camera_round_trip(tmp_path):
    cam = CylindricalCamera(width=W, height=H, fx=W / (2 * math.pi), cx=W / 2 - 0.25, fy=9.5, cy=7.25)
    write_seq(tmp_path / "s", camera=cam)
    (seq,) = scan_dataset(tmp_path)
    assert seq.camera == cam
