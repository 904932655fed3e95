"""Mesh loading errors and the exact SDF against slow, obviously correct references
(trimesh's closest point, libigl's exact winding number, the analytic sphere). Metres."""

from __future__ import annotations

import numpy as np
import pytest

from collider_server.engine.meshes import ExactSDF, Mesh, unsigned_distance
from collider_server.making.mesh_files import MeshError, load_mesh


def write(path, text: str | bytes):
    (path.write_bytes if isinstance(text, bytes) else path.write_text)(text)
    return path


TETRA = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def test_load_mesh_reads_an_obj_with_its_hash(tmp_path):
    mesh = load_mesh(write(tmp_path / "tetra.obj", TETRA))
    assert mesh.vertices.shape == (4, 3) and mesh.faces.shape == (4, 3)
    assert mesh.vertices.dtype == np.float64 and mesh.faces.dtype == np.int64
    assert mesh.name == "tetra" and len(mesh.sha256) == 64
    np.testing.assert_array_equal(mesh.bounds, [[0, 0, 0], [1, 1, 1]])


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("missing.obj", None, "no such mesh file"),
        ("folder.obj", "DIR", "is a directory, not a mesh file"),
        ("points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n", r"mesh is empty \(no triangles\)"),
        ("empty.obj", "", r"mesh is empty \(no triangles\)"),
        ("flat.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "mesh is flat"),
        ("blob.obj", bytes(range(256)) * 3, "cannot read mesh"),
        ("broken.ply", "hello world\n", "cannot read mesh"),
        ("nan.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n", "NaN or Inf"),
    ],
)
def test_load_mesh_errors_name_the_file_and_the_problem(tmp_path, name, content, message):
    path = tmp_path / name
    if content == "DIR":
        path.mkdir()
    elif content is not None:
        write(path, content)
    with pytest.raises(MeshError, match=message) as caught:
        load_mesh(path)
    assert str(caught.value).startswith(str(path))
    assert isinstance(caught.value, ValueError)


def test_load_mesh_refuses_too_many_faces(tmp_path):
    with pytest.raises(MeshError, match="more than this machine handles"):
        load_mesh(write(tmp_path / "tetra.obj", TETRA), max_faces=3)


def test_load_mesh_orients_inward_wound_triangles_outward(tmp_path):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    inward = tmp_path / "inward.obj"
    trimesh.Trimesh(sphere.vertices, sphere.faces[:, ::-1], process=False).export(inward)
    mesh = load_mesh(inward)
    # An outward open mesh far from the origin stays as it is (its volume is taken about its box
    # centre, where a missing cap cannot flip the sign).
    cut = sphere.faces[sphere.vertices[sphere.faces].mean(axis=1)[:, 2] > -0.09]
    far = tmp_path / "open-far.obj"
    trimesh.Trimesh(sphere.vertices + [0.0, 0.0, -100.0], cut, process=False).export(far)
    assert ExactSDF(load_mesh(far)).signed_distance(np.array([[0.0, 0.0, -100.0]]))[0] < -0.09
    # Negative inside, and the on-surface gradient (the face normal) points away from the centre.
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.2]])
    distance = ExactSDF(mesh).signed_distance(points)
    assert distance[0] < -0.09 and distance[1] > 0.09
    on_surface = mesh.vertices[mesh.faces[:, 0]]
    sdf = ExactSDF(mesh)
    d, closest, face = sdf.query(on_surface)
    normal = sdf.gradient(on_surface, d, closest, face)
    assert (np.einsum("ij,ij->i", normal, on_surface) > 0).all()


def test_transformed_keeps_orientation_outward(analytic_shape):
    sphere = analytic_shape("sphere").mesh
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    for matrix in (np.diag([2.0, 2.0, 2.0, 1.0]), mirror):
        moved = sphere.transformed(matrix)
        assert ExactSDF(moved).signed_distance(np.zeros((1, 3)))[0] < 0  # centre still inside


def test_exact_sdf_matches_slow_references(analytic_shape, brute_force_closest_point):
    """Closest point vs brute force over every triangle (slow, obviously correct); sign vs
    libigl's exact winding number; both vs the analytic torus within the facet error."""
    import igl

    shape = analytic_shape("torus")
    mesh = shape.mesh
    rng = np.random.default_rng(0)
    points = np.concatenate([shape.sample(100, 1), rng.uniform(-0.2, 0.2, (40, 3))])
    distance, closest, _face = ExactSDF(mesh).query(points, chunk_points=64)
    triangles = mesh.vertices[mesh.faces]
    for i, point in enumerate(points):
        nearest, nearest_point = brute_force_closest_point(triangles, point)
        assert abs(abs(distance[i]) - nearest) < 1e-12, i
        assert np.linalg.norm(closest[i] - nearest_point) < 1e-9, i
    winding = igl.winding_number(mesh.vertices, mesh.faces, points)
    np.testing.assert_array_equal(distance < 0, winding > 0.5)
    assert np.abs(distance - shape.sdf(points)).max() < shape.facet_error


def test_exact_sdf_sign_on_an_open_mesh(analytic_shape):
    """The fast winding number gives the right inside on a sphere with a hole punched in it."""
    sphere = analytic_shape("sphere").mesh
    centroids = sphere.vertices[sphere.faces].mean(axis=1)
    keep = centroids[:, 2] < 0.095  # remove a cap of faces near the north pole
    open_mesh = Mesh(sphere.vertices, sphere.faces[keep], "open-sphere")
    points = analytic_shape("sphere").sample(300, 2)
    points = points[points[:, 2] < 0.05]
    distance = ExactSDF(open_mesh).signed_distance(points)
    truth = np.linalg.norm(points, axis=1) - 0.1
    clear = np.abs(truth) > 1e-3
    np.testing.assert_array_equal(np.sign(distance[clear]), np.sign(truth[clear]))


def test_the_winding_number_hierarchy_is_built_once_and_answers_as_libigl_per_call(analytic_shape):
    """The kept hierarchy gives libigl's per-call fast winding number to the last bit (near the
    open sphere's hole too, where it is far from 0 and 1), and later calls reuse it."""
    import igl

    sphere = analytic_shape("sphere").mesh
    keep = sphere.vertices[sphere.faces].mean(axis=1)[:, 2] < 0.095
    exact = ExactSDF(Mesh(sphere.vertices, sphere.faces[keep], "open-sphere"))
    points = np.random.default_rng(3).uniform(-0.15, 0.15, (2000, 3))
    first = exact.winding_number(points)
    hierarchy = exact._winding
    np.testing.assert_array_equal(first, igl.fast_winding_number(exact.mesh.vertices.astype(np.float64),
                                                                 exact.mesh.faces.astype(np.int64), points))
    assert ((first > 0.1) & (first < 0.9)).any()  # the hole's neighbourhood is in the sample
    np.testing.assert_array_equal(exact.winding_number(points[::-1]), first[::-1])
    assert exact._winding is hierarchy


def test_exact_gradient_is_unit_and_outward(analytic_shape):
    sphere = analytic_shape("sphere")
    exact = ExactSDF(sphere.mesh)
    points = np.concatenate([sphere.sample(200, 3), sphere.mesh.vertices[:20]])
    distance, closest, face = exact.query(points)
    gradient = exact.gradient(points, distance, closest, face)
    np.testing.assert_allclose(np.linalg.norm(gradient, axis=1), 1.0, atol=1e-12)
    assert np.einsum("ij,ij->i", gradient, sphere.gradient(points)).min() > np.cos(np.radians(3))


def test_text_formats_refuse_binary_data_but_not_other_encodings(tmp_path):
    """A binary blob named .obj is unreadable whatever encoding guesser trimesh finds installed;
    an OBJ whose comment is Latin-1 (not UTF-8) still loads."""
    blob = tmp_path / "blob.obj"
    blob.write_bytes(b"v 0 0 0\n" + bytes(range(256)))
    with pytest.raises(MeshError, match="cannot read mesh \\(binary data"):
        load_mesh(blob)
    latin = tmp_path / "latin.obj"
    latin.write_bytes("# Créé à Paris\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
                      "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n".encode("latin-1"))
    assert load_mesh(latin).faces.shape == (4, 3)


def test_the_unsigned_distance_of_a_surface_that_does_not_cross_itself_is_the_exact_sdfs_size():
    """:func:`unsigned_distance` (no union, no sign: the reconstruction check's other direction)
    against the exact SDF's magnitude on an icosphere (radius 0.1 m), points inside and out, and
    against the analytic sphere within the facets' sag."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    mesh = Mesh(sphere.vertices, sphere.faces, "sphere")
    points = np.random.default_rng(3).normal(size=(2000, 3)) * 0.08
    distance = unsigned_distance(mesh, points)
    np.testing.assert_allclose(distance, np.abs(ExactSDF(mesh).query(points)[0]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(distance, np.abs(np.linalg.norm(points, axis=1) - 0.1), rtol=0, atol=1e-3)
