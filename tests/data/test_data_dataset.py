import pickle
import warnings

import numpy as np
import pytest
import torch
from PIL import Image
from torch.utils.data import DataLoader

from cylsfm import CylindricalCamera, PinholeCamera, inverse_warp
from cylsfm.data import (
    AugmentConfig,
    DatasetError,
    DatasetWarning,
    SampleOptions,
    SequenceDataset,
    SequenceWriter,
    SnippetIndex,
    StaticFilter,
    build_index,
    camera_of,
)
from cylsfm.data.synth.room import make_pose, render_room
from cylsfm.errors import InputError
from cylsfm.geometry import relative_pose

W, H = 64, 16
KEYS = {"target", "sources", "intrinsics", "camera_model", "size", "sequence", "frame", "index"}


def random_frames(n, seed=0, w=W, h=H):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(n)]


def write_seq(path, imgs=None, n=5, depth=True, poses=None, mask=False, camera=None, seed=0):
    camera = camera or CylindricalCamera.full(W, H)
    imgs = imgs if imgs is not None else random_frames(n, seed, camera.width, camera.height)
    w = SequenceWriter(path, camera, compress_level=1)
    for i, img in enumerate(imgs):
        w.add_frame(img, np.full((camera.height, camera.width), 1.0 + i, np.float32) if depth else None)
    if poses is True:
        poses = np.stack([make_pose(0.3 * i, 0.0, 0.1 * i, yaw_deg=4 * i).numpy() for i in range(len(imgs))])
    m = None
    if mask:
        m = np.zeros((camera.height, camera.width), bool)
        m[:, : camera.width // 2] = True
    w.finish(poses if poses is not None else None, mask=m)
    return imgs


def as_tensor(img):
    return torch.from_numpy(img).permute(2, 0, 1).float() / 255


# ----------------------------------------------------------------------------------------- samples
def test_sample_contents_and_source_order(tmp_path):
    imgs = write_seq(tmp_path / "s", n=7, poses=True, mask=True)
    ds = SequenceDataset(build_index(tmp_path, seq_length=5))
    assert len(ds) == 3
    s = ds[1]
    assert set(s) == KEYS | {"depth", "pose_gt", "mask"}
    assert s["frame"] == "000003" and s["sequence"] == "s" and s["index"] == 1
    assert s["target"].dtype == torch.float32 and torch.equal(s["target"], as_tensor(imgs[3]))
    assert s["sources"].shape == (4, 3, H, W)
    for k, f in enumerate((1, 2, 4, 5)):
        assert torch.equal(s["sources"][k], as_tensor(imgs[f]))
    assert s["depth"].shape == (1, H, W) and (s["depth"] == 4.0).all()
    assert s["mask"].shape == (1, H, W) and s["mask"][0, 0, 0] == 1 and s["mask"][0, 0, -1] == 0
    c2w = torch.from_numpy(ds.sequences[0].poses)
    for k, f in enumerate((1, 2, 4, 5)):
        assert torch.allclose(s["pose_gt"][k], relative_pose(c2w[3], c2w[f]).float(), atol=1e-6)
    assert s["camera_model"] == "cylindrical" and s["size"] == (W, H)
    # stride 2
    ds2 = SequenceDataset(build_index(tmp_path, seq_length=3, stride=2))
    assert ds2.targets() == [("s", f"{i:06d}") for i in (2, 3, 4)]
    assert ds2.snippet(0) == ("s", ["000000", "000002", "000004"])
    assert torch.equal(ds2[0]["sources"][1], as_tensor(imgs[4]))


def test_intrinsics_pyramid_and_camera_of(tmp_path):
    cam = PinholeCamera(width=64, height=20, fx=30.0, cx=31.0, fy=29.0, cy=9.0)
    write_seq(tmp_path / "s", n=3, camera=cam)
    s = SequenceDataset(build_index(tmp_path))[0]
    assert s["intrinsics"].shape == (4, 4) and s["intrinsics"].dtype == torch.float32
    for scale, (w, h) in enumerate([(64, 20), (32, 10), (16, 5), (8, 3)]):
        ref = cam.resized(w, h)
        assert s["intrinsics"][scale].tolist() == pytest.approx([ref.fx, ref.cx, ref.fy, ref.cy], rel=1e-6)
        got = camera_of(s, scale)
        assert got.model == "pinhole" and got.size == (w, h) and got.cx == pytest.approx(ref.cx)
    batch = next(iter(DataLoader(SequenceDataset(build_index(tmp_path)), batch_size=1)))
    bc = camera_of(batch, 1)
    assert bc.size == (32, 10) and bc.fx.shape == (1,) and float(bc.fx[0]) == pytest.approx(15.0)


def test_resize(tmp_path):
    imgs = write_seq(tmp_path / "s", n=3, mask=True)
    ds = SequenceDataset(build_index(tmp_path), SampleOptions(size=(W // 2, H // 2)))
    s = ds[0]
    expect = imgs[1].astype(np.float64).reshape(H // 2, 2, W // 2, 2, 3).mean((1, 3)) / 255
    assert np.abs(s["target"].permute(1, 2, 0).numpy() - expect).max() <= 1 / 255 + 1e-6
    assert s["sources"].shape == (2, 3, H // 2, W // 2) and s["depth"].shape == (1, H // 2, W // 2)
    assert s["mask"].shape == (1, H // 2, W // 2)
    cam = camera_of(s)
    ref = CylindricalCamera.full(W, H).resized(W // 2, H // 2)
    assert cam.wraps and cam.cx == pytest.approx(ref.cx) and cam.fy == pytest.approx(ref.fy)


def test_keys_are_those_of_every_sample(tmp_path):
    write_seq(tmp_path / "a", n=3, poses=True, mask=True)
    write_seq(tmp_path / "b", n=3, depth=False, seed=1)
    ds = SequenceDataset(build_index(tmp_path))
    batch = next(iter(DataLoader(ds, batch_size=2)))
    assert set(batch) == KEYS | {"depth", "mask"}  # b has no poses: no pose_gt anywhere
    assert (ds[1]["depth"] == 0).all() and (ds[1]["mask"] == 1).all()
    assert set(SequenceDataset(build_index(tmp_path), SampleOptions(ground_truth=False))[0]) == KEYS | {
        "mask"
    }
    # only sequences actually used decide the keys
    split = tmp_path / "a_only.txt"
    split.write_text("a 000001\n")
    assert "pose_gt" in SequenceDataset(build_index(tmp_path, split=split))[0]


def test_sizes_must_agree_without_resize(tmp_path):
    write_seq(tmp_path / "a", n=3)
    write_seq(tmp_path / "b", n=3, camera=CylindricalCamera.full(2 * W, 2 * H))
    with pytest.raises(DatasetError, match="differ in image size"):
        SequenceDataset(build_index(tmp_path))
    ds = SequenceDataset(build_index(tmp_path), SampleOptions(size=(W, H)))
    assert ds[1]["target"].shape == (3, H, W)


def test_bad_arguments(tmp_path):
    write_seq(tmp_path / "s", n=3, camera=PinholeCamera.from_fov(W, H, 90))
    # invalid argument values are the project's own error (the CLI reports them), and still ValueErrors
    with pytest.raises(InputError, match="seq_length"):
        SequenceDataset(build_index(tmp_path, seq_length=2))
    with pytest.raises(InputError, match="mirror_prob"):
        AugmentConfig(mirror_prob=2.0)
    with pytest.raises(InputError, match="static filter"):
        StaticFilter(method="magic")
    for size in ((0, H), (W, 2.5), (W,)):
        with pytest.raises(InputError, match="size"):
            SequenceDataset(build_index(tmp_path), SampleOptions(size=size))
    with pytest.raises(InputError, match="camera model"):
        camera_of({**SequenceDataset(build_index(tmp_path))[0], "camera_model": "fisheye"})
    assert issubclass(InputError, ValueError)
    with pytest.raises(DatasetError, match=r"poses\.txt"):
        SequenceDataset(build_index(tmp_path, static=StaticFilter(method="poses")))


# ----------------------------------------------------------------------------------------- bad input
def test_bad_inputs_name_the_file(tmp_path):
    write_seq(tmp_path / "s", n=4, poses=True)
    (tmp_path / "s" / "camera.json").rename(tmp_path / "camera.bak")
    with pytest.raises(DatasetError, match=r"missing camera\.json"):
        SequenceDataset(build_index(tmp_path))
    (tmp_path / "camera.bak").rename(tmp_path / "s" / "camera.json")

    img = tmp_path / "s" / "images" / "000002.png"
    good = img.read_bytes()
    Image.fromarray(np.zeros((H, W - 1, 3), np.uint8)).save(img)
    with pytest.raises(DatasetError, match=r"000002\.png"):
        SequenceDataset(build_index(tmp_path))
    img.write_bytes(good[: len(good) // 2])  # header intact, pixels truncated
    ds = SequenceDataset(build_index(tmp_path))
    with pytest.raises(DatasetError, match=r"000002\.png"):
        ds[0]
    img.write_bytes(good)

    np.save(tmp_path / "s" / "depth" / "000001.npy", np.full((H, W), np.nan, np.float32))
    ds = SequenceDataset(build_index(tmp_path))
    with pytest.raises(DatasetError, match=r"000001\.npy.*non-finite"):
        ds[0]
    np.save(tmp_path / "s" / "depth" / "000001.npy", np.ones((H, W), np.float32))

    poses = tmp_path / "s" / "poses.txt"
    poses.write_text("\n".join(poses.read_text().splitlines()[:-1]) + "\n")
    with pytest.raises(DatasetError, match=r"poses\.txt.*3 poses but 4 frames"):
        SequenceDataset(build_index(tmp_path))


def test_skip_bad_at_scan_time(tmp_path):
    write_seq(tmp_path / "s", n=7)
    Image.fromarray(np.zeros((H + 2, W, 3), np.uint8)).save(tmp_path / "s" / "images" / "000002.png")
    with pytest.raises(DatasetError, match=r"000002\.png"):
        SequenceDataset(build_index(tmp_path))
    with pytest.warns(DatasetWarning, match=r"000002\.png"):
        ds = SequenceDataset(build_index(tmp_path, skip_bad=True))
    # frames 0-1 and 3-6 are separate runs: no snippet bridges the bad frame
    assert [ds.snippet(i)[1] for i in range(len(ds))] == [
        ["000003", "000004", "000005"],
        ["000004", "000005", "000006"],
    ]


def test_skip_bad_at_load_time_replaces_the_sample(tmp_path):
    write_seq(tmp_path / "s", n=7)
    img = tmp_path / "s" / "images" / "000004.png"
    img.write_bytes(img.read_bytes()[:200])  # header intact, pixels truncated
    np.save(tmp_path / "s" / "depth" / "000001.npy", -np.ones((H, W), np.float32))
    # snippets: 0 = (0,1,2), 1 = (1,2,3), 2 = (2,3,4), 3 = (3,4,5), 4 = (4,5,6)
    ds = SequenceDataset(build_index(tmp_path, skip_bad=True))
    assert len(ds) == 5  # the headers are fine
    with pytest.warns(DatasetWarning, match=r"000001\.npy"):
        assert ds[0]["index"] == 1  # the target's depth is bad: the next sample
    with pytest.warns(DatasetWarning, match=r"000004\.png"):
        assert ds[2]["index"] == 1  # 2, 3, 4 hold frame 4, 0 has the bad depth: wraps round to 1
    # deterministic, and known bad samples are skipped without decoding (or warning) again
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert [ds[i]["index"] for i in range(5)] == [1, 1, 1, 1, 1]
    # the loader never crashes
    assert len(list(DataLoader(ds, batch_size=2))) == 3


@pytest.mark.parametrize("resize", [None, (32, 8)])
def test_frame_cache_gives_the_same_samples(tmp_path, resize):
    """Frames decoded once (cache) give bit-identical samples, augmented ones included, to decoding each
    time; a frame that fails to decode still fails where it is used, naming the file."""
    write_seq(tmp_path / "a", n=6, poses=True, mask=True, seed=1)
    write_seq(tmp_path / "b", n=5, seed=2)
    aug = AugmentConfig()
    plain = SequenceDataset(build_index(tmp_path), SampleOptions(size=resize, augment=aug))
    cached = SequenceDataset(build_index(tmp_path), SampleOptions(size=resize, augment=aug, cache=True))
    assert plain.frame_cache is None and cached.frame_cache is not None
    assert len(cached.frame_cache.frames) == 11  # every frame once
    for i in range(len(plain)):
        torch.manual_seed(i)
        a = plain[i]
        torch.manual_seed(i)
        b = cached[i]
        assert a.keys() == b.keys()
        for k in a:
            if isinstance(a[k], torch.Tensor):
                assert torch.equal(a[k], b[k]), k
            else:
                assert a[k] == b[k], k
    assert (
        SequenceDataset(build_index(tmp_path), SampleOptions(cache="auto")).frame_cache is not None
    )  # a few KiB always fit
    img = tmp_path / "b" / "images" / "000003.png"
    img.write_bytes(img.read_bytes()[:200])
    broken = SequenceDataset(
        build_index(tmp_path), SampleOptions(cache=True)
    )  # decoding errors wait for the sample that uses them
    with pytest.raises(DatasetError, match=r"000003\.png"):
        broken[len(broken) - 1]
    with pytest.raises(InputError, match="cache"):
        SequenceDataset(build_index(tmp_path), SampleOptions(cache="always"))


# ----------------------------------------------------------------------------------------- static frames
def test_static_frames_removed_by_poses(tmp_path):
    xs = [0.0, 0.0, 0.1, 0.1, 0.2, 0.21, 0.3, 0.4]
    poses = np.stack([make_pose(x, 0, 0).numpy() for x in xs])
    write_seq(tmp_path / "s", n=len(xs), poses=poses)
    for method in ("poses", "auto"):
        ds = SequenceDataset(build_index(tmp_path, static=StaticFilter(method=method, min_translation=0.05)))
        snippets = [[int(f) for f in ds.snippet(i)[1]] for i in range(len(ds))]
        assert snippets == [[0, 2, 4], [2, 4, 6], [4, 6, 7]]
        s = ds[0]
        assert torch.allclose(s["pose_gt"][1][:3, 3], torch.tensor([-0.1, 0.0, 0.0]), atol=1e-6)
    assert len(SequenceDataset(build_index(tmp_path))) == len(xs) - 2


def test_static_frames_removed_by_image_difference(tmp_path):
    a, b, c, d = random_frames(4, seed=5)
    write_seq(tmp_path / "s", imgs=[a, a, b, b, c, d])
    ds = SequenceDataset(build_index(tmp_path, static=StaticFilter(method="auto")))
    assert [[int(f) for f in ds.snippet(i)[1]] for i in range(len(ds))] == [[0, 2, 4], [2, 4, 5]]
    with pytest.warns(DatasetWarning, match="no samples"):
        ds = SequenceDataset(build_index(tmp_path, static=StaticFilter(method="image", min_image_diff=0.5)))
    assert len(ds) == 0


# ----------------------------------------------------------------------------------------- augmentation
@pytest.fixture(scope="module")
def room_root(tmp_path_factory):
    """A 3-frame sequence of the analytic room: sideways and forward motion with yaw."""
    root = tmp_path_factory.mktemp("room")
    cam = CylindricalCamera.full(128, 32)
    w = SequenceWriter(root / "room", cam, compress_level=1)
    poses = [make_pose(0.25 * i, 0.05 * i, 0.2 * i, yaw_deg=6 * i) for i in range(3)]
    for p in poses:
        img, depth = render_room(cam, p, 2)
        w.add_frame((img[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8), depth[0, 0].numpy())
    w.finish(torch.stack(poses).numpy())
    return root


def warp_ratio(sample, poses=None):
    """Smallest over the sources of (error without warping) / (error of the warped source)."""
    cam = camera_of(sample)
    tgt, depth = sample["target"][None], sample["depth"][None]
    poses = sample["pose_gt"] if poses is None else poses
    ratios = []
    for k in range(sample["sources"].shape[0]):
        src = sample["sources"][k : k + 1]
        warped, valid = inverse_warp(src, depth, poses[k : k + 1], cam)
        m = valid.float()
        assert m.mean() > 0.5
        err = float(((warped - tgt).abs() * m).sum() / m.sum())
        base = float(((src - tgt).abs() * m).sum() / m.sum())
        ratios.append(base / err)
    return min(ratios)


def test_unaugmented_ground_truth_is_consistent(room_root):
    assert warp_ratio(SequenceDataset(build_index(room_root))[0]) > 3


def test_mirror_keeps_geometry_consistent(room_root):
    plain = SequenceDataset(build_index(room_root))[0]
    s = SequenceDataset(
        build_index(room_root), SampleOptions(augment=AugmentConfig(mirror_prob=1.0, color_jitter=False))
    )[0]
    assert torch.equal(s["target"], plain["target"].flip(-1))
    assert torch.equal(s["depth"], plain["depth"].flip(-1))
    assert float(s["intrinsics"][0, 1]) == pytest.approx(127 - 64)
    assert warp_ratio(s) > 3
    # the test can fail: the unmirrored poses do not explain the mirrored images
    assert warp_ratio(s, plain["pose_gt"]) < 2


def test_all_augmentations_together(room_root):
    ds = SequenceDataset(build_index(room_root), SampleOptions(augment=AugmentConfig(mirror_prob=0.5)))
    torch.manual_seed(1)
    for _ in range(4):
        s = ds[0]
        assert 0 <= float(s["target"].min()) and float(s["target"].max()) <= 1
        assert warp_ratio(s) > 3


def test_color_jitter_is_the_same_for_all_frames(tmp_path):
    (a,) = random_frames(1, seed=9)
    write_seq(tmp_path / "s", imgs=[a, a, a])
    ds = SequenceDataset(build_index(tmp_path), SampleOptions(augment=AugmentConfig(mirror=False, hue=0.2)))
    torch.manual_seed(0)
    s = ds[0]
    assert not torch.allclose(s["target"], as_tensor(a), atol=0.01)
    assert torch.equal(s["sources"][0], s["target"]) and torch.equal(s["sources"][1], s["target"])


# ----------------------------------------------------------------------------------------- loading
def test_dataloader_with_workers(tmp_path):
    write_seq(tmp_path / "a", n=6, poses=True, mask=True)
    write_seq(tmp_path / "b", n=6, poses=True, seed=2)
    ds = SequenceDataset(build_index(tmp_path), SampleOptions(augment=AugmentConfig()))
    pickle.loads(pickle.dumps(ds))
    loader = DataLoader(ds, batch_size=4, shuffle=True, num_workers=2)
    seen = []
    for batch in loader:
        assert batch["target"].shape[1:] == (3, H, W) and batch["sources"].shape[1:] == (2, 3, H, W)
        assert batch["pose_gt"].shape[1:] == (2, 4, 4)
        cam = camera_of(batch)
        assert cam.wraps and cam.fx.shape == (batch["target"].shape[0],)
        seen += batch["index"].tolist()
    assert sorted(seen) == list(range(len(ds))) == list(range(8))


def test_an_extra_mask_is_in_every_sample_and_follows_the_mirror(tmp_path):
    """The mask of ``train --mask`` (a helmet at one azimuth): multiplied with each sequence's own mask,
    mirrored with a mirrored sample; a mask of another aspect ratio is refused, naming the file."""
    write_seq(tmp_path / "a", n=4, mask=True)  # its own mask: the left half
    write_seq(tmp_path / "b", n=4, seed=1)
    helmet = np.full((H * 2, W * 2), 255, np.uint8)
    helmet[:, : W // 2] = 0  # the leftmost quarter is the helmet
    Image.fromarray(helmet).save(tmp_path / "helmet.png")
    plain = SequenceDataset(build_index(tmp_path), SampleOptions(mask=tmp_path / "helmet.png"))
    want = torch.ones(1, H, W)
    want[..., : W // 4] = 0
    seqs = [plain.snippet(i)[0] for i in range(len(plain))]
    a, b = plain[seqs.index("a")]["mask"], plain[seqs.index("b")]["mask"]
    torch.testing.assert_close(b, want)
    torch.testing.assert_close(a, want * (torch.arange(W) < W // 2).float())  # with the sequence's own
    mirrored = SequenceDataset(
        build_index(tmp_path),
        SampleOptions(
            mask=tmp_path / "helmet.png", augment=AugmentConfig(mirror_prob=1.0, color_jitter=False)
        ),
    )
    torch.testing.assert_close(mirrored[seqs.index("b")]["mask"], want.flip(-1))
    Image.fromarray(np.full((H, 2 * H), 255, np.uint8)).save(tmp_path / "equirect.png")
    with pytest.raises(DatasetError, match=r"equirect\.png: a .* mask for .* panoramas"):
        SequenceDataset(build_index(tmp_path), SampleOptions(mask=tmp_path / "equirect.png"))


# ----------------------------------------------------------------------------------------- the index
def test_an_index_built_once_serves_every_dataset(tmp_path, monkeypatch):
    """The dataset is scanned, filtered and split once, by build_index; datasets built on the index load
    its snippets in its order, however they load them, without reading the dataset's layout again."""
    write_seq(tmp_path / "a", n=5, poses=True)
    write_seq(tmp_path / "b", n=4, seed=1)
    index = build_index(tmp_path, seq_length=3)
    assert isinstance(index, SnippetIndex) and len(index) == 5 and index.center == 1
    assert index.frames.tolist() == [[0, 1, 2], [1, 2, 3], [2, 3, 4], [0, 1, 2], [1, 2, 3]]
    assert index.owners.tolist() == [0, 0, 0, 1, 1] and index.used == [0, 1]
    assert index.snippet(3) == ("b", ["000000", "000001", "000002"])

    def no_scan(*args, **kwargs):
        raise AssertionError("the dataset scanned again")

    monkeypatch.setattr("cylsfm.data.index.scan_dataset", no_scan)
    plain = SequenceDataset(index)
    small = SequenceDataset(index, SampleOptions(size=(W // 2, H // 2), ground_truth=False, cache=True))
    assert plain.targets() == small.targets() == index.targets()
    assert [plain[i]["frame"] for i in range(len(plain))] == [
        "000001",
        "000002",
        "000003",
        "000001",
        "000002",
    ]
    assert small[4]["target"].shape == (3, H // 2, W // 2) and "depth" not in small[4]
    assert "pose_gt" not in plain[0]  # b has no poses


def test_sample_options_are_checked_where_they_are_made():
    assert SampleOptions(size=(8.0, 4)).size == (8, 4)
    with pytest.raises(InputError, match="size"):
        SampleOptions(size=(0, 4))
    with pytest.raises(InputError, match="cache"):
        SampleOptions(cache="sometimes")
