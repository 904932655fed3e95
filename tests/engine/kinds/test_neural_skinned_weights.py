"""The weight field of kind ``neural-skinned`` (the rest pose's skinning weights the map to the
rest pose reads): the fine grid's blocks near the skin answer as the whole fine grid would, the
numba passes as the numpy rule, with no network (the generated arm)."""

import numpy as np
import pytest

from collider_server.engine.kinds.neural_skinned import (
    BLOCK_CELLS,
    blend_at,
    rest_maps,
    weight_field,
    weights_at,
)
from collider_server.engine.meshes import Mesh
from collider_server.engine.skinning import pose_at
from collider_server.making.sampling import surface_band_points
from collider_server.making.skinned import skinned_arm
from collider_server.making.training.data import normalisation


@pytest.fixture(scope="module")
def arm():
    skin = skinned_arm()
    centre, radius = normalisation(Mesh(skin.vertices, skin.faces, "rest"), 0.1)
    band = 2.0 * radius / 64
    return (skin, centre, radius, weight_field(skin, centre, radius, 16, 64, band),
            weight_field(skin, centre, radius, 64), weight_field(skin, centre, radius, 16))


def test_the_blocks_answer_as_the_whole_fine_grid_near_the_skin_and_the_coarse_grid_far_from_it(arm):
    skin, centre, radius, blocks, dense, coarse = arm
    count = (64 // BLOCK_CELLS) ** 3
    assert 0 < len(blocks.block_joints) < count / 4  # a share of the blocks: the ones near the skin
    near = surface_band_points(Mesh(skin.vertices, skin.faces, "rest"), 3000, 5e-3, 1)
    joints = skin.skeleton.joint_count
    np.testing.assert_allclose(weights_at(near, blocks, centre, radius, joints),
                               weights_at(near, dense, centre, radius, joints), atol=1e-12)
    # Far from the skin (no block there) the coarse grid answers.
    far = centre + np.array([[0.0, 0.3, 0.3], [0.0, -0.3, 0.3], [0.2, 0.0, -0.3]])
    np.testing.assert_allclose(weights_at(far, blocks, centre, radius, joints),
                               weights_at(far, coarse, centre, radius, joints), atol=1e-12)
    # Near the elbow's blend the fine grid follows the skin's own weights closer than the coarse.
    own = np.zeros((len(skin.vertices), joints))
    for k in range(skin.joints.shape[1]):
        np.add.at(own, (np.arange(len(own)), skin.joints[:, k]), skin.weights[:, k])
    fine_miss = np.abs(weights_at(skin.vertices, blocks, centre, radius, joints) - own).max(axis=1)
    coarse_miss = np.abs(weights_at(skin.vertices, coarse, centre, radius, joints) - own).max(axis=1)
    assert np.percentile(fine_miss, 99) < 0.5 * np.percentile(coarse_miss, 99)


def test_the_fused_blend_reads_the_blocks_as_the_numpy_rule(arm):
    skin, centre, radius, blocks, _, _ = arm
    transforms, _ = pose_at(skin, "wave", 0.5)
    _, posed = rest_maps(skin.skeleton, transforms)
    points = np.concatenate([surface_band_points(Mesh(skin.vertices, skin.faces, "rest"), 3000, 1e-2, 2),
                             np.random.default_rng(3).uniform(-0.6, 1.0, (500, 3))])  # some beyond the cube
    fused = blend_at(points, posed[:, :3, :], blocks, centre, radius)
    reference = blend_at(points, posed[:, :3, :], blocks, centre, radius, fused=False)
    np.testing.assert_allclose(fused, reference, atol=1e-12)
