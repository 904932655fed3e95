"""The torch side of the project, in three layers:

- :mod:`.engine`, the query core: for batches of points, the signed distance to an object, the
  outward normal and the contact point at a collision offset ``eps``, through one interface over
  four kinds of collider: ``neural`` (the paper's network), ``voxel``, ``mesh`` (exact) and
  ``kdtree`` (the paper's approximate baseline);
- :mod:`.making`, colliders made from meshes: baking, training, evaluation;
- :mod:`.service`, the HTTP service over a model repository.

Lengths are in the collider's units (metres for the shipped models). The names below are the
engine's public API; the query rules themselves live in :mod:`collider_contract`.
"""

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
