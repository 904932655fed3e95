"""The exact mesh kind and the kdtree (nearest-vertex) estimate on a tetrahedron small enough to
work by hand: vertices at the origin and 0.1 m along each axis, faces outward. Collider frame,
metres."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from collider_server.engine.collider import ColliderInfo
from collider_server.engine.kinds import KINDS, KDTreeCollider, MeshCollider, NeuralCollider, VoxelCollider
from collider_server.engine.kinds.kdtree import POINTS_PER_THREAD, vertex_normals
from collider_server.engine.meshes import Mesh

A = 0.1
VERTICES = np.array([[0, 0, 0], [A, 0, 0], [0, A, 0], [0, 0, A]], np.float64)
# Outward: the x = 0, y = 0 and z = 0 faces, and the slanted one x + y + z = A.
FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int64)
LO, HI = VERTICES.min(axis=0), VERTICES.max(axis=0)
SQRT3 = np.sqrt(3.0)


def tetrahedron(name="tet"):
    return Mesh(VERTICES, FACES, name)


def info(kind, **changes):
    return ColliderInfo("tet", kind, LO.tolist(), HI.tolist(), **changes)


def test_kinds_by_name():
    from collider_server.engine.kinds.neural_skinned import ArticulatedNeuralCollider
    from collider_server.engine.kinds.skinned import SkinnedCollider

    assert KINDS == {"neural": NeuralCollider, "voxel": VoxelCollider, "mesh": MeshCollider,
                     "kdtree": KDTreeCollider, "skinned": SkinnedCollider,
                     "neural-skinned": ArticulatedNeuralCollider}


def test_vertex_normals_by_hand():
    """Area-weighted: at the origin the three right-angle faces (-x, -y, -z, equal areas); at
    (A, 0, 0) the -y and -z faces (area A^2/2) and the slanted face (area sqrt(3) A^2/2, normal
    (1, 1, 1)/sqrt(3)) sum to +x. A vertex no face uses gets a zero normal, not NaN."""
    mesh = Mesh(np.vstack([VERTICES, [[1.0, 1.0, 1.0]]]), FACES, "tet")
    normals = vertex_normals(mesh)
    expected = np.array([[-1, -1, -1] / SQRT3, [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]])
    np.testing.assert_allclose(normals, expected, rtol=0, atol=1e-15)


def test_kdtree_distance_is_signed_by_the_nearest_vertex_normal():
    collider = KDTreeCollider.from_mesh(info("kdtree", approximate=True), tetrahedron())
    points = np.array([[-0.01, -0.01, -0.01],  # outside, beyond the origin
                       [0.01, 0.01, 0.01],  # inside, nearest the origin
                       [0.12, 0.01, 0.0],  # outside, beyond (A, 0, 0)
                       [0.08, 0.01, 0.0],  # inside, nearest (A, 0, 0)
                       [0.0, 0.0, 0.13]])  # outside, beyond (0, 0, A)
    distance, gradient = collider.evaluate(points, True)
    nearest = np.array([0, 0, 1, 1, 3])
    unsigned = np.linalg.norm(points - VERTICES[nearest], axis=1)
    np.testing.assert_allclose(distance, unsigned * np.array([1, -1, 1, -1, 1]), rtol=0, atol=1e-15)
    np.testing.assert_allclose(gradient, vertex_normals(tetrahedron())[nearest], rtol=0, atol=1e-15)
    only, none = collider.evaluate(points, False)
    assert none is None
    np.testing.assert_array_equal(only, distance)


def test_kdtree_on_many_points_answers_as_one_query_of_them_all():
    """Past POINTS_PER_THREAD points the query runs in threads: each point keeps its own answer."""
    points = np.random.default_rng(0).uniform(-0.05, 0.15, (3 * POINTS_PER_THREAD + 5, 3))
    collider = KDTreeCollider.from_mesh(info("kdtree"), tetrahedron())
    unsigned, index = collider.tree.query(points)
    distance, gradient = collider.evaluate(points, True)
    np.testing.assert_array_equal(np.abs(distance), unsigned)
    np.testing.assert_array_equal(gradient, collider.normals[index])


#: Interrupts (as Ctrl-C or SIGTERM raise them) land while the kdtree waits for its threads; then
#: the collider is dropped and memory reused. SciPy's own threads (``workers=-1``) ran on into
#: freed memory: a segmentation fault within 15 rounds (6 tries of 6).
INTERRUPTED_QUERIES = """
import gc, signal, numpy as np
from collider_server.engine.collider import ColliderInfo
from collider_server.engine.kinds import KDTreeCollider

def interrupt(signum, frame):
    raise KeyboardInterrupt
signal.signal(signal.SIGALRM, interrupt)
rng = np.random.default_rng(0)
interrupted = 0
for _ in range(15):
    vertices = rng.random((20_000, 3))
    collider = KDTreeCollider(ColliderInfo("cloud", "kdtree", [0, 0, 0], [1, 1, 1]), vertices, vertices)
    signal.setitimer(signal.ITIMER_REAL, 0.002 + 0.006 * rng.random())
    try:
        collider.evaluate(rng.random((100_000, 3)), False)
        signal.setitimer(signal.ITIMER_REAL, 0)
    except KeyboardInterrupt:
        interrupted += 1
    del collider
    gc.collect()
    reused = [np.ones(100_000) for _ in range(20)]
print(interrupted)
"""


def test_a_kdtree_query_interrupted_while_its_threads_run_does_not_crash_the_process():
    done = subprocess.run([sys.executable, "-c", INTERRUPTED_QUERIES], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout) > 0  # the interrupts did land during queries


def test_kdtree_is_not_clamped_to_its_box():
    """Far outside the box the estimate is still |p - nearest vertex| (no box rule)."""
    collider = KDTreeCollider.from_mesh(info("kdtree"), tetrahedron())
    point = np.array([[0.5, -0.2, 0.05]])
    distance = collider.query(point).distance
    np.testing.assert_allclose(distance, np.linalg.norm(point - VERTICES[1], axis=1), rtol=1e-6)  # 0.45 m; the box rule: 0.497 m


def test_kdtree_tensors_round_trip():
    collider = KDTreeCollider.from_mesh(info("kdtree"), tetrahedron())
    tensors = collider.tensors()
    assert set(tensors) == {"vertices", "normals"}
    assert tensors["vertices"].dtype == np.float64 and tensors["normals"].dtype == np.float64
    np.testing.assert_array_equal(tensors["vertices"], VERTICES)
    rebuilt = KDTreeCollider.from_tensors(collider.info, {k: v.astype(np.float32) for k, v in tensors.items()})
    assert rebuilt.vertices.dtype == np.float64 and rebuilt.normals.dtype == np.float64
    points = LO + np.random.default_rng(0).random((20, 3)) * (HI - LO)
    np.testing.assert_allclose(rebuilt.evaluate(points, True)[1], collider.evaluate(points, True)[1], atol=1e-7)


@pytest.mark.parametrize("tensors, message", [
    ({"vertices": VERTICES}, "kdtree model must hold 'vertices' and 'normals', found ['vertices']"),
    ({"vertices": VERTICES, "normals": VERTICES, "faces": FACES},
     "kdtree model must hold 'vertices' and 'normals', found ['faces', 'normals', 'vertices']"),
    ({"vertices": VERTICES, "normals": VERTICES[:3]}, "kdtree vertices and normals must both be (v, 3)"),
    ({"vertices": VERTICES[:, :2], "normals": VERTICES[:, :2]}, "kdtree vertices and normals must both be (v, 3)"),
    ({"vertices": VERTICES[:, None], "normals": VERTICES[:, None]}, "kdtree vertices and normals must both be (v, 3)"),
    ({"vertices": VERTICES.ravel(), "normals": VERTICES.ravel()}, "kdtree vertices and normals must both be (v, 3)"),
    ({"vertices": np.zeros((0, 3)), "normals": np.zeros((0, 3))}, "kdtree model holds no vertices"),
])
def test_kdtree_from_tensors_messages(tensors, message):
    with pytest.raises(ValueError) as error:
        KDTreeCollider.from_tensors(info("kdtree"), tensors)
    assert str(error.value) == message


def test_mesh_collider_is_exact_outside_its_box(brute_force_closest_point):
    """No box rule for the exact kind: beyond the box the distance is still the mesh's own
    (here below what the clamped rule would give), the normal points from the closest point."""
    collider = MeshCollider(info("mesh"), tetrahedron())
    point = np.array([0.3, 0.05, -0.1])
    exact, closest = brute_force_closest_point(VERTICES[FACES], point)
    result = collider.query(point[None], ["distance", "normal"])
    assert result.distance[0] == pytest.approx(exact, abs=1e-12)
    np.testing.assert_allclose(result.normal[0], (point - closest) / exact, atol=1e-9)
    clamped = np.clip(point, LO, HI)
    assert exact < np.linalg.norm(point - clamped) + brute_force_closest_point(VERTICES[FACES], clamped)[0] - 1e-3


def test_mesh_collider_inside_by_hand():
    """Inside, near the x = 0 face: distance -x, normal -x (the face's outward normal)."""
    collider = MeshCollider(info("mesh"), tetrahedron())
    points = np.array([[0.01, 0.02, 0.03], [0.005, 0.03, 0.02]])
    distance, gradient = collider.evaluate(points, True)
    np.testing.assert_allclose(distance, -points[:, 0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(gradient, [[-1, 0, 0]] * 2, rtol=0, atol=1e-12)
    only, none = collider.evaluate(points, False)
    assert none is None
    np.testing.assert_array_equal(only, distance)


def test_mesh_tensors_round_trip_and_name():
    collider = MeshCollider(info("mesh", source={"mesh": "tetra.obj"}), tetrahedron())
    tensors = collider.tensors()
    assert set(tensors) == {"vertices", "faces"}
    assert tensors["vertices"].dtype == np.float64 and tensors["faces"].dtype == np.int32
    np.testing.assert_array_equal(tensors["faces"], FACES)
    rebuilt = MeshCollider.from_tensors(collider.info, tensors)
    assert rebuilt.mesh.name == "tetra.obj"
    assert rebuilt.mesh.faces.dtype == np.int64 and rebuilt.mesh.vertices.dtype == np.float64
    np.testing.assert_array_equal(rebuilt.mesh.vertices, VERTICES)
    assert MeshCollider.from_tensors(info("mesh"), tensors).mesh.name == "mesh"
    # The last vertex may be used (indices up to v - 1).
    assert int(rebuilt.mesh.faces.max()) == len(VERTICES) - 1


@pytest.mark.parametrize("tensors, message", [
    ({"vertices": VERTICES}, "mesh model must hold 'vertices' and 'faces', found ['vertices']"),
    ({"vertices": VERTICES[:, :2], "faces": FACES},
     "mesh arrays have wrong shapes: vertices (4, 2), faces (4, 3)"),
    ({"vertices": VERTICES.ravel(), "faces": FACES}, "mesh arrays have wrong shapes: vertices (12,), faces (4, 3)"),
    ({"vertices": VERTICES, "faces": FACES[:, :2]}, "mesh arrays have wrong shapes: vertices (4, 3), faces (4, 2)"),
    ({"vertices": VERTICES, "faces": FACES.ravel()}, "mesh arrays have wrong shapes: vertices (4, 3), faces (12,)"),
    ({"vertices": VERTICES, "faces": np.zeros((0, 3), np.int32)}, "mesh model holds no faces"),
    ({"vertices": VERTICES, "faces": FACES - 1}, "mesh faces index vertices that do not exist"),
    ({"vertices": VERTICES, "faces": FACES + 1}, "mesh faces index vertices that do not exist"),
])
def test_mesh_from_tensors_messages(tensors, message):
    with pytest.raises(ValueError) as error:
        MeshCollider.from_tensors(info("mesh"), tensors)
    assert str(error.value) == message


def test_mesh_file_dtypes_whatever_the_arrays_held():
    """The file holds float64 vertices and int32 faces; a loaded mesh float64 and int64 (the
    dtypes Mesh documents), from float32 / int32 arrays too."""
    loose = Mesh(VERTICES.astype(np.float32), FACES.astype(np.int32), "tet")
    tensors = MeshCollider(info("mesh"), loose).tensors()
    assert tensors["vertices"].dtype == np.float64 and tensors["faces"].dtype == np.int32
    rebuilt = MeshCollider.from_tensors(info("mesh"), {"vertices": VERTICES.astype(np.float32),
                                                      "faces": FACES.astype(np.int32)})
    assert rebuilt.mesh.vertices.dtype == np.float64 and rebuilt.mesh.faces.dtype == np.int64
