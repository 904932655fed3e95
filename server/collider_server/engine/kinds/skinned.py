"""The exact collider of a skinned mesh (kind ``skinned``): at any pose of its skeleton, the exact
signed distance to the mesh skinned there (linear blend skinning,
:mod:`collider_server.engine.skinning`), answered by :class:`~collider_server.engine.meshes.ExactSDF`
(libigl's AABB tree and fast winding number over the posed vertices), and the surface's velocity
at each point's closest surface point: the skinned vertices' velocities (the skinning's time
derivative) weighted by the closest point's barycentric coordinates in its triangle.

A query gives the pose as a clip and a time (the clip's channels sampled by the glTF rules, the
time wrapped or clamped by the animations' rule, :class:`~collider_contract.Timeline`) or as the
joints' world transforms in the collider frame (with their time derivatives for ``velocity``).
Each distinct pose builds one tree over the posed vertices (libigl's Python binding has no refit;
the topology's edge index is computed once for every pose); the latest ``keep`` poses are kept,
so a pose asked again costs no build. Exact everywhere, no domain rule.
"""

from __future__ import annotations

import threading
import time as clock

import numpy as np

from collider_contract import SkeletonPose

from ..collider import Collider, ColliderInfo
from ..kept import Kept
from ..meshes import ExactSDF, Mesh, barycentric, edge_index
from ..skinning import Channel, Clip, Skeleton, Skin, pose_at, skin_velocities, skin_vertices

#: Samples per interval between two consecutive key times of a clip (over all its channels) at
#: which :func:`clip_max_surface_speed` measures the skin's speed (at least 4: the midpoints are
#: among them).
SPEED_SAMPLES_PER_KEY = 4
#: What :func:`clip_max_surface_speed` multiplies the fastest sampled speed by. Within a key
#: interval a joint turns or moves along one smooth path (slerp, lerp or a cubic), so a vertex's
#: speed is a smooth function of time there; its peak can fall between two samples a quarter of
#: an interval apart, and the fastest sample then falls short of it by a fraction of the speed's
#: change over that quarter. 1.25 leaves that room (measured on the arm's and the walker's clips:
#: the fastest of 32 to 64 samples per interval is within 1.1 % of the fastest of 4,
#: tests/engine/kinds/test_skinned.py).
SPEED_SAFETY = 1.25

#: The arrays of a skinned model file besides its channels' (``channel.<n>.times`` and
#: ``channel.<n>.values``, described by ``info.settings["channels"]``).
SKIN_TENSORS = ("vertices", "faces", "joints", "weights", "parents", "rest_translation",
                "rest_rotation", "rest_scale", "inverse_bind", "root")


class PosedSkin:
    """The skin at one pose: its exact SDF, and its vertex velocities when asked for.

    exact : :class:`ExactSDF` of the posed mesh (collider frame)
    joint_velocities : (J, 4, 4) float64 or None (a still skeleton)
    """

    def __init__(self, skin: Skin, exact: ExactSDF, joint_transforms: np.ndarray,
                 joint_velocities: np.ndarray | None):
        self.skin = skin
        self.exact = exact
        self.joint_transforms = joint_transforms
        self.joint_velocities = joint_velocities
        self._velocities = None

    def vertex_velocities(self) -> np.ndarray | None:
        """(V, 3) float64, metres per second, collider frame, or None (still); computed once."""
        if self.joint_velocities is None:
            return None
        if self._velocities is None:
            self._velocities = skin_velocities(self.skin, self.joint_transforms,
                                               self.joint_velocities)
        return self._velocities


class SkinnedCollider(Collider):
    """``tensors()``: :data:`SKIN_TENSORS` and each channel's ``channel.<n>.times`` /
    ``channel.<n>.values``; ``info.skeleton`` describes the joints and clips (names, parents,
    durations, ``loop``), ``info.settings["channels"]`` each channel as ``[clip index, joint,
    path, interpolation]``."""

    kind = "skinned"
    chunk_points = 200_000
    clamps_to_domain = False
    gradient_in_one_pass = True

    def __init__(self, info: ColliderInfo, skin: Skin, keep: int = 4):
        super().__init__(info)
        self.skin = skin
        self.loop = bool(info.skeleton.get("loop", True))
        self._edges = edge_index(skin.faces)  # the same at every pose
        self._cache: Kept[PosedSkin] = Kept(keep)
        self._lock = threading.Lock()  # the build counts
        #: trees built, and the seconds they took (skinning included; measured)
        self.builds = 0
        self.build_s = 0.0

    @property
    def skinned(self) -> bool:
        return True

    # -- poses ------------------------------------------------------------------------------

    def posed(self, time: float | None, skeleton: SkeletonPose | None) -> PosedSkin:
        """The skin at the pose of a query: ``skeleton``'s joint transforms, or its clip (None:
        the first) at ``time`` seconds; with neither, the rest pose. Cached by pose."""
        key = pose_key(time, skeleton)

        def build() -> PosedSkin:
            started = clock.perf_counter()
            transforms, velocities = resolve_pose(self.skin, self.loop, key, skeleton)
            mesh = Mesh(skin_vertices(self.skin, transforms), self.skin.faces, self.info.name)
            posed = PosedSkin(self.skin, ExactSDF(mesh, self._edges), transforms, velocities)
            spent = clock.perf_counter() - started
            with self._lock:
                self.builds += 1
                self.build_s += spent
            return posed

        return self._cache.get(key, build)

    # -- the kind's interface ---------------------------------------------------------------

    def evaluate(self, local, want_gradient):
        distance, gradient, _ = self.evaluate_at(local, want_gradient, None)
        return distance, gradient

    def evaluate_at(self, local, want_gradient, time, skeleton: SkeletonPose | None = None):
        posed = self.posed(time, skeleton)
        exact = posed.exact
        distance, closest, face = exact.query(local)
        if not want_gradient:
            return distance, None, None
        gradient = exact.gradient(local, distance, closest, face)
        vertex_velocities = posed.vertex_velocities()
        if vertex_velocities is None:
            return distance, gradient, None
        corners = self.skin.faces[face]  # (m, 3) vertex indices
        weights = barycentric(closest, exact.mesh.vertices[corners])
        velocity = np.einsum("mj,mjc->mc", weights, vertex_velocities[corners])
        return distance, gradient, velocity

    def tensors(self):
        return skin_tensors(self.skin)

    @classmethod
    def from_tensors(cls, info, tensors, device=None):
        return cls(info, skin_from_tensors(info, tensors))


def pose_key(time: float | None, skeleton: SkeletonPose | None) -> tuple:
    """The cache key of a query's pose (hashable): its joint transforms (and velocities), or its
    clip (None: the first) and time, or the rest pose when it gives neither."""
    if skeleton is not None and skeleton.joint_transforms is not None:
        return ("joints", skeleton.joint_transforms.tobytes(),
                None if skeleton.joint_velocities is None else skeleton.joint_velocities.tobytes())
    if time is not None:
        return ("clip", None if skeleton is None else skeleton.clip, float(time))
    return ("rest",)


def resolve_pose(skin: Skin, loop: bool, key: tuple, skeleton: SkeletonPose | None):
    """The pose of :func:`pose_key`'s ``key``: ``(joint_transforms (J, 4, 4), joint_velocities
    (J, 4, 4) or None: still)`` float64, collider frame (a clip's time wrapped when ``loop``, else
    clamped; the rest pose is still)."""
    if key[0] == "joints":
        transforms = np.asarray(skeleton.joint_transforms, dtype=np.float64)
        velocities = (None if skeleton.joint_velocities is None
                      else np.asarray(skeleton.joint_velocities, dtype=np.float64))
        return transforms, velocities
    if key[0] == "clip":
        transforms, velocities = pose_at(skin, key[1], key[2], "loop" if loop else "clamp")
        return transforms, (velocities if velocities.any() else None)
    return skin.skeleton.rest_world(), None


def skin_tensors(skin: Skin) -> dict:
    """The arrays a model file stores of ``skin``: :data:`SKIN_TENSORS` and each channel's
    ``channel.<n>.times`` / ``channel.<n>.values`` (:func:`channel_layout`'s order)."""
    skeleton = skin.skeleton
    out = {"vertices": skin.vertices, "faces": skin.faces.astype(np.int32),
           "joints": skin.joints.astype(np.int32), "weights": skin.weights,
           "parents": skeleton.parents.astype(np.int32),
           "rest_translation": skeleton.rest_translation,
           "rest_rotation": skeleton.rest_rotation, "rest_scale": skeleton.rest_scale,
           "inverse_bind": skeleton.inverse_bind, "root": skeleton.root}
    n = 0
    for clip in skin.clips:
        for channel in clip.channels:
            out[f"channel.{n}.times"] = channel.times
            out[f"channel.{n}.values"] = channel.values
            n += 1
    return {k: np.asarray(v) for k, v in out.items()}


def clip_sample_times(clip: Clip, per_key: int = SPEED_SAMPLES_PER_KEY) -> np.ndarray:
    """(n,) float64 seconds in ``[0, duration_s]``: every key time of every channel of ``clip``
    and the clip's ends, each interval between two of them cut into ``per_key`` equal parts (its
    midpoint among them when ``per_key`` is even), and a hair before each interval's end (a key's
    velocity is the next segment's: the one before it ends there)."""
    keys = [np.asarray(c.times, dtype=np.float64) for c in clip.channels]
    knots = np.unique(np.clip(np.concatenate([[0.0, clip.duration_s], *keys]), 0.0,
                              clip.duration_s))
    if len(knots) < 2:
        return knots
    starts, lengths = knots[:-1], np.diff(knots)
    parts = starts[:, None] + lengths[:, None] * (np.arange(per_key) / per_key)[None, :]
    ends = knots[1:] - 1e-9 * lengths
    return np.unique(np.concatenate([parts.ravel(), ends, knots]))


def clip_max_surface_speed(skin: Skin, clip: Clip, per_key: int = SPEED_SAMPLES_PER_KEY,
                           safety: float = SPEED_SAFETY) -> float:
    """The fastest any vertex of ``skin`` moves in ``clip``, collider units per second: the
    largest ``skin_velocities`` over :func:`clip_sample_times` times ``safety`` (why:
    :data:`SPEED_SAFETY`). A surface point moves at a blend of its triangle's vertices'
    velocities, so no point is faster than the fastest vertex. A STEP channel's jump between two
    keys has no speed and is not bounded (the pose teleports there)."""
    fastest = 0.0
    for t in clip_sample_times(clip, per_key):
        transforms, velocities = pose_at(skin, clip.name, float(t), "clamp")
        if velocities.any():
            speeds = np.linalg.norm(skin_velocities(skin, transforms, velocities), axis=1)
            fastest = max(fastest, float(speeds.max()))
    return fastest * safety


def skeleton_description(skin: Skin, loop: bool) -> dict:
    """``ColliderInfo.skeleton`` / ``ModelInfo.skeleton`` of a skinned model (JSON): ``joints``
    (names), ``parents`` (indices, -1 for a root), ``clips`` (each ``name``, ``duration_s`` and
    ``max_surface_speed``: :func:`clip_max_surface_speed`, collider units per second) and
    ``loop`` (a clip's time wraps beyond its ends, else it is clamped)."""
    return {"joints": list(skin.skeleton.names),
            "parents": [int(p) for p in skin.skeleton.parents],
            "clips": [{"name": c.name, "duration_s": c.duration_s,
                       "max_surface_speed": clip_max_surface_speed(skin, c)}
                      for c in skin.clips],
            "loop": bool(loop)}


def channel_layout(skin: Skin) -> list:
    """``info.settings["channels"]``: per stored channel ``[clip index, joint, path,
    interpolation]``, in the order of the ``channel.<n>`` arrays."""
    return [[i, c.joint, c.path, c.interpolation]
            for i, clip in enumerate(skin.clips) for c in clip.channels]


def skin_from_tensors(info: ColliderInfo, tensors: dict) -> Skin:
    """The :class:`Skin` of a skinned model file's arrays and info; ValueError naming what does
    not fit."""
    layout = info.settings.get("channels", [])
    description = info.skeleton
    if not isinstance(description, dict) or not description.get("joints"):
        raise ValueError("a skinned model needs its skeleton's description (joints, parents, "
                         "clips) in its info")
    expected = set(SKIN_TENSORS) | {f"channel.{n}.{part}" for n in range(len(layout))
                                    for part in ("times", "values")}
    if set(tensors) != expected:
        missing, extra = sorted(expected - set(tensors)), sorted(set(tensors) - expected)
        raise ValueError(f"skinned model arrays do not fit its info: missing {missing}, "
                         f"unexpected {extra}")
    f64 = {k: np.asarray(tensors[k], dtype=np.float64) for k in tensors if k not in
           ("faces", "joints", "parents")}
    clips_info = description.get("clips", [])
    skeleton = Skeleton(description["joints"], np.asarray(tensors["parents"], dtype=np.int64),
                        f64["rest_translation"], f64["rest_rotation"], f64["rest_scale"],
                        f64["inverse_bind"], f64["root"])
    channels: list[list] = [[] for _ in clips_info]
    for n, entry in enumerate(layout):
        if not (isinstance(entry, list) and len(entry) == 4 and isinstance(entry[0], int)
                and 0 <= entry[0] < len(clips_info)):
            raise ValueError(f"channel {n} of the skinned model's layout is malformed: {entry!r}")
        clip_index, joint, path, interpolation = entry
        channels[clip_index].append(Channel(joint, path, interpolation, f64[f"channel.{n}.times"],
                                            f64[f"channel.{n}.values"]))
    clips = tuple(Clip(c["name"], tuple(ch), c["duration_s"]) for c, ch in zip(clips_info, channels))
    skin = Skin(f64["vertices"], np.asarray(tensors["faces"], dtype=np.int64),
                np.asarray(tensors["joints"], dtype=np.int64), f64["weights"], skeleton, clips)
    if len(skin.faces) == 0:
        raise ValueError("skinned model holds no faces")
    for clip in clips:
        for channel in clip.channels:
            if not 0 <= channel.joint < skeleton.joint_count:
                raise ValueError(f"clip {clip.name!r} animates joint {channel.joint}, but the "
                                 f"skeleton has {skeleton.joint_count}")
    return skin
