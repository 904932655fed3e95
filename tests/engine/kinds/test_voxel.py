"""The voxel kind: trilinear interpolation and its analytic gradient, checked on fields whose
interpolant is known exactly, and the baking of the grid. Collider frame, metres."""

from __future__ import annotations

import re

import numpy as np
import pytest

from collider_server.engine.collider import ColliderInfo
from collider_server.engine.kinds.voxel import VoxelCollider
from collider_server.engine.meshes import ExactSDF
from collider_server.making.bake import bake_grid, padded_box

LO, HI = np.array([-0.1, -0.2, 0.0]), np.array([0.3, 0.1, 0.25])
SHAPE = (9, 7, 12)


def grid_axes():
    return [np.linspace(LO[i], HI[i], SHAPE[i]) for i in range(3)]


def voxel_of(values: np.ndarray) -> VoxelCollider:
    info = ColliderInfo("grid", "voxel", LO.tolist(), HI.tolist())
    return VoxelCollider(info, values, "cpu")


def inside(n, seed):
    return LO + np.random.default_rng(seed).random((n, 3)) * (HI - LO)


def test_a_linear_field_is_reproduced_exactly():
    """Trilinear interpolation of a linear function is the function; its gradient the slope."""
    slope, offset = np.array([0.6, -0.48, 0.64]), 0.01
    x, y, z = np.meshgrid(*grid_axes(), indexing="ij")
    values = slope[0] * x + slope[1] * y + slope[2] * z + offset
    collider = voxel_of(values)
    points = inside(500, 0)
    distance, gradient = collider.evaluate(points, True)
    np.testing.assert_allclose(distance, points @ slope + offset, rtol=0, atol=1e-6)
    np.testing.assert_allclose(gradient, np.tile(slope, (500, 1)), rtol=0, atol=1e-4)


def test_grid_nodes_return_the_stored_values():
    values = np.random.default_rng(1).normal(size=SHAPE).astype(np.float32)
    collider = voxel_of(values)
    x, y, z = np.meshgrid(*grid_axes(), indexing="ij")
    nodes = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    distance, _ = collider.evaluate(nodes, False)
    np.testing.assert_allclose(distance, values.reshape(-1), rtol=0, atol=2e-6)


def test_gradient_is_the_derivative_of_the_interpolant():
    values = np.random.default_rng(2).normal(size=SHAPE).astype(np.float32)
    collider = voxel_of(values)
    spacing = (HI - LO) / (np.array(SHAPE) - 1)
    # Points well inside cells (the interpolant is smooth there), central differences.
    cells = np.random.default_rng(3).integers(0, np.array(SHAPE) - 1, (200, 3))
    points = LO + (cells + np.random.default_rng(4).uniform(0.2, 0.8, (200, 3))) * spacing
    _, gradient = collider.evaluate(points, True)
    h = 1e-3 * spacing.min()
    fd = np.empty_like(points)
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        fd[:, axis] = (collider.evaluate(points + step, False)[0]
                       - collider.evaluate(points - step, False)[0]) / (2 * h)
    np.testing.assert_allclose(gradient, fd, rtol=2e-3, atol=2e-3 * np.abs(fd).max())


@pytest.mark.parametrize("chunk_points", [150, 300, 10**6])  # x-slabs of 1, 3 (3 + 3 + 3 + 1), 10
def test_bake_grid_samples_the_exact_sdf_at_the_corners(analytic_shape, chunk_points):
    shape = analytic_shape("box")
    lo, hi = padded_box(shape.mesh, 0.1)
    grid = bake_grid(ExactSDF(shape.mesh), lo, hi, 10, chunk_points=chunk_points, show_progress=False)
    axes = [np.linspace(lo[i], hi[i], 10) for i in range(3)]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    truth = shape.sdf(np.stack([x, y, z], axis=-1).reshape(-1, 3)).reshape(10, 10, 10)
    assert grid.dtype == np.float32 and grid.shape == (10, 10, 10)
    np.testing.assert_allclose(grid, truth, rtol=0, atol=1e-7)
    assert (grid[[0, -1]] > 0).all()  # the padded box is outside the solid


@pytest.mark.parametrize("resolution", [4, 2048])
def test_bake_grid_resolution_bounds(analytic_shape, resolution):
    shape = analytic_shape("box")
    with pytest.raises(ValueError, match=rf"^resolution must be in 8\.\.1024, got {resolution}$"):
        bake_grid(ExactSDF(shape.mesh), *padded_box(shape.mesh, 0.1), resolution, show_progress=False)


@pytest.mark.parametrize("grid, message", [
    (np.zeros((4, 4)), "must be 3-D"),
    (np.zeros((4, 1, 4)), "at least 2 samples per axis"),
])
def test_bad_grids_are_rejected(grid, message):
    with pytest.raises(ValueError, match=message):
        voxel_of(grid)
    with pytest.raises(ValueError, match="exactly one tensor 'grid'"):
        VoxelCollider.from_tensors(ColliderInfo("g", "voxel", LO.tolist(), HI.tolist()),
                                   {"grid": np.zeros(SHAPE), "extra": np.zeros(1)})


def test_a_multilinear_field_is_reproduced_exactly():
    """In every cell the trilinear interpolant of a multilinear field (xy, yz, xz and xyz terms)
    is the field itself: distance and gradient in closed form, metres."""
    def field(x, y, z):
        return 0.03 + x - 2 * y + 0.5 * z + 4 * x * y - 3 * y * z + 2 * x * z + 5 * x * y * z

    def gradient_of(x, y, z):
        return np.stack([1 + 4 * y + 2 * z + 5 * y * z, -2 + 4 * x - 3 * z + 5 * x * z,
                         0.5 - 3 * y + 2 * x + 5 * x * y], axis=1)

    collider = voxel_of(field(*np.meshgrid(*grid_axes(), indexing="ij")))
    points = inside(400, 5)
    distance, gradient = collider.evaluate(points, True)
    np.testing.assert_allclose(distance, field(*points.T), rtol=0, atol=2e-6)
    np.testing.assert_allclose(gradient, gradient_of(*points.T), rtol=0, atol=2e-4)


def test_one_cell_by_hand():
    """A 2 x 2 x 2 grid (one cell) over [0, 2] x [0, 1] x [0, 4] m: at the point a quarter,
    half and three quarters across, the trilinear weights are (3/4, 1/4), (1/2, 1/2),
    (1/4, 3/4)."""
    values = np.arange(8, dtype=np.float32).reshape(2, 2, 2) ** 2  # c_ijk = (4i + 2j + k)^2
    collider = VoxelCollider(ColliderInfo("one", "voxel", [0, 0, 0], [2, 1, 4]), values, "cpu")
    assert collider.resolution == (2, 2, 2) and collider.device == "cpu"
    expected = sum(values[i, j, k] * (0.75 if i == 0 else 0.25) * 0.5 * (0.25 if k == 0 else 0.75)
                   for i in (0, 1) for j in (0, 1) for k in (0, 1))
    distance, gradient = collider.evaluate(np.array([[0.5, 0.5, 3.0]]), True)
    assert distance[0] == pytest.approx(expected, abs=1e-5)
    # d/dx = (mean over the x = 2 face - mean over the x = 0 face, same y/z weights) / 2 m.
    dx = sum((values[1, j, k] - values[0, j, k]) * 0.5 * (0.25 if k == 0 else 0.75)
             for j in (0, 1) for k in (0, 1)) / 2.0
    dy = sum((values[i, 1, k] - values[i, 0, k]) * (0.75 if i == 0 else 0.25) * (0.25 if k == 0 else 0.75)
             for i in (0, 1) for k in (0, 1)) / 1.0
    dz = sum((values[i, j, 1] - values[i, j, 0]) * (0.75 if i == 0 else 0.25) * 0.5
             for i in (0, 1) for j in (0, 1)) / 4.0
    np.testing.assert_allclose(gradient[0], [dx, dy, dz], rtol=1e-6)
    assert distance.dtype == np.float64 and gradient.dtype == np.float64


def test_corners_and_faces_of_the_box_use_the_edge_cells():
    """Points on the box's faces (first and last grid planes) interpolate within the edge cells,
    gradient included (a linear field: exact)."""
    slope = np.array([0.6, -0.48, 0.64])
    x, y, z = np.meshgrid(*grid_axes(), indexing="ij")
    collider = voxel_of(slope[0] * x + slope[1] * y + slope[2] * z)
    rng = np.random.default_rng(6)
    points = inside(60, 7)
    points[:20, 0], points[20:40, 1], points[40:, 2] = HI[0], LO[1], HI[2]
    corners = np.array(np.meshgrid(*zip(LO, HI), indexing="ij")).reshape(3, -1).T
    points = np.concatenate([points, corners, LO + rng.random((5, 3)) * 0.01 * (HI - LO)])
    distance, gradient = collider.evaluate(points, True)
    np.testing.assert_allclose(distance, points @ slope, rtol=0, atol=1e-6)
    np.testing.assert_allclose(gradient, np.tile(slope, (len(points), 1)), rtol=0, atol=1e-4)


def test_tensors_round_trip():
    values = np.random.default_rng(8).normal(size=SHAPE).astype(np.float32)
    collider = voxel_of(values)
    tensors = collider.tensors()
    assert set(tensors) == {"grid"} and tensors["grid"].dtype == np.float32
    np.testing.assert_array_equal(tensors["grid"], values)
    assert collider.nbytes() == values.nbytes
    rebuilt = VoxelCollider.from_tensors(collider.info, tensors, "cpu")
    assert rebuilt.resolution == SHAPE
    points = inside(50, 9)
    np.testing.assert_array_equal(rebuilt.evaluate(points, True)[1], collider.evaluate(points, True)[1])
    # float64 grids are stored as float32
    assert voxel_of(values.astype(np.float64)).tensors()["grid"].dtype == np.float32


def test_the_smallest_grid_is_accepted():
    collider = voxel_of(np.zeros((2, 2, 2)))
    assert collider.resolution == (2, 2, 2)
    np.testing.assert_array_equal(collider.evaluate(inside(5, 10), False)[0], 0.0)


@pytest.mark.parametrize("grid, message", [
    (np.zeros((4, 4)), "voxel grid must be 3-D with at least 2 samples per axis, got (4, 4)"),
    (np.zeros((4, 1, 4)), "voxel grid must be 3-D with at least 2 samples per axis, got (4, 1, 4)"),
    (np.zeros((2, 2, 2, 2)), "voxel grid must be 3-D with at least 2 samples per axis, got (2, 2, 2, 2)"),
])
def test_bad_grid_messages(grid, message):
    with pytest.raises(ValueError) as error:
        voxel_of(grid)
    assert str(error.value) == message


def test_from_tensors_message():
    with pytest.raises(ValueError) as error:
        VoxelCollider.from_tensors(ColliderInfo("g", "voxel", LO.tolist(), HI.tolist()),
                                   {"grid": np.zeros(SHAPE), "extra": np.zeros(1)})
    assert str(error.value) == "voxel model must hold exactly one tensor 'grid', found ['extra', 'grid']"


def test_padded_box_by_hand(analytic_shape):
    mesh = analytic_shape("box").mesh
    lo, hi = mesh.bounds
    grown_lo, grown_hi = padded_box(mesh, 0.25)
    margin = 0.25 * (hi - lo).max()
    np.testing.assert_allclose(grown_lo, lo - margin, rtol=0, atol=1e-15)
    np.testing.assert_allclose(grown_hi, hi + margin, rtol=0, atol=1e-15)
    assert margin > 0 and not np.allclose(hi - lo, (hi - lo).max())  # not a cube: the largest side


def test_bake_grid_smallest_resolution_and_its_progress_bar(analytic_shape, capsys):
    """Resolution 8 (the lower bound) bakes; the bar (stderr) names the grid and counts points."""
    shape = analytic_shape("box")
    lo, hi = padded_box(shape.mesh, 0.1)
    grid = bake_grid(ExactSDF(shape.mesh), lo, hi, 8)
    assert grid.shape == (8, 8, 8)
    np.testing.assert_allclose(grid[0, 0, 0], shape.sdf(lo[None])[0], rtol=0, atol=1e-7)
    np.testing.assert_allclose(grid[-1, -1, -1], shape.sdf(hi[None])[0], rtol=0, atol=1e-7)
    err = capsys.readouterr().err
    assert re.search(r"(^|\r)bake 8\^3: ", err) and "512/512" in err and "pt/s]" in err
    bake_grid(ExactSDF(shape.mesh), lo, hi, 8, show_progress=False)
    assert capsys.readouterr().err == ""


def test_the_device_is_checked():
    """The device argument is resolved (and refused when unknown), also through from_tensors."""
    info = ColliderInfo("g", "voxel", LO.tolist(), HI.tolist())
    with pytest.raises(ValueError, match=r"^unknown device 'abacus'; use 'cpu', 'cuda' or 'auto'$"):
        VoxelCollider(info, np.zeros(SHAPE), "abacus")
    with pytest.raises(ValueError, match=r"^unknown device 'abacus'"):
        VoxelCollider.from_tensors(info, {"grid": np.zeros(SHAPE)}, "abacus")
    assert VoxelCollider.from_tensors(info, {"grid": np.zeros(SHAPE)}, "cpu").device == "cpu"


def test_the_bake_estimate_times_grid_slabs_after_the_trees_are_built():
    """Issue 35: voxel bake estimates were 4-6x too long: the timed probe also built the mesh's
    lookup trees (three probes in a row: 73, 41, 29 us per point) and asked scattered points,
    which cost more than the grid's neighbouring ones. The timed call now asks whole x-slabs of
    the grid being estimated, the winding number's hierarchy already built."""
    import trimesh

    from collider_server.engine.meshes import Mesh
    from collider_server.making.bake import exact_seconds_per_point, grid_axes

    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    sdf = ExactSDF(Mesh(np.asarray(ball.vertices), np.asarray(ball.faces)))
    calls = []
    real = sdf.signed_distance

    def spy(points):
        calls.append((np.array(points), sdf._winding is not None))
        return real(points)

    sdf.signed_distance = spy
    lo, hi = padded_box(sdf.mesh, 0.1)
    per_point = exact_seconds_per_point(sdf, lo, hi, 24)
    assert 0 < per_point < 1e-2
    (points, built) = calls[-1]  # the timed call
    assert built and len(calls) == 2  # a first call built the trees, untimed
    axes = grid_axes(lo, hi, 24)
    assert len(points) == 4 * 24 * 24  # four whole x-slabs of the 24^3 grid
    slabs = sorted(set(points[:, 0].tolist()))
    assert slabs == [axes[0][i] for i in (3, 9, 15, 21)]  # evenly spread over x
    for axis in (1, 2):
        assert set(points[:, axis].tolist()) == set(axes[axis].tolist())
