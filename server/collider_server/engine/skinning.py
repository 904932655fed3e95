"""Skinned meshes: a skeleton, clips of joint motion and linear blend skinning (glTF 2.0 rules).

Pure numpy, float64, the collider frame, metres and seconds. A :class:`Skin` is a closed rest
(bind-pose) mesh whose vertices follow up to K joints each with weights summing to 1; its
:class:`Skeleton` is a tree of joints with rest local transforms (translation, rotation as a unit
quaternion in glTF order ``(x, y, z, w)``, scale) and inverse bind matrices. A :class:`Clip` moves
joints by keyframed :class:`Channel` s, sampled as the glTF 2.0 specification says:

- ``LINEAR``: linear interpolation; rotations by spherical linear interpolation (slerp) along the
  shortest arc;
- ``STEP``: the value of the keyframe at or before the time;
- ``CUBICSPLINE``: the cubic Hermite spline through the values, with the stored in- and
  out-tangents scaled by the keyframe interval; rotations normalised afterwards;
- before a channel's first or after its last keyframe its end value is held.

A pose of the whole skeleton is its joints' world transforms ``(J, 4, 4)`` in the collider frame
(``root @`` the chain of local transforms); a vertex is skinned as
``sum_k w_k (T_{j_k} @ inverse_bind_{j_k}) v`` and moves at ``sum_k w_k (dT_{j_k}/dt @
inverse_bind_{j_k}) v``. Segments are right-continuous like an animation's
(:mod:`collider_contract.animation`): at a keyframe the rate is that of the segment after it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from collider_contract import Timeline

#: The paths a channel may animate, and how many numbers a value of each has.
PATH_WIDTHS = {"translation": 3, "rotation": 4, "scale": 3}
#: The keyframe interpolations of glTF 2.0.
INTERPOLATIONS = ("LINEAR", "STEP", "CUBICSPLINE")
#: How a clip runs beyond its ends: as an animation's time rule (wrap or hold).
TIME_MODES = ("loop", "clamp")


# --------------------------------------------------------------------------------------------
# Quaternions (x, y, z, w), as glTF stores them


def _quat_bilinear(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The symmetric bilinear part B of a unit quaternion's rotation matrix, R(q) = I + 2 B(q, q).

    a, b : (..., 4) float64 (x, y, z, w); returns (..., 3, 3). The derivative of R along dq is
    then 4 B(q, dq).
    """
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)

    def sym(p, q, r, s):  # (p q)(a, b) symmetrised: (p_a q_b + q_a p_b) / 2
        return 0.5 * (p * s + q * r)

    xx = sym(ax, ax, bx, bx)
    yy = sym(ay, ay, by, by)
    zz = sym(az, az, bz, bz)
    xy = sym(ax, ay, bx, by)
    xz = sym(ax, az, bx, bz)
    yz = sym(ay, az, by, bz)
    xw = sym(ax, aw, bx, bw)
    yw = sym(ay, aw, by, bw)
    zw = sym(az, aw, bz, bw)
    rows = [
        [-(yy + zz), xy - zw, xz + yw],
        [xy + zw, -(xx + zz), yz - xw],
        [xz - yw, yz + xw, -(xx + yy)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def quaternion_matrices(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of quaternions: q (..., 4) float64 (x, y, z, w), normalised here;
    returns (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.eye(3) + 2.0 * _quat_bilinear(q, q)


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> tuple[np.ndarray, np.ndarray]:
    """Spherical linear interpolation of unit quaternions (4,) along the shortest arc.

    Returns ``(q, dq/du)``, both (4,) float64; ``u`` in [0, 1].
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(q0 @ q1)
    if dot < 0.0:  # q and -q are the same rotation: take the shorter way round
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly parallel: normalised lerp, no division by a vanishing sine
        p = (1.0 - u) * q0 + u * q1
        dp = q1 - q0
        n = np.linalg.norm(p)
        q = p / n
        return q, (dp - q * (q @ dp)) / n
    theta = np.arccos(min(dot, 1.0))
    sin = np.sin(theta)
    a, b = np.sin((1.0 - u) * theta) / sin, np.sin(u * theta) / sin
    da, db = -theta * np.cos((1.0 - u) * theta) / sin, theta * np.cos(u * theta) / sin
    return a * q0 + b * q1, da * q0 + db * q1


# --------------------------------------------------------------------------------------------
# The data model


@dataclass(frozen=True)
class Skeleton:
    """A tree of joints and its bind pose.

    names : (J,) str, unique
    parents : (J,) int64, -1 for a root; every parent's index is smaller than its child's
    rest_translation : (J, 3) float64, metres, each joint's rest local translation (parent frame)
    rest_rotation : (J, 4) float64, unit quaternions (x, y, z, w), rest local rotations
    rest_scale : (J, 3) float64, rest local scale
    inverse_bind : (J, 4, 4) float64, collider frame -> each joint's frame at bind
    root : (4, 4) float64, the transform above the joint roots, so ``world = root @ chain``
    """

    names: tuple
    parents: np.ndarray
    rest_translation: np.ndarray
    rest_rotation: np.ndarray
    rest_scale: np.ndarray
    inverse_bind: np.ndarray
    root: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self):
        object.__setattr__(self, "names", tuple(str(n) for n in self.names))
        j = len(self.names)
        if j == 0:
            raise ValueError("a skeleton needs at least one joint")
        if len(set(self.names)) != j:
            raise ValueError("the joints' names must be unique")
        for name, shape in (("parents", (j,)), ("rest_translation", (j, 3)),
                            ("rest_rotation", (j, 4)), ("rest_scale", (j, 3)),
                            ("inverse_bind", (j, 4, 4)), ("root", (4, 4))):
            value = np.asarray(getattr(self, name), dtype=np.int64 if name == "parents"
                               else np.float64)
            if value.shape != shape:
                raise ValueError(f"{name} must be {list(shape)} for {j} joints, "
                                 f"got {list(value.shape)}")
            if name != "parents" and not np.all(np.isfinite(value)):
                raise ValueError(f"{name} has non-finite values")
            object.__setattr__(self, name, value)
        parents = self.parents
        if np.any((parents >= np.arange(j)) | (parents < -1)):
            bad = int(np.flatnonzero((parents >= np.arange(j)) | (parents < -1))[0])
            raise ValueError(f"joint {bad} ({self.names[bad]!r}) has parent {int(parents[bad])}: "
                             f"every parent must come before its child (or be -1)")
        norms = np.linalg.norm(self.rest_rotation, axis=1)
        if np.any(np.abs(norms - 1.0) > 1e-3):
            raise ValueError("rest_rotation must be unit quaternions")
        object.__setattr__(self, "rest_rotation", self.rest_rotation / norms[:, None])

    @property
    def joint_count(self) -> int:
        return len(self.names)

    def rest_local(self) -> np.ndarray:
        """(J, 4, 4) float64: the rest local transforms."""
        return trs_matrices(self.rest_translation, self.rest_rotation, self.rest_scale)

    def rest_world(self) -> np.ndarray:
        """(J, 4, 4) float64: the joints' world transforms at rest, collider frame."""
        return world_transforms(self, self.rest_local())


@dataclass(frozen=True)
class Channel:
    """One animated property of one joint.

    joint : index into the skeleton
    path : "translation", "rotation" or "scale"
    interpolation : "LINEAR", "STEP" or "CUBICSPLINE"
    times : (k,) float64 seconds, strictly increasing
    values : (k, c) float64, or (k, 3, c) for CUBICSPLINE (in-tangent, value, out-tangent);
        c = 3 for translation (metres) and scale, 4 for rotation (x, y, z, w)
    """

    joint: int
    path: str
    interpolation: str
    times: np.ndarray
    values: np.ndarray

    def __post_init__(self):
        if self.path not in PATH_WIDTHS:
            raise ValueError(f"a channel's path must be one of {sorted(PATH_WIDTHS)}, "
                             f"got {self.path!r}")
        if self.interpolation not in INTERPOLATIONS:
            raise ValueError(f"a channel's interpolation must be one of {list(INTERPOLATIONS)}, "
                             f"got {self.interpolation!r}")
        times = np.asarray(self.times, dtype=np.float64).reshape(-1)
        values = np.asarray(self.values, dtype=np.float64)
        c = PATH_WIDTHS[self.path]
        shape = (len(times), 3, c) if self.interpolation == "CUBICSPLINE" else (len(times), c)
        if len(times) == 0:
            raise ValueError("a channel needs at least one keyframe")
        if values.shape != shape:
            raise ValueError(f"a {self.interpolation} {self.path} channel of {len(times)} "
                             f"keyframes needs values {list(shape)}, got {list(values.shape)}")
        if not (np.all(np.isfinite(times)) and np.all(np.isfinite(values))):
            raise ValueError(f"the {self.path} channel of joint {self.joint} has non-finite values")
        if np.any(np.diff(times) <= 0):
            raise ValueError(f"the {self.path} channel of joint {self.joint}: keyframe times "
                             f"must increase strictly")
        object.__setattr__(self, "joint", int(self.joint))
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "values", values)

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The value (c,) and its rate of change d/dt (c,) per second at ``t`` seconds.

        Held (rate zero) before the first and at or after the last keyframe.
        """
        times, values = self.times, self.values
        cubic = self.interpolation == "CUBICSPLINE"
        if t < times[0] or t >= times[-1]:
            value = values[0 if t < times[0] else -1]
            value = value[1] if cubic else value
            return _normalised(self.path, value.copy(), np.zeros_like(value))
        k = min(int(np.searchsorted(times, t, side="right")) - 1, len(times) - 2)
        dt = times[k + 1] - times[k]
        u = (t - times[k]) / dt
        if self.interpolation == "STEP":
            return values[k].copy(), np.zeros(values.shape[1])
        if self.interpolation == "LINEAR":
            if self.path == "rotation":
                q, dq = slerp(values[k], values[k + 1], u)
                return q, dq / dt
            return (1.0 - u) * values[k] + u * values[k + 1], (values[k + 1] - values[k]) / dt
        # cubic Hermite: tangents are stored per second, so scaled by the interval
        p0, m0 = values[k, 1], dt * values[k, 2]
        p1, m1 = values[k + 1, 1], dt * values[k + 1, 0]
        u2, u3 = u * u, u * u * u
        p = (2 * u3 - 3 * u2 + 1) * p0 + (u3 - 2 * u2 + u) * m0 + (-2 * u3 + 3 * u2) * p1 \
            + (u3 - u2) * m1
        dp = ((6 * u2 - 6 * u) * p0 + (3 * u2 - 4 * u + 1) * m0 + (-6 * u2 + 6 * u) * p1
              + (3 * u2 - 2 * u) * m1) / dt
        return _normalised(self.path, p, dp)


def _normalised(path: str, value: np.ndarray, rate: np.ndarray):
    """A rotation's value normalised to a unit quaternion (and its rate with it); others as
    they are."""
    if path != "rotation":
        return value, rate
    n = np.linalg.norm(value)
    q = value / n
    return q, (rate - q * (q @ rate)) / n


@dataclass(frozen=True)
class Clip:
    """A named motion of the skeleton: channels over ``[0, duration_s]`` seconds.

    name : the clip's name, unique in its skin
    channels : tuple of :class:`Channel`
    duration_s : seconds, >= 0 (glTF: the last keyframe time over every channel)
    """

    name: str
    channels: tuple
    duration_s: float

    def __post_init__(self):
        object.__setattr__(self, "channels", tuple(self.channels))
        duration = float(self.duration_s)
        if not (np.isfinite(duration) and duration >= 0):
            raise ValueError(f"clip {self.name!r}: duration_s must be finite and >= 0, "
                             f"got {self.duration_s!r}")
        object.__setattr__(self, "duration_s", duration)

    def local_trs(self, skeleton: Skeleton, t: float):
        """The joints' local TRS at ``t`` seconds: ``(translation (J, 3), rotation (J, 4),
        scale (J, 3))`` float64; joints or paths without a channel keep the rest TRS."""
        trs, _ = self.local_trs_rates(skeleton, t)
        return trs

    def local_trs_rates(self, skeleton: Skeleton, t: float):
        """``((translation, rotation, scale), (their d/dt))`` at ``t`` seconds, shapes as
        :meth:`local_trs`; the rates are zero where no channel moves."""
        trs = [skeleton.rest_translation.copy(), skeleton.rest_rotation.copy(),
               skeleton.rest_scale.copy()]
        rates = [np.zeros_like(a) for a in trs]
        slot = {"translation": 0, "rotation": 1, "scale": 2}
        for channel in self.channels:
            if not 0 <= channel.joint < skeleton.joint_count:
                raise ValueError(f"clip {self.name!r} animates joint {channel.joint}, but the "
                                 f"skeleton has {skeleton.joint_count}")
            value, rate = channel.sample(t)
            trs[slot[channel.path]][channel.joint] = value
            rates[slot[channel.path]][channel.joint] = rate
        return tuple(trs), tuple(rates)


@dataclass(frozen=True)
class Skin:
    """A closed rest mesh bound to a skeleton.

    vertices : (V, 3) float64, metres, bind-pose positions in the collider frame
    faces : (F, 3) int64, a closed surface (seams welded)
    joints : (V, K) int64, the joints each vertex follows
    weights : (V, K) float64, >= 0, each row summing to 1
    skeleton : the :class:`Skeleton`
    clips : tuple of :class:`Clip` (possibly empty), unique names
    """

    vertices: np.ndarray
    faces: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    skeleton: Skeleton
    clips: tuple = ()

    def __post_init__(self):
        vertices = np.asarray(self.vertices, dtype=np.float64)
        faces = np.asarray(self.faces, dtype=np.int64)
        joints = np.asarray(self.joints, dtype=np.int64)
        weights = np.asarray(self.weights, dtype=np.float64)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise ValueError(f"vertices must be (V, 3), got {list(vertices.shape)}")
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must be (F, 3), got {list(faces.shape)}")
        if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
            raise ValueError("faces index vertices that do not exist")
        if joints.ndim != 2 or joints.shape[0] != len(vertices) or weights.shape != joints.shape:
            raise ValueError(f"joints and weights must both be (V, K) with V = {len(vertices)}, "
                             f"got {list(joints.shape)} and {list(weights.shape)}")
        if joints.size and (joints.min() < 0 or joints.max() >= self.skeleton.joint_count):
            raise ValueError(f"joints index joints that do not exist (the skeleton has "
                             f"{self.skeleton.joint_count})")
        if not (np.all(np.isfinite(vertices)) and np.all(np.isfinite(weights))):
            raise ValueError("vertices and weights must be finite")
        if np.any(weights < 0) or np.any(np.abs(weights.sum(axis=1) - 1.0) > 1e-6):
            raise ValueError("each vertex's weights must be >= 0 and sum to 1")
        clips = tuple(self.clips)
        names = [c.name for c in clips]
        if len(set(names)) != len(names):
            raise ValueError(f"clip names must be unique, got {names}")
        for name, value in (("vertices", vertices), ("faces", faces), ("joints", joints),
                            ("weights", weights), ("clips", clips)):
            object.__setattr__(self, name, value)

    @property
    def clip_names(self) -> list[str]:
        return [c.name for c in self.clips]

    def clip(self, name: str | None = None) -> Clip:
        """The clip called ``name`` (None: the first); a ValueError names the ones there are."""
        if not self.clips:
            raise ValueError("this skin has no clips")
        if name is None:
            return self.clips[0]
        for clip in self.clips:
            if clip.name == name:
                return clip
        raise ValueError(f"no clip {name!r}; the clips are {self.clip_names}")


# --------------------------------------------------------------------------------------------
# Poses and skinning


def trs_matrices(translation: np.ndarray, rotation: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Local transforms ``T @ R @ S``: translation (J, 3), rotation (J, 4) quaternions (x, y, z,
    w), scale (J, 3) -> (J, 4, 4) float64."""
    translation = np.asarray(translation, dtype=np.float64)
    scale = np.asarray(scale, dtype=np.float64)
    out = np.zeros(translation.shape[:-1] + (4, 4))
    out[..., :3, :3] = quaternion_matrices(rotation) * scale[..., None, :]
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def _trs_rates(trs, rates) -> np.ndarray:
    """d/dt of :func:`trs_matrices` given the TRS and their rates: (J, 4, 4) float64, 1/s."""
    _, rotation, scale = trs
    d_translation, d_rotation, d_scale = rates
    q = rotation / np.linalg.norm(rotation, axis=-1, keepdims=True)
    r = quaternion_matrices(q)
    d_r = 4.0 * _quat_bilinear(q, d_rotation)
    out = np.zeros(q.shape[:-1] + (4, 4))
    out[..., :3, :3] = d_r * scale[..., None, :] + r * d_scale[..., None, :]
    out[..., :3, 3] = d_translation
    return out


def world_transforms(skeleton: Skeleton, local: np.ndarray) -> np.ndarray:
    """The joints' world transforms (J, 4, 4) float64 in the collider frame from their local
    transforms ``local`` (J, 4, 4): ``root @ ... @ local[parent] @ local[j]``."""
    world, _ = _world_and_rates(skeleton, local, None)
    return world


def _world_and_rates(skeleton: Skeleton, local: np.ndarray, local_rates: np.ndarray | None):
    """World transforms and (when ``local_rates`` is given) their d/dt by the product rule."""
    local = np.asarray(local, dtype=np.float64)
    world = np.empty_like(local)
    rates = None if local_rates is None else np.empty_like(local)
    for j, parent in enumerate(skeleton.parents):  # parents come first: one pass down the tree
        above = skeleton.root if parent < 0 else world[parent]
        world[j] = above @ local[j]
        if rates is not None:
            d_above = np.zeros((4, 4)) if parent < 0 else rates[parent]
            rates[j] = d_above @ local[j] + above @ local_rates[j]
    return world, rates


def clip_time(clip: Clip, time_s: float, mode: str = "loop") -> tuple[float, bool]:
    """Where ``time_s`` falls in ``clip``: ``(local time in [0, duration_s], held)``, by the
    animations' time rule (:class:`collider_contract.Timeline`): ``loop`` wraps, ``clamp`` holds
    the ends (``held`` true: the skeleton stands still there)."""
    if mode not in TIME_MODES:
        raise ValueError(f"mode must be one of {list(TIME_MODES)}, got {mode!r}")
    if clip.duration_s <= 0.0:  # a single pose: nothing to wrap or run
        return 0.0, True
    timeline = Timeline.of_clip(clip.duration_s, loop=mode == "loop")
    return timeline.local_time(float(time_s)), timeline.held(float(time_s))


def pose_at(skin: Skin, clip_name: str | None, time_s: float,
            mode: str = "loop") -> tuple[np.ndarray, np.ndarray]:
    """The pose of ``skin`` at ``time_s`` seconds in clip ``clip_name`` (None: the first).

    Returns ``(joint_transforms (J, 4, 4), joint_velocities (J, 4, 4))`` float64: the joints'
    world transforms in the collider frame and their exact time derivatives (1/s; zero where the
    clip is held by ``mode="clamp"``).
    """
    clip = skin.clip(clip_name)
    local_t, held = clip_time(clip, time_s, mode)
    trs, rates = clip.local_trs_rates(skin.skeleton, local_t)
    local = trs_matrices(*trs)
    local_rates = np.zeros_like(local) if held else _trs_rates(trs, rates)
    return _world_and_rates(skin.skeleton, local, local_rates)


def _skinning_matrices(skin: Skin, joint_transforms: np.ndarray) -> np.ndarray:
    """(J, 3, 4): each joint's ``T_j @ inverse_bind_j`` without its last row."""
    m = np.asarray(joint_transforms, dtype=np.float64)
    j = skin.skeleton.joint_count
    if m.shape != (j, 4, 4):
        raise ValueError(f"joint transforms must be [{j}, 4, 4], got {list(m.shape)}")
    return (m @ skin.skeleton.inverse_bind)[:, :3, :]


def _blend(skin: Skin, matrices: np.ndarray, homogeneous: float) -> np.ndarray:
    """``sum_k w_k M_{j_k} [v, homogeneous]`` for every vertex: (V, 3) float64."""
    v = skin.vertices
    out = np.zeros_like(v)
    for k in range(skin.joints.shape[1]):  # K is small (4 in glTF); V is large: vectorise over V
        m = matrices[skin.joints[:, k]]
        out += skin.weights[:, k, None] * (np.einsum("vij,vj->vi", m[:, :, :3], v)
                                           + homogeneous * m[:, :, 3])
    return out


def skin_vertices(skin: Skin, joint_transforms: np.ndarray) -> np.ndarray:
    """Linear blend skinning: the vertices (V, 3) float64, metres, collider frame, at the pose
    ``joint_transforms`` (J, 4, 4) (the joints' world transforms, collider frame)."""
    return _blend(skin, _skinning_matrices(skin, joint_transforms), 1.0)


def skin_velocities(skin: Skin, joint_transforms: np.ndarray,
                    joint_velocities: np.ndarray) -> np.ndarray:
    """The skinned vertices' velocities (V, 3) float64, metres per second, collider frame:
    ``sum_k w_k (dT_{j_k}/dt @ inverse_bind_{j_k}) v`` for joint transforms (J, 4, 4) and their
    time derivatives ``joint_velocities`` (J, 4, 4, 1/s). ``joint_transforms`` fixes nothing in
    linear blend skinning's derivative; it is checked for shape so the pair stays consistent."""
    _skinning_matrices(skin, joint_transforms)
    return _blend(skin, _skinning_matrices(skin, joint_velocities), 1.0)


# --------------------------------------------------------------------------------------------
# Random poses: where a skinned model is trained and measured off its recorded clips

#: The largest turn (degrees) of a joint's local rotation in a perturbed random pose
#: (:func:`random_poses`): training, ``collider eval``, ``collider bench`` and the benchmarks.
PERTURB_DEG = 15.0


@dataclass(frozen=True)
class RandomPoses:
    """Poses drawn by :func:`random_poses`.

    transforms : (n, J, 4, 4) float64, the joints' world transforms, collider frame
    clips : n clip names (None: the skin has no clip, the rest pose was perturbed)
    times : (n,) float64, seconds in each pose's clip (0 without a clip)
    perturbed : (n,) bool, whether the pose's local rotations were turned off the clip
    perturb_deg : the largest turn of a perturbed pose's joints, degrees
    """

    transforms: np.ndarray
    clips: tuple
    times: np.ndarray
    perturbed: np.ndarray
    perturb_deg: float

    def __len__(self) -> int:
        return len(self.transforms)


def random_rotations(rng: np.random.Generator, count: int, max_deg: float) -> np.ndarray:
    """(count, 3, 3) float64 rotations about uniform random axes by angles uniform in
    ``[0, max_deg]`` degrees (Rodrigues' formula)."""
    axis = rng.normal(size=(count, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.radians(rng.uniform(0.0, max_deg, count))
    k = np.zeros((count, 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k = k - np.swapaxes(k, 1, 2)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


def random_poses(skin: Skin, count: int, seed: int, perturb_deg: float = PERTURB_DEG,
                 perturbed_share: float = 1.0) -> RandomPoses:
    """``count`` random poses of ``skin``, reproducible from ``seed``: the one rule by which a
    skinned model is trained (``making.training.articulated``) and measured (``collider eval``,
    ``collider bench``, ``benchmarks/articulated_neural.py``) at poses nobody recorded.

    Each pose: a uniformly random clip of the skin and a uniform random time in ``[0,
    duration_s]`` of it (the rest pose when the skin has no clip); for the last ``perturbed_share``
    of them (rounded), every joint's local rotation then turned by :func:`random_rotations`
    about a uniform random axis by an angle uniform in ``[0, perturb_deg]`` (applied on the right,
    in the joint's own frame; translations and scales as the clip has them). "Within the clip's
    range" means this fixed limit, not each joint's own range over the clip: a joint the clip
    does not move is turned too, by up to ``perturb_deg`` from its clip rotation.
    """
    if count < 0 or not 0.0 <= perturbed_share <= 1.0 or not 0.0 <= perturb_deg <= 180.0:
        raise ValueError(f"random_poses: count >= 0, perturbed_share in [0, 1] and perturb_deg in "
                         f"[0, 180] needed, got {count}, {perturbed_share}, {perturb_deg}")
    rng = np.random.default_rng(seed)
    skeleton = skin.skeleton
    transforms = np.empty((count, skeleton.joint_count, 4, 4))
    clips: list = []
    times = np.zeros(count)
    perturbed_from = count - int(round(count * perturbed_share))
    for i in range(count):
        if skin.clips:
            clip = skin.clips[rng.integers(len(skin.clips))]
            times[i] = rng.uniform(0.0, clip.duration_s)
            local = trs_matrices(*clip.local_trs(skeleton, times[i]))
            clips.append(clip.name)
        else:
            local = skeleton.rest_local()
            clips.append(None)
        if i >= perturbed_from:
            local[:, :3, :3] = local[:, :3, :3] @ random_rotations(rng, skeleton.joint_count, perturb_deg)
        transforms[i] = world_transforms(skeleton, local)
    return RandomPoses(transforms, tuple(clips), times, np.arange(count) >= perturbed_from,
                       float(perturb_deg))
