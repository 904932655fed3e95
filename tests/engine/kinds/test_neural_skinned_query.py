"""The query passes of kind ``neural-skinned`` beside their references, with no network and no
training (the generated arm at a bent pose): the candidate rows written from the mask, the union
over a point's parts, the gradient's pull-back, the velocity the Newton kernel leaves at each
rest point, the first files' fixed-point map to the rest pose and the pose codes."""

import dataclasses

import numpy as np
import pytest

from collider_server.engine.kinds import grid_kernels
from collider_server.engine.kinds import neural_skinned as ns
from collider_server.engine.kinds.neural_skinned import (
    DIVERGED,
    allowed_labels,
    blend_at,
    carried_rows,
    carry_to_rest,
    clamp_to_cube,
    joined_rows,
    part_boxes,
    part_candidates,
    part_labels,
    pose_codes,
    pull_back,
    rest_maps,
    skinned_rest,
    spread_stride,
    union_of_parts,
    weight_field,
)
from collider_server.engine.meshes import Mesh
from collider_server.engine.skinning import pose_at, skin_vertices, world_transforms
from collider_server.making.sampling import surface_band_points
from collider_server.making.skinned import skinned_arm
from collider_server.making.training.data import normalisation

pytestmark = pytest.mark.skipif(not grid_kernels.available(), reason="the fast passes are numba's")


@pytest.fixture(scope="module")
def arm():
    """The arm with the elbow bent (wave at 0.5 s), its rest pose's labels, boxes and weight field,
    and points in the +-10 mm band of the posed skin plus some far from it."""
    skin = skinned_arm()
    centre, radius = normalisation(Mesh(skin.vertices, skin.faces, "rest"), 0.1)
    cell = 2.0 * radius / 32
    labels = part_labels(skin, centre, radius, 32, band=3.0 * cell)
    boxes = part_boxes(skin, cell)
    field = weight_field(skin, centre, radius, 16, 64, 2.0 * radius / 64)
    transforms, velocities = pose_at(skin, "wave", 0.5)
    to_rest, posed = rest_maps(skin.skeleton, transforms)
    moving = (velocities @ skin.skeleton.inverse_bind)[:, :3, :]
    band = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 4000, 1e-2, 3)
    points = np.concatenate([band, np.random.default_rng(4).uniform(-0.4, 0.9, (500, 3))])
    return skin, centre, radius, labels, boxes, field, to_rest, posed, moving, points


def _candidates(arm, neighbours=True, fused=True):
    skin, centre, radius, labels, boxes, _, to_rest, _, _, points = arm
    return part_candidates(points, to_rest, labels, centre, radius, allowed_labels(skin.skeleton.parents, neighbours),
                           boxes, fused=fused)


def test_the_candidate_rows_written_from_the_mask_are_the_numpy_rule_s_bit_for_bit(arm):
    fused, reference = _candidates(arm, fused=True), _candidates(arm, fused=False)
    for a, b in zip(fused, reference):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    point, joint, _ = fused
    assert len(point) > len(arm[-1])  # with neighbours some points have several parts
    # Sorted by joint, then point.
    assert np.all(np.diff(joint) >= 0)
    assert np.all(np.diff(point)[np.diff(joint) == 0] > 0)


def test_the_retry_s_joined_rows_are_numpy_s_concatenation_and_gather():
    rng = np.random.default_rng(8)
    source = rng.permutation(700)[:650]  # rows of the first 500 and of the 200 retried, in any order
    for make in (lambda m: rng.normal(size=(m, 3, 3)), lambda m: rng.integers(0, 9, m),
                 lambda m: rng.random(m) < 0.5):
        a, b = make(500), make(200)
        fused = joined_rows(a, b, source)
        assert fused.dtype == a.dtype and fused.shape == (650,) + a.shape[1:]
        np.testing.assert_array_equal(fused, np.concatenate([a, b])[source])
        np.testing.assert_array_equal(fused, joined_rows(a, b, source, fused=False))


def test_the_union_takes_the_least_usable_row_and_the_lowest_joint_on_a_tie(arm):
    point, _, _ = _candidates(arm)
    n = len(arm[-1])
    rng = np.random.default_rng(5)
    distance = np.round(rng.uniform(-1.0, 1.0, len(point)), 1)  # many ties
    usable = rng.uniform(size=len(point)) > 0.1
    usable[np.unique(point, return_index=True)[1]] = True  # every point keeps a row
    best, row = union_of_parts(distance, point, usable, n)
    reference = union_of_parts(distance, point, usable, n, fused=False)
    np.testing.assert_array_equal(best, reference[0])
    np.testing.assert_array_equal(row, reference[1])
    # The rule itself, point by point.
    for p in rng.choice(n, 300, replace=False):
        mine = np.flatnonzero((point == p) & usable)
        least = distance[mine].min()
        assert best[p] == least
        assert row[p] == mine[distance[mine] == least][0]  # the first row: the lowest joint
    assert not np.isin(row, np.flatnonzero(~usable)).any()


def test_the_pull_back_is_the_transposed_map_times_the_gradient(arm):
    rng = np.random.default_rng(6)
    gradient, inverse = rng.normal(size=(800, 3)), rng.normal(size=(800, 3, 3))
    row = rng.integers(0, 800, 500)
    np.testing.assert_allclose(pull_back(gradient, inverse, row), pull_back(gradient, inverse, row, fused=False),
                               rtol=0, atol=1e-14)
    np.testing.assert_allclose(pull_back(gradient, inverse, row)[0], inverse[row[0]].T @ gradient[row[0]], atol=1e-14)


def test_the_clamp_into_the_cube_is_numpy_s_bit_for_bit(arm):
    _, centre, radius = arm[:3]
    rest = centre + radius * np.random.default_rng(7).uniform(-1.3, 1.3, (5000, 3))
    rest[:3] = centre + radius  # on the cube's corner: inside
    lo, hi = centre - radius, centre + radius
    clamped, outside = clamp_to_cube(rest, lo, hi)
    reference = clamp_to_cube(rest, lo, hi, fused=False)
    assert clamped.dtype == np.float32
    np.testing.assert_array_equal(clamped, reference[0])
    np.testing.assert_array_equal(outside, reference[1])
    assert 0 < len(outside) < len(rest) and outside[0] >= 3
    np.testing.assert_array_equal(clamped, np.clip(rest, lo, hi).astype(np.float32))


@pytest.mark.parametrize("last_step", [0.0, ns.NEWTON_LAST_STEP])
def test_the_newton_kernel_s_velocity_is_the_skinning_s_motion_at_its_rest_point(arm, monkeypatch, last_step):
    _, centre, radius, _, _, field, to_rest, posed, moving, points = arm
    point, joint, rigid = _candidates(arm, neighbours=False)
    monkeypatch.setattr(ns, "NEWTON_LAST_STEP", last_step)
    args = (points, point, joint, rigid, to_rest, posed, field, centre, radius, 8, "newton")
    carried = carried_rows(*args, moving=moving)
    # The rows and maps are carry_to_rest's (which drops the unusable rows).
    keep, rest, inverse = carry_to_rest(*args)
    np.testing.assert_array_equal(np.flatnonzero(carried.usable), keep)
    np.testing.assert_array_equal(carried.rest[keep], rest)
    np.testing.assert_array_equal(carried.inverse[keep], inverse)
    # The velocity: the weights' blend of the maps' motion at the final rest point (blend_at); the
    # weights are those of the last evaluation, before a short last step where one was taken
    # (NEWTON_LAST_STEP: a step under 0.1 mm here moves the blend by a few thousandths of it).
    homogeneous = np.concatenate([carried.rest, np.ones((len(point), 1))], axis=1)
    expected = np.einsum("nab,nb->na", blend_at(carried.rest, moving, field, centre, radius), homogeneous)
    assert np.abs(expected).max() > 0.1  # the elbow bends: the skin moves
    atol = 1e-12 if last_step == 0.0 else 1e-3 * np.abs(expected).max()
    np.testing.assert_allclose(carried.velocity, expected, rtol=0, atol=atol)
    exact = np.abs(carried.velocity - expected).max(axis=1) <= 1e-12
    assert exact.all() if last_step == 0.0 else 0.05 < exact.mean() < 0.95  # the short last steps are taken
    # Without the kernel (numpy) or without a motion there is none: blend_at answers then.
    assert carried_rows(*args, fused=False, moving=moving).velocity is None
    assert carried_rows(*args).velocity is None


@pytest.mark.parametrize("fused", [True, False])
def test_a_short_last_newton_step_lands_where_the_steps_to_convergence_do(arm, monkeypatch, fused):
    """NEWTON_LAST_STEP: a step under it is taken without evaluating the map after it, only where
    it stays in its cell of the weights (across a cell face the field's derivative jumps and
    Newton's error is no longer of the step's square); the rest points are the converged ones to
    well within the tolerance, and the map's linear part is the one before the step. (The arm's
    steps across cell faces miss by under 0.3 um: the cell condition is checked on the shipped
    walker, test_neural_skinned_model.py.)"""
    _, centre, radius, _, _, field, to_rest, posed, _, points = arm
    point, joint, rigid = _candidates(arm, neighbours=False)
    args = (points, point, joint, rigid, to_rest, posed, field, centre, radius, 8, "newton", fused)
    monkeypatch.setattr(ns, "NEWTON_LAST_STEP", 0.0)
    full = carried_rows(*args)
    monkeypatch.undo()
    short = carried_rows(*args)
    np.testing.assert_array_equal(short.converged, full.converged)
    both = short.converged
    moved = np.linalg.norm(short.rest - full.rest, axis=1)[both]
    assert moved.max() < 1e-3 * ns.NEWTON_TOLERANCE * radius, moved.max()
    changed = np.abs(short.inverse - full.inverse).max(axis=(1, 2))[both]
    assert 0.05 < np.mean(changed > 0) < 0.95  # the short steps are taken (their map is the one before)
    assert np.quantile(changed, 0.99) < 1e-2


def test_with_no_skinning_steps_each_row_keeps_its_part_s_rigid_image_and_map(arm):
    """0 iterations (a rigid-parts model): every row is usable and converged at its part's rigid
    image, and its map is that part's linear map (m, 3, 3), so the gradient's pull-back is the
    same through the numba pass and numpy."""
    _, centre, radius, _, _, field, to_rest, posed, _, points = arm
    point, joint, rigid = _candidates(arm)
    carried = carried_rows(points, point, joint, rigid, to_rest, posed, field, centre, radius, 0)
    assert carried.usable.dtype == carried.converged.dtype == bool
    assert carried.usable.all() and carried.converged.all() and carried.velocity is None
    np.testing.assert_array_equal(carried.rest, rigid)
    assert carried.inverse.shape == (len(point), 3, 3)
    for r in np.random.default_rng(9).choice(len(point), 50, replace=False):
        np.testing.assert_allclose(carried.inverse[r], np.linalg.inv(posed[joint[r]])[:3, :3], rtol=0, atol=1e-12)
    gradient = np.random.default_rng(10).normal(size=(len(point), 3))
    row = np.arange(len(point))
    np.testing.assert_allclose(pull_back(gradient, carried.inverse, row),
                               pull_back(gradient, carried.inverse, row, fused=False), rtol=0, atol=1e-14)


def test_the_newton_pass_s_tasks_take_every_chunk_once_spread_over_the_rows():
    """Task i takes chunk (i * stride) % chunks: every chunk once, and each half of the tasks (one
    thread's share under numba's static schedule) reaches over all the rows, not one half."""
    for chunks in (0, 1, 2, 3, 7, 64, 525, 1024, 1025):
        stride = spread_stride(chunks)
        taken = (np.arange(chunks) * stride) % max(chunks, 1)
        np.testing.assert_array_equal(np.sort(taken), np.arange(chunks))
        if chunks >= 64:
            first_half = taken[: chunks // 2]
            assert first_half.min() < chunks // 8 and first_half.max() > chunks - chunks // 8
            assert abs(np.mean(first_half) - chunks / 2) < 0.05 * chunks
def _landing_miss(rest, x, arm):
    """(m,) metres: how far the skinning at rest points ``rest`` (m, 3) puts them from the posed
    points ``x`` (m, 3) (0 where ``rest`` is their rest-pose image)."""
    _, centre, radius, _, _, field, _, posed, _, _ = arm
    homogeneous = np.concatenate([rest, np.ones((len(rest), 1))], axis=1)
    return np.linalg.norm(np.einsum("mab,mb->ma", blend_at(rest, posed[:, :3, :], field, centre, radius), homogeneous)
                          - x, axis=1)


def test_the_fixed_point_steps_carry_posed_points_to_their_rest_images(arm):
    """The first model files' map (``skinning_solver`` ``fixed-point``): steps ``x_rest <- M^-1 x``
    from each candidate's rigid image, through the numba pass and numpy alike; the rows
    :func:`carried_rows` keeps are those steps' (the rigid image where they went wild)."""
    _, centre, radius, _, _, field, to_rest, posed, _, points = arm
    point, joint, rigid = _candidates(arm, neighbours=False)
    x = points[point]
    rest, inverse = skinned_rest(x, rigid, posed, field, centre, radius, 8)
    assert rest.dtype == inverse.dtype == np.float64 and rest.shape == (len(x), 3) and inverse.shape == (len(x), 3, 3)
    some = slice(None, None, 8)  # (the numpy rule takes 1 s over all the rows)
    reference = skinned_rest(x[some], rigid[some], posed, field, centre, radius, 8, fused=False)
    np.testing.assert_allclose(rest[some], reference[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(inverse[some], reference[1], rtol=0, atol=1e-9)
    # Rigid images in float32: float64 answers all the same, the caller's array left alone.
    rigid32 = rigid[some].astype(np.float32)
    rest32, _ = skinned_rest(x[some], rigid32, posed, field, centre, radius, 8)
    assert rest32.dtype == np.float64
    np.testing.assert_allclose(rest32, skinned_rest(x[some], rigid32, posed, field, centre, radius, 8, fused=False)[0],
                               rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rigid32, rigid[some].astype(np.float32))
    # In the +-10 mm band the skinning puts the rest points back on the posed points: the rigid
    # images miss by up to 26 mm (p99) where the elbow blends, 8 steps by 0.6 mm (measured).
    band = point < 4000
    before, after = _landing_miss(rigid, x, arm)[band], _landing_miss(rest, x, arm)[band]
    assert np.percentile(before, 99) > 0.01 and np.percentile(after, 99) < 1e-3, np.percentile(after, 99)
    # The map: the linear part of the last step's M^-1 (M at the rest point of the step before).
    before_last, _ = skinned_rest(x, rigid, posed, field, centre, radius, 7)
    expected = np.linalg.inv(blend_at(before_last, posed[:, :3, :], field, centre, radius)[:, :, :3])
    np.testing.assert_allclose(inverse, expected, rtol=0, atol=1e-9)
    # carried_rows: every row usable and converged, the steps' rows where they stayed within
    # DIVERGED of the rigid image, the rigid image and its part's map where they did not.
    carried = carried_rows(points, point, joint, rigid, to_rest, posed, field, centre, radius, 8, "fixed-point")
    assert carried.usable.all() and carried.converged.all() and carried.velocity is None
    wild = np.linalg.norm(rest - rigid, axis=1) > DIVERGED * radius
    assert 0 < wild.sum() < 0.01 * len(x)
    np.testing.assert_array_equal(carried.rest[~wild], rest[~wild])
    np.testing.assert_array_equal(carried.inverse[~wild], inverse[~wild])
    np.testing.assert_array_equal(carried.rest[wild], rigid[wild])
    np.testing.assert_allclose(carried.inverse[wild], np.linalg.inv(posed[joint[wild]])[:, :3, :3], atol=1e-12)


def test_pose_codes_are_zero_at_rest_and_leave_the_joints_scale_out(arm):
    """The codes of a rig whose joints are scaled (a character in centimetres under a scaled
    root, say) are those of the same rotations unscaled: zero at the rest pose."""
    skin = arm[0]
    skeleton = skin.skeleton
    scaled = dataclasses.replace(skeleton, rest_scale=np.array([[1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [0.5, 0.5, 0.5]]))
    assert not pose_codes(scaled, scaled.rest_world(), 2).any()
    transforms, _ = pose_at(skin, "wave", 0.5)
    codes = pose_codes(skeleton, transforms, 2)
    assert codes.dtype == np.float32 and codes.shape == (3, 18) and np.abs(codes).max() > 0.5  # the elbow bends
    parents = skeleton.parents
    above = np.where((parents >= 0)[:, None, None], transforms[np.maximum(parents, 0)], skeleton.root)
    local = np.linalg.solve(above, transforms)
    local[:, :3, :3] *= scaled.rest_scale[:, None, :]  # T R S: each joint's scale in its own frame
    np.testing.assert_allclose(pose_codes(scaled, world_transforms(scaled, local), 2), codes, atol=1e-6)


def test_the_weight_passes_per_row_helpers_are_inlined():
    """A numba call that passes arrays takes and releases a reference to each, and a pass's
    threads contend for the shared tables' counts: inlined, the Newton pass took 0.76x the time
    on the walker and the fixed-point steps 0.53x, with the same bits (docs/neural.md). The
    answers cannot tell, so the rule is checked here."""
    for helper in (ns._weight_source, ns._corner_weight, ns._gather_weights, ns._newton_terms_one, ns._add_offsets,
                   ns._same_weight_cell, ns._inverse3, ns._blend_one, ns._fine_cell, ns._table_blend, ns._table_terms,
                   ns._gather_scratch, ns._add_blended_offset):
        assert helper.targetoptions.get("inline") == "always", helper.__name__
