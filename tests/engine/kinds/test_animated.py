"""Animated colliders (kinds ``mesh`` and ``voxel`` with an ``animation``): exact at any time
against an independent per-time libigl evaluation of the interpolated mesh, the surface's
velocity against closed forms, the time rule at the ends, keyframe grids, the model file.

Animations: the project's generated ones (collider_server.making.animations), written to OBJ +
PC2 and read back as a user's would be. Metres, seconds; collider frame = world frame (identity
pose) unless a pose is given."""

from __future__ import annotations

import math

import numpy as np
import pytest

from collider_contract import QueryError
from collider_server.engine.modelfile import load_collider, save_collider
from collider_server.making import animations
from collider_server.making.animation_files import load_animation, write_animation
from collider_server.making.bake import bake_animated_collider, bake_collider

RNG = np.random.default_rng(5)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The arm and the pulsing sphere as OBJ + PC2 files, and the sphere's analytic reference."""
    folder = tmp_path_factory.mktemp("animations")
    write_animation(animations.bending_arm(), folder, "arm")
    sphere, reference = animations.pulsing_sphere()
    write_animation(sphere, folder, "sphere")
    return folder, reference


@pytest.fixture(scope="module")
def arm(files):
    folder, _ = files
    animation = load_animation(folder / "arm.obj", folder / "arm.pc2", 24.0, loop=True)
    return animation, bake_animated_collider(animation, "mesh", "arm")


@pytest.fixture(scope="module")
def sphere(files):
    folder, reference = files
    animation = load_animation(folder / "sphere.obj", folder / "sphere.pc2", 12.0, loop=False)
    return animation, bake_animated_collider(animation, "mesh", "sphere"), reference


def independent_distance(frames: np.ndarray, faces: np.ndarray, fps: float, t: float, points):
    """libigl's own distance (its AABB tree, built by ``igl.signed_distance``) to the mesh whose
    vertices are interpolated here, by frame index, between the two frames around ``t`` (inside
    the animation: no loop or clamp), signed by libigl's fast winding number (the rule the mesh
    kind documents: on an open mesh such as the bunny it differs from the exact winding
    number's near the holes)."""
    import igl

    position = t * fps
    k = min(int(math.floor(position)), len(frames) - 2)
    u = position - k
    vertices = (1.0 - u) * frames[k] + u * frames[k + 1]
    points = np.asarray(points, np.float64)
    unsigned, _, _, _ = igl.signed_distance(points, vertices, faces,
                                            sign_type=igl.SIGNED_DISTANCE_TYPE_UNSIGNED)
    inside = igl.fast_winding_number(vertices, faces, points) > 0.5
    return np.where(inside, -np.abs(unsigned), np.abs(unsigned)), vertices


def band_points(vertices, faces, n, band, seed):
    from collider_server.engine.meshes import Mesh
    from collider_server.making.sampling import surface_band_points

    return surface_band_points(Mesh(vertices, faces), n, band, seed)


@pytest.fixture(scope="module")
def bunny(tmp_path_factory):
    """The twisting bunny (35,947 vertices and one per closed hole, 25 frames at 12 fps) through
    its files."""
    from tests.conftest import REPO_ROOT

    from collider_server.making.animation_files import read_obj

    folder = tmp_path_factory.mktemp("bunny")
    write_animation(animations.twisting_bunny(read_obj(REPO_ROOT / "examples/meshes/stanford-bunny.obj")),
                    folder, "bunny")
    animation = load_animation(folder / "bunny.obj", folder / "bunny.pc2", 12.0, loop=True)
    return animation, bake_animated_collider(animation, "mesh", "bunny")


def test_closing_holes_makes_a_box_with_a_missing_side_watertight_and_its_inside_exact():
    """Two triangles of a box's side removed: :func:`animations.closed` adds one vertex and a fan
    of four faces wound as their neighbours; the winding number is then 1 inside and 0 outside
    (not 0.5 near where the side was)."""
    import trimesh

    from collider_server.engine.meshes import ExactSDF, Mesh
    from collider_server.making.mesh_check import check_mesh

    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    faces = np.asarray(box.faces)
    side = np.all(np.asarray(box.vertices)[faces][:, :, 0] > 0.09, axis=1)  # the +x side
    open_box = Mesh(np.asarray(box.vertices), faces[~side], "open")
    assert check_mesh(open_box).holes == 1
    shut = animations.closed(open_box)
    assert len(shut.vertices) == 9 and len(shut.faces) == 14
    assert check_mesh(shut).watertight and check_mesh(shut).intersecting_pairs == 0
    np.testing.assert_allclose(shut.vertices[-1], [0.1, 0.0, 0.0], atol=1e-12)
    points = np.array([[0.09, 0.0, 0.0], [0.11, 0.0, 0.0], [0.0, 0.0, 0.0], [0.3, 0.0, 0.0]])
    np.testing.assert_allclose(ExactSDF(shut).winding_number(points), [1, 0, 1, 0], atol=1e-3)


@pytest.mark.slow
def test_the_twisting_bunny_is_closed_in_every_frame(bunny):
    """The scan's five holes (its open base) closed: watertight, one piece, in every frame."""
    from collider_server.making.mesh_check import check_animation

    check = check_animation(bunny[0])
    assert check.watertight and check.pieces == 1 and check.holes == 0


@pytest.mark.parametrize("which, times, per_band", [
    ("arm", 6, 1500), ("sphere", 6, 1500), pytest.param("bunny", 2, 500, marks=pytest.mark.slow)])
def test_exact_kind_equals_an_independent_libigl_evaluation_at_random_times(which, times, per_band,
                                                                             request):
    """Random times between frames, +-1 mm and +-10 mm bands around the surface at that time:
    the mesh kind's distance equals libigl's on the interpolated vertices to 1e-6 m."""
    animation, collider = request.getfixturevalue(which)[:2]
    frames = np.asarray(animation.frames)
    fps = animation.timeline.frame_rate_hz
    duration = animation.timeline.duration_s
    worst = 0.0
    for t in RNG.uniform(0.0, duration, times):
        _, vertices = independent_distance(frames, animation.faces, fps, t, np.zeros((1, 3)))
        points = np.concatenate([band_points(vertices, animation.faces, n, band, int(1e3 * t))
                                 for band, n in ((1e-3, per_band), (1e-2, per_band))])
        truth, _ = independent_distance(frames, animation.faces, fps, t, points)
        got = collider.query(points, "distance", time=t).distance
        worst = max(worst, float(np.abs(got.astype(np.float64) - truth).max()))
    assert worst <= 1e-6, worst


def test_the_sphere_matches_its_analytic_reference_and_velocity(sphere):
    """The pulsing, moving sphere: the distance is the analytic sphere's within the tessellation
    gap; the surface velocity at each contact's closest point q is c' + r' (q - c) / r exactly."""
    _, collider, reference = sphere
    for t in (0.013, 0.37, 0.5, 0.91):
        centre, radius, dc, dr = reference.at(t)
        assert np.linalg.norm(dc) > 0.05 or abs(dr) > 0.05  # it really moves at these times
        points = centre + RNG.normal(size=(400, 3)) * radius * 0.4
        points = centre + (points - centre) * (radius * RNG.uniform(0.9, 1.1, (400, 1))
                                               / np.linalg.norm(points - centre, axis=1, keepdims=True))
        result = collider.query(points, ["distance", "normal", "velocity"], time=t)
        # Subdivision 3: the faces lie at most about 0.005 r inside the sphere.
        np.testing.assert_allclose(result.distance, reference.signed_distance(points, t), atol=0.006 * radius)
        closest = points - result.distance[:, None].astype(np.float64) * result.normal
        np.testing.assert_allclose(result.velocity, reference.surface_velocity(closest, t),
                                   rtol=1e-5, atol=2e-6)


def test_velocity_at_a_vertex_is_the_vertex_velocity(arm):
    """At a point on a vertex of the moving forearm the velocity is that vertex's finite
    difference between the two frames around t (times the frame rate)."""
    animation, collider = arm
    frames = np.asarray(animation.frames)
    t = 0.3  # segment 7 of 24 fps
    k, u, _rate = animation.timeline.locate(t)
    vertices = (1 - u) * frames[k] + u * frames[k + 1]
    tip = int(np.argmax(vertices[:, 0]))  # the hand's pole
    result = collider.query(vertices[tip:tip + 1], ["velocity"], time=t)
    expected = (frames[k + 1, tip] - frames[k, tip]) * 24.0
    assert np.linalg.norm(expected) > 0.3  # m/s: the hand moves
    np.testing.assert_allclose(result.velocity[0], expected, rtol=1e-6)


def test_the_ends_loop_or_clamp(sphere, files):
    """Clamped: before 0 and from the end on, the end frames held, velocity zero; looping: the
    time wraps by the duration."""
    animation, clamped, _ = sphere
    duration = animation.timeline.duration_s
    points = RNG.uniform(-0.2, 0.2, (200, 3))
    end = clamped.query(points, ["distance", "velocity"], time=duration)
    later = clamped.query(points, ["distance", "velocity"], time=duration + 7.3)
    np.testing.assert_array_equal(end.distance, later.distance)
    assert not later.velocity.any() and not end.velocity.any()
    before = clamped.query(points, ["distance", "velocity"], time=-2.0)
    first = clamped.query(points, ["distance"], time=0.0)
    np.testing.assert_array_equal(before.distance, first.distance)
    assert not before.velocity.any()
    assert clamped.query(points, ["velocity"], time=0.0).velocity.any()  # it starts moving at 0
    looping = bake_animated_collider(load_animation(files[0] / "sphere.obj", files[0] / "sphere.pc2",
                                                    12.0, loop=True), "mesh", "looping")
    inside = looping.query(points, ["distance", "velocity"], time=0.3)
    wrapped = looping.query(points, ["distance", "velocity"], time=0.3 + 3 * duration)
    np.testing.assert_allclose(wrapped.distance, inside.distance, atol=1e-7)
    np.testing.assert_allclose(wrapped.velocity, inside.velocity, atol=1e-6)


def test_time_is_required_and_a_static_model_ignores_it(arm, sphere):
    _, collider = arm
    with pytest.raises(QueryError, match="is animated: give the time") as caught:
        collider.query(np.zeros((2, 3)), "distance")
    assert caught.value.code == "missing-time" and caught.value.status == 422
    with pytest.raises(QueryError, match="time must be a finite number") as caught:
        collider.query(np.zeros((2, 3)), "distance", time=float("nan"))
    assert caught.value.code == "bad-time"
    static = bake_collider(sphere[0].frame(0), "mesh", "still")
    points = RNG.uniform(-0.2, 0.2, (50, 3))
    np.testing.assert_array_equal(static.query(points, ["distance", "normal"]).distance,
                                  static.query(points, ["distance", "normal"], time=123.0).distance)


def test_one_tree_per_distinct_time_and_the_same_answer_in_tiny_chunks(files):
    folder, _ = files
    animation = load_animation(folder / "arm.obj", folder / "arm.pc2", 24.0, loop=True)
    collider = bake_animated_collider(animation, "mesh", "arm")
    points = RNG.uniform(-0.1, 0.6, (600, 3))
    whole = collider.query(points, ["distance", "normal", "velocity"], time=0.41)
    collider.query(points, ["distance"], time=0.41)
    assert collider.exact.builds == 1  # the second query at that time reused the tree
    collider.chunk_points = 17
    chunked = collider.query(points, ["distance", "normal", "velocity"], time=0.41)
    assert collider.exact.builds == 1
    for name in ("distance", "normal", "velocity"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(chunked, name))
    collider.query(points[:5], "distance", time=0.42)
    assert collider.exact.builds == 2 and collider.exact.build_s > 0


def test_a_pose_and_its_velocity_add_the_frame_motion(arm):
    """World velocity = the frame's motion at the contact + the surface's own, rotated and
    scaled into the world (collider_contract.answers)."""
    _, collider = arm
    angle = 0.4
    pose = np.eye(4)
    pose[:3, :3] = 2.0 * np.array([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0],
                                   [0, 0, 1]])
    pose[:3, 3] = [0.3, -0.2, 0.1]
    local = RNG.uniform(-0.05, 0.55, (300, 3))
    world = local @ pose[:3, :3].T + pose[:3, 3]
    rate = np.zeros((4, 4))
    rate[:3, 3] = [0.0, 0.0, 1.5]  # the frame rises at 1.5 m/s
    own = collider.query(local, ["velocity", "contact"], time=0.2)
    placed = collider.query(world, ["velocity", "contact"], time=0.2, pose=pose, pose_velocity=rate)
    expected = own.velocity.astype(np.float64) @ pose[:3, :3].T + [0.0, 0.0, 1.5]
    np.testing.assert_allclose(placed.velocity, expected, atol=1e-5)


@pytest.fixture(scope="module")
def voxel_arm(arm):
    animation, _ = arm
    return bake_animated_collider(animation, "voxel", "arm-voxel", resolution=32, keyframes=7,
                                  show_progress=False)


def test_voxel_keyframes_are_the_static_grids_and_interpolate_linearly(arm, voxel_arm):
    """At a keyframe the grid is the static bake of that frame; between two keyframes the
    distance is linear in time and the velocity is -df/dt along the unit normal."""
    animation, _ = arm
    timeline = voxel_arm.timeline
    assert (timeline.frames, timeline.duration_s) == (7, pytest.approx(animation.timeline.duration_s))
    assert voxel_arm.info.animation["frames"] == 7 and voxel_arm.info.settings["keyframes"] == 7
    # Keyframe 2 is source frame 8 (24 frames / 6 intervals): its static bake, same box.
    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.bake import bake_grid

    grid = bake_grid(ExactSDF(animation.frame(8)), voxel_arm.domain_min, voxel_arm.domain_max, 32,
                     show_progress=False)
    np.testing.assert_array_equal(voxel_arm.tensors()["grids"][2], grid)
    points = RNG.uniform(voxel_arm.domain_min, voxel_arm.domain_max, (500, 3))
    t0, t1 = 2 / timeline.frame_rate_hz, 3 / timeline.frame_rate_hz
    d0 = voxel_arm.query(points, "distance", time=t0).distance.astype(np.float64)
    d1 = voxel_arm.query(points, "distance", time=t1).distance.astype(np.float64)
    middle = voxel_arm.query(points, ["distance", "normal", "velocity"], time=0.25 * t0 + 0.75 * t1)
    np.testing.assert_allclose(middle.distance, 0.25 * d0 + 0.75 * d1, atol=1e-6)
    expected = -((d1 - d0) / (t1 - t0))[:, None] * middle.normal
    np.testing.assert_allclose(middle.velocity, expected, atol=1e-4)


def test_voxel_keyframes_track_the_exact_surface(arm, voxel_arm):
    """Near the surface at a time between keyframes the voxel distance is within a few cells of
    the exact one, and the normal speed has the sign of the exact surface's."""
    animation, exact = arm
    t = 0.37
    mesh = animation.mesh_at(t)
    points = band_points(mesh.vertices, mesh.faces, 2000, 1e-3, 3)
    truth = exact.query(points, ["distance", "normal", "velocity"], time=t)
    got = voxel_arm.query(points, ["distance", "normal", "velocity"], time=t)
    cell = float((voxel_arm.domain_max - voxel_arm.domain_min).max()) / 31
    assert np.abs(got.distance - truth.distance).max() < 2 * cell
    exact_normal_speed = np.einsum("ij,ij->i", truth.velocity, truth.normal)
    voxel_normal_speed = np.einsum("ij,ij->i", got.velocity, got.normal)
    moving = np.abs(exact_normal_speed) > 0.2
    assert moving.sum() > 100
    agree = np.sign(voxel_normal_speed[moving]) == np.sign(exact_normal_speed[moving])
    assert agree.mean() > 0.95
    tangential = got.velocity - voxel_normal_speed[:, None] * got.normal
    assert np.abs(tangential).max() < 1e-5  # none: an implicit surface does not say


@pytest.mark.parametrize("kind", ["mesh", "voxel"])
def test_animated_models_round_trip_through_their_files(tmp_path, arm, voxel_arm, kind):
    collider = arm[1] if kind == "mesh" else voxel_arm
    path = save_collider(collider, tmp_path / f"{kind}.safetensors")
    loaded = load_collider(path, "cpu")
    assert type(loaded) is type(collider) and loaded.animated
    assert loaded.info.animation == collider.info.animation
    assert loaded.info.animation["loop"] is True and loaded.info.source["cache"] == "arm.pc2"
    assert len(loaded.info.source["cache_sha256"]) == 64
    points = RNG.uniform(-0.1, 0.6, (300, 3))
    for t in (0.0, 0.33, 5.01):
        a = collider.query(points, ["distance", "normal", "velocity"], time=t)
        b = loaded.query(points, ["distance", "normal", "velocity"], time=t)
        for name in ("distance", "normal", "velocity"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_a_model_file_with_a_bad_animation_is_refused(tmp_path, arm):
    from collider_server.engine.modelfile import ModelFileError

    collider = arm[1]
    collider.info.animation = {**collider.info.animation, "frames": 3}
    try:
        path = save_collider(collider, tmp_path / "bad.safetensors")
    finally:
        collider.info.animation = {**collider.info.animation, "frames": 25}
    with pytest.raises(ModelFileError, match="25 frames, but the timeline has 3"):
        load_collider(path)
    kdtree = bake_collider(arm[0].frame(0), "kdtree", "k")
    kdtree.info.animation = dict(arm[1].info.animation)
    path = save_collider(kdtree, tmp_path / "k.safetensors")
    with pytest.raises(ModelFileError, match="a kdtree collider cannot be animated"):
        load_collider(path)


@pytest.mark.parametrize("damage, message", [
    (lambda t: t.pop("faces"), r"must hold 'frames' and 'faces', found \['frames'\]"),
    (lambda t: t.update(extra=np.zeros(1)), r"found \['extra', 'faces', 'frames'\]"),
    (lambda t: t.update(faces=np.zeros((4, 4), np.int32)), r"wrong shapes: frames \(25, \d+, 3\), faces \(4, 4\)"),
    (lambda t: t.update(faces=np.zeros(12, np.int32)), r"wrong shapes: .*faces \(12,\)"),
    (lambda t: t.update(frames=t["frames"][..., :2]), r"wrong shapes: frames \(25, \d+, 2\)"),
], ids=["no faces", "an extra array", "quads", "flat faces", "2d frames"])
def test_an_animated_mesh_model_whose_arrays_do_not_fit_says_which(arm, damage, message):
    """(a ValueError: :func:`load_collider` says it as the file's problem, no traceback)"""
    from collider_server.engine.kinds.animated_mesh import AnimatedMeshCollider

    collider = arm[1]
    tensors = collider.tensors()
    damage(tensors)
    with pytest.raises(ValueError, match=message):
        AnimatedMeshCollider.from_tensors(collider.info, tensors)
