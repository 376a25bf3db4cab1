"""The loop-finding stage of :func:`cylsfm.odometry`: a tracked ride's loops found
(:mod:`~cylsfm.odometry.loops.detect`), verified (:mod:`~cylsfm.odometry.loops.verify`) and checked
against the odometry (:mod:`~cylsfm.odometry.loops.check`), once for a set of loop settings: the pipeline
keeps the result in the run's state with :attr:`LoopSearch.key`, and other loop settings look again on the
same tracking."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from ...errors import CylsfmError
from ...evaluate.pose_metrics import chain_poses
from ...runtime import fingerprint
from .check import check_loops
from .detect import loop_candidates
from .loop import Loop
from .verify import verify_loops

if TYPE_CHECKING:
    from ..job import Job
    from ..state import State

__all__ = ["LoopSearch", "find_loops"]


@dataclass
class LoopSearch:
    """What the loop-finding stage gave: every verified pair (accepted or not, each with its reason), the
    fingerprint of the loop settings they were found with, and the seconds it took (0 when the state had
    them already: ``fresh`` is then ``False``)."""

    loops: list[Loop]
    key: str
    seconds: float
    fresh: bool


def find_loops(job: Job, state: State, steps: np.ndarray) -> LoopSearch:
    """The ride's loops (see the module docstring).

    Args:
        job: the run (its ride is read again for the candidates' frames).
        state: the tracked ride (place descriptors, median depths) and the loops found before, if any.
        steps: the odometry's consecutive steps ``T_{j->j+1}`` ``[M-1,4,4]``, whose drift bounds where a
            revisit may lie.

    Raises:
        CylsfmError: a candidate's frame that cannot be read again.
    """
    settings = job.settings.loop
    key = fingerprint(asdict(settings))
    if state.loops is not None and state.loop_key == key:
        return LoopSearch(state.loops, key, 0.0, fresh=False)
    t = time.perf_counter()
    c2w = chain_poses(steps)
    reach = np.asarray(state.reach, dtype=np.float64)
    known = np.isfinite(reach)
    fallback = 10 * float(np.median(np.linalg.norm(steps[:, :3, 3], axis=1)))  # no depth: ~ten steps
    reach = np.where(known, reach, float(np.median(reach[known])) if known.any() else fallback)
    pairs = loop_candidates(torch.from_numpy(np.stack(state.places)), settings, c2w, reach)
    images, depth = _frames(job, {i for i, _, _ in pairs} | {j for _, j, _ in pairs})
    found = verify_loops(
        pairs, images.__getitem__, depth.__getitem__, job.view, settings, mask=job.view_mask, c2w=c2w
    )
    found = check_loops(found, c2w, reach, settings)
    return LoopSearch(found, key, time.perf_counter() - t, fresh=True)


def _frames(job: Job, wanted: set[int]) -> tuple[dict[int, torch.Tensor], dict[int, torch.Tensor]]:
    """The views ``[3,h,w]`` and depths ``[1,h,w]`` of frames ``wanted``, read again from the ride."""
    images: dict[int, torch.Tensor] = {}
    for i, rgb in job.ride.pick(wanted):
        images[i] = job.images([rgb])[0].cpu()
    missing = wanted - images.keys()
    if missing:
        raise CylsfmError(
            f"{job.ride.path}: frames {sorted(missing)[:5]} could not be read again for the loops"
        )
    order, depth = sorted(wanted), {}
    batch = job.settings.batch_size
    for n in range(0, len(order), batch):
        chunk = order[n : n + batch]
        d = job.depth(chunk, torch.stack([images[i] for i in chunk]).to(job.predictor.device))
        depth.update(zip(chunk, job.view_of(d).cpu(), strict=True))
    return {i: job.view_of(x) for i, x in images.items()}, depth
