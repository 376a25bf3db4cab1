"""Typed training configuration: dataclasses, presets, YAML files and command-line overrides.

A run's resolved configuration is saved as ``RUN/config.yaml`` and inside every checkpoint, so that a
checkpoint alone rebuilds its networks and knows the image size and projection it was trained on. It holds
only what the user chose: what a run measures on its data is the checkpoint's run metadata
(:mod:`cylsfm.model.checkpoint`).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from ..atomic import atomic_write_text
from ..errors import InputError, reading
from ..losses import LossConfig

__all__ = [
    "PRESETS",
    "DataConfig",
    "ModelConfig",
    "OptimConfig",
    "SfmConfig",
    "TrainConfig",
    "apply_overrides",
    "config_from_dict",
    "config_metadata",
    "config_to_dict",
    "load_config",
    "preset",
    "resumed_config",
    "save_config",
]


class ConfigError(InputError):
    """A configuration file or override is invalid."""


@dataclass
class DataConfig:
    """Which frames are trained on, at what size, and how they are augmented."""

    root: str = ""
    width: int = 512
    height: int = 128
    seq_length: int = 3
    stride: int = 1
    split: str | None = "train"  # None: every frame; a name (train/val/test) of a split file, or a path
    split_name: str = "default"
    fov: float = 360.0  # horizontal field of view kept (centred crop); < 360 turns wrap-around off
    mirror: bool = True
    color_jitter: bool = True
    static_filter: str = "auto"  # auto | poses | image | none
    min_translation: float = 0.05
    min_image_diff: float = 0.01
    mask: str | None = None  # image of pixels to use (white), e.g. the helmet excluded
    workers: int | None = None  # loader processes; None: 0 on the CPU with cached frames, else 2
    cache: bool | str = "auto"  # frames decoded once and kept in memory (auto: when they fit easily)
    # a folder of the rides' own adjusted geometry (one cylsfm odometry output per ride, named as the ride):
    # the targets of loss.sfm_depth_weight, sfm_pose_weight, sfm_dense_weight and sfm_synthesis (no labels)
    geometry: str | None = None


@dataclass
class ModelConfig:
    """The networks: wrap-around, explainability masks and the pose head."""

    wrap: bool = True
    explainability: bool = False
    # "mean" (the paper's spatial average) | "equivariant" (yaw-equivariant; full panoramas only: it turns
    # each column by its azimuth on the whole circle) | "auto" (equivariant on full panoramas, mean on crops)
    pose_head: str = "mean"
    compass: bool = False  # add the visual compass's yaw to the pose (used on full panoramas only)
    # pose from frame pairs, g(t, s) - g(s, t): no bias, no slot prior once trained
    antisymmetric: bool = False
    # A training scaffold for the antisymmetric pose network (cylsfm.train.scaffold): a learned motion per
    # source slot (the prior that the paper's head learns in its bias) carries the pose alone until step
    # prior_fade_start, then is blended out linearly until step prior_fade_end, after which the pair
    # network alone carries the motion. Meanwhile the pair network is taught the prior's translation (an
    # L1 term of weight prior_distill times the prior's weight). 0 and 0: no scaffold. Used only with
    # model.antisymmetric (the paper's head has its prior in its bias).
    prior_fade_start: int = 0
    prior_fade_end: int = 0
    prior_distill: float = 1.0

    def __post_init__(self) -> None:
        if self.pose_head not in ("mean", "equivariant", "auto"):
            raise ConfigError(
                f"model.pose_head must be 'mean', 'equivariant' or 'auto', got {self.pose_head!r}"
            )
        if self.prior_fade_start < 0 or self.prior_fade_end < 0 or self.prior_distill < 0:
            raise ConfigError(
                "model.prior_fade_start, model.prior_fade_end and model.prior_distill must be >= 0"
            )

    @property
    def scaffold(self) -> bool:
        """Whether the pose network carries a fading slot prior (see ``prior_fade_start``)."""
        return self.antisymmetric and self.prior_fade_end > 0


@dataclass
class OptimConfig:
    lr: float = 2e-4
    beta1: float = 0.9
    beta2: float = 0.999
    weight_decay: float = 0.0


@dataclass
class SfmConfig:
    """Rounds of training from the rides' own geometry (``cylsfm train --sfm-rounds N``; the rounds are run
    by :func:`cylsfm.rounds.train_rounds`, above the odometry): plain training for ``first_share`` of the
    budget, then ``rounds`` times: the odometry with the bundle adjustment over every training ride, and
    training on with the adjusted points and poses as targets (``loss.sfm_*`` set from these).

    Attributes:
        rounds: geometry passes (0: plain self-supervision).
        first_share: the share of the budget (minutes or steps) trained before the first pass.
        depth_weight: ``loss.sfm_depth_weight`` once a ride has its geometry.
        pose_weight: ``loss.sfm_pose_weight``.
        dense_weight: ``loss.sfm_dense_weight``: each frame's depth taught its fusion with its
            neighbours' by the adjusted poses (the odometry then writes every frame's depth; 0: none).
        synthesis: ``loss.sfm_synthesis``: warp with the adjusted poses.
        refine: the odometry's direct alignment before the adjustment (slower, a better start).
    """

    rounds: int = 0
    first_share: float = 0.5
    depth_weight: float = 0.1
    pose_weight: float = 0.1
    dense_weight: float = 0.1
    synthesis: bool = False
    refine: bool = True

    def __post_init__(self) -> None:
        weights = (self.depth_weight, self.pose_weight, self.dense_weight)
        if self.rounds < 0 or not 0 < self.first_share < 1 or min(weights) < 0:
            raise ConfigError(
                "sfm.rounds must be >= 0, sfm.first_share in (0, 1), sfm.depth_weight, sfm.pose_weight and "
                f"sfm.dense_weight >= 0; got {self.rounds}, {self.first_share}, {', '.join(map(str, weights))}"
            )


@dataclass
class TrainConfig:
    """Everything a run needs; ``preset`` names the preset it started from."""

    preset: str = "default"
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    sfm: SfmConfig = field(default_factory=SfmConfig)
    batch_size: int = 4
    max_steps: int = 60000
    minutes: float | None = None  # wall-clock budget; stops (with a checkpoint) when spent
    seed: int = 0
    device: str = "auto"  # auto | cpu | cuda | cuda:N
    amp: bool = True  # networks in bf16/fp16 where native (CUDA; CPUs with AVX-512 BF16 or AMX), else fp32
    channels_last: bool | None = None  # None: where it is faster (CUDA, AVX-512 CPUs; not AVX2 CPUs)
    log_every: int = 25
    image_every: int = 500
    checkpoint_every: int = 2000  # also kept as step_NNNNNNN.pt
    latest_every: int = 200  # latest.pt, overwritten atomically

    def __post_init__(self) -> None:
        if self.batch_size < 1:
            raise ConfigError(f"batch_size must be >= 1, got {self.batch_size}")
        if self.max_steps < 0:
            raise ConfigError(f"max_steps must be >= 0, got {self.max_steps}")
        if self.data.seq_length < 2:
            raise ConfigError(f"data.seq_length must be >= 2, got {self.data.seq_length}")
        if not 0 < self.data.fov <= 360:
            raise ConfigError(f"data.fov must be in (0, 360], got {self.data.fov}")
        self._check_rules()

    def _check_rules(self) -> None:
        """The rules between settings: the one place they are checked."""
        m = self.model
        if m.pose_head == "equivariant" and self.data.fov < 360:
            raise ConfigError(
                "model.pose_head=equivariant needs full 360-degree panoramas (data.fov = 360); "
                "'auto' takes the paper's mean head for crops"
            )
        if m.antisymmetric and m.explainability:
            raise ConfigError(
                "model.antisymmetric has no explainability masks: set model.explainability=false, or "
                "model.antisymmetric=false (--no-antisymmetric) for a one-pass pose network"
            )
        if m.explainability and self.loss.explain_weight > 0 and self.loss.min_reprojection:
            raise ConfigError(
                "model.explainability masks and loss.min_reprojection are alternatives: use one "
                "(loss.min_reprojection=false for the paper's masks)"
            )
        if m.prior_fade_end != 0 and m.prior_fade_start > m.prior_fade_end:
            raise ConfigError(
                "model.prior_fade_start and model.prior_fade_end must satisfy start <= end, got "
                f"{m.prior_fade_start} and {m.prior_fade_end}"
            )

    @property
    def pose_head(self) -> str:
        """The pose head built: ``model.pose_head``, with ``auto`` resolved by the field of view."""
        if self.model.pose_head == "auto":
            return "equivariant" if self.data.fov >= 360 else "mean"
        return self.model.pose_head

    @property
    def wrap(self) -> bool:
        """Wrap-around is used only on full panoramas."""
        return self.model.wrap and self.data.fov >= 360


# ----------------------------------------------------------------------------- presets
def _improved() -> TrainConfig:
    cfg = TrainConfig(preset="improved")
    cfg.loss = LossConfig(
        smooth_weight=0.0,
        image_smooth_weight=1e-3,
        image_smooth_order=1,
        smooth_mean_normalize=True,
        ssim_weight=0.85,
        min_reprojection=True,
        automask=True,
        full_resolution=True,
    )
    return cfg


def _default() -> TrainConfig:
    """The improved recipe with a pose model that measures the motion (RESULTS.md, "A pose network that
    measures the motion"): the visual compass's yaw plus an antisymmetric, yaw-equivariant pair network, trained
    under a slot-prior scaffold that fades out between steps 300 and 800."""
    cfg = _improved()
    cfg.preset = "default"
    cfg.model.compass = True
    cfg.model.antisymmetric = True
    cfg.model.pose_head = "auto"
    cfg.model.prior_fade_start = 300
    cfg.model.prior_fade_end = 800
    return cfg


def _paper_synthia() -> TrainConfig:
    cfg = TrainConfig(preset="paper-synthia")
    cfg.loss = LossConfig(smooth_weight=2.0, explain_weight=0.0)
    cfg.model = ModelConfig(explainability=False)
    cfg.max_steps = 60000
    return cfg


def _paper_headcam() -> TrainConfig:
    cfg = TrainConfig(preset="paper-headcam")
    cfg.loss = LossConfig(smooth_weight=0.0, image_smooth_weight=0.2, image_smooth_order=1)
    cfg.model = ModelConfig(explainability=False)
    cfg.max_steps = 60000
    return cfg


PRESETS = {
    "default": _default,
    "improved": _improved,
    "paper-synthia": _paper_synthia,
    "paper-headcam": _paper_headcam,
}


def preset(name: str) -> TrainConfig:
    """A fresh configuration of the preset ``name`` (see :data:`PRESETS`)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r} (choose from {', '.join(PRESETS)})")
    return PRESETS[name]()


# ----------------------------------------------------------------------------- (de)serialisation
def config_to_dict(cfg: TrainConfig) -> dict[str, Any]:
    """Plain nested dict (YAML- and checkpoint-safe types only)."""
    return asdict(cfg)


def _build(cls: type, data: Any, where: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(str(k) for k in set(data) - set(known))  # YAML keys may be numbers
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)} (known: {', '.join(known)})")
    kwargs = {}
    for name, value in data.items():
        sub = _NESTED.get((cls, name))
        kwargs[name] = _build(sub, value, f"{where}.{name}") if sub else value
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


_NESTED = {
    (TrainConfig, "data"): DataConfig,
    (TrainConfig, "model"): ModelConfig,
    (TrainConfig, "loss"): LossConfig,
    (TrainConfig, "optim"): OptimConfig,
    (TrainConfig, "sfm"): SfmConfig,
}


#: Settings that were measured, not adopted and removed (RESULTS.md, "Rejected options"; the commit
#: below still has them): ``key -> the value that meant "off"``. A configuration that holds the "off"
#: value (every run saved before the removal) loads as before; one that turned the option on is refused.
REMOVED = {
    "data.mirror_exact": False,
    "data.roll": False,
    "data.reverse": False,
    "data.still": 0.0,
    "loss.still_weight": None,  # any value: it weighed data.still's term
    "model.pose_level": 7,
    "model.pose_antipodal": False,
    "model.align_distill": 0.0,
    "model.align_distill_start": None,
    "model.align_distill_terms": None,
    "plain_photometric_steps": 0,
}
REMOVED_AT = "94a2060"


#: What earlier versions recorded in the configuration although the run measured it on its data: now the
#: checkpoint's run metadata. ``key -> its name there``. A configuration that holds one loads without it;
#: :func:`config_metadata` reads its value.
MOVED_TO_METADATA = {"data.vfov_h": "vfov_h"}


def config_metadata(data: Any) -> dict[str, Any]:
    """The run metadata that a configuration saved by an earlier version holds (:data:`MOVED_TO_METADATA`;
    values that were not yet measured, ``None``, are left out)."""
    out = {}
    for key, name in MOVED_TO_METADATA.items():
        node = data
        for part in key.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        if node is not None:
            out[name] = node
    return out


def _drop_removed(data: dict[str, Any], where: str) -> dict[str, Any]:
    """``data`` without the :data:`REMOVED` settings it holds "off" (one held on is a ``ConfigError``) and
    without the run metadata of :data:`MOVED_TO_METADATA`."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    for key in MOVED_TO_METADATA:
        section, name = key.split(".")
        if isinstance(out.get(section), dict):
            out[section].pop(name, None)
    for key, off in REMOVED.items():
        *section, name = key.split(".")
        node = out.get(section[0]) if section else out
        if not isinstance(node, dict) or name not in node:
            continue
        value = node.pop(name)
        if off is not None and value != off:
            raise ConfigError(
                f"{where}: {key}={value!r} is an option that was measured, not adopted and removed "
                f"(RESULTS.md, rejected options; commit {REMOVED_AT} has it): this configuration cannot be "
                "rebuilt by this version"
            )
    return out


def config_from_dict(data: dict[str, Any], where: str = "config", saved: bool = False) -> TrainConfig:
    """Rebuild a :class:`TrainConfig`; unknown keys and invalid values are errors naming ``where``.

    A user's configuration names a preset and the fields to change: missing fields take the preset's
    values. A ``saved`` one (a checkpoint's, a run's ``config.yaml``) lists every field that existed when
    it was written: a missing field is one added since, and takes the dataclass default (the setting
    off), so that old runs rebuild the networks they trained, whatever the presets are today.
    """
    if isinstance(data, dict):
        data = _drop_removed(data, where)
    if saved and isinstance(data, dict):
        base = TrainConfig(preset=str(data.get("preset", "default")))
    else:
        base = preset(data.get("preset", "default")) if isinstance(data, dict) else TrainConfig()
    merged = _merge(config_to_dict(base), data, where)
    return _build(TrainConfig, merged, where)


def _merge(base: dict, update: Any, where: str) -> dict:
    if not isinstance(update, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(update).__name__}")
    out = dict(base)
    for k, v in update.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v, f"{where}.{k}")
        else:
            out[k] = v
    return out


def load_config(path: str | os.PathLike[str], saved: bool = False) -> TrainConfig:
    """Read a YAML configuration (a preset name plus any fields to change; ``saved``: a run's own
    ``config.yaml``, see :func:`config_from_dict`)."""
    path = Path(path)
    with reading(path, ConfigError):
        text = path.read_text()
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not a valid YAML configuration ({exc})") from None
    return config_from_dict(data or {}, where=str(path), saved=saved)


def save_config(cfg: TrainConfig, path: str | os.PathLike[str]) -> None:
    """Write the resolved configuration as YAML, atomically."""
    atomic_write_text(path, yaml.safe_dump(config_to_dict(cfg), sort_keys=False))


def apply_overrides(cfg: TrainConfig, overrides: list[str]) -> TrainConfig:
    """Apply ``key.sub=value`` overrides (values parsed as YAML scalars), returning a new config."""
    data = config_to_dict(cfg)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} is not of the form key=value (e.g. loss.ssim_weight=0.85)")
        key, raw = item.split("=", 1)
        node = data
        parts = key.strip().split(".")
        for p in parts[:-1]:
            if not isinstance(node.get(p), dict):
                raise ConfigError(f"override {item!r}: {p!r} is not a section of the configuration")
            node = node[p]
        if parts[-1] not in node:
            raise ConfigError(f"override {item!r}: unknown key {key!r}")
        try:
            node[parts[-1]] = yaml.safe_load(raw)
        except yaml.YAMLError as exc:
            raise ConfigError(f"override {item!r}: cannot parse the value ({exc})") from None
    return _build(TrainConfig, data, "overrides")


#: Settings a resumed run may change: the budget, the hardware, where the data is, and how often it logs.
#: Everything else would make the resumed run a different run; it keeps its saved value.
RESUMABLE_KEYS = (
    "max_steps",
    "data.geometry",  # a round of training from the rides' own geometry (cylsfm.rounds) sets these
    "loss.sfm_depth_weight",
    "loss.sfm_pose_weight",
    "loss.sfm_dense_weight",
    "loss.sfm_synthesis",
    "minutes",
    "device",
    "data.workers",
    "data.root",
    "log_every",
    "image_every",
    "checkpoint_every",
    "latest_every",
)


def resumed_config(saved: TrainConfig, asked: TrainConfig) -> TrainConfig:
    """The configuration of a resumed run: ``saved`` with the :data:`RESUMABLE_KEYS` of ``asked``; a
    warning names every other setting of ``asked`` that differs and is ignored."""
    saved_d, asked_d = _flatten(config_to_dict(saved)), _flatten(config_to_dict(asked))
    ignored = [
        f"{k} (kept {saved_d.get(k)!r}, asked {v!r})"
        for k, v in asked_d.items()
        if k not in RESUMABLE_KEYS and v != saved_d.get(k)
    ]
    if ignored:
        warnings.warn(
            "a resumed run keeps its configuration; ignored: " + ", ".join(ignored), UserWarning, stacklevel=4
        )
    data = config_to_dict(saved)
    for key in RESUMABLE_KEYS:
        *sections, name = key.split(".")
        node = data
        for section in sections:
            node = node[section]
        node[name] = asked_d[key]
    return config_from_dict(data, where="resumed configuration", saved=True)


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out
