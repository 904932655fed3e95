"""The torch side of the project, in three layers:

- :mod:`.engine`, the query core: for batches of points, the signed distance to an object, the
  outward normal and the contact point at a collision offset ``eps``, through one interface over
  the kinds of :mod:`.engine.kinds`: ``neural`` (the paper's network and the grid networks),
  ``voxel``, ``mesh`` (exact) and ``kdtree`` (the paper's approximate baseline), the first three
  also animated (one collider for a whole animation);
- :mod:`.making`, colliders made from meshes: baking, training, evaluation;
- :mod:`.service`, the HTTP service over a model repository.

Lengths are in the collider's units (metres for the shipped models). The names below are the
engine's public API; the query rules themselves live in :mod:`collider_contract`.
"""

import os

# OpenMP's idle threads (torch's pool, and numba's, which loads the same libgomp) spin after each
# parallel region by default. On a busy CPU that spinning took the cores from the next call of
# the same process: a voxel query right after a grid network's took 1.2 s instead of 20 ms, 0.6 s
# of it CPU time spent spinning (measured at load 6 on 2 cores, `collider bench`). Sleeping idle
# threads cost microseconds per call instead. libgomp reads this when it loads (with torch), so it
# is set before anything imports torch; a value the user set wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from collider_contract import FIELDS, MAX_COORDINATE_M, Pose, PoseError, QueryResult, as_pose

from .engine import Collider, ColliderInfo, ModelFileError, ModelRepository, load_collider, save_collider

__all__ = [
    "FIELDS",
    "MAX_COORDINATE_M",
    "Collider",
    "ColliderInfo",
    "ModelFileError",
    "ModelRepository",
    "Pose",
    "PoseError",
    "QueryResult",
    "as_pose",
    "load_collider",
    "save_collider",
]
