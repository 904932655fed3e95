"""Skinned colliders from a :class:`~collider_server.engine.skinning.Skin`, and a generated skinned
arm to test them with (nothing downloaded).

- :func:`skinned_collider`: the exact ``skinned`` collider of a skin (save it with
  :func:`collider_server.engine.modelfile.save_collider`);
- :func:`skinned_arm`: a capsule arm along +x with a shoulder, an elbow and a wrist, its vertices
  weighted smoothly across each joint, and two clips ("wave": LINEAR keys; "reach": CUBICSPLINE
  rotations, a STEP wrist and a moving root). Metres, its own frame, z up.
"""

from __future__ import annotations

import math

import numpy as np

from ..engine.collider import ColliderInfo
from ..engine.kinds.skinned import SkinnedCollider, channel_layout, skeleton_description
from ..engine.skinning import (
    Channel,
    Clip,
    Skeleton,
    Skin,
    pose_at,
    skin_vertices,
    trs_matrices,
    world_transforms,
)
from .animations import capsule

#: Clip times at which :func:`skinned_collider` samples each clip for the domain box.
DOMAIN_SAMPLES = 17


def skinned_collider(skin: Skin, name: str, *, loop: bool = True, padding: float = 0.1,
                     units: str = "m", meters_per_unit: float = 1.0,
                     source: dict | None = None) -> SkinnedCollider:
    """The exact ``skinned`` collider named ``name`` of ``skin`` (its units and frame).

    loop : a clip's time wraps beyond its ends (True) or is clamped to them (False)
    padding : fraction of the largest side added around the box of the rest pose and of each
        clip sampled at :data:`DOMAIN_SAMPLES` times (the domain, for the record: the exact kind
        answers everywhere)
    source : ``ColliderInfo.source`` (the file it was read from); default: counts only
    """
    if not (np.isfinite(padding) and padding >= 0):
        raise ValueError(f"padding must be a finite number >= 0 (fraction of the largest side), "
                         f"got {padding}")
    boxes = [skin.vertices]
    for clip in skin.clips:
        for t in np.linspace(0.0, clip.duration_s, DOMAIN_SAMPLES):
            boxes.append(skin_vertices(skin, pose_at(skin, clip.name, t, "clamp")[0]))
    stacked = np.concatenate(boxes)
    lo, hi = stacked.min(axis=0), stacked.max(axis=0)
    margin = padding * float((hi - lo).max())
    info = ColliderInfo(
        name=name, kind="skinned", domain_min=(lo - margin).tolist(),
        domain_max=(hi + margin).tolist(), units=units, meters_per_unit=meters_per_unit,
        source=dict(source) if source is not None else {
            "mesh": name, "vertices": len(skin.vertices), "faces": len(skin.faces),
            "joints": skin.skeleton.joint_count},
        settings={"padding": padding, "channels": channel_layout(skin)},
        skeleton=skeleton_description(skin, loop))
    return SkinnedCollider(info, skin)


def _about(axis, angle: float) -> np.ndarray:
    """(x, y, z, w) of a rotation by ``angle`` radians about the unit ``axis``."""
    axis = np.asarray(axis, dtype=np.float64)
    return np.concatenate([axis * math.sin(angle / 2), [math.cos(angle / 2)]])


def _smoothstep(x: np.ndarray, centre: float, blend: float) -> np.ndarray:
    s = np.clip((x - (centre - blend)) / (2.0 * blend), 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def skinned_arm(length: float = 0.5, radius: float = 0.04, elbow: float = 0.25,
                wrist: float = 0.42, blend: float = 0.05) -> Skin:
    """A capsule arm along +x (shoulder at the origin, hand at ``length``, metres) with joints
    ``shoulder``, ``elbow`` (x = ``elbow``) and ``wrist`` (x = ``wrist``); each vertex follows the
    two joints around it, the weight a smoothstep of x over ``+-blend`` about the joint. Clips:

    - ``wave`` (1 s, LINEAR): the shoulder swings about z by +-30 degrees, the elbow bends up
      (towards +z) by up to 60 degrees, the wrist by +-20;
    - ``reach`` (2 s): the elbow by a CUBICSPLINE rotation, the wrist by STEP, the shoulder
      translated along x by a LINEAR channel.
    """
    rest = capsule(length, radius)
    x = rest.vertices[:, 0]
    at_elbow = _smoothstep(x, elbow, blend)  # shoulder -> elbow
    at_wrist = _smoothstep(x, wrist, blend)  # elbow -> wrist
    near_wrist = x > 0.5 * (elbow + wrist)
    joints = np.where(near_wrist[:, None], [1, 2], [0, 1]).astype(np.int64)
    weights = np.where(near_wrist[:, None], np.stack([1.0 - at_wrist, at_wrist], axis=1),
                       np.stack([1.0 - at_elbow, at_elbow], axis=1))
    translation = np.array([[0.0, 0.0, 0.0], [elbow, 0.0, 0.0], [wrist - elbow, 0.0, 0.0]])
    rotation = np.tile([0.0, 0.0, 0.0, 1.0], (3, 1))
    scale = np.ones((3, 3))
    parents = np.array([-1, 0, 1])
    names = ("shoulder", "elbow", "wrist")
    rest_world = world_transforms(
        Skeleton(names, parents, translation, rotation, scale, np.tile(np.eye(4), (3, 1, 1))),
        trs_matrices(translation, rotation, scale))
    skeleton = Skeleton(names, parents, translation, rotation, scale, np.linalg.inv(rest_world))

    up = (0.0, -1.0, 0.0)  # a positive angle about -y turns +x towards +z
    times = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    wave = Clip("wave", (
        Channel(0, "rotation", "LINEAR", times,
                [_about((0, 0, 1), math.radians(a)) for a in (0, 30, 0, -30, 0)]),
        Channel(1, "rotation", "LINEAR", times,
                [_about(up, math.radians(a)) for a in (0, 30, 60, 30, 0)]),
        Channel(2, "rotation", "LINEAR", times,
                [_about(up, math.radians(a)) for a in (0, 20, 0, -20, 0)]),
    ), 1.0)
    cubic = np.zeros((3, 3, 4))
    cubic[:, 1] = [_about(up, 0.0), _about(up, math.radians(70)), _about(up, 0.0)]
    cubic[1, 0] = cubic[1, 2] = [0.0, -0.2, 0.0, 0.0]  # tangents per second, at the middle key
    reach = Clip("reach", (
        Channel(1, "rotation", "CUBICSPLINE", [0.0, 1.0, 2.0], cubic),
        Channel(2, "rotation", "STEP", [0.0, 0.5, 1.5],
                [_about(up, 0.0), _about(up, math.radians(25)), _about(up, 0.0)]),
        Channel(0, "translation", "LINEAR", [0.0, 1.0, 2.0],
                [[0.0, 0.0, 0.0], [0.05, 0.0, 0.02], [0.0, 0.0, 0.0]]),
    ), 2.0)
    return Skin(rest.vertices, rest.faces, joints, weights, skeleton, (wave, reach))
