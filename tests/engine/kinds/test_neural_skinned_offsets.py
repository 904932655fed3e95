"""The surface offsets of kind ``neural-skinned`` (architecture ``surface_offsets``): per fine block
corner, the posed mesh's flat triangle against the weight field's skinning of the corner's closest
rest surface point, added to the Newton map. On the Khronos RiggedFigure, whose large faces span
its joints, they take the map's floor from most of a millimetre to a few micrometres at a clip
time; the numba passes answer as the numpy rule; the velocity is the map's time derivative."""


import numpy as np
import pytest

from collider_contract.skeleton import SkeletonPose
from collider_server.engine.kinds import grid_kernels
from collider_server.engine.kinds import neural_skinned as ns
from collider_server.engine.meshes import Mesh
from collider_server.engine.skinning import pose_at, random_poses, skin_vertices
from collider_server.making.sampling import surface_band_points

pytestmark = pytest.mark.skipif(not grid_kernels.available(), reason="the fast passes are numba's")

def test_the_offsets_carry_the_rest_surface_onto_the_posed_triangles(figure):
    """The exact rest SDF read through the map, the minimum over each point's rows, against the
    exact skinned kind at a clip time (the arms turned 40 degrees): without the offsets the
    figure's faces, skinned inside, bend off the flat posed triangles (measured 0.75 mm mean);
    with them the map lands on the triangles (7 um)."""
    exact, skin, rest_sdf, anchors, mine = figure
    transforms = pose_at(skin, "animation 0", 0.9)[0]
    to_rest, posed = ns.rest_maps(skin.skeleton, transforms)
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 3000, 1e-3, 5)
    truth = exact.query(points, "distance", joint_transforms=transforms).distance
    offsets = ns.surface_offsets(anchors, mine[-1], skin, posed[:, :3, :])
    errors = []
    for with_offsets in (None, offsets):
        point, _, rest, _ = ns.parts_through_skinning(points, to_rest, posed, *mine, 8, "newton", "retry-labels",
                                                      offsets=with_offsets)
        least = np.full(len(points), np.inf)
        np.minimum.at(least, point, rest_sdf.query(rest)[0])
        errors.append(np.abs(least - truth).mean())
    plain, offset = errors
    assert plain > 3e-4 and offset < 0.05 * plain and offset < 2e-5, (plain, offset)


@pytest.mark.parametrize("kind", ["clip", "off the clip"])
def test_the_fused_offsets_and_map_answer_as_the_numpy_rule(figure, kind):
    _, skin, _, anchors, mine = figure
    transforms = (pose_at(skin, "animation 0", 0.6)[0] if kind == "clip"
                  else random_poses(skin, 1, 17, perturbed_share=1.0).transforms[0])
    to_rest, posed = ns.rest_maps(skin.skeleton, transforms)
    field = mine[-1]
    offsets = ns.surface_offsets(anchors, field, skin, posed[:, :3, :])
    np.testing.assert_allclose(offsets, ns.surface_offsets(anchors, field, skin, posed[:, :3, :], fused=False),
                               rtol=0, atol=1e-14)
    assert np.abs(offsets).max() > 1e-3  # the figure's faces bend by millimetres
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 2000, 1e-2, 6)
    fused = ns.parts_through_skinning(points, to_rest, posed, *mine, 8, "newton", "retry-labels", offsets=offsets)
    reference = ns.parts_through_skinning(points, to_rest, posed, *mine, 8, "newton", "retry-labels", fused=False,
                                          offsets=offsets)
    for a, b in zip(fused[:2], reference[:2]):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(fused[2], reference[2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(fused[3], reference[3], rtol=0, atol=1e-9)


def test_the_velocity_is_the_offset_map_s_time_derivative(figure, monkeypatch):
    """At each row's rest point, the Newton kernel's velocity equals the map (weights and offsets)
    differenced between two nearby clip times; and, with no short last step, the numpy rule's."""
    _, skin, _, anchors, mine = figure
    field, centre, radius = mine[-1], mine[1], mine[2]
    t, h = 0.6, 1e-4
    transforms, velocities = pose_at(skin, "animation 0", t)
    to_rest, posed = ns.rest_maps(skin.skeleton, transforms)
    moving = (velocities @ skin.skeleton.inverse_bind)[:, :3, :]
    offsets = ns.surface_offsets(anchors, field, skin, posed[:, :3, :])
    moving_offsets = ns.surface_offsets(anchors, field, skin, moving)
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 2000, 1e-3, 7)
    point, joint, rigid = ns.part_candidates(points, to_rest, *mine[:5])
    monkeypatch.setattr(ns, "NEWTON_LAST_STEP", 0.0)
    rows = ns.carried_rows(points, point, joint, rigid, to_rest, posed, field, centre, radius, 8, "newton",
                           moving=moving, offsets=offsets, moving_offsets=moving_offsets)
    np.testing.assert_allclose(rows.velocity, ns._velocity_at(rows.rest, moving, field, centre, radius,
                                                                moving_offsets), rtol=0, atol=1e-12)

    def mapped(time):
        maps = ns.rest_maps(skin.skeleton, pose_at(skin, "animation 0", time)[0])[1][:, :3, :]
        homogeneous = np.concatenate([rows.rest, np.ones((len(rows.rest), 1))], axis=1)
        lbs = np.einsum("nab,nb->na", ns.blend_at(rows.rest, maps, field, centre, radius), homogeneous)
        return lbs + ns.offsets_at(rows.rest, ns.surface_offsets(anchors, field, skin, maps), field, centre,
                                   radius)[0]

    differenced = (mapped(t + h) - mapped(t - h)) / (2 * h)
    assert np.abs(differenced).max() > 0.1  # the arms move
    np.testing.assert_allclose(rows.velocity, differenced, rtol=0, atol=1e-5)
    # Without the offsets' velocity the surface's motion is off by the offsets' own (the check can tell).
    plain = ns.carried_rows(points, point, joint, rigid, to_rest, posed, field, centre, radius, 8, "newton",
                            moving=moving, offsets=offsets)
    assert np.abs(plain.velocity - differenced).max() > 1e-3


def _pose_and_motion(figure, kind):
    """``(transforms, to_rest, posed, moving, offsets, moving_offsets)`` of the figure at a clip
    time or a pose off its clip (the clip time's joint velocities as the motion)."""
    _, skin, _, anchors, mine = figure
    transforms, velocities = pose_at(skin, "animation 0", 0.6)
    if kind != "clip":
        transforms = random_poses(skin, 1, 19, perturbed_share=1.0).transforms[0]
    to_rest, posed = ns.rest_maps(skin.skeleton, transforms)
    moving = (velocities @ skin.skeleton.inverse_bind)[:, :3, :]
    offsets, moving_offsets = ns.surface_offsets(anchors, mine[-1], skin, np.stack([posed[:, :3, :], moving]))
    return transforms, to_rest, posed, moving, offsets, moving_offsets


def test_the_blended_table_holds_each_fine_corner_s_skinning_map_and_offsets(figure):
    """blended_blocks: per fine corner and map set, the maps summed by the corner's stored weights
    (divided by their sum: the skinning's map there, blend_at's), the sum, then the offsets; numba
    and numpy alike."""
    _, _, _, _, mine = figure
    _, centre, radius, _, _, field = mine
    _, _, posed, moving, offsets, moving_offsets = _pose_and_motion(figure, "clip")
    sets, set_offsets = np.stack([posed[:, :3, :], moving]), np.stack([offsets, moving_offsets])
    table = ns.blended_blocks(field, sets, set_offsets)
    assert table.shape == field.block_joints.shape[:4] + (2 * ns.BLENDED_CHANNELS,)
    np.testing.assert_allclose(table, ns.blended_blocks(field, sets, set_offsets, fused=False), rtol=0, atol=1e-14)
    np.testing.assert_array_equal(ns.blended_blocks(field, sets)[..., 13:16], 0.0)  # no offsets: none added
    # Stored blocks' inner corners (on a block's faces a neighbour's cells may answer) at their rest
    # positions, the fine grid's nodes, where the field's weights are that corner's alone.
    cells = field.block_index.shape[0] * ns.BLOCK_CELLS
    block = np.argwhere(field.block_index >= 0)[:: max(1, len(field.block_joints) // 40)]
    inner = np.stack(np.meshgrid(*[np.arange(1, ns.BLOCK_CELLS)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    node = block[:, None, :] * ns.BLOCK_CELLS + inner[None]
    position = (centre + radius * (2.0 * node / cells - 1.0)).reshape(-1, 3)
    row = np.repeat(field.block_index[tuple(block.T)], len(inner))
    corner = np.tile(inner, (len(block), 1))
    at = table[row, corner[:, 0], corner[:, 1], corner[:, 2]]
    for i, (maps, offset) in enumerate(zip(sets, set_offsets)):
        channels = at[:, i * ns.BLENDED_CHANNELS:(i + 1) * ns.BLENDED_CHANNELS]
        np.testing.assert_allclose(channels[:, :12].reshape(-1, 3, 4) / channels[:, 12, None, None],
                                   ns.blend_at(position, maps, field, centre, radius), rtol=0, atol=1e-9)
        np.testing.assert_array_equal(channels[:, 13:], offset[row, corner[:, 0], corner[:, 1], corner[:, 2]])


@pytest.mark.parametrize("kind", ["clip", "off the clip"])
def test_a_long_newton_pass_reads_the_pose_s_table_and_answers_as_the_sums_per_joint(figure, monkeypatch, kind):
    """NEWTON_TABLE_ROWS: a pass of that many rows reads the fine blocks through the pose's
    blended_blocks table (the maps, offsets and motion in one read per corner); its roots, maps and
    velocities are those of the weights summed per joint, the same sums regrouped by corner."""
    _, skin, _, _, mine = figure
    labels, centre, radius, allowed, boxes, field = mine
    transforms, to_rest, posed, moving, offsets, moving_offsets = _pose_and_motion(figure, kind)
    points = np.concatenate([  # the skin, and far points: the coarse grid's (no table there)
        surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 3000, 1e-2, 9),
        np.random.default_rng(3).uniform(centre - radius, centre + radius, (300, 3))])
    point, joint, rigid = ns.part_candidates(points, to_rest, labels, centre, radius, allowed, boxes)
    args = (points, point, joint, rigid, to_rest, posed, field, centre, radius, 8, "newton")
    motion = {"moving": moving, "offsets": offsets, "moving_offsets": moving_offsets}
    monkeypatch.setattr(ns, "NEWTON_TABLE_ROWS", len(point) + 1)
    by_joint = ns.carried_rows(*args, **motion)
    monkeypatch.setattr(ns, "NEWTON_TABLE_ROWS", len(point))
    by_table = ns.carried_rows(*args, **motion)
    np.testing.assert_array_equal(by_table.converged, by_joint.converged)
    np.testing.assert_array_equal(by_table.usable, by_joint.usable)
    assert by_table.converged.mean() > 0.9
    np.testing.assert_allclose(by_table.rest, by_joint.rest, rtol=0, atol=1e-12)
    np.testing.assert_allclose(by_table.inverse, by_joint.inverse, rtol=0, atol=1e-9)
    np.testing.assert_allclose(by_table.velocity, by_joint.velocity, rtol=0, atol=1e-12)
    # The table is what such a pass reads: another pose's table moves its roots.
    other = ns.rest_maps(skin.skeleton, pose_at(skin, "animation 0", 0.1)[0])[1][:, :3, :]
    built = ns.blended_blocks
    monkeypatch.setattr(ns, "blended_blocks", lambda f, maps, o: built(f, np.concatenate([other[None], maps[1:]]), o))
    assert np.abs(ns.carried_rows(*args, **motion).rest - by_joint.rest).max() > 1e-3


def test_a_collider_builds_a_pose_s_table_once_and_answers_through_it_as_without(figure, figure_model, monkeypatch):
    """A query long enough for the table (NEWTON_TABLE_ROWS) builds the pose's table once and
    keeps it for that pose: its chunks and retried rows, and the next query at the pose, read
    the same one; a new pose, or a query without the motion, builds its own. The answers are the
    sums per joint's."""
    _, skin, _, _, _ = figure
    collider = figure_model()
    transforms, velocities = pose_at(skin, "animation 0", 0.6)
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 2000, 1e-2, 4)
    pose = SkeletonPose(joint_transforms=transforms, joint_velocities=velocities)
    monkeypatch.setattr(ns, "NEWTON_TABLE_ROWS", 10**9)
    by_joint = collider.evaluate_at(points, True, None, pose)
    built, build = [], ns.pose_table
    monkeypatch.setattr(ns, "pose_table", lambda *a: built.append(a[2] is not None) or build(*a))
    monkeypatch.setattr(ns, "NEWTON_TABLE_ROWS", 500)
    by_table = collider.evaluate_at(points, True, None, pose)
    for a, b in zip(by_table, by_joint):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    collider.evaluate_at(points[:1000], True, None, pose)
    assert built == [True]  # one table for the pose, with its motion
    collider.evaluate_at(points, False, None, pose)
    other = SkeletonPose(joint_transforms=pose_at(skin, "animation 0", 0.2)[0], joint_velocities=velocities)
    collider.evaluate_at(points, True, None, other)
    assert built == [True, False, True]
    collider.evaluate_at(points[:400], True, None, pose)  # under the threshold: no table
    assert built == [True, False, True]


def test_a_pose_table_must_match_the_pass_s_motion(figure):
    _, skin, _, _, mine = figure
    labels, centre, radius, allowed, boxes, field = mine
    transforms, to_rest, posed, moving, offsets, moving_offsets = _pose_and_motion(figure, "clip")
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 200, 1e-2, 9)
    point, joint, rigid = ns.part_candidates(points, to_rest, labels, centre, radius, allowed, boxes)
    still = ns.pose_table(field, posed, None, offsets)
    with pytest.raises(ValueError, match="16 channels for a pass with the motion"):
        ns.carried_rows(points, point, joint, rigid, to_rest, posed, field, centre, radius, 8, "newton",
                        moving=moving, offsets=offsets, moving_offsets=moving_offsets, table=still)


def test_the_fused_velocity_at_rest_points_is_the_numpy_rule(figure):
    """_velocity_at (the motion of the rows a Newton pass gave up on, at their rigid images; of a
    fixed-point model's rows): the numba pass answers as blend_at and offsets_at, in the fine
    blocks, on the coarse grid and beyond the cube, with and without the offsets' motion."""
    _, skin, _, _, mine = figure
    _, centre, radius, _, _, field = mine
    _, _, _, moving, _, moving_offsets = _pose_and_motion(figure, "off the clip")
    rng = np.random.default_rng(12)
    rest = np.concatenate([skin.vertices + rng.normal(0, 0.01, skin.vertices.shape),
                           rng.uniform(centre - 1.2 * radius, centre + 1.2 * radius, (2000, 3))])
    for offsets in (moving_offsets, None):
        fused = ns._velocity_at(rest, moving, field, centre, radius, offsets)
        np.testing.assert_allclose(fused, ns._velocity_at(rest, moving, field, centre, radius, offsets, fused=False),
                                   rtol=0, atol=1e-12)
    assert np.abs(fused - ns._velocity_at(rest, moving, field, centre, radius, moving_offsets)).max() > 1e-4


def test_a_model_with_offsets_answers_by_them_and_its_rows_are_the_query_s(figure, figure_model):
    """A collider whose architecture has ``surface_offsets`` computes its anchors once and each
    pose's offsets (and their velocity) with the pose; ``parts_at`` gives the rows its query's
    union takes, through the same offsets."""
    _, skin, _, _, mine = figure
    collider = figure_model()
    assert collider.anchors is not None
    transforms, velocities = pose_at(skin, "animation 0", 0.6)
    pose = SkeletonPose(joint_transforms=transforms, joint_velocities=velocities)
    prepared = collider.pose(None, pose)
    assert prepared.offsets is not None and prepared.moving_offsets is not None
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 1000, 1e-3, 8)
    point, joint, rest, _ = collider.parts_at(points, None, pose)
    expected = ns.parts_through_skinning(points, prepared.to_rest, prepared.posed, *mine, 8, "newton",
                                         "retry-labels", offsets=prepared.offsets)
    np.testing.assert_array_equal(rest, expected[2])
    plain = ns.parts_through_skinning(points, prepared.to_rest, prepared.posed, *mine, 8, "newton", "retry-labels")
    joints = skin.skeleton.joint_count
    keys, plain_keys = point * joints + joint, plain[0] * joints + plain[1]
    both, mine_at, plain_at = np.intersect1d(keys, plain_keys, return_indices=True)
    assert len(both) > 0.9 * len(points)
    assert np.abs(plain[2][plain_at] - rest[mine_at]).max() > 1e-4  # the offsets move the rest points
    distance, _, velocity = collider.evaluate_at(points, True, None, pose)
    assert np.isfinite(distance).all() and velocity is not None


def test_offsets_need_the_fine_field_and_the_newton_map():
    with pytest.raises(ValueError, match="surface_offsets"):
        ns.ArticulatedGridArchitecture(joints=3, surface_offsets=True)
    with pytest.raises(ValueError, match="surface_offsets"):
        ns.ArticulatedGridArchitecture(joints=3, surface_offsets=True, fine_weight_resolution=64)
    assert not ns.ArticulatedGridArchitecture(joints=3).surface_offsets  # the files before them
