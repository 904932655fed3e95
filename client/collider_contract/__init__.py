"""The query contract: what a collider query is and how it is answered, wherever it is asked
(numpy + msgpack only, no torch).

One home for the rules that the engine, the HTTP service (``collider_server``) and the SDK's
embedded and remote backends (``collider_client``) share, so that their answers and refusals are
the same by construction:

- :mod:`.wire`: how bodies and arrays travel (msgpack, JSON);
- :mod:`.pose`: poses (collider frame -> world frame) and the coordinate range;
- :mod:`.queries`: a query's fields, points, pose, eps and mode, validated, and its wire body;
- :mod:`.answers`: the eps policy, the assembly of the fields, the scene rule, and the functions
  that answer a model query or a scene query given a way to evaluate a collider;
- :mod:`.results`: what an answer and a model description are;
- :mod:`.animation`: how an animated collider runs in time (frames, rate, loop or clamp);
- :mod:`.skeleton`: the pose of a skinned collider's skeleton in a query (a clip at a time, or
  the joints' transforms);
- :mod:`.point_cache`: the files animations travel in (OBJ + PC2 vertex cache);
- :mod:`.errors`: :class:`QueryError`, every refusal's status, problem code and message.
"""

from .animation import Timeline
from .answers import (
                      DEFAULT_EPS_METERS,
                      Evaluate,
                      Evaluation,
                      answer_model_query,
                      answer_scene_query,
                      check_finite,
                      default_eps,
                      finish,
                      finish_scene,
                      nearest_collider,
                      prepare,
                      require_time,
                      resolve_eps,
)
from .errors import TITLES, QueryError, unknown_model
from .pose import IDENTITY, MAX_COORDINATE_M, MAX_SCALE, Pose, PoseError, as_pose, transform_points
from .queries import (
                      FIELDS,
                      GRADIENT_FIELDS,
                      ModelQuery,
                      Placed,
                      SceneCollider,
                      SceneQuery,
                      check_eps,
                      check_fields,
                      check_points,
                      check_pose_velocity,
                      check_time,
)
from .results import ModelInfo, QueryResult
from .skeleton import (
                      SkeletonPose,
                      check_joint_transforms,
                      check_joint_velocities,
                      check_skeleton_pose,
)
from .wire import WireError

__all__ = [
                      "DEFAULT_EPS_METERS",
                      "FIELDS",
                      "GRADIENT_FIELDS",
                      "IDENTITY",
                      "MAX_COORDINATE_M",
                      "MAX_SCALE",
                      "TITLES",
                      "Evaluate",
                      "Evaluation",
                      "ModelInfo",
                      "ModelQuery",
                      "Placed",
                      "Pose",
                      "PoseError",
                      "QueryError",
                      "QueryResult",
                      "SceneCollider",
                      "SceneQuery",
                      "SkeletonPose",
                      "Timeline",
                      "WireError",
                      "answer_model_query",
                      "answer_scene_query",
                      "as_pose",
                      "check_eps",
                      "check_fields",
                      "check_finite",
                      "check_joint_transforms",
                      "check_joint_velocities",
                      "check_points",
                      "check_pose_velocity",
                      "check_skeleton_pose",
                      "check_time",
                      "default_eps",
                      "finish",
                      "finish_scene",
                      "nearest_collider",
                      "prepare",
                      "require_time",
                      "resolve_eps",
                      "transform_points",
                      "unknown_model",
]
