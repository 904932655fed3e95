"""The voxel kind: trilinear interpolation and its analytic gradient, checked on fields whose
interpolant is known exactly, and the baking of the grid. Collider frame, metres."""

from __future__ import annotations

import numpy as np
import pytest

from collider_server.collider import ColliderInfo
from collider_server.kinds.voxel import VoxelCollider, bake_grid, padded_box
from collider_server.meshes import ExactSDF

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


def test_bake_grid_samples_the_exact_sdf_at_the_corners(analytic_shape):
    shape = analytic_shape("box")
    lo, hi = padded_box(shape.mesh, 0.1)
    grid = bake_grid(ExactSDF(shape.mesh), lo, hi, 10, chunk_points=150, show_progress=False)
    axes = [np.linspace(lo[i], hi[i], 10) for i in range(3)]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    truth = shape.sdf(np.stack([x, y, z], axis=-1).reshape(-1, 3)).reshape(10, 10, 10)
    assert grid.dtype == np.float32 and grid.shape == (10, 10, 10)
    np.testing.assert_allclose(grid, truth, rtol=0, atol=1e-7)
    assert (grid[[0, -1]] > 0).all()  # the padded box is outside the solid


@pytest.mark.parametrize("resolution", [4, 2048])
def test_bake_grid_resolution_bounds(analytic_shape, resolution):
    shape = analytic_shape("box")
    with pytest.raises(ValueError, match=r"resolution must be in 8\.\.1024"):
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
