"""The walker: a generated human figure the project owns (nothing downloaded), skinned to a
20-joint skeleton, with a walk cycle and a wave, to test skinned colliders end to end.

- **Body**: ellipsoids (hips, belly, chest, head) and capsules (neck, arms, legs, feet), merged
  into one smooth closed surface by marching cubes of the smooth minimum of their distances;
  about 1.73 m tall, Y up, metres, facing +z, feet on y = 0, arms 45 degrees down from the
  shoulders (an A pose).
- **Skeleton**: pelvis, three spine joints, neck, head, and per side a clavicle, upper arm,
  forearm, hand, thigh, shin and foot (20 joints); every rest rotation is the identity, so a
  joint's bind frame is its rest position.
- **Weights**: from each vertex's distance to the bones (the segment from a joint to its child),
  ``exp(-(d - d_nearest) / blend_m)`` over the nearest bone's joint and its parent and children,
  the 4 largest kept and normalised: smooth across joints, never across the body to the other leg.
- **Clips**: ``walk`` (1 s, loops: hips, knees, ankles, arms, a pelvis bob and twist, in place),
  ``wave`` (2 s: the right arm rises, its forearm waves, and back down).

Its exact reference, :meth:`Walker.reference_vertices`: the vertices skinned by this module's own
forward kinematics (rotation matrices from the keyframe angles, no quaternions) from the same
float32-rounded numbers the glTF file stores. :func:`collider_server.making.gltf_writer
.write_gltf` writes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..engine.meshes import Mesh
from ..engine.skinning import Channel, Clip, Skeleton, Skin

#: (name, parent, rest position (x, y, z) metres) of every joint, parents first.
JOINTS = (
    ("pelvis", -1, (0.0, 0.95, 0.0)),
    ("spine", 0, (0.0, 1.05, 0.0)),
    ("spine1", 1, (0.0, 1.18, 0.0)),
    ("chest", 2, (0.0, 1.32, 0.0)),
    ("neck", 3, (0.0, 1.47, 0.0)),
    ("head", 4, (0.0, 1.57, 0.0)),
    ("clavicle.L", 3, (0.04, 1.43, 0.0)),
    ("upper_arm.L", 6, (0.18, 1.43, 0.0)),
    ("forearm.L", 7, (0.18 + 0.28 * math.sin(math.pi / 4), 1.43 - 0.28 * math.cos(math.pi / 4), 0.0)),
    ("hand.L", 8, (0.18 + 0.53 * math.sin(math.pi / 4), 1.43 - 0.53 * math.cos(math.pi / 4), 0.0)),
    ("clavicle.R", 3, (-0.04, 1.43, 0.0)),
    ("upper_arm.R", 10, (-0.18, 1.43, 0.0)),
    ("forearm.R", 11, (-0.18 - 0.28 * math.sin(math.pi / 4), 1.43 - 0.28 * math.cos(math.pi / 4), 0.0)),
    ("hand.R", 12, (-0.18 - 0.53 * math.sin(math.pi / 4), 1.43 - 0.53 * math.cos(math.pi / 4), 0.0)),
    ("thigh.L", 0, (0.10, 0.92, 0.0)),
    ("shin.L", 14, (0.10, 0.50, 0.0)),
    ("foot.L", 15, (0.10, 0.09, 0.0)),
    ("thigh.R", 0, (-0.10, 0.92, 0.0)),
    ("shin.R", 17, (-0.10, 0.50, 0.0)),
    ("foot.R", 18, (-0.10, 0.09, 0.0)),
)
NAMES = tuple(j[0] for j in JOINTS)
PARENTS = np.array([j[1] for j in JOINTS], dtype=np.int64)
POSITIONS = np.array([j[2] for j in JOINTS], dtype=np.float64)


def _index(name: str) -> int:
    return NAMES.index(name)


def _hand_end(side: str) -> np.ndarray:
    sign = 1.0 if side == "L" else -1.0
    return POSITIONS[_index(f"hand.{side}")] + 0.10 * np.array([sign * math.sin(math.pi / 4),
                                                                -math.cos(math.pi / 4), 0.0])


#: Each joint's bone: the segment (start, end) its vertices follow, metres, rest pose.
def _bones() -> np.ndarray:
    p = {n: POSITIONS[i] for i, n in enumerate(NAMES)}
    bones = {
        "pelvis": (p["pelvis"] - [0, 0.05, 0], p["spine"]),
        "spine": (p["spine"], p["spine1"]),
        "spine1": (p["spine1"], p["chest"]),
        "chest": (p["chest"], p["neck"]),
        "neck": (p["neck"], p["head"]),
        "head": (p["head"], p["head"] + [0, 0.12, 0.02]),
    }
    for side in "LR":
        bones[f"clavicle.{side}"] = (p[f"clavicle.{side}"], p[f"upper_arm.{side}"])
        bones[f"upper_arm.{side}"] = (p[f"upper_arm.{side}"], p[f"forearm.{side}"])
        bones[f"forearm.{side}"] = (p[f"forearm.{side}"], p[f"hand.{side}"])
        bones[f"hand.{side}"] = (p[f"hand.{side}"], _hand_end(side))
        bones[f"thigh.{side}"] = (p[f"thigh.{side}"], p[f"shin.{side}"])
        bones[f"shin.{side}"] = (p[f"shin.{side}"], p[f"foot.{side}"])
        bones[f"foot.{side}"] = (p[f"foot.{side}"], p[f"foot.{side}"] + [0, -0.04, 0.16])
    return np.array([bones[n] for n in NAMES], dtype=np.float64)


BONES = _bones()


# -- the body ----------------------------------------------------------------------------------

def _capsule(points, a, b, radius):
    ab = np.asarray(b, float) - a
    u = np.clip(((points - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + u[:, None] * ab), axis=1) - radius


def _ellipsoid(points, centre, radii):
    """A distance-like function of an ellipsoid (exact on its surface, scaled by its smallest
    radius elsewhere): enough for a smooth union's zero level."""
    radii = np.asarray(radii, float)
    return (np.linalg.norm((points - centre) / radii, axis=1) - 1.0) * radii.min()


def body_distance(points: np.ndarray, blend_m: float = 0.03) -> np.ndarray:
    """(n,) the body's smooth distance at ``points`` (n, 3) metres, rest pose: the polynomial
    smooth minimum (blend radius ``blend_m``) of the parts' distances; negative inside."""
    p = {n: POSITIONS[i] for i, n in enumerate(NAMES)}
    parts = [
        _ellipsoid(points, [0.0, 0.93, 0.0], [0.16, 0.12, 0.105]),  # hips
        _ellipsoid(points, [0.0, 1.12, 0.0], [0.135, 0.14, 0.095]),  # belly
        _ellipsoid(points, [0.0, 1.32, 0.0], [0.165, 0.13, 0.105]),  # chest
        _capsule(points, p["chest"] + [0, 0.1, 0], p["head"], 0.05),  # neck
        _ellipsoid(points, p["head"] + [0, 0.06, 0.015], [0.085, 0.105, 0.1]),  # head
    ]
    for side in "LR":
        s = {n: p[f"{n}.{side}"] for n in ("clavicle", "upper_arm", "forearm", "hand", "thigh", "shin", "foot")}.get
        parts += [
            _capsule(points, s("clavicle") + [0, -0.02, 0], s("upper_arm"), 0.06),  # shoulder
            _capsule(points, s("upper_arm"), s("forearm"), 0.048),
            _capsule(points, s("forearm"), s("hand"), 0.04),
            _capsule(points, s("hand"), _hand_end(side), 0.035),
            _capsule(points, s("thigh") + [0, -0.02, 0], s("shin"), 0.075),
            _capsule(points, s("shin"), s("foot"), 0.052),
            _capsule(points, s("foot") + [0, -0.04, -0.02], s("foot") + [0, -0.05, 0.15], 0.042),
        ]
    d = parts[0]
    for other in parts[1:]:  # smooth minimum: the parts grow together within blend_m
        h = np.clip(0.5 + 0.5 * (other - d) / blend_m, 0.0, 1.0)
        d = other * (1 - h) + d * h - blend_m * h * (1 - h)
    return d


def body_mesh(spacing_m: float = 0.025) -> Mesh:
    """The body's surface (marching cubes of :func:`body_distance` on a grid of ``spacing_m``),
    a closed mesh, triangles wound outward, float64 metres, Y up."""
    from skimage.measure import marching_cubes

    from .mesh_check import merged
    from .mesh_files import check_has_volume

    lo, hi = np.array([-0.75, -0.04, -0.2]), np.array([0.75, 1.78, 0.28])
    axes = [np.arange(lo[i], hi[i] + spacing_m, spacing_m) for i in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    values = body_distance(points).reshape([len(a) for a in axes])
    verts, faces, _, _ = marching_cubes(values, level=0.0, spacing=(spacing_m,) * 3)
    # Marching cubes repeats a vertex that falls on a grid corner: merge them.
    verts, faces, _ = merged(verts + lo, faces)
    mesh = Mesh(verts, faces, "walker")
    return mesh if check_has_volume(mesh, "walker") > 0 else Mesh(verts, faces[:, ::-1].copy(), "walker")


def bone_weights(vertices: np.ndarray, blend_m: float = 0.025, influences: int = 4):
    """(V, K) joints and weights of ``vertices`` (V, 3) metres, rest pose: ``exp(-(d -
    d_nearest) / blend_m)`` over the bones of the nearest bone's joint, its parent and its
    children, the ``influences`` largest kept, normalised."""
    a, b = BONES[:, 0], BONES[:, 1]
    ab = b - a
    u = np.clip(np.einsum("vjk,jk->vj", vertices[:, None] - a, ab) / (ab * ab).sum(1), 0.0, 1.0)
    d = np.linalg.norm(vertices[:, None] - (a + u[..., None] * ab), axis=2)  # (V, J)
    nearest = d.argmin(axis=1)
    j = len(NAMES)
    near = np.eye(j, dtype=bool)  # the joints a joint's vertices may follow
    for child, parent in enumerate(PARENTS):
        if parent >= 0:
            near[child, parent] = near[parent, child] = True
    allowed = near[nearest]
    w = np.where(allowed, np.exp(-(d - d.min(axis=1, keepdims=True)) / blend_m), 0.0)
    joints = np.argsort(-w, axis=1)[:, :influences]
    weights = np.take_along_axis(w, joints, axis=1)
    weights[weights < 1e-4] = 0.0
    return joints.astype(np.int64), weights / weights.sum(axis=1, keepdims=True)


# -- the clips ---------------------------------------------------------------------------------

def _axis_angle_quaternion(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([axis * math.sin(angle / 2), [math.cos(angle / 2)]])


def _rotation_matrix(axis, angle) -> np.ndarray:
    """Rodrigues' formula (no quaternion): the reference's own rotation."""
    x, y, z = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


@dataclass(frozen=True)
class Motion:
    """One clip as keyframes of joint rotations (axis, angle) and the pelvis's translation.

    times : (k,) seconds; rotations : {joint: (axis (3,), angles (k,) radians)};
    pelvis_offset : (k, 3) metres added to the pelvis's rest position
    """

    name: str
    times: np.ndarray
    rotations: dict
    pelvis_offset: np.ndarray


def walk_motion(frames: int = 31, duration_s: float = 1.0) -> Motion:
    """The walk cycle, in place: ``frames`` keyframes over ``duration_s``, the last the first."""
    t = np.linspace(0.0, duration_s, frames)
    phase = 2 * np.pi * t / duration_s
    x, y = [1.0, 0, 0], [0, 1.0, 0]
    deg = np.radians
    rot = {}
    for side, shift in (("L", 0.0), ("R", np.pi)):
        ph = phase + shift
        rot[f"thigh.{side}"] = (x, -deg(25) * np.sin(ph))  # forward is -angle about +x
        rot[f"shin.{side}"] = (x, deg(5) + deg(30) * np.clip(np.sin(ph - 1.2), 0, None) ** 1.5)
        rot[f"foot.{side}"] = (x, -deg(10) * np.sin(ph + 0.6))
        # Arms swing against the legs, about the axis across the body's front.
        rot[f"upper_arm.{side}"] = (x, deg(18) * np.sin(ph))
        rot[f"forearm.{side}"] = (x, -deg(10) - deg(10) * (1 + np.sin(ph)) / 2)
    rot["pelvis"] = (y, deg(6) * np.sin(phase))
    rot["spine1"] = (y, -deg(8) * np.sin(phase))
    bob = np.stack([np.zeros(frames), 0.015 * np.cos(2 * phase), np.zeros(frames)], axis=1)
    return Motion("walk", t, {k: (np.asarray(a, float), np.asarray(v, float)) for k, (a, v) in rot.items()}, bob)


def wave_motion(frames: int = 41, duration_s: float = 2.0) -> Motion:
    """The right arm rises (about the body's front axis), its forearm waves three times, and it
    comes back down; ``frames`` keyframes over ``duration_s``."""
    t = np.linspace(0.0, duration_s, frames)
    up = np.sin(np.pi * t / duration_s) ** 2  # 0 -> 1 -> 0
    deg = np.radians
    rot = {
        "upper_arm.R": (np.array([0, 0, 1.0]), -deg(100) * up),
        "forearm.R": (np.array([0, 0, 1.0]), -deg(40) * up + deg(25) * up * np.sin(6 * np.pi * t / duration_s)),
        "clavicle.R": (np.array([0, 0, 1.0]), -deg(12) * up),
        "spine1": (np.array([0, 0, 1.0]), deg(4) * up),
    }
    return Motion("wave", t, rot, np.zeros((frames, 3)))


# -- the walker --------------------------------------------------------------------------------

@dataclass(frozen=True)
class Walker:
    """The generated figure: its rest mesh, skinning and motions, every number rounded to
    float32 as a glTF file stores it.

    vertices : (V, 3) float64 metres; faces : (F, 3) int64; joints, weights : (V, 4)
    motions : tuple of :class:`Motion`
    """

    vertices: np.ndarray
    faces: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    motions: tuple

    def keyframes(self, motion: Motion):
        """Per keyframe the joints' local translation (k, J, 3) and rotation (k, J, 4)
        quaternions, float32-rounded, as the file stores them."""
        k, j = len(motion.times), len(NAMES)
        translation = np.empty((k, j, 3))
        rotation = np.tile([0.0, 0.0, 0.0, 1.0], (k, j, 1))
        local = POSITIONS - np.where(PARENTS[:, None] >= 0, POSITIONS[PARENTS], 0.0)
        translation[:] = local
        translation[:, 0] += motion.pelvis_offset
        for name, (axis, angles) in motion.rotations.items():
            rotation[:, _index(name)] = [_axis_angle_quaternion(axis, a) for a in angles]
        return _f32(translation), _f32(rotation)

    def skin(self) -> Skin:
        """The walker as an engine :class:`Skin` (rest = bind pose; LINEAR clips)."""
        local = _f32(POSITIONS - np.where(PARENTS[:, None] >= 0, POSITIONS[PARENTS], 0.0))
        inverse_bind = np.tile(np.eye(4), (len(NAMES), 1, 1))
        inverse_bind[:, :3, 3] = -_f32(POSITIONS)
        skeleton = Skeleton(NAMES, PARENTS, local, np.tile([0.0, 0, 0, 1], (len(NAMES), 1)),
                            np.ones((len(NAMES), 3)), inverse_bind)
        clips = []
        for motion in self.motions:
            translation, rotation = self.keyframes(motion)
            times = _f32(motion.times)
            channels = [Channel(0, "translation", "LINEAR", times, translation[:, 0])]
            channels += [Channel(_index(n), "rotation", "LINEAR", times, rotation[:, _index(n)])
                         for n in motion.rotations]
            clips.append(Clip(motion.name, tuple(channels), float(times[-1])))
        return Skin(self.vertices, self.faces, self.joints, self.weights, skeleton, tuple(clips))

    def reference_vertices(self, motion: Motion, key: int) -> np.ndarray:
        """(V, 3) float64 metres: the vertices at keyframe ``key`` of ``motion`` by this
        module's own forward kinematics and skinning: each joint's world rotation and position
        composed from Rodrigues matrices of the keyframe angles, then ``sum_k w_k (R_j (v -
        rest_j) + position_j)``."""
        rotations = np.tile(np.eye(3), (len(NAMES), 1, 1))
        for name, (axis, angles) in motion.rotations.items():
            rotations[_index(name)] = _rotation_matrix(axis, angles[key])
        world_r = np.empty_like(rotations)
        world_p = np.empty((len(NAMES), 3))
        rest = _f32(POSITIONS)
        for j, parent in enumerate(PARENTS):
            offset = rest[j] - (rest[parent] if parent >= 0 else 0.0)
            if parent < 0:
                world_r[j], world_p[j] = rotations[j], offset + _f32(motion.pelvis_offset[key])
            else:
                world_r[j] = world_r[parent] @ rotations[j]
                world_p[j] = world_r[parent] @ offset + world_p[parent]
        out = np.zeros_like(self.vertices)
        for k in range(self.joints.shape[1]):
            j = self.joints[:, k]
            moved = np.einsum("vij,vj->vi", world_r[j], self.vertices - rest[j]) + world_p[j]
            out += self.weights[:, k, None] * moved
        return out


def _f32(a) -> np.ndarray:
    return np.asarray(a, dtype=np.float32).astype(np.float64)


def make_walker(spacing_m: float = 0.025) -> Walker:
    """The walker with its body meshed at ``spacing_m`` (0.025 m: about 8,000 faces)."""
    mesh = body_mesh(spacing_m)
    vertices = _f32(mesh.vertices)
    joints, weights = bone_weights(vertices)
    weights = _f32(weights)  # as stored: sums within float32 rounding of 1
    return Walker(vertices, mesh.faces, joints, weights, (walk_motion(), wave_motion()))


def walk_animation(walker: Walker, frames: int | None = None):
    """The walk as an animated mesh (what ``collider animate walker`` writes as OBJ + PC2):
    ``frames`` frames over its second (default its 31 keyframes at 30 fps), the walker skinned
    at each by the engine (equal to :meth:`Walker.reference_vertices` on the keyframes), turned
    Z up like the project's other animations, looping."""
    from collider_contract import Timeline

    from ..engine.animated_meshes import AnimatedMesh, max_surface_speed
    from ..engine.skinning import pose_at, skin_vertices
    from .placement import Y_UP_TO_Z_UP

    skin = walker.skin()
    clip = skin.clip("walk")
    frames = frames or len(walk_motion().times)
    times = np.linspace(0.0, clip.duration_s, frames)
    rotation = Y_UP_TO_Z_UP[:3, :3]
    out = np.stack([skin_vertices(skin, pose_at(skin, "walk", t, "clamp")[0]) @ rotation.T
                    for t in times])
    rate = (frames - 1) / clip.duration_s
    timeline = Timeline(frames, rate, True, max_surface_speed(out, rate))
    return AnimatedMesh(out, skin.faces, timeline, "walker")
