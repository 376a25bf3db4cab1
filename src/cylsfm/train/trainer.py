"""The training loop: view synthesis with DispNet and PoseExpNet, on one device or data-parallel.

Plain PyTorch, readable top to bottom (in the spirit of monodepth2): build the data, the networks and the
optimiser, then repeat ``step()``. Every loss term is logged to TensorBoard (``RUN/tb``) and to
``RUN/metrics.jsonl``; images (target, warped sources, photometric error, explainability, disparity)
every ``image_every`` steps. Checkpoints are written atomically (``RUN/checkpoints/latest.pt`` and every
``checkpoint_every`` steps ``step_NNNNNNN.pt``); ``resume`` continues exactly: networks, optimiser, AMP
scaler, step, random states and the data order.

Data parallel: start one process per device with ``torchrun --nproc_per_node N -m cylsfm.cli train ...``
(or several nodes); each process takes its shard of every epoch, gradients are averaged by
``DistributedDataParallel`` (NCCL on GPUs, gloo on CPUs), and rank 0 logs and writes checkpoints.
"""

from __future__ import annotations

import json
import logging
import math
import os
import random
import shutil
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor, nn

from ..data.dataset import AugmentConfig, SampleOptions, SequenceDataset, StaticFilter, camera_of
from ..data.index import build_index
from ..data.strips import StripDataset, is_strip_dataset
from ..errors import CylsfmError
from ..model.build import build_models, upgrade_pose_state
from ..model.checkpoint import dataset_metadata, load_checkpoint, save_checkpoint
from ..model.config import TrainConfig, config_from_dict, config_to_dict, resumed_config, save_config
from ..runtime import autocast_dtype, network_precision, prefers_channels_last, progress_bar
from .distributed import init_distributed
from .objective import Objective, SfMNet, batch_on
from .optim import Adam
from .rng import restore_rng, rng_state
from .sampler import ResumableSampler, SeededDataset
from .scaffold import SlotPriorScaffold
from .stopping import CONTINUE, NON_FINITE, OUT_OF_TIME, SIGNALLED, StopRequests, agree

__all__ = ["NonFiniteLossError", "SfMNet", "Trainer", "train"]

log = logging.getLogger(__name__)


#: What a run writes into its directory: an existing one means the directory holds a run.
_RUN_OUTPUTS = ("checkpoints", "metrics.jsonl", "tb")


#: fp16 steps with overflowing gradients in a row after which training stops (the scaler halves its scale
#: at each, so this many means the overflow is not the scale's).
_MAX_SKIPPED_IN_A_ROW = 50


class NonFiniteLossError(CylsfmError):
    """The loss or the gradients became NaN or infinite; the last good checkpoint is kept."""


class Trainer:
    """Trains the networks of ``cfg`` into ``run_dir`` (see the module docstring)."""

    def __init__(
        self, cfg: TrainConfig, run_dir: str | os.PathLike[str], resume: bool = False, overwrite: bool = False
    ) -> None:
        self.run_dir = Path(run_dir)
        self.dist, self.device = init_distributed(cfg.device)
        state = None
        if not resume:
            self._start_afresh(overwrite)
        if resume:
            ckpt = self.run_dir / "checkpoints" / "latest.pt"
            if not ckpt.exists():
                raise CylsfmError(f"{ckpt}: nothing to resume (no checkpoint in {self.run_dir})")
            state = load_checkpoint(ckpt, map_location="cpu")
            cfg = resumed_config(config_from_dict(state["config"], f"{ckpt} (config)", saved=True), cfg)
        self.cfg = cfg
        self.step = 0
        self._check_size()
        self._seed_everything(cfg.seed + self.dist.rank)

        # ---- data
        self.dataset = self._dataset()
        if len(self.dataset) < cfg.batch_size * self.dist.world:
            raise CylsfmError(
                f"{cfg.data.root}: only {len(self.dataset)} training samples for batch size {cfg.batch_size}"
                f" x {self.dist.world} process(es)"
            )
        if cfg.data.mask and isinstance(self.dataset, StripDataset):
            raise CylsfmError(
                f"{cfg.data.mask}: --mask needs a dataset of format v1 (cylsfm prepare); the strips of the "
                "original SfMLearner code carry no masks"
            )
        # run metadata: what the networks will expect of panoramas given to them later, measured once
        self.dataset_metadata = dataset_metadata(state) if state is not None else {}
        if self.dataset_metadata.get("vfov_h") is None:
            self.dataset_metadata["vfov_h"] = self._vfov_h()

        # ---- networks, the scaffold, the objective and the optimiser
        disp_net, pose_net = build_models(cfg)
        self.scaffold = (
            SlotPriorScaffold(
                cfg.data.seq_length - 1,
                cfg.model.prior_fade_start,
                cfg.model.prior_fade_end,
                cfg.model.prior_distill,
            )
            if cfg.model.scaffold
            else None
        )
        self.model = SfMNet(disp_net, self.scaffold, pose_net).to(self.device)
        self.objective = Objective(cfg.loss, cfg.wrap)
        self.channels_last = (
            prefers_channels_last(self.device) if cfg.channels_last is None else bool(cfg.channels_last)
        )
        if self.channels_last:
            self.model = self.model.to(memory_format=torch.channels_last)
        fused = self.device.type in ("cuda", "cpu")
        self.optimizer = Adam(  # torch's, without copying channels-last weights in its fused update
            self.model.parameters(),
            lr=cfg.optim.lr,
            betas=(cfg.optim.beta1, cfg.optim.beta2),
            weight_decay=cfg.optim.weight_decay,
            fused=fused,
        )
        self.amp_dtype = autocast_dtype(self.device, cfg.amp)
        # fp16 only: the loss is scaled and a step whose gradients overflowed is skipped (and counted)
        self.scaler = torch.amp.GradScaler(self.device.type, enabled=self.amp_dtype == torch.float16)
        self.skipped = 0  # steps skipped for overflowing fp16 gradients, over the whole run
        self._skipped_in_a_row = 0
        if state is not None:
            self._restore(state)
        self.net: nn.Module = self.model
        if self.dist.world > 1:
            ids = [self.device.index] if self.device.type == "cuda" else None
            self.net = nn.parallel.DistributedDataParallel(self.model, device_ids=ids)

        # ---- outputs
        self.writer = None
        if self.dist.main:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            save_config(cfg, self.run_dir / "config.yaml")

    # ------------------------------------------------------------------ set-up helpers
    def _dataset(self) -> SequenceDataset | StripDataset:
        """The training samples: dataset format v1, or the strips prepared for the original SfMLearner code
        (a root with ``train.txt`` and no ``camera.json`` sequences; cylindrical intrinsics in ``cam.txt``)."""
        d = self.cfg.data
        augment = AugmentConfig(mirror=d.mirror, color_jitter=d.color_jitter)
        root = Path(d.root)
        if is_strip_dataset(root):
            if d.geometry:
                raise CylsfmError(
                    f"{root}: the rides' own geometry (data.geometry) needs a dataset of format v1"
                )
            split = d.split or "train"
            return StripDataset(root, split, d.seq_length, "cylindrical", (d.width, d.height), augment)
        static = StaticFilter(d.static_filter, d.min_translation, d.min_image_diff)
        index = build_index(d.root, d.split, d.split_name, d.seq_length, d.stride, static)
        options = SampleOptions(
            size=(d.width, d.height),
            augment=augment,
            ground_truth=False,  # self-supervised: depth and poses are never read
            cache=d.cache,
            mask=d.mask,  # in every sample, so that it follows the mirror
            geometry=d.geometry,  # the rides' own adjusted geometry (no labels), or None
        )
        return SequenceDataset(index, options)

    def _start_afresh(self, overwrite: bool) -> None:
        """Refuse to train over an existing run (its checkpoints and logs) unless asked to start it over;
        then its outputs are removed (by the first process), saying which."""
        done = [p for p in _RUN_OUTPUTS if (self.run_dir / p).exists()]
        if not done:
            return
        if not overwrite:
            raise CylsfmError(
                f"{self.run_dir}: already holds a run ({', '.join(done)}): --resume continues it, --overwrite "
                "starts it again (replacing those)"
            )
        if self.dist.main:
            for name in done:
                path = self.run_dir / name
                shutil.rmtree(path) if path.is_dir() else path.unlink()
            log.info("%s: removed %s of the run started over", self.run_dir, ", ".join(done))

    def _vfov_h(self) -> float | None:
        """The vertical extent ``h`` in ``[-vfov_h, vfov_h]`` of the training panoramas (``None``: not
        cylindrical), recorded so that images given to the network later are fitted to it."""
        cam = camera_of(self.dataset[0])
        if cam.model != "cylindrical":
            return None
        return round((float(cam.cy) + 0.5) / float(cam.fy), 6)

    def _check_size(self) -> None:
        from ..geometry import CylindricalCamera
        from ..nn.layers import check_input_size

        w, h = self.cfg.data.width, self.cfg.data.height
        if self.cfg.data.fov < 360:
            w = CylindricalCamera.full(w, h).crop(self.cfg.data.fov).width
        try:
            check_input_size(w, h, self.cfg.wrap)
        except ValueError as exc:
            raise CylsfmError(
                f"training size {self.cfg.data.width}x{h} (network input {w}x{h}): {exc}"
            ) from None

    @staticmethod
    def _seed_everything(seed: int) -> None:
        random.seed(seed)
        np.random.seed(seed % 2**32)  # noqa: NPY002 - third-party code may draw from the global state
        torch.manual_seed(seed)

    def _loader(self) -> torch.utils.data.DataLoader:
        consumed = self.step * self.cfg.batch_size
        sampler = ResumableSampler(
            len(self.dataset), seed=self.cfg.seed, rank=self.dist.rank, world=self.dist.world, start=consumed
        )
        workers = self.cfg.data.workers
        if workers is None:  # auto: frames decoded once cost the step little on the main process (CPU;
            # BENCHMARKS.md)
            cached = getattr(self.dataset, "frame_cache", None) is not None
            workers = 0 if cached and self.device.type == "cpu" else 2
        return torch.utils.data.DataLoader(
            SeededDataset(self.dataset),
            batch_size=self.cfg.batch_size,
            sampler=sampler,
            num_workers=workers,
            pin_memory=self.device.type == "cuda",
            drop_last=True,
            persistent_workers=workers > 0,
            prefetch_factor=4 if workers > 0 else None,
        )

    # ------------------------------------------------------------------ one step
    def compute_loss(self, sample: dict[str, Any]) -> tuple[Tensor, dict[str, Tensor], dict[str, Any]]:
        """The networks on one loader batch and every loss term (see :mod:`cylsfm.train.objective`)."""
        batch = batch_on(sample, self.device, self.cfg.data.fov, self.channels_last)
        with network_precision(self.device, self.amp_dtype):
            outputs = self.net(*batch.network_inputs(), self.step)
        return self.objective(batch, outputs)

    def train_step(self, batch: dict[str, Any]) -> tuple[dict[str, float], dict[str, Tensor]]:
        self.net.train()
        total, terms, visuals = self.compute_loss(batch)
        finite = bool(torch.isfinite(total))
        if agree(CONTINUE if finite else NON_FINITE, self.dist.world, self.device) == NON_FINITE:
            values = ", ".join(f"{k}={float(v.detach()):.4g}" for k, v in terms.items())
            raise NonFiniteLossError(
                f"non-finite loss at step {self.step + 1} "
                f"({values if not finite else 'in another process'}); the last good checkpoint is kept in "
                f"{self.run_dir / 'checkpoints'}"
            )
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(total).backward()
        self.scaler.unscale_(self.optimizer)  # (a no-op without fp16)
        grad_norm = float(self._grad_norm())  # the same in every process: DDP averaged the gradients
        if not math.isfinite(grad_norm):
            self._overflowed(grad_norm, terms)
        else:
            self._skipped_in_a_row = 0
        self.scaler.step(self.optimizer)  # with fp16, skips the update when the gradients overflowed
        self.scaler.update()
        self.step += 1
        scalars = {k: float(v.detach()) for k, v in terms.items()}
        scalars["grad_norm"] = grad_norm
        if self.scaler.is_enabled():
            scalars["skipped_steps"] = float(self.skipped)
            scalars["loss_scale"] = float(self.scaler.get_scale())
        scalars["translation_norm"] = float(visuals.pop("translation_norm"))
        if self.scaffold is not None:
            scalars["prior_weight"] = self.scaffold.weight_at(self.step - 1)
        return scalars, visuals

    def _grad_norm(self) -> Tensor:
        """The L2 norm of every parameter's gradient together (inf or NaN when one is not finite)."""
        grads = [p.grad for p in self.model.parameters() if p.grad is not None]
        return torch.nn.utils.get_total_norm(grads) if grads else torch.zeros(())

    def _overflowed(self, grad_norm: float, terms: dict[str, Tensor]) -> None:
        """A non-finite gradient: with fp16 the scaler skips the step (stopping only after
        ``_MAX_SKIPPED_IN_A_ROW`` such steps in a row); in fp32 or bf16 training stops before the
        optimiser writes it into the weights, so the last checkpoint stays good."""
        self._skipped_in_a_row += 1
        if self.scaler.is_enabled() and self._skipped_in_a_row < _MAX_SKIPPED_IN_A_ROW:
            self.skipped += 1
            return
        values = ", ".join(f"{k}={float(v.detach()):.4g}" for k, v in terms.items())
        why = f"{self._skipped_in_a_row} fp16 steps in a row" if self.scaler.is_enabled() else "a step"
        raise NonFiniteLossError(
            f"non-finite gradients (norm {grad_norm}) in {why} at step {self.step + 1} ({values}); the "
            f"weights were not updated and the last good checkpoint is kept in {self.run_dir / 'checkpoints'}"
        )

    # ------------------------------------------------------------------ checkpoints
    def state(self) -> dict[str, Any]:
        return {
            "config": config_to_dict(self.cfg),
            "dataset": dict(self.dataset_metadata),
            "step": self.step,
            "disp_net": self.model.disp_net.state_dict(),
            "pose_net": self.model.pose_net.state_dict(),
            **({"scaffold": self.scaffold.state_dict()} if self.scaffold is not None else {}),
            "optimizer": self.optimizer.state_dict(),
            "scaler": self.scaler.state_dict(),
            "skipped_steps": self.skipped,
            "rng": rng_state(),
            "sampler": {"consumed": self.step * self.cfg.batch_size, "seed": self.cfg.seed},
        }

    def _restore(self, state: dict[str, Any]) -> None:
        self.model.disp_net.load_state_dict(state["disp_net"])
        pose, prior = upgrade_pose_state(state["pose_net"], self.cfg.model.antisymmetric)
        self.model.pose_net.load_state_dict(pose)
        if self.scaffold is not None:  # a training checkpoint of an earlier version kept it in the network
            scaffold = state.get("scaffold") or ({"slot_prior": prior} if prior is not None else None)
            if scaffold is None:
                raise CylsfmError(f"{self.run_dir}: the checkpoint has no state of its run's scaffold")
            self.scaffold.load_state_dict(scaffold)
        if "optimizer" in state:
            self.optimizer.load_state_dict(state["optimizer"])
        if state.get("scaler"):
            self.scaler.load_state_dict(state["scaler"])
        self.skipped = int(state.get("skipped_steps", 0))
        self.step = int(state["step"])
        restore_rng(state.get("rng") or {})

    def save(self, keep: bool = False) -> None:
        if not self.dist.main:
            return
        state = self.state()
        save_checkpoint(self.run_dir / "checkpoints" / "latest.pt", state)
        if keep:
            save_checkpoint(self.run_dir / "checkpoints" / f"step_{self.step:07d}.pt", state)

    # ------------------------------------------------------------------ logging
    def _log(self, scalars: dict[str, float], visuals: dict[str, Tensor], rate: float) -> None:
        if not self.dist.main:
            return
        if self.writer is None:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self.writer = SummaryWriter(str(self.run_dir / "tb"))
            except ImportError:  # pragma: no cover - tensorboard is a dependency
                self.writer = False
        row = {"step": self.step, "time": time.time(), "samples_per_s": rate, **scalars}
        with open(self.run_dir / "metrics.jsonl", "a") as fh:
            fh.write(json.dumps(row) + "\n")
        if self.writer:
            for k, v in scalars.items():
                self.writer.add_scalar(
                    f"loss/{k}" if k in ("photometric", "smooth", "explain", "total") else k, v, self.step
                )
            self.writer.add_scalar("samples_per_s", rate, self.step)

    def _log_images(self, visuals: dict[str, Tensor]) -> None:
        if not (self.dist.main and self.writer):
            return
        w = self.writer
        w.add_image("target", visuals["target"][0].clamp(0, 1), self.step)
        if visuals.get("warped") is not None:
            for k in range(visuals["warped"].shape[1]):
                w.add_image(f"warped/source_{k}", visuals["warped"][0, k].clamp(0, 1), self.step)
        if visuals.get("error") is not None:
            e = visuals["error"][0]
            w.add_image("photometric_error", (e / e.max().clamp(min=1e-6)), self.step)
        d = visuals["disparity"][0]
        w.add_image("disparity", (d - d.min()) / (d.max() - d.min()).clamp(min=1e-6), self.step)
        if visuals.get("explainability") is not None:
            for k in range(visuals["explainability"].shape[1]):
                w.add_image(f"explainability/source_{k}", visuals["explainability"][0, k : k + 1], self.step)

    # ------------------------------------------------------------------ the loop
    def fit(self, progress: bool = True) -> dict[str, Any]:
        """Train until ``max_steps`` or the ``minutes`` budget; returns a summary."""
        cfg = self.cfg
        start_step, t0 = self.step, time.monotonic()
        deadline = t0 + cfg.minutes * 60 if cfg.minutes else math.inf
        bar = _Progress(cfg, self.step, progress and self.dist.main)
        self._last_log, self._samples_since = time.monotonic(), 0
        stopped, stops = "max_steps", StopRequests()
        try:
            with stops.installed():
                for batch in self._loader():
                    if self.step >= cfg.max_steps:
                        break
                    mine = (
                        SIGNALLED
                        if stops.signal
                        else OUT_OF_TIME
                        if time.monotonic() >= deadline
                        else CONTINUE
                    )
                    verdict = agree(mine, self.dist.world, self.device)  # every process stops at this step
                    if verdict != CONTINUE:
                        stopped = "minutes" if verdict == OUT_OF_TIME else "interrupted"
                        break
                    scalars, visuals = self.train_step(batch)
                    self._after_step(scalars, visuals)
                    bar.update(self.step, scalars["total"])
        except KeyboardInterrupt:  # a second Ctrl-C: at once, within the step
            stopped = "interrupted"
        finally:
            bar.close()
        if stopped == "interrupted" and self.dist.main:
            why = stops.signal or "a signal to another process"
            warnings.warn(
                f"stopped by {why} at step {self.step}; saving a checkpoint (--resume continues)",
                stacklevel=1,
            )
        if stopped != "max_steps" or self.step > start_step:
            self.save(keep=False)
        if self.writer:
            self.writer.flush()
        note = self.scaffold.unfinished(self.step) if self.scaffold is not None else None
        if note and self.dist.main:
            warnings.warn(note, UserWarning, stacklevel=2)
        return {
            "steps": self.step,
            "stopped": stopped,
            "seconds": time.monotonic() - t0,
            "run_dir": str(self.run_dir),
        }

    def _after_step(self, scalars: dict[str, float], visuals: dict[str, Tensor]) -> None:
        """Log the losses (every ``log_every`` steps and the first), images, and write checkpoints."""
        cfg = self.cfg
        self._samples_since += cfg.batch_size * self.dist.world
        if self.step % cfg.log_every == 0 or self.step == 1:
            now = time.monotonic()
            self._log(scalars, visuals, self._samples_since / max(now - self._last_log, 1e-9))
            self._last_log, self._samples_since = now, 0
        if cfg.image_every and self.step % cfg.image_every == 0:
            self._log_images(visuals)
        keep = cfg.checkpoint_every and self.step % cfg.checkpoint_every == 0
        if keep or (cfg.latest_every and self.step % cfg.latest_every == 0):
            self.save(keep=bool(keep))

    def close(self) -> None:
        if self.writer:
            self.writer.close()
        if self.dist.world > 1 and dist.is_initialized():
            dist.destroy_process_group()


class _Progress:
    """The training progress bar: with a time budget it counts the budget's seconds (so the ETA is the
    budget's end), otherwise steps."""

    def __init__(self, cfg: TrainConfig, step: int, enabled: bool) -> None:
        self.by_time = cfg.minutes is not None
        self.t0 = time.monotonic()
        self.bar = None
        if enabled:
            total = round(cfg.minutes * 60) if self.by_time else cfg.max_steps
            self.bar = progress_bar(total=total, unit="s" if self.by_time else "step", leave=True)
            if not self.by_time:
                self.bar.update(step)

    def update(self, step: int, loss: float) -> None:
        if self.bar is None:
            return
        if self.by_time:
            self.bar.update(min(round(time.monotonic() - self.t0), self.bar.total) - self.bar.n)
            self.bar.set_postfix(step=step, loss=f"{loss:.4f}", refresh=False)
        else:
            self.bar.update(1)
            self.bar.set_postfix(loss=f"{loss:.4f}", refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def train(
    cfg: TrainConfig,
    run_dir: str | os.PathLike[str],
    resume: bool = False,
    progress: bool = True,
    overwrite: bool = False,
) -> dict:
    """Build a :class:`Trainer` and run it (closing TensorBoard and the process group afterwards).
    ``resume`` continues the run in ``run_dir``; without it a run already there is refused unless
    ``overwrite`` starts it again."""
    trainer = Trainer(cfg, run_dir, resume=resume, overwrite=overwrite)
    try:
        return trainer.fit(progress=progress)
    finally:
        trainer.close()
