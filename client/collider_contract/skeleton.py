"""The pose of a skinned collider's skeleton in a query: one form for the engine, the service and
the SDK.

A skinned model (kind ``skinned``) is asked either

- in a **clip** at a **time**: ``clip`` (a clip's name; left out: the model's first) with the
  query's ``time`` (seconds; wrapped or clamped beyond the clip's ends by the model's ``loop``,
  the rule of :class:`~.animation.Timeline`), the joints' velocities following from the clip; or
- at **joint transforms**: ``joint_transforms`` (J, 4, 4), each joint's world transform in the
  collider frame (collider units; the model's joints in ``ModelInfo.skeleton["joints"]`` order),
  each a rotation times an optional uniform scale plus a translation within the coordinate
  range; with optional ``joint_velocities`` (J, 4, 4), their time derivatives (1/s and collider
  units/s, bottom rows zero) for ``velocity`` (left out: the skeleton is still).

The query's ``pose`` (collider frame -> world) applies on top, as for every model.
``ModelInfo.skeleton`` (a dict: ``joints``, ``parents``, ``clips`` each with ``name`` and
``duration_s``, ``loop``) describes a skinned model; it is empty for any other, and those refuse
a skeleton pose (422 ``not-skinned``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import QueryError
from .pose import PoseError, as_pose

#: The most joints a pose may have (glTF characters have tens to a few hundred).
MAX_JOINTS = 4096
#: The longest clip name, characters.
MAX_CLIP_NAME = 256
#: The keys a query (or a scene collider) gives a skeleton pose with.
SKELETON_KEYS = ("clip", "joint_transforms", "joint_velocities")


@dataclass(frozen=True)
class SkeletonPose:
    """A validated skeleton pose (see the module docstring): ``clip`` (a name, or None: the
    first, asked at the query's time) or ``joint_transforms`` (J, 4, 4) float64 with optional
    ``joint_velocities`` (J, 4, 4) float64, collider frame."""

    clip: str | None = None
    joint_transforms: np.ndarray | None = None
    joint_velocities: np.ndarray | None = None

    def key(self) -> tuple:
        """Equal for equal poses (hashable): requests with the same key share one evaluation."""
        return (self.clip,
                None if self.joint_transforms is None else self.joint_transforms.tobytes(),
                None if self.joint_velocities is None else self.joint_velocities.tobytes())

    def to_body(self, nested: bool = False) -> dict[str, Any]:
        """The wire keys of this pose (arrays as numpy, or as nested lists when ``nested``: a
        scene collider's, inside a list)."""
        body: dict[str, Any] = {}
        if self.clip is not None:
            body["clip"] = self.clip
        for key in ("joint_transforms", "joint_velocities"):
            value = getattr(self, key)
            if value is not None:
                body[key] = value.tolist() if nested else value
        return body


def check_clip(value, where: str = "clip") -> str | None:
    """A clip's name: None, or a non-empty string of at most :data:`MAX_CLIP_NAME` characters."""
    if value is None:
        return None
    if not isinstance(value, str) or not 0 < len(value) <= MAX_CLIP_NAME:
        raise QueryError(f"{where} must be a clip's name (a string of 1 to {MAX_CLIP_NAME} "
                         f"characters), got {value!r:.60}", code="bad-clip")
    return value


def _stack(value, where: str, code: str) -> np.ndarray:
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise QueryError(f"{where} must be a (J, 4, 4) array of numbers: {exc}", code=code) from None
    if array.ndim != 3 or array.shape[1:] != (4, 4) or not 0 < len(array) <= MAX_JOINTS:
        raise QueryError(f"{where} must have shape (J, 4, 4) with 1 <= J <= {MAX_JOINTS}, got "
                         f"{list(array.shape)}", code=code)
    return array


def check_joint_transforms(value, where: str = "joint_transforms") -> np.ndarray | None:
    """Joints' world transforms (J, 4, 4) float64, collider frame, or None: each finite, a
    rotation times a uniform scale (the rule of a pose, :func:`~.pose.as_pose`), its translation
    within the coordinate range, its bottom row [0, 0, 0, 1]."""
    if value is None:
        return None
    array = _stack(value, where, "bad-joint-transforms")
    for j, matrix in enumerate(array):
        try:
            as_pose(matrix)
        except PoseError as exc:  # "pose ..." -> "joint_transforms[j] ..."
            message = str(exc)
            message = message[len("pose"):] if message.startswith("pose") else f": {message}"
            raise QueryError(f"{where}[{j}]{message}", code="bad-joint-transforms") from None
    return array


def check_joint_velocities(value, where: str = "joint_velocities") -> np.ndarray | None:
    """The joints' transforms' time derivatives (J, 4, 4) float64, or None: each the derivative
    of a pose (:func:`~.queries.check_pose_velocity`'s rule: finite, bounded, bottom row zero)."""
    from .queries import check_pose_velocity  # (queries imports this module)

    if value is None:
        return None
    array = _stack(value, where, "bad-joint-velocities")
    for j, matrix in enumerate(array):
        check_pose_velocity(matrix, f"{where}[{j}]", code="bad-joint-velocities")
    return array


def check_skeleton_pose(clip=None, joint_transforms=None, joint_velocities=None,
                        where: str = "") -> SkeletonPose | None:
    """A query's skeleton pose from its three keys (``where``: a prefix for the refusals, e.g.
    ``colliders[1].``), or None when none is given. A clip and joint transforms together, or
    joint velocities without transforms, are refused."""
    clip = check_clip(clip, f"{where}clip")
    transforms = check_joint_transforms(joint_transforms, f"{where}joint_transforms")
    velocities = check_joint_velocities(joint_velocities, f"{where}joint_velocities")
    if clip is not None and transforms is not None:
        raise QueryError(f"give {where}clip (with a time) or {where}joint_transforms, not both",
                         code="bad-joint-transforms")
    if velocities is not None:
        if transforms is None:
            raise QueryError(f"{where}joint_velocities needs {where}joint_transforms",
                             code="bad-joint-velocities")
        if velocities.shape != transforms.shape:
            raise QueryError(f"{where}joint_velocities has shape {list(velocities.shape)}, "
                             f"{where}joint_transforms {list(transforms.shape)}: they must match",
                             code="bad-joint-velocities")
    if clip is None and transforms is None:
        return None
    return SkeletonPose(clip, transforms, velocities)


def require_skeleton_pose(pose: SkeletonPose | None, time: float | None, skeleton: dict | None,
                          where: str) -> None:
    """Refuse (422) a skeleton pose that does not fit the model ``where`` (``skeleton``: its
    ``ModelInfo.skeleton``, empty or None for a model without one): a pose for a model without
    a skeleton (``not-skinned``), a skinned model asked with neither a time nor joint transforms
    (``missing-time``), joint transforms of another joint count (``bad-joint-transforms``), a
    clip it does not have (``unknown-clip``)."""
    if not skeleton:
        if pose is not None:
            given = [k for k in SKELETON_KEYS if pose.to_body().get(k) is not None]
            verb = "is" if len(given) == 1 else "are"
            raise QueryError(f"{where} has no skeleton: {' and '.join(given)} {verb} for skinned "
                             f"models only", code="not-skinned")
        return
    joints = skeleton.get("joints", [])
    clips = [c.get("name") for c in skeleton.get("clips", [])]
    if pose is not None and pose.joint_transforms is not None:
        if len(pose.joint_transforms) != len(joints):
            raise QueryError(f"{where} has {len(joints)} joints, joint_transforms has "
                             f"{len(pose.joint_transforms)}", code="bad-joint-transforms")
        return
    if time is None:
        raise QueryError(f"{where} is skinned: give the time (seconds) to ask its clip at, or "
                         f"joint_transforms", code="missing-time")
    if not clips:
        raise QueryError(f"{where} has no clips: give joint_transforms", code="unknown-clip")
    if pose is not None and pose.clip is not None and pose.clip not in clips:
        raise QueryError(f"{where} has no clip {pose.clip!r}; its clips are {clips}",
                         code="unknown-clip")
