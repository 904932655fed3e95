"""USD stages written here with the pxr API: time-sampled points read as an animated mesh, and a
UsdSkel character read as a Skin whose skinning equals UsdSkel's own (SkinningQuery
.ComputeSkinnedPoints), in metres, world frame; one-line errors for stages that cannot be used."""

import numpy as np
import pytest

from collider_server.engine.skinning import pose_at, skin_vertices
from collider_server.making.animation_files import AnimationError, load_animation
from collider_server.making.characters import read_character
from collider_server.making.usd import UsdError, read_usd_animation

pxr = pytest.importorskip("pxr")
from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

CUBE_POINTS = [(x, y, z) for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)]
CUBE_QUADS = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]


def cube_stage(path, samples=(0, 2, 4, 6, 8), per_second=24.0, meters_per_unit=0.01):
    """A cube (half-size 1 unit, quads) whose points grow by 10 % per sample and whose parent
    moves 5 units along x per sample."""
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetTimeCodesPerSecond(per_second)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    xform = UsdGeom.Xform.Define(stage, "/Mover")
    move = xform.AddTranslateOp()
    mesh = UsdGeom.Mesh.Define(stage, "/Mover/Cube")
    mesh.CreateFaceVertexCountsAttr([4] * 6)
    mesh.CreateFaceVertexIndicesAttr([i for q in CUBE_QUADS for i in q])
    points = mesh.CreatePointsAttr()
    for k, t in enumerate(samples):
        points.Set([Gf.Vec3f(*(np.array(p) * (1 + 0.1 * k))) for p in CUBE_POINTS], t)
        move.Set(Gf.Vec3d(5.0 * k, 0, 0), t)
    stage.GetRootLayer().Save()
    return path


def test_time_sampled_points_are_an_animated_mesh_in_metres(tmp_path):
    animation = read_usd_animation(cube_stage(tmp_path / "cube.usda"), loop=True)
    assert animation.timeline.frames == 5 and animation.timeline.frame_rate_hz == 12.0
    assert animation.timeline.loop and animation.faces.shape == (12, 3)
    for k in range(5):
        expected = (np.array(CUBE_POINTS) * (1 + 0.1 * k) + [5.0 * k, 0, 0]) * 0.01
        np.testing.assert_allclose(animation.frames[k], expected, atol=1e-7)
    # Wound outward whatever the file's winding: a positive volume.
    v = animation.frames[0][animation.faces]
    assert np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() > 0


def test_the_animation_path_reads_a_stage_and_checks_its_rate(tmp_path):
    stage = cube_stage(tmp_path / "cube.usda")
    assert load_animation(stage, stage, 12.0).timeline.frames == 5
    with pytest.raises(AnimationError, match="its frames play at 12 per second .*give --fps 12"):
        load_animation(stage, stage, 24.0)
    with pytest.raises(AnimationError, match="a USD stage holds its own frames"):
        load_animation(stage, tmp_path / "other.pc2", 12.0)


def test_stages_that_cannot_be_an_animation(tmp_path):
    with pytest.raises(UsdError, match="no mesh with time-sampled points"):
        read_usd_animation(cube_stage(tmp_path / "still.usda", samples=(0,)))
    with pytest.raises(UsdError, match="unevenly spaced"):
        read_usd_animation(cube_stage(tmp_path / "uneven.usda", samples=(0, 1, 3)))
    bad = tmp_path / "bad.usda"
    bad.write_text("#usda 1.0\ndef Mesh \"x\" {\n")
    with pytest.raises(UsdError, match="bad.usda: cannot open the USD stage") as caught:
        read_usd_animation(bad)
    assert "\n" not in str(caught.value)


def skinned_stage(path):
    """A 0.2 x 0.2 x 1 m box (centimetres, Z up) along z under a SkelRoot moved 10 cm along x,
    two joints (base, and tip at 50 cm), weights blending over 25..75 cm, the mesh's joint list
    in the other order, and an animation bending the tip 60 degrees and back over 1 s."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(24)
    root = UsdSkel.Root.Define(stage, "/Char")
    UsdGeom.Xformable(root).AddTranslateOp().Set(Gf.Vec3d(10, 0, 0))
    skel = UsdSkel.Skeleton.Define(stage, "/Char/Skel")
    skel.CreateJointsAttr(["base", "base/tip"])
    tip = Gf.Matrix4d(1).SetTranslate(Gf.Vec3d(0, 0, 50))
    skel.CreateBindTransformsAttr([Gf.Matrix4d(1), tip])
    skel.CreateRestTransformsAttr([Gf.Matrix4d(1), tip])
    heights = [0, 25, 50, 75, 100]
    points = [(x, y, z) for z in heights for (x, y) in [(-10, -10), (10, -10), (10, 10), (-10, 10)]]
    quads = [(r * 4 + k, r * 4 + (k + 1) % 4, r * 4 + (k + 1) % 4 + 4, r * 4 + k + 4)
             for r in range(4) for k in range(4)] + [(3, 2, 1, 0), (16, 17, 18, 19)]
    mesh = UsdGeom.Mesh.Define(stage, "/Char/Body")
    mesh.CreatePointsAttr([Gf.Vec3f(*p) for p in points])
    mesh.CreateFaceVertexCountsAttr([4] * len(quads))
    mesh.CreateFaceVertexIndicesAttr([i for q in quads for i in q])
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointsAttr(["base/tip", "base"])  # the mesh's own joint order
    w = np.clip((np.array(points)[:, 2] - 25) / 50, 0, 1)
    binding.CreateJointIndicesPrimvar(False, 2).Set([j for _ in w for j in (1, 0)])
    binding.CreateJointWeightsPrimvar(False, 2).Set([float(x) for wi in w for x in (1 - wi, wi)])
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
    anim = UsdSkel.Animation.Define(stage, "/Char/Skel/Bend")
    anim.CreateJointsAttr(["base/tip"])
    anim.CreateTranslationsAttr().Set([Gf.Vec3f(0, 0, 50)])
    anim.CreateScalesAttr().Set([Gf.Vec3h(1, 1, 1)])
    rotations = anim.CreateRotationsAttr()
    for code, degrees in [(0, 0), (12, 60), (24, 0)]:
        rotations.Set([Gf.Quatf(Gf.Rotation(Gf.Vec3d(1, 0, 0), degrees).GetQuat())], code)
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    stage.GetRootLayer().Save()
    return path


def usdskel_points(path, time_s):
    """UsdSkel's own skinning of the stage's mesh at ``time_s``, world frame, metres."""
    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    root = UsdSkel.Root(stage.GetPrimAtPath("/Char"))
    cache.Populate(root, Usd.PrimDefaultPredicate)
    binding = cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate)[0]
    query = cache.GetSkelQuery(binding.GetSkeleton())
    target = binding.GetSkinningTargets()[0]
    code = time_s * stage.GetTimeCodesPerSecond()
    points = Vt.Vec3fArray(UsdGeom.Mesh(target.GetPrim()).GetPointsAttr().Get(code))
    assert target.ComputeSkinnedPoints(query.ComputeSkinningTransforms(code), points, code)
    world = np.array(UsdGeom.XformCache(code).GetLocalToWorldTransform(query.GetPrim())).T
    return (np.array(points, dtype=np.float64) @ world[:3, :3].T + world[:3, 3]) * 0.01


def test_a_usdskel_character_skins_as_usdskel_does(tmp_path):
    path = skinned_stage(tmp_path / "char.usda")
    read = read_character(path)
    skin = read.skin
    assert read.notes == ("scaled to metres (0.01 m per stage unit)",)
    assert skin.skeleton.names == ("base", "tip") and skin.skeleton.parents.tolist() == [-1, 0]
    assert [(c.name, c.duration_s) for c in skin.clips] == [("Bend", 1.0)]
    np.testing.assert_allclose(skin.skeleton.root[:3, 3], [0.1, 0, 0])
    bent = skin_vertices(skin, pose_at(skin, "Bend", 0.5)[0])
    assert np.abs(bent - skin_vertices(skin, pose_at(skin, "Bend", 0.0)[0])).max() > 0.2
    for t in (0.0, 0.2, 0.5, 0.77, 1.0):
        ours = skin_vertices(skin, pose_at(skin, "Bend", t, mode="clamp")[0])
        np.testing.assert_allclose(ours, usdskel_points(path, t), rtol=0, atol=1e-6)


def test_a_stage_without_a_skeleton_is_not_a_character(tmp_path):
    with pytest.raises(UsdError, match="cube.usda: no skinned mesh"):
        read_character(cube_stage(tmp_path / "cube.usda"))


def test_collider_bake_reads_stages(capsys, tmp_path):
    """``collider bake STAGE --animation STAGE --fps F --kind mesh`` and ``collider bake STAGE
    --kind skinned`` make models; a wrong rate is one line, exit 2."""
    from collider_cli import main
    from collider_server.engine.modelfile import load_collider

    cube = cube_stage(tmp_path / "cube.usda")
    models = tmp_path / "models"
    assert main(["bake", str(cube), "--animation", str(cube), "--fps", "12", "--loop",
                 "--kind", "mesh", "--name", "cube", "--models", str(models), "--quiet"]) == 0
    assert load_collider(models / "cube.safetensors").info.animation["frames"] == 5
    char = skinned_stage(tmp_path / "char.usda")
    assert main(["bake", str(char), "--kind", "skinned", "--name", "char", "--models", str(models)]) == 0
    out = capsys.readouterr().out
    assert "char.usda: scaled to metres (0.01 m per stage unit)" in out
    assert "kind skinned: 2 joints, 1 clip(s): Bend 1 s; they clamp" in out
    assert main(["bake", str(cube), "--animation", str(cube), "--fps", "30", "--kind", "mesh",
                 "--name", "cube", "--models", str(models)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("its frames play at 12 per second (timeCodesPerSecond and the samples' "
                        "spacing), not 30: give --fps 12") and "\n" not in err
