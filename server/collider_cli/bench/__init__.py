"""``collider bench`` and the error-budget bake: what accuracy costs in time, for one mesh on
this machine.

- :mod:`.plan`: which colliders are compared and how each is built (cached);
- :mod:`.timing`: every (collider, path, device, mode, size) cell timed in interleaved rounds:
  median, spread, process CPU time, unstable figures retimed;
- :mod:`.run`: the measurement run, returning every raw figure as a JSON-ready dict;
- :mod:`.report`: tables, the Pareto front (or why none is called), the error-vs-time PNG, the
  files;
- :mod:`.budget`: an error budget in, the fastest collider that meets it out.

The engine knows nothing of this package; it only calls the engine (and the client SDK for the
served half, started with :mod:`collider_cli.launch`).
"""

from .budget import Budget, NothingMeetsBudget, rank
from .plan import PlanConfig
from .run import QUICK, BenchConfig, run_bench
from .timing import TimingPolicy

__all__ = [
           "QUICK",
           "BenchConfig",
           "Budget",
           "NothingMeetsBudget",
           "PlanConfig",
           "TimingPolicy",
           "rank",
           "run_bench",
]
