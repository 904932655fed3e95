"""The dilated label grid of kind ``neural-skinned`` (architecture ``label_dilation``): near a
boundary between parts a cell of the rest pose's label grid names every part within the dilation,
so that a point whose rigid image falls just across a boundary keeps its part as a candidate. On
the Khronos RiggedFigure off its clip, where the label rule misses the truth's part at its worst
points, one cell lowers the map's floor by more than half for about half a row more a point."""

import numpy as np
import pytest

from collider_contract.skeleton import SkeletonPose
from collider_server.engine.kinds import grid_kernels
from collider_server.engine.kinds import neural_skinned as ns
from collider_server.engine.meshes import Mesh
from collider_server.engine.modelfile import load_collider, save_collider
from collider_server.engine.skinning import random_poses, skin_vertices
from collider_server.making.sampling import surface_band_points

pytestmark = pytest.mark.skipif(not grid_kernels.available(), reason="the fast passes are numba's")


def _named_near(labels: np.ndarray, joints: int, cells: int) -> np.ndarray:
    """(J, R, R, R) bool, by shifting the grid (the reference): whether a labelled cell has a cell
    of joint j within ``cells`` cells along every axis."""
    r = labels.shape[0]
    padded = np.pad(labels, cells, constant_values=ns.NO_PART)
    near = np.zeros((joints,) + labels.shape, bool)
    span = range(2 * cells + 1)
    for i in span:
        for j in span:
            for k in span:
                block = padded[i:i + r, j:j + r, k:k + r]
                for joint in range(joints):
                    near[joint] |= block == joint
    return near & (labels != ns.NO_PART)


def test_a_dilated_cell_names_every_part_within_its_cells(figure):
    skin, mine = figure[1], figure[4]
    labels, joints = mine[0], figure[1].skeleton.joint_count
    dilated, sets, dropped = ns.dilated_labels(labels, joints, 1)
    assert dropped == 0 and (dilated != labels).sum() > 100  # boundaries widened, every set coded
    allowed = ns.allowed_labels(skin.skeleton.parents, False, sets)
    near = _named_near(labels, joints, 1)
    for joint in range(joints):
        np.testing.assert_array_equal(allowed[joint][dilated], near[joint])
    assert not allowed[:, ns.NO_PART].any()
    plain, plain_sets, _ = ns.dilated_labels(labels, joints, 0)
    assert plain is labels and not plain_sets[joints:].any()


def test_sets_beyond_the_codes_keep_their_own_label():
    """250 joints leave 5 codes (250 .. 254) for the 7 sets of neighbouring slabs: the commonest
    take them, the other cells keep their own label and are counted."""
    labels = np.full((16, 16, 16), ns.NO_PART, np.uint8)
    labels[:, :, :8] = np.arange(16)[:, None, None] // 2  # slabs of joints 0..7 along x, 2 cells thick
    dilated, sets, dropped = ns.dilated_labels(labels, 250, 1)
    codes = np.unique(dilated[(dilated >= 250) & (dilated != ns.NO_PART)])
    assert len(codes) == 5 and dropped > 0
    kept = (dilated == labels) & (labels != ns.NO_PART)
    assert kept.sum() >= dropped
    for code in codes:
        assert sets[code].sum() == 2  # two neighbouring slabs


def _floor(figure, transforms, cells):
    exact, skin, rest_sdf, anchors, mine = figure
    labels, centre, radius, _, boxes, field = mine
    dilated, sets, _ = ns.dilated_labels(labels, skin.skeleton.joint_count, cells)
    allowed = ns.allowed_labels(skin.skeleton.parents, False, sets)
    to_rest, posed = ns.rest_maps(skin.skeleton, transforms)
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 3000, 1e-3, 13)
    truth = exact.query(points, "distance", joint_transforms=transforms).distance
    offsets = ns.surface_offsets(anchors, field, skin, posed[:, :3, :])
    point, _, rest, _ = ns.parts_through_skinning(points, to_rest, posed, dilated, centre, radius, allowed, boxes,
                                                  field, 8, "newton", "retry-labels", offsets=offsets)
    least = np.full(len(points), np.inf)
    np.minimum.at(least, point, rest_sdf.query(rest)[0])
    return np.abs(least - truth).mean(), len(point) / len(points)


def test_one_cell_of_dilation_lowers_the_floor_off_the_clip(figure):
    """At a pose off the clip where the label rule misses parts (measured: 0.38 -> 0.10 mm mean,
    1.15 -> 1.71 rows a point; at four other poses 0.03-0.55 mm fell by 0-25 %)."""
    transforms = random_poses(figure[1], 1, 2026, perturbed_share=1.0).transforms[0]
    (plain, plain_rows), (dilated, dilated_rows) = _floor(figure, transforms, 0), _floor(figure, transforms, 1)
    assert dilated < 0.5 * plain, (plain, dilated)
    assert dilated_rows < plain_rows + 1.0, (plain_rows, dilated_rows)


def test_a_model_with_a_dilated_grid_keeps_its_sets_in_its_file(figure, figure_model, tmp_path):
    skin = figure[1]
    collider = figure_model(label_dilation=1)
    assert collider.allowed[:, skin.skeleton.joint_count:ns.NO_PART].any()
    transforms = random_poses(skin, 1, 31, perturbed_share=1.0).transforms[0]
    pose = SkeletonPose(joint_transforms=transforms)
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 1000, 1e-3, 14)
    rows = collider.parts_at(points, None, pose)
    assert len(rows[0]) > len(figure_model().parts_at(points, None, pose)[0])  # more candidates
    loaded = load_collider(save_collider(collider, tmp_path / "figure-dilated.safetensors"))
    np.testing.assert_array_equal(loaded.allowed, collider.allowed)
    for a, b in zip(loaded.parts_at(points, None, pose), rows):  # the same candidates, the same rest points
        np.testing.assert_array_equal(a, b)


def test_files_before_it_have_no_dilation():
    assert ns.ArticulatedGridArchitecture(joints=3).label_dilation == 0
    with pytest.raises(ValueError, match="label_dilation"):
        ns.ArticulatedGridArchitecture(joints=3, label_dilation=-1)


def test_the_training_dilates_where_it_lowers_the_map_s_floor(figure):
    """``choose_label_dilation`` at 8 poses off the clips: the RiggedFigure's floor halves with one
    cell (measured 0.116 -> 0.062 mm), so it is taken; the generated walker's does not move (0.094
    mm both), so its grid stays as labelled, at 1.0 row a point instead of 1.6."""
    import dataclasses

    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.training.articulated import (
        ARTICULATED_PRESET,
        choose_label_dilation,
        rest_tables,
    )
    from collider_server.making.training.data import normalisation
    from collider_server.making.walker import make_walker

    _, skin, rest_sdf, anchors, mine = figure
    labels, centre, radius, _, boxes, field = mine
    arch = dataclasses.replace(ARTICULATED_PRESET, joints=skin.skeleton.joint_count)
    cells, why = choose_label_dilation(skin, arch, centre, radius, labels, boxes, field, anchors, rest_sdf, 1e-3, 0)
    assert cells == 1 and why.startswith("label dilation 1 (the map's floor"), why

    walker = make_walker().skin()
    rest = Mesh(walker.vertices, walker.faces, "rest")
    centre, radius = normalisation(rest, 0.1)
    arch = dataclasses.replace(ARTICULATED_PRESET, joints=walker.skeleton.joint_count)
    labels, boxes, field, anchors = rest_tables(walker, arch, centre, radius)
    cells, why = choose_label_dilation(walker, arch, centre, radius, labels, boxes, field, anchors, ExactSDF(rest),
                                       1e-3, 0)
    assert cells == 0, why
