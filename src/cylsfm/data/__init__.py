"""Datasets, loaders and synthetic scenes."""

from .dataset import (
    NUM_SCALES,
    AugmentConfig,
    SequenceDataset,
    StaticFilter,
    build_sample,
    camera_class,
    camera_of,
    intrinsics_pyramid,
)
from .format import (
    DatasetError,
    DatasetWarning,
    SequenceInfo,
    SequenceWriter,
    atomic_write_bytes,
    load_depth,
    load_image,
    load_mask,
    read_tum,
    save_depth,
    save_png,
    scan_dataset,
    write_tum,
)
from .splits import make_splits, read_split, snippet_offsets, split_path
from .strips import StripDataset, read_cam_txt

__all__ = [
    "NUM_SCALES",
    "AugmentConfig",
    "DatasetError",
    "DatasetWarning",
    "SequenceDataset",
    "SequenceInfo",
    "SequenceWriter",
    "StaticFilter",
    "StripDataset",
    "atomic_write_bytes",
    "build_sample",
    "camera_class",
    "camera_of",
    "intrinsics_pyramid",
    "load_depth",
    "load_image",
    "load_mask",
    "make_splits",
    "read_cam_txt",
    "read_split",
    "read_tum",
    "save_depth",
    "save_png",
    "scan_dataset",
    "snippet_offsets",
    "split_path",
    "write_tum",
]
