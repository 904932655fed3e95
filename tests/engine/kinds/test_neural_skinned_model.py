"""The shipped articulated network (``models/walker-neural.safetensors``, kind ``neural-skinned``)
read as the first model files stored it (the fixed-point map through the coarse weight grid),
beyond its grid's cube (the box rule), and its network's distance gradient (training's); the
truth: the exact signed distance to the posed skin the file holds. Metres, collider frame."""

import dataclasses

import numpy as np
import pytest
import torch

from collider_server.engine.kinds.neural_skinned import NETWORK_PREFIX, ArticulatedNeuralCollider, pose_codes
from collider_server.engine.meshes import ExactSDF, Mesh
from collider_server.engine.modelfile import load_collider
from collider_server.engine.repository import ModelRepository
from collider_server.engine.skinning import random_poses, skin_vertices
from collider_server.making.sampling import surface_band_points


@pytest.fixture(scope="module")
def walker():
    path = ModelRepository().path("walker-neural")
    if not path.is_file():
        pytest.skip(f"no shipped articulated walker at {path}")
    collider = load_collider(path, "cpu")
    (transforms,) = random_poses(collider.skin, 1, seed=8642).transforms  # a pose off the clips
    return collider, transforms


def test_a_model_file_from_before_the_newton_map_answers_through_its_fixed_point_steps(walker):
    """A file whose architecture has no ``skinning_solver``, fine weight blocks, candidate rule or
    surface offsets (the first files) loads with the first map: fixed-point steps through its coarse weight grid.
    The walker's network (trained through the Newton map) read so, in the +-1 mm band at a pose
    off its clips: mean 1.0 mm, p90 0.86 mm off (measured); its parts' rigid images alone (no
    steps): mean 2.1, p90 3.7 mm (the file before); the file's own map: mean 0.14 mm."""
    collider, transforms = walker
    tensors = {k: v for k, v in collider.tensors().items() if not k.startswith(NETWORK_PREFIX + "weight_block")}
    first = {k: v for k, v in collider.info.settings["architecture"].items()
             if k not in ("skinning_solver", "fine_weight_resolution", "weight_blocks", "candidate_rule",
                          "surface_offsets")}
    info = dataclasses.replace(collider.info, settings={**collider.info.settings, "architecture": first})
    old = ArticulatedNeuralCollider.from_tensors(info, tensors)
    assert old.arch.skinning_solver == "fixed-point" and old.arch.candidate_rule == "own-label"
    assert not len(old.weights.block_joints) and old.weights.block_index.shape == (0, 0, 0)
    mesh = Mesh(skin_vertices(collider.skin, transforms), collider.skin.faces, "posed")
    points = surface_band_points(mesh, 2000, 1e-3, seed=30)
    truth = ExactSDF(mesh).signed_distance(points)  # the exact skinned kind's answer
    error = np.abs(old.query(points, "distance", joint_transforms=transforms).distance - truth)
    assert error.mean() < 1.5e-3 and np.percentile(error, 90) < 1.2e-3, (error.mean(), np.percentile(error, 90))


def test_beyond_the_grid_s_cube_the_distance_grows_by_the_way_out_and_the_normal_points_along_it(walker):
    """The box rule where a point's rest image leaves the grid's cube (the network's domain):
    the value at the cube's nearest point plus the way there, the normal along that way. At
    the rest pose (each part's map the identity), a step of 10 cm straight out from a face of
    the cube adds 10 cm to the distance."""
    collider, _ = walker
    rest = collider.skin.skeleton.rest_world()
    centre, radius = collider.centre, collider.radius
    rng = np.random.default_rng(12)
    points, outward = [], []
    for axis in range(3):
        for side in (-1.0, 1.0):
            p = centre + radius * rng.uniform(-0.8, 0.8, (20, 3))
            p[:, axis] = centre[axis] + side * 1.2 * radius
            n = np.zeros(3)
            n[axis] = side
            points.append(p)
            outward.append(np.tile(n, (20, 1)))
    points, outward = np.concatenate(points), np.concatenate(outward)
    near = collider.query(points, ("distance", "normal"), joint_transforms=rest)
    further = collider.query(points + 0.1 * outward, ("distance", "normal"), joint_transforms=rest)
    assert (near.distance >= 0.2 * radius - 1e-6).all()  # at least the way to the cube
    # (a few points change parts on the way: another part's value at the cube)
    assert np.mean(np.abs(further.distance - near.distance - 0.1) < 1e-5) > 0.9
    np.testing.assert_allclose(near.normal, outward, atol=1e-5)
    np.testing.assert_allclose(further.normal, outward, atol=1e-5)


def test_the_network_s_gradient_is_the_slope_of_its_distance(walker):
    """``value_and_gradient`` (what training fits) gives the network's own distance and, in the
    rest frame, its slope (central differences of ``forward``, 0.1 mm steps), at rest points
    near the skin with each vertex's main part and the pose's codes."""
    collider, transforms = walker
    network = collider.network
    skin = collider.skin
    rng = np.random.default_rng(13)
    vertex = rng.choice(len(skin.vertices), 300, replace=False)
    rest = torch.from_numpy((skin.vertices[vertex] + rng.normal(0.0, 2e-3, (300, 3))).astype(np.float32))
    joint = torch.from_numpy(skin.joints[vertex, np.argmax(skin.weights[vertex], axis=1)].astype(np.int64))
    code = torch.from_numpy(pose_codes(skin.skeleton, transforms, collider.arch.pose_slots))[joint]
    h = 1e-4
    steps = torch.cat([torch.zeros(1, 3), h * torch.eye(3), -h * torch.eye(3)])  # one forward call for all
    with torch.no_grad():
        distance, gradient = network.value_and_gradient(rest, joint, code)
        values = network((rest[None] + steps[:, None]).reshape(-1, 3), joint.repeat(7), code.repeat(7, 1)).reshape(7, -1)
    np.testing.assert_allclose(distance.numpy(), values[0].numpy(), rtol=0, atol=1e-6)
    slope = ((values[1:4] - values[4:7]) / (2 * h)).T
    assert gradient.shape == (300, 3)
    norm = gradient.norm(dim=1)
    assert 0.8 < float(norm.median()) < 1.2  # a distance: about unit slope near the skin
    miss = (gradient - slope).norm(dim=1) / norm
    assert float(miss.median()) < 0.02, float(miss.median())


def test_a_short_last_newton_step_is_taken_only_within_its_cell_of_the_weights(walker, monkeypatch):
    """NEWTON_LAST_STEP on the shipped walker's weight field (1M points in the +-10 mm band at a
    pose off the clips, where rows' short last steps cross cell faces): every row lands within
    1 um of where the steps to convergence land. Taken across a cell face as well, where the
    field's derivative jumps, 1-11 um off at some 50 rows of a million (measured)."""
    from collider_server.engine.kinds import neural_skinned as ns

    collider, _ = walker
    skin = collider.skin
    transforms = random_poses(skin, 6, 11, perturbed_share=0.5).transforms[4]
    to_rest, posed = ns.rest_maps(skin.skeleton, transforms)
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 1_000_000, 1e-2, 5)
    point, joint, rigid = ns.part_candidates(points, to_rest, collider.labels, collider.centre, collider.radius,
                                             collider.allowed, collider.part_boxes)
    args = (points, point, joint, rigid, to_rest, posed, collider.weights, collider.centre, collider.radius, 8,
            "newton")
    monkeypatch.setattr(ns, "NEWTON_LAST_STEP", 0.0)
    full = ns.carried_rows(*args)
    monkeypatch.undo()
    short = ns.carried_rows(*args)
    both = full.converged & short.converged
    assert both.mean() > 0.999
    moved = np.linalg.norm(short.rest - full.rest, axis=1)[both]
    assert moved.max() < 1e-6, np.sort(moved)[-10:]
