"""Loop closure: the places a ride comes back to, found, verified, checked, and the whole ride optimised
with them.

One module a job, in the order they run:

- :mod:`.settings` -- :class:`LoopSettings`, how loops are looked for and accepted;
- :mod:`.detect` -- candidate pairs by heading-invariant place descriptors, matched along sequences;
- :mod:`.verify` -- each candidate verified by geometry: the visual compass and direct alignment both
  ways;
- :mod:`.check` -- the verified loops checked against the odometry's plausible drift and each other;
- :mod:`.graph` -- the Sim(3) pose graph (GTSAM) that closes the accepted loops;
- :mod:`.search` -- the stage that runs detect, verify and check on a tracked ride;
- :mod:`.loop` -- :class:`Loop` (a verified pair) and :class:`Reason` (why it was or was not accepted, a
  code); :mod:`.store` -- how the run's saved state keeps them.
"""

from .check import check_loops
from .detect import loop_candidates, sequence_distances
from .graph import GraphSettings, close_loops, closed_steps
from .loop import Loop, Reason
from .search import LoopSearch, find_loops
from .settings import LoopSettings
from .store import loops_from_arrays, loops_to_arrays
from .verify import depth_ratio, verify_loops

__all__ = [
    "GraphSettings",
    "Loop",
    "LoopSearch",
    "LoopSettings",
    "Reason",
    "check_loops",
    "close_loops",
    "closed_steps",
    "depth_ratio",
    "find_loops",
    "loop_candidates",
    "loops_from_arrays",
    "loops_to_arrays",
    "sequence_distances",
    "verify_loops",
]
