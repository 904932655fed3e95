"""The query contract: what a collider query is, wherever it is answered (numpy + msgpack only).

One home for the rules that the HTTP service (``collider_server.service``) and the SDK's
embedded backend (``collider_client``) share, so that their answers and refusals are the same by
construction: the wire codec (:mod:`.wire`), the result and model types (:mod:`.results`) and
poses with the coordinate range (:mod:`.pose`).
"""

from .pose import MAX_COORDINATE_M, MAX_SCALE, Pose, PoseError, as_pose
from .results import ModelInfo, QueryResult
from .wire import FIELDS, GRADIENT_FIELDS, WireError, check_fields

__all__ = [
    "FIELDS",
    "GRADIENT_FIELDS",
    "MAX_COORDINATE_M",
    "MAX_SCALE",
    "ModelInfo",
    "Pose",
    "PoseError",
    "QueryResult",
    "WireError",
    "as_pose",
    "check_fields",
]
