"""USD stages (``usd-core``'s ``pxr``): a mesh whose points are time-sampled, read as an animated
mesh (the OBJ + PC2 path's :class:`~collider_server.engine.animated_meshes.AnimatedMesh`), and a
UsdSkel character, read as a :class:`~collider_server.engine.skinning.Skin`.

Both come out in metres (the stage's ``metersPerUnit`` applied, and said in the notes) in the
stage's world frame and up axis (``--z-up`` turns a Y-up stage, as for any file).

- **Time-sampled points**: every ``Mesh`` whose ``points`` have more than one time sample (with
  the same samples, merged), at each sample, moved by its world transform at that time;
  polygons split into fans. The samples must be evenly spaced: frame k at ``k * spacing /
  timeCodesPerSecond`` seconds from the first.
- **UsdSkel**: the one ``Skeleton`` skinned meshes are bound to (``UsdSkel.Cache``): its joints
  and topology, rest transforms (local) as TRS, world bind transforms (``inverse_bind`` their
  inverses), the meshes' points through their ``geomBindTransform`` and their joint influences
  (remapped to the skeleton's joint order), the skeleton's world transform as ``root``, and its
  animation source as one LINEAR clip of its time samples (translations, rotations, scales of
  the joints it animates). Blend shapes are ignored (said), as glTF morph targets are.

Every problem is a :class:`UsdError` (a ValueError) naming the file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from collider_contract import Timeline

from ..engine.animated_meshes import AnimatedMesh, max_surface_speed
from ..engine.meshes import Mesh
from ..engine.skinning import Channel, Clip, Skeleton, Skin
from .gltf import SkinFile
from .mesh_files import check_has_volume, file_sha256
from .placement import transformed_skin
from .transforms import matrix_trs

#: Suffixes of USD stages (text, binary, zipped).
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")


class UsdError(ValueError):
    """A USD stage that cannot be read as an animated mesh or a character."""


def _open(path: Path):
    from pxr import Tf, Usd

    if path.is_dir():
        raise UsdError(f"{path}: is a directory, not a USD stage")
    if not path.is_file():
        raise UsdError(f"{path}: no such USD stage")
    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:
        first = str(exc).strip().splitlines()[-1].strip() if str(exc).strip() else "unreadable"
        raise UsdError(f"{path}: cannot open the USD stage ({first})") from None
    if stage is None:
        raise UsdError(f"{path}: cannot open the USD stage")
    return stage


def _matrix(m) -> np.ndarray:
    """A Gf.Matrix4d (row vectors: ``p' = p M``) as a (4, 4) column-vector transform."""
    return np.array(m, dtype=np.float64).reshape(4, 4).T


def _triangles(counts: np.ndarray, indices: np.ndarray, where: str) -> np.ndarray:
    """(F, 3) int64 fans of the polygons ``counts`` over ``indices``."""
    if counts.sum() != len(indices) or np.any(counts < 3):
        raise UsdError(f"{where}: faceVertexCounts do not fit faceVertexIndices (or a face has "
                       "fewer than 3 corners)")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    fans = [np.stack([np.full(c - 2, indices[s]), indices[s + 1:s + c - 1], indices[s + 2:s + c]], axis=1)
            for s, c in zip(starts, counts, strict=True)]
    return np.concatenate(fans).astype(np.int64)


def _topology(mesh, where: str) -> np.ndarray:
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
    if not len(counts):
        raise UsdError(f"{where}: the mesh has no faces")
    return _triangles(counts, indices, where)


def _meters(stage) -> float:
    from pxr import UsdGeom

    return float(UsdGeom.GetStageMetersPerUnit(stage))


# -- time-sampled points ------------------------------------------------------------------------

def read_usd_animation(path: str | Path, loop: bool = False) -> AnimatedMesh:
    """The meshes of ``path`` whose points are time-sampled, as one animated mesh in metres,
    world frame, triangles wound outward; frame rate from the stage's timeCodesPerSecond and
    the samples' spacing; ``loop`` as for any animation."""
    from pxr import Usd, UsdGeom

    path = Path(path)
    stage = _open(path)
    meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    animated = [m for m in meshes if m.GetPointsAttr().GetNumTimeSamples() > 1]
    if not animated:
        raise UsdError(f"{path}: no mesh with time-sampled points ({len(meshes)} mesh(es), none "
                       "animated by its points)")
    samples = [tuple(m.GetPointsAttr().GetTimeSamples()) for m in animated]
    if len(set(samples)) > 1:
        raise UsdError(f"{path}: the animated meshes {[str(m.GetPath()) for m in animated]} are "
                       "sampled at different times")
    times = np.array(samples[0], dtype=np.float64)
    spacing = np.diff(times)
    if not np.allclose(spacing, spacing[0], rtol=1e-9, atol=1e-9):
        raise UsdError(f"{path}: the points' time samples are unevenly spaced ({times[:6].tolist()} ...); "
                       "a vertex cache needs one frame every so many time codes")
    rate = float(stage.GetTimeCodesPerSecond()) / float(spacing[0])
    scale = _meters(stage)
    frames, faces, offset = [], [], 0
    for mesh in animated:
        where = f"{path}: {mesh.GetPath()}"
        faces.append(_topology(mesh, where) + offset)
        cache = UsdGeom.XformCache()
        per_time = []
        for t in times:
            points = np.asarray(mesh.GetPointsAttr().Get(Usd.TimeCode(t)), dtype=np.float64)
            if len(per_time) and points.shape != per_time[0].shape:
                raise UsdError(f"{where}: {len(points)} points at time {t:g}, {len(per_time[0])} "
                               "at the first: a vertex cache keeps its vertices")
            cache.SetTime(Usd.TimeCode(t))
            world = _matrix(cache.GetLocalToWorldTransform(mesh.GetPrim()))
            per_time.append(points @ world[:3, :3].T + world[:3, 3])
        offset += len(per_time[0])
        frames.append(np.stack(per_time))
    frames = np.concatenate(frames, axis=1) * scale
    faces = np.concatenate(faces)
    if not np.all(np.isfinite(frames)):
        raise UsdError(f"{path}: non-finite points")
    try:
        volume = check_has_volume(Mesh(frames[0], faces), f"{path} (first sample)")
    except ValueError as exc:
        raise UsdError(str(exc)) from None
    if volume < 0:
        faces = faces[:, ::-1].copy()
    timeline = Timeline(len(frames), rate, bool(loop), max_surface_speed(frames, rate))
    digest = file_sha256(path)
    return AnimatedMesh(frames, faces, timeline, path.stem, digest, path.name, digest)


# -- UsdSkel ------------------------------------------------------------------------------------

def read_usd_skin(path: str | Path) -> SkinFile:
    """The UsdSkel character of ``path``: its skinned meshes, skeleton and animation, in metres
    and the stage's world frame."""
    from pxr import Usd, UsdSkel

    path = Path(path)
    stage = _open(path)
    notes: list[str] = []
    cache = UsdSkel.Cache()
    bindings = []
    for prim in stage.Traverse():
        if prim.IsA(UsdSkel.Root):
            root = UsdSkel.Root(prim)
            cache.Populate(root, Usd.PrimDefaultPredicate)
            bindings += [b for b in cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate)
                         if b.GetSkinningTargets()]
    if not bindings:
        raise UsdError(f"{path}: no skinned mesh (no SkelRoot with a Skeleton bound to a mesh)")
    if len(bindings) > 1:
        raise UsdError(f"{path}: {len(bindings)} skeletons with skinned meshes "
                       f"({[str(b.GetSkeleton().GetPath()) for b in bindings]}): one skinned "
                       "character per file is supported")
    binding = bindings[0]
    query = cache.GetSkelQuery(binding.GetSkeleton())
    if not query:
        raise UsdError(f"{path}: the skeleton {binding.GetSkeleton().GetPath()} is invalid")
    skeleton = _skeleton(path, stage, query)
    order = {str(name): j for j, name in enumerate(query.GetJointOrder())}
    vertices, faces, joints, weights = _skinned_meshes(path, binding, order, notes)
    # Collider frame = world: the bind-pose vertices and inverse binds taken through the root.
    root = skeleton.root
    vertices = vertices @ root[:3, :3].T + root[:3, 3]
    skeleton = Skeleton(skeleton.names, skeleton.parents, skeleton.rest_translation,
                        skeleton.rest_rotation, skeleton.rest_scale,
                        skeleton.inverse_bind @ np.linalg.inv(root), root)
    sums = weights.sum(axis=1)
    if np.any(sums <= 0):
        raise UsdError(f"{path}: {int((sums <= 0).sum())} points have no joint weight")
    off = np.abs(sums - 1.0)
    if np.any(off > 1e-6):
        notes.append(f"normalised the weights of {int((off > 1e-6).sum()):,} points that did not "
                     f"sum to 1 (off by up to {off.max():.3g})")
    weights = weights / sums[:, None]
    try:
        volume = check_has_volume(Mesh(vertices, faces), str(path))
    except ValueError as exc:
        raise UsdError(str(exc)) from None
    if volume < 0:
        faces = faces[:, ::-1].copy()
    clips = _clips(path, query, order, stage)
    try:
        skin = Skin(vertices, faces, joints, weights, skeleton, tuple(clips))
    except ValueError as exc:
        raise UsdError(f"{path}: {exc}") from None
    scale = _meters(stage)
    if scale != 1.0:
        skin = transformed_skin(skin, np.diag([scale, scale, scale, 1.0]))
        notes.append(f"scaled to metres ({scale:g} m per stage unit)")
    return SkinFile(skin, tuple(notes), path.stem, file_sha256(path))


def _skeleton(path: Path, stage, query) -> Skeleton:
    from pxr import Usd, UsdGeom

    names = [str(n) for n in query.GetJointOrder()]
    parents = np.asarray(query.GetTopology().GetParentIndices(), dtype=np.int64)
    if np.any(parents >= np.arange(len(parents))):
        raise UsdError(f"{path}: the skeleton's joints are not ordered parents first")
    rest = query.ComputeJointLocalTransforms(Usd.TimeCode.Default(), True)
    binds = query.GetJointWorldBindTransforms()
    if rest is None or len(rest) != len(names) or binds is None or len(binds) != len(names):
        raise UsdError(f"{path}: the skeleton needs restTransforms and bindTransforms for each "
                       f"of its {len(names)} joints")
    trs = []
    for name, m in zip(names, rest, strict=True):
        try:
            trs.append(matrix_trs(_matrix(m)))
        except ValueError as exc:
            raise UsdError(f"{path}: joint {name!r}'s rest transform is {exc}") from None
    root = _matrix(UsdGeom.XformCache().GetLocalToWorldTransform(query.GetPrim()))
    inverse_bind = np.linalg.inv(np.stack([_matrix(m) for m in binds]))
    # Unique short names where the paths' last parts are (else the full joint paths).
    short = [n.rsplit("/", 1)[-1] for n in names]
    names = short if len(set(short)) == len(short) else names
    return Skeleton(names, parents, np.array([t for t, _, _ in trs]), np.array([r for _, r, _ in trs]),
                    np.array([s for _, _, s in trs]), inverse_bind, root)


def _skinned_meshes(path: Path, binding, order: dict, notes: list):
    from pxr import UsdGeom

    parts, offset, width = [], 0, 0
    for target in binding.GetSkinningTargets():
        prim = target.GetPrim()
        where = f"{path}: {prim.GetPath()}"
        if not prim.IsA(UsdGeom.Mesh):
            notes.append(f"ignored the skinned {prim.GetTypeName()} {prim.GetPath()} (not a mesh)")
            continue
        mesh = UsdGeom.Mesh(prim)
        points = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
        if target.HasBlendShapes():
            notes.append(f"ignored the blend shapes of {prim.GetPath()} (the rest shape is read)")
        influences = target.ComputeVaryingJointInfluences(len(points))
        if influences is None:
            raise UsdError(f"{where}: its joint influences cannot be read (jointIndices / jointWeights)")
        k = target.GetNumInfluencesPerComponent()
        joints = np.asarray(influences[0], dtype=np.int64).reshape(len(points), k)
        weights = np.asarray(influences[1], dtype=np.float64).reshape(len(points), k)
        mesh_order = target.GetJointOrder()
        if mesh_order:  # the mesh's own joint list: map it onto the skeleton's
            missing = [str(n) for n in mesh_order if str(n) not in order]
            if missing:
                raise UsdError(f"{where}: skel:joints names joints the skeleton lacks: {missing[:5]}")
            remap = np.array([order[str(n)] for n in mesh_order], dtype=np.int64)
            if joints.size and joints.max() >= len(remap):
                raise UsdError(f"{where}: a joint index beyond its {len(remap)} skel:joints")
            joints = remap[joints]
        elif joints.size and (joints.min() < 0 or joints.max() >= len(order)):
            raise UsdError(f"{where}: a joint index beyond the skeleton's {len(order)} joints")
        bind = _matrix(target.GetGeomBindTransform())
        vertices = points @ bind[:3, :3].T + bind[:3, 3]
        parts.append((vertices, _topology(mesh, where) + offset, joints, weights))
        offset += len(points)
        width = max(width, k)
    if not parts:
        raise UsdError(f"{path}: no skinned mesh")

    def pad(a):  # every point gets the most influences any mesh has
        return np.pad(a, ((0, 0), (0, width - a.shape[1])))

    return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
            np.concatenate([pad(p[2]) for p in parts]), np.concatenate([pad(p[3]) for p in parts]))


def _clips(path: Path, query, order: dict, stage) -> list[Clip]:
    """The skeleton's animation source as one LINEAR clip (none when it has no animation)."""
    anim = query.GetAnimQuery()
    if not anim:
        return []
    names = [str(n) for n in anim.GetJointOrder()]
    unknown = [n for n in names if n not in order]
    if unknown:
        raise UsdError(f"{path}: the animation {anim.GetPrim().GetPath()} names joints the "
                       f"skeleton lacks: {unknown[:5]}")
    codes = list(anim.GetJointTransformTimeSamples()) or [0.0]
    per_second = float(stage.GetTimeCodesPerSecond())
    t_values, r_values, s_values = [], [], []
    for code in codes:
        translations, rotations, scales = anim.ComputeJointLocalTransformComponents(code)
        t_values.append(np.asarray(translations, dtype=np.float64))
        # Gf.Quatf is (real, imaginary): glTF order is (x, y, z, w).
        r_values.append(np.array([[*q.GetImaginary(), q.GetReal()] for q in rotations], dtype=np.float64))
        s_values.append(np.asarray(scales, dtype=np.float64))
    times = np.asarray(codes, dtype=np.float64) / per_second
    channels = []
    for a, name in enumerate(names):
        joint = order[name]
        for kind, values in (("translation", t_values), ("rotation", r_values), ("scale", s_values)):
            channels.append(Channel(joint, kind, "LINEAR", times, np.stack([v[a] for v in values])))
    return [Clip(anim.GetPrim().GetName(), tuple(channels), float(times[-1]))]
