"""Datasets, loaders and synthetic scenes.

The files of the format (:mod:`.io`) and its directory layout (:mod:`.format`), split files
(:mod:`.splits`), samples (:mod:`.sample`) and their augmentation (:mod:`.augment`), static-frame removal
(:mod:`.static`), a dataset's snippets (:mod:`.index`), the datasets (:mod:`.dataset`, :mod:`.strips`), resampling into a cylinder
(:mod:`.convert`) and synthetic data (:mod:`.synth`).
"""

from .augment import AugmentConfig
from .dataset import SampleOptions, SequenceDataset
from .format import DatasetWarning, SequenceInfo, SequenceWriter, scan_dataset
from .index import SnippetIndex, build_index
from .io import (
    DatasetError,
    atomic_write_bytes,
    load_depth,
    load_image,
    load_mask,
    read_tum,
    save_depth,
    save_png,
    write_tum,
)
from .sample import NUM_SCALES, build_sample, camera_class, camera_of, intrinsics_pyramid
from .splits import make_splits, read_split, snippet_offsets, split_path
from .static import StaticFilter
from .strips import StripDataset, read_cam_txt

__all__ = [
    "NUM_SCALES",
    "AugmentConfig",
    "DatasetError",
    "DatasetWarning",
    "SampleOptions",
    "SequenceDataset",
    "SequenceInfo",
    "SequenceWriter",
    "SnippetIndex",
    "StaticFilter",
    "StripDataset",
    "atomic_write_bytes",
    "build_index",
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
