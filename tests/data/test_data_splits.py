import numpy as np
import pytest

from cylsfm import CylindricalCamera
from cylsfm.data import (
    DatasetError,
    SequenceDataset,
    SequenceWriter,
    build_index,
    make_splits,
    read_split,
    scan_dataset,
)
from cylsfm.data.splits import split_targets
from cylsfm.errors import InputError

W, H = 32, 8


def write_seq(path, n):
    w = SequenceWriter(path, CylindricalCamera.full(W, H), compress_level=0)
    rng = np.random.default_rng(n)
    for _ in range(n):
        w.add_frame(rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
    w.finish()


def snippet_frames(entries, seq_length, stride):
    k = (seq_length - 1) // 2
    out = set()
    for seq, stem in entries:
        t = int(stem)
        out.update((seq, t + o * stride) for o in range(-k, k + 1))
    return out


def test_sequence_mode(tmp_path):
    for i in range(7):
        write_seq(tmp_path / f"seq_{i:03d}", 6)
    paths = make_splits(tmp_path, mode="sequence", seed=3)
    assert set(paths) == {"train", "val", "test"}
    assert paths["val"] == tmp_path / "splits" / "default" / "val.txt"
    parts = {k: read_split(p, tmp_path) for k, p in paths.items()}
    seqs = {k: {s for s, _ in v} for k, v in parts.items()}
    assert all(seqs[k] for k in seqs), seqs  # every part gets at least one sequence
    assert sum(len(v) for v in seqs.values()) == 7
    assert not (seqs["train"] & seqs["val"] or seqs["train"] & seqs["test"] or seqs["val"] & seqs["test"])
    # all frames with a full snippet, none at the borders
    assert sum(len(v) for v in parts.values()) == 7 * 4
    assert all(1 <= int(f) <= 4 for v in parts.values() for _, f in v)
    again = make_splits(tmp_path, name="again", mode="sequence", seed=3)
    assert all(
        again[k].read_text().split("\n", 1)[1] == paths[k].read_text().split("\n", 1)[1] for k in paths
    )
    other = make_splits(tmp_path, name="other", mode="sequence", seed=4)
    assert any(other[k].read_text() != paths[k].read_text() for k in paths)


def test_sequence_mode_with_few_sequences(tmp_path):
    write_seq(tmp_path / "a", 5)
    write_seq(tmp_path / "b", 5)
    parts = {k: read_split(p, tmp_path) for k, p in make_splits(tmp_path).items()}
    assert len({s for s, _ in parts["train"]}) == 1 and parts["train"]
    assert len({s for s, _ in parts["val"] + parts["test"]}) == 1


@pytest.mark.parametrize("seq_length, stride", [(3, 1), (5, 2)])
def test_frame_mode_follows_the_papers_rule(tmp_path, seq_length, stride):
    write_seq(tmp_path / "a", 80)
    write_seq(tmp_path / "b", 50)
    paths = make_splits(
        tmp_path, mode="frame", fractions=(0.9, 0.05, 0.05), seed=1, seq_length=seq_length, stride=stride
    )
    parts = {k: read_split(p, tmp_path) for k, p in paths.items()}
    assert all(parts.values())
    train = snippet_frames(parts["train"], seq_length, stride)
    val = snippet_frames(parts["val"], seq_length, stride)
    test = snippet_frames(parts["test"], seq_length, stride)
    # no frame of a test or validation snippet is used in training as a target or a source
    assert not train & test
    assert not train & val
    assert not val & test
    reach = (seq_length - 1) // 2 * stride
    n_cand = 80 + 50 - 4 * reach
    assert len(parts["test"]) == round(0.05 * n_cand) and len(parts["val"]) == round(0.05 * n_cand)
    # the snippets a dataset forms from the split obey the rule too
    ds = SequenceDataset(build_index(tmp_path, seq_length=seq_length, stride=stride, split="train"))
    used = {(seq, int(f)) for i in range(len(ds)) for seq, frames in [ds.snippet(i)] for f in frames}
    assert used == train and not used & (val | test)
    assert len(ds) == len(parts["train"])


def test_read_split_validation(tmp_path):
    write_seq(tmp_path / "seq_a", 4)
    good = tmp_path / "good.txt"
    good.write_text("# comment\n\nseq_a 000001  # trailing\nseq_a 000002\n")
    assert read_split(good, tmp_path) == [("seq_a", "000001"), ("seq_a", "000002")]
    bad_lines = {
        "seq_b 000001": "unknown sequence",
        "seq_a 000009": "unknown frame",
        "seq_a": "expected",
        "../seq_a 000001": "leave the dataset root",
        "/abs 000001": "leave the dataset root",
        "seq_a ../images/000001": "leave the dataset root",
        ".. 000001": "leave the dataset root",
    }
    for line, problem in bad_lines.items():
        path = tmp_path / "bad.txt"
        path.write_text("seq_a 000001\n" + line + "\n")
        with pytest.raises(DatasetError, match=problem) as info:
            read_split(path, tmp_path)
        assert f"{path}:2:" in str(info.value)
    with pytest.raises(DatasetError, match="not found"):
        read_split(tmp_path / "nope.txt", tmp_path)
    with pytest.raises(DatasetError, match="cannot read"):
        read_split(tmp_path, tmp_path)  # a directory


def test_dataset_with_split_files(tmp_path):
    write_seq(tmp_path / "seq_a", 6)
    split = tmp_path / "mine.txt"
    split.write_text("seq_a 000003\nseq_a 000001\n")
    ds = SequenceDataset(build_index(tmp_path, split=split))
    assert ds.targets() == [("seq_a", "000003"), ("seq_a", "000001")]
    assert ds[0]["frame"] == "000003"
    # a target without a full snippet is skipped with a warning
    split.write_text("seq_a 000000\nseq_a 000002\n")
    with pytest.warns(UserWarning, match="1 of 2 targets"):
        ds = SequenceDataset(build_index(tmp_path, split=split))
    assert ds.targets() == [("seq_a", "000002")]
    with pytest.raises(DatasetError, match="cylsfm split"):
        SequenceDataset(build_index(tmp_path, split="train"))
    make_splits(tmp_path, name="x", fractions=(1.0, 0.0, 0.0))
    assert len(SequenceDataset(build_index(tmp_path, split="train", split_name="x"))) == 4
    # what a split means: a part of a named split, or a file
    seqs = scan_dataset(tmp_path)
    path, targets = split_targets(tmp_path, "train", seqs, "x")
    assert path == tmp_path / "splits" / "x" / "train.txt" and targets == [
        ("seq_a", f"{i:06d}") for i in range(1, 5)
    ]
    assert split_targets(tmp_path, split, seqs) == (split, [("seq_a", "000000"), ("seq_a", "000002")])


def test_bad_arguments(tmp_path):
    write_seq(tmp_path / "a", 4)
    with pytest.raises(InputError, match="fractions"):
        make_splits(tmp_path, fractions=(0.5, 0.2, 0.2))
    with pytest.raises(InputError, match="mode"):
        make_splits(tmp_path, mode="random")
    with pytest.raises(InputError, match="split name"):
        make_splits(tmp_path, name="../x")
    with pytest.raises(InputError, match="seq_length"):
        make_splits(tmp_path, seq_length=4)
    with pytest.raises(InputError, match="stride"):
        make_splits(tmp_path, stride=0)
