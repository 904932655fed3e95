"""Every kind against the exact SDF on the real test meshes (skipped when the shared meshes
folder is absent): the open Stanford bunny (metres), fandisk (sharp creases) and Suzanne (open,
self-touching pieces), in each mesh's own units and frame. Bounds are relative to the mesh size
and the voxel cell; measured values are 2-5x below them."""

from __future__ import annotations

import numpy as np
import pytest

from collider_server.engine.meshes import ExactSDF, Mesh
from collider_server.making.bake import bake_collider
from collider_server.making.sampling import surface_band_points

MESHES = ["stanford-bunny.obj", "fandisk.obj", "suzanne.obj"]
RESOLUTION = 64


_CACHE: dict = {}


def _colliders(mesh):
    """The baked kinds of ``mesh``, built once per session (keyed by the file's hash)."""
    key = ("colliders", mesh.sha256)
    if key not in _CACHE:
        _CACHE[key] = {kind: bake_collider(mesh, kind, kind, resolution=RESOLUTION, device="cpu",
                                       show_progress=False) for kind in ("voxel", "mesh", "kdtree")}
    return _CACHE[key]


def _truth(mesh, n=2000, seed=0):
    """Points in a band of 1 % of the largest side around the surface, their exact signed
    distance and the unit direction to the exact closest point (cached)."""
    key = ("truth", mesh.sha256, n, seed)
    if key not in _CACHE:
        _CACHE[key] = _compute_truth(mesh, n, seed)
    return _CACHE[key]


def _compute_truth(mesh, n, seed):
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    points = surface_band_points(mesh, n, 0.01 * extent, seed)
    exact = ExactSDF(mesh)
    distance, closest, face = exact.query(points)
    return points, distance, exact.gradient(points, distance, closest, face), extent


def edges(mesh):
    tri = mesh.vertices[mesh.faces]
    return np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)


@pytest.mark.parametrize("name", MESHES)
def test_voxel_kind_is_within_a_fraction_of_a_cell(load_shared_mesh, name):
    mesh = load_shared_mesh(name)
    voxel = _colliders(mesh)["voxel"]
    points, distance, normal, extent = _truth(mesh)
    cell = float(np.max((voxel.domain_max - voxel.domain_min) / (RESOLUTION - 1)))
    result = voxel.query(points, ["distance", "normal"])
    error = np.abs(result.distance - distance)
    assert error.mean() < 0.05 * cell and error.max() < 0.6 * cell, (error.mean() / cell, error.max() / cell)
    clear = np.abs(distance) > 0.2 * 0.01 * extent
    assert (np.sign(result.distance[clear]) != np.sign(distance[clear])).mean() < 0.03
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", result.normal, normal), -1, 1)))
    assert angle.mean() < 15.0


@pytest.mark.parametrize("name", MESHES)
def test_mesh_kind_is_exact(load_shared_mesh, brute_force_closest_point, name):
    """Against brute force over every triangle of the surface distances are measured to
    (unsigned; the mesh, or where it crosses itself, as Suzanne does, its union's boundary:
    ``tests/engine/test_union.py`` proves that one) and libigl's exact winding number (sign),
    independent of the AABB tree and the fast winding number the kind uses."""
    import igl

    mesh = load_shared_mesh(name)
    points, distance, _normal, extent = _truth(mesh)
    result = _colliders(mesh)["mesh"].query(points, ["distance", "normal", "contact"], eps=1e-3 * extent)
    np.testing.assert_allclose(result.distance, distance, rtol=1e-6, atol=1e-9 * extent)
    union = ExactSDF(mesh).union
    assert (union is not None) == (name == "suzanne.obj")
    triangles = mesh.vertices[mesh.faces] if union is None else union.vertices[union.faces]
    for i in range(0, len(points), 100):  # 20 points: brute force is slow on 69k faces
        nearest, _ = brute_force_closest_point(triangles, points[i])
        assert abs(abs(result.distance[i]) - nearest) < 1e-6 * abs(nearest) + 1e-12 * extent
    winding = igl.winding_number(mesh.vertices, mesh.faces, points[::10])
    clear = np.abs(distance[::10]) > 1e-4 * extent
    np.testing.assert_array_equal((result.distance[::10] < 0)[clear], (winding > 0.5)[clear])
    again = _colliders(mesh)["mesh"].query(result.contact, "distance").distance
    # Concave creases pull a pushed point towards a neighbouring face: most contacts are exact.
    assert np.mean(np.abs(again - 1e-3 * extent) < 1e-6 * extent) > 0.95


@pytest.mark.parametrize("name", MESHES)
def test_kdtree_kind_is_an_upper_bound_within_an_edge(load_shared_mesh, name):
    """Where the exact distance is to the mesh's nearest triangle: where a surface crosses
    itself or buries a part (Suzanne) it is to the union's boundary instead, and the kdtree
    kind answers the nearest vertex, buried or not."""
    import igl

    mesh = load_shared_mesh(name)
    points, distance, _, extent = _truth(mesh)
    nearest = np.sqrt(igl.point_mesh_squared_distance(points, mesh.vertices, mesh.faces)[0])
    plain = np.abs(np.abs(distance) - nearest) <= 1e-9 * extent
    assert plain.mean() > 0.9
    points, distance = points[plain], distance[plain]
    result = _colliders(mesh)["kdtree"].query(points, "distance")
    excess = np.abs(result.distance) - np.abs(distance)
    assert excess.min() > -1e-6 * extent
    assert excess.max() <= edges(mesh).max()
    if name == "stanford-bunny.obj":  # dense and smooth: the nearest vertex's side is right
        clear = np.abs(distance) > edges(mesh).mean()
        assert (np.sign(result.distance[clear]) != np.sign(distance[clear])).mean() < 0.01


def test_trained_neural_bunny_if_shipped(load_shared_mesh):
    """The shipped neural bunny (``models/bunny.safetensors``, trained separately) against the
    exact SDF in the +-1 mm band, in the frame it was trained in (``source.transform``)."""
    from collider_server.engine.modelfile import load_collider
    from collider_server.engine.repository import ModelRepository

    path = ModelRepository().path("bunny")
    if not path.is_file():
        pytest.skip(f"no trained neural bunny at {path} yet")
    collider = load_collider(path, "cpu")
    mesh = load_shared_mesh("stanford-bunny.obj")
    assert collider.info.kind == "neural"
    assert collider.info.source.get("sha256") == mesh.sha256
    mesh = mesh.transformed(np.asarray(collider.info.source.get("transform", np.eye(4))))
    points = surface_band_points(mesh, 2000, 1e-3, 11)
    sdf = ExactSDF(mesh)
    distance, closest, face = sdf.query(points)
    true_normal = sdf.gradient(points, distance, closest, face)
    result = collider.query(points, ["distance", "normal"])
    assert np.isfinite(result.distance).all() and np.isfinite(result.normal).all()
    # Measured on 100k points: 0.0167 mm mean error, 3.7 deg mean normal error (models/README.md).
    assert np.abs(result.distance - distance).mean() < 0.03e-3
    angle = np.degrees(np.arccos(np.clip((result.normal * true_normal).sum(axis=1), -1, 1)))
    assert angle.mean() < 6.0


def test_shipped_4d_twisting_bunny_against_its_exact_animation():
    """The shipped 4D network (``models/twisting-bunny-neural.safetensors``) against the exact
    interpolated twisting bunny it was trained on (``collider animate twisting-bunny --frames
    61``, the same file by sha256) at random times between its frames, in the +-1 mm band;
    its velocity is the exact surface's (sliding included: the deformation says where each
    point goes) to a few mm/s. Metres, seconds."""
    from tests.conftest import REPO_ROOT

    from collider_server.engine.animated_meshes import ExactAtTimes
    from collider_server.engine.meshes import barycentric
    from collider_server.engine.modelfile import load_collider
    from collider_server.engine.repository import ModelRepository
    from collider_server.making.animation_files import read_obj
    from collider_server.making.animations import twisting_bunny
    from collider_server.making.sampling import band_sets

    path = ModelRepository().path("twisting-bunny-neural")
    if not path.is_file():
        pytest.skip(f"no shipped 4D twisting bunny at {path}")
    collider = load_collider(path, "cpu")
    animation = twisting_bunny(read_obj(REPO_ROOT / "examples" / "meshes" / "stanford-bunny.obj"), frames=61, fps=30.0)
    assert collider.animated and collider.info.source["frames"] == 61
    assert collider.info.source["faces"] == len(animation.faces)
    exact = ExactAtTimes(animation, keep=1)
    errors, speed_errors, velocity_errors = [], [], []
    for i, t in enumerate((0.13, 0.71, 1.58)):  # between frames (30 fps)
        sdf, k, rate = exact.at(t)
        points = band_sets(sdf.mesh, 2000, 20 + i, 1.0)["band_1mm"]
        truth, closest, face = sdf.query(points)
        got = collider.query(points, ["distance", "normal", "velocity"], time=t)
        errors.append(np.abs(got.distance - truth))
        normal = sdf.gradient(points, truth, closest, face)
        # The exact surface's velocity: the vertices' interpolated at the closest point.
        corners = animation.faces[face]
        step = (animation.frames[k + 1] - animation.frames[k]) * rate
        velocity = np.einsum("mj,mjc->mc", barycentric(closest, sdf.mesh.vertices[corners]), step[corners])
        true_speed = np.einsum("ij,ij->i", velocity, normal)
        speed_errors.append(np.abs(np.einsum("ij,ij->i", got.velocity, normal) - true_speed))
        velocity_errors.append(np.linalg.norm(got.velocity - velocity, axis=1))
    # Measured at 50 times x 2,000 points: 0.016 mm mean, 0.33 mm/s mean normal-speed error (the
    # surface moves up to 190 mm/s); here 0.015 mm, 0.42 mm/s, the velocity vector 0.75 mm/s.
    assert np.concatenate(errors).mean() < 0.04e-3
    assert np.concatenate(speed_errors).mean() < 1.5e-3
    assert np.concatenate(velocity_errors).mean() < 2e-3
    # 3-8 mm from the surface the warp's stretch shows: corrected, 0.058 mm mean (0.185 without).
    from collider_server.making.sampling import surface_band_points

    far = []
    for i, t in enumerate((0.13, 0.71, 1.58)):
        sdf, _, _ = exact.at(t)
        points = surface_band_points(sdf.mesh, 3000, 0.008, 40 + i)
        truth = sdf.signed_distance(points)
        keep = np.abs(truth) > 0.003
        far.append(np.abs(collider.query(points[keep], ["distance"], time=t).distance - truth[keep]))
    assert np.concatenate(far).mean() < 0.1e-3


def test_shipped_articulated_walker_against_its_exact_skin():
    """The shipped articulated network (``models/walker-neural.safetensors``, kind
    ``neural-skinned``: ``collider train`` of the generated walker, docs/characters.md) at two
    random poses off its clips (every joint turned by up to 15 degrees; seeds apart from
    training's) against the exact skinned kind of the skin the file holds (the union of the posed
    skin), in the +-1 mm band. Measured at 100 such poses (models/README.md): mean 0.119 mm, p99
    0.80 mm, 1.01 % sign errors beyond 0.2 mm, normals 3.3 deg mean. Metres."""
    from collider_server.engine.modelfile import load_collider
    from collider_server.engine.repository import ModelRepository
    from collider_server.engine.skinning import random_poses, skin_vertices
    from collider_server.making.skinned import skinned_collider
    from collider_server.making.walker import make_walker

    path = ModelRepository().path("walker-neural")
    if not path.is_file():
        pytest.skip(f"no shipped articulated walker at {path}")
    collider = load_collider(path, "cpu")
    assert collider.info.kind == "neural-skinned" and len(collider.skin.faces) == len(make_walker().faces)
    exact = skinned_collider(collider.skin, "walker", loop=True)
    errors, truths, answers, angles = [], [], [], []
    for i, transforms in enumerate(random_poses(collider.skin, 2, seed=8642).transforms):
        mesh = Mesh(skin_vertices(collider.skin, transforms), collider.skin.faces, "posed")
        points = surface_band_points(mesh, 3000, 1e-3, seed=30 + i)
        truth = exact.query(points, ("distance", "normal"), joint_transforms=transforms)
        got = collider.query(points, ("distance", "normal"), joint_transforms=transforms)
        errors.append(np.abs(got.distance - truth.distance))
        truths.append(truth.distance)
        answers.append(got.distance)
        angles.append(np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", got.normal, truth.normal), -1, 1))))
    error, truth, answer, angle = (np.concatenate(a) for a in (errors, truths, answers, angles))
    clear = np.abs(truth) > 2e-4
    wrong = (np.sign(answer) != np.sign(truth))[clear].mean()
    assert error.mean() < 3e-4 and np.percentile(error, 99) < 2.5e-3, (error.mean(), np.percentile(error, 99))
    assert wrong < 0.04, wrong
    assert angle.mean() < 8.0, angle.mean()


def test_the_shipped_articulated_walker_answers_alike_through_torch_and_the_fused_kernel():
    """The articulated network's torch path (the reference, and the CUDA path: the grid encoded
    per part with its first bias) against the fused CPU kernel on the shipped walker at a pose
    off its clips, 4,000 points of the +-10 mm band and of its box: the same distances and
    normals to float32 rounding (the kernel sums in another order). Metres."""
    from collider_server.engine.modelfile import load_collider
    from collider_server.engine.repository import ModelRepository
    from collider_server.engine.skinning import random_poses, skin_vertices
    from collider_server.making.sampling import box_points

    path = ModelRepository().path("walker-neural")
    if not path.is_file():
        pytest.skip(f"no shipped articulated walker at {path}")
    collider = load_collider(path, "cpu")
    (transforms,) = random_poses(collider.skin, 1, seed=97531).transforms
    mesh = Mesh(skin_vertices(collider.skin, transforms), collider.skin.faces, "posed")
    points = np.concatenate([surface_band_points(mesh, 3000, 1e-2, seed=5),
                             box_points(collider.domain_min, collider.domain_max, 1000, seed=6)])
    grid = collider.network.grid
    answers = {}
    for fused in (True, False):
        grid.fused = fused
        answers[fused] = collider.query(points, ("distance", "normal"), joint_transforms=transforms)
    grid.fused = True
    scale = float(np.abs(answers[False].distance).max())
    np.testing.assert_allclose(answers[True].distance, answers[False].distance, rtol=0, atol=1e-5 * scale)
    cosine = np.einsum("ij,ij->i", answers[True].normal, answers[False].normal)
    assert cosine.min() > 0.999, cosine.min()
