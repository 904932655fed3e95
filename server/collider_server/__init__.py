"""Collider engine, training and HTTP service (the torch side of the project).

The engine answers, for batches of points, the signed distance to an object, the outward normal
and the contact point at a collision offset ``eps``, through one interface over four kinds of
collider: ``neural`` (the paper's network), ``voxel``, ``mesh`` (exact) and ``kdtree`` (the
paper's approximate baseline). Lengths are in the collider's units (metres for the shipped models).
"""

from collider_contract import MAX_COORDINATE_M, Pose, PoseError, as_pose

from .collider import FIELDS, Collider, ColliderInfo, QueryResult
from .modelfile import ModelFileError, load_collider, save_collider
from .repository import ModelRepository

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
