"""The articulated neural collider (kind ``neural-skinned``): a small one trained for a few
hundred steps on the generated skinned arm answers at poses it never saw, against the exact
skinned kind (libigl over the skinned mesh) as the truth."""

import dataclasses

import numpy as np
import pytest

from collider_server.engine.kinds.neural_skinned import (
    NETWORK_PREFIX,
    ArticulatedGridArchitecture,
    ArticulatedNeuralCollider,
    allowed_labels,
    carry_to_rest,
    labels_seen,
    part_candidates,
    rest_maps,
    skinned_rest,
    weight_field,
    weights_and_gradient,
    weights_at,
)
from collider_server.engine.meshes import Mesh
from collider_server.engine.modelfile import load_collider, save_collider
from collider_server.engine.skinning import pose_at, skin_vertices
from collider_server.making.sampling import surface_band_points
from collider_server.making.skinned import skinned_arm, skinned_collider
from collider_server.making.training import TrainConfig
from collider_server.making.training.articulated import ARTICULATED_PRESET, sample_poses, train_articulated

#: A small field (4 levels up to 64 cells, 2^12 rows) so that a few hundred steps train it; the
#: map and the candidate rule of the preset (Newton steps through the weight grid and its fine
#: blocks near the skin, with the surface offsets; points with no root tried again).
SMALL = ArticulatedGridArchitecture(levels=4, max_resolution=64, table_log2=12, table_dtype="float16",
                                    label_resolution=32, skinning_solver="newton", skinning_iterations=8,
                                    fine_weight_resolution=96, candidate_rule="retry-labels", surface_offsets=True)


#: A few hundred steps of the arm.
CONFIG = TrainConfig(samples=30_000, steps=300, batch_size=2048, validation_points=2_000, threads=1)


@pytest.fixture(scope="module")
def trained():
    skin = skinned_arm()
    # One cell of label dilation set (the arm's floor would not choose it), so that its path is trained.
    result = train_articulated(skin, "arm-neural", CONFIG, arch=SMALL, poses=24, show_progress=False,
                               label_dilation=1)
    return skin, result, skinned_collider(skin, "arm")


def test_it_answers_a_pose_it_never_saw_with_a_bounded_error_and_the_right_sign(trained):
    skin, result, exact = trained
    collider = result.collider
    assert collider.info.kind == "neural-skinned" and collider.skinned
    errors, angles = [], []
    for transforms in sample_poses(skin, 3, seed=4242):  # perturbed clip poses, not trained on
        posed = exact.posed(None, _pose(transforms))
        points = surface_band_points(posed.exact.mesh, 3000, 1e-3, seed=5)
        truth = exact.query(points, ("distance", "normal"), joint_transforms=transforms)
        answer = collider.query(points, ("distance", "normal"), joint_transforms=transforms)
        errors.append(np.abs(answer.distance - truth.distance))
        cos = np.clip(np.einsum("ij,ij->i", answer.normal, truth.normal), -1, 1)
        angles.append(np.degrees(np.arccos(cos)))
    error, angle = np.concatenate(errors), np.concatenate(angles)
    assert error.mean() < 3e-3, f"mean error {error.mean() * 1e3:.2f} mm in the +-1 mm band"
    # (measured: 5.1 deg mean; 15 with the gradient not pulled back through the map to the rest pose)
    assert angle.mean() < 8.0, f"mean normal error {angle.mean():.1f} deg"
    # Far inside (on the bone, 4 cm deep) and far outside (6 cm off the skin) of each part at a
    # new pose: the sign.
    transforms = sample_poses(skin, 1, seed=99)[0]
    _, posed = rest_maps(skin.skeleton, transforms)
    rest = np.array([[0.12, 0.0, 0.0, 1.0], [0.35, 0.0, 0.0, 1.0], [0.46, 0.0, 0.0, 1.0]])
    off = rest + [0.0, 0.0, 0.10, 0.0]
    points = np.stack([(posed[k % 3] @ r)[:3] for k, r in enumerate(np.concatenate([rest, off]))])
    d = collider.query(points, "distance", joint_transforms=transforms).distance
    assert (d[:3] < 0).all() and (d[3:] > 0).all(), d


def test_velocity_is_the_skinning_s_motion_at_the_rest_point(trained):
    skin, result, exact = trained
    # Mid-forearm, away from the blends: the skin moves rigidly with the elbow, and the exact kind's
    # velocity (the skinning's derivative at the closest point) is the same motion.
    transforms, _ = pose_at(skin, "wave", 0.37)
    _, posed = rest_maps(skin.skeleton, transforms)
    rest = np.array([[0.33, 0.0, 0.041, 1.0], [0.34, 0.041, 0.0, 1.0], [0.32, 0.0, -0.041, 1.0]])
    points = np.stack([(posed[1] @ r)[:3] for r in rest])
    answer = result.collider.query(points, ("distance", "velocity"), clip="wave", time=0.37)
    truth = exact.query(points, ("distance", "velocity"), clip="wave", time=0.37)
    # The exact kind answers the velocity of the closest surface point, this kind that of the point
    # itself (up to 1 mm off the skin, turning at ~2 rad/s): equal within 1 %.
    np.testing.assert_allclose(answer.velocity, truth.velocity, atol=1e-2 * np.abs(truth.velocity).max())
    # At joint transforms with no velocities the skeleton is still.
    still = result.collider.query(points, ("velocity",), joint_transforms=transforms)
    assert not still.velocity.any()


def test_the_training_samples_are_carried_as_the_query_carries_points(trained):
    """The samples' rows (each candidate's part and rest point) at a pose are those the trained
    model's query takes there (``parts_at``: its rule, weights and surface offsets)."""
    from collider_contract.skeleton import SkeletonPose
    from collider_server.making.training.articulated import make_samples

    skin, result, _ = trained
    collider = result.collider
    transforms = sample_poses(skin, 1, 41, perturbed_share=1.0)[0]
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 500, 1e-3, 42)
    assert collider.arch.label_dilation == 1 and collider.allowed[:, len(skin.skeleton.parents):].any()
    samples = make_samples(skin, transforms[None], len(points), lambda mesh, p: (points, np.ones(len(points), bool)),
                           collider.arch, collider.centre, collider.radius, collider.labels, collider.part_boxes,
                           collider.weights, False, "samples", collider.anchors, collider.network.label_sets.numpy())
    point, joint, rest, _ = collider.parts_at(points, None, SkeletonPose(joint_transforms=transforms))
    order = np.lexsort((joint, point))  # the samples' rows: by point, then by joint
    np.testing.assert_array_equal(np.repeat(np.arange(len(points)), samples.count), point[order])
    np.testing.assert_array_equal(samples.joint, joint[order])
    np.testing.assert_allclose(samples.rest, rest[order], rtol=0, atol=1e-6)  # float32 samples


def test_the_best_validation_is_the_query_s_error_at_the_held_out_poses(trained):
    """The validation reads its samples as the query answers (the map, the dilated label grid,
    the union): the trained model's query at the run's held-out poses and points errs by the
    best validation figure it reports (float32 against the fused kernel: within 1 %)."""
    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.training.articulated import VALIDATION_POSES

    skin, result, _ = trained
    collider = ArticulatedNeuralCollider.from_tensors(result.collider.info, result.collider.tensors())
    collider.patches = None  # the validation measures the network (the exact patches answer near the skin)
    errors = []
    for p, transforms in enumerate(sample_poses(skin, VALIDATION_POSES, CONFIG.seed + 77)):
        mesh = Mesh(skin_vertices(skin, transforms), skin.faces, "posed")
        points = surface_band_points(mesh, max(CONFIG.validation_points // VALIDATION_POSES, 100), 1e-3,
                                     CONFIG.seed + 500 + p)
        answer = collider.query(points, "distance", joint_transforms=transforms).distance
        errors.append(np.abs(answer - ExactSDF(mesh).query(points)[0]))
    assert np.concatenate(errors).mean() * 1e3 == pytest.approx(result.best_validation_mm, rel=0.01)


def test_the_training_says_which_label_dilation_it_chose_and_keeps_it(trained):
    skin, set_one, _ = trained
    assert set_one.collider.info.settings["training"]["label_dilation_choice"] is None  # set, not chosen
    said = []
    result = train_articulated(skin, "arm-neural", TrainConfig(samples=2_000, steps=1, validation_points=200,
                                                               threads=1),
                               arch=SMALL, poses=8, show_progress=False, say=said.append)
    (line,) = said
    assert line.startswith(f"label dilation {result.collider.arch.label_dilation} (the map's floor"), line
    assert result.collider.info.settings["training"]["label_dilation_choice"] == line


def test_the_training_says_how_many_label_cells_its_dilation_left_without_a_code(trained, monkeypatch):
    """A skeleton of many joints leaves the label grid few set codes (255 - J), and a cell near a
    boundary whose set finds none keeps its own label (dilated_labels counts them, tested with
    the rule): the training says how many and keeps the count. (The arm's 3 joints leave codes
    to spare, so its count is made up here.)"""
    from collider_server.making.training import articulated

    skin, _, _ = trained
    real = articulated.dilated_labels
    monkeypatch.setattr(articulated, "dilated_labels",
                        lambda labels, joints, cells: real(labels, joints, cells)[:2] + (1234 if cells else 0,))
    said = []
    result = train_articulated(skin, "arm-neural", TrainConfig(samples=2_000, steps=1, validation_points=200,
                                                               threads=1),
                               arch=SMALL, poses=8, show_progress=False, label_dilation=1, say=said.append)
    (line,) = said
    assert line.startswith("label dilation 1: 1,234 cells near a part boundary keep their own label (the grid's "
                           f"{255 - skin.skeleton.joint_count} set codes ran out)"), line
    assert result.collider.info.settings["training"]["label_cells_uncoded"] == 1234


def test_the_training_samples_rows_are_the_query_s_at_their_pose(trained, monkeypatch):
    """The rows each training sample is learnt through (its candidate parts and their rest points:
    the dilated grid's sets, the surface offsets, the retry) are the rows the trained model's
    query takes at that pose (``parts_at``): the network learns what it will be asked."""
    from collider_server.making.training import articulated

    skin, _, _ = trained
    made, real = [], articulated.make_samples

    def recording(skin_, poses, per_pose, sampler, *args, **kwargs):
        points = []

        def sample(mesh, p):
            out = sampler(mesh, p)
            points.append(out[0])
            return out

        made.append((poses, points, real(skin_, poses, per_pose, sample, *args, **kwargs)))
        return made[-1][2]

    monkeypatch.setattr(articulated, "make_samples", recording)
    result = train_articulated(skin, "arm-neural", TrainConfig(samples=16_000, steps=1, validation_points=200,
                                                               threads=1),
                               arch=SMALL, poses=8, show_progress=False, label_dilation=1)
    poses, points, samples = made[0]  # the training's samples (the validation's come next)
    assert result.collider.arch.label_dilation == 1
    for p in range(len(poses)):
        point, joint, rest, _ = result.collider.parts_at(points[p], None, _pose(poses[p]))
        order = np.argsort(point, kind="stable")  # the samples' rows: by point, then joint
        rows = samples.pose == p
        np.testing.assert_array_equal(samples.joint[rows], joint[order])
        np.testing.assert_allclose(samples.rest[rows], rest[order], rtol=0, atol=1e-6)


def test_the_model_file_round_trips(trained, tmp_path):
    _, result, _ = trained
    path = save_collider(result.collider, tmp_path / "arm-neural.safetensors")
    loaded = load_collider(path)
    points = np.random.default_rng(3).uniform(-0.1, 0.6, (2000, 3))
    a = result.collider.query(points, ("distance", "normal", "velocity"), clip="reach", time=1.3)
    b = loaded.query(points, ("distance", "normal", "velocity"), clip="reach", time=1.3)
    # The file stores the table in float16 (the architecture's table_dtype): a small rounding.
    np.testing.assert_allclose(a.distance, b.distance, atol=2e-4)
    assert loaded.info.skeleton == result.collider.info.skeleton
    # The torch ops (the reference, and the CUDA path) answer as the fused CPU kernel.
    loaded.network.grid.fused = False
    loaded._cache.clear()
    c = loaded.query(points, ("distance", "normal", "velocity"), clip="reach", time=1.3)
    np.testing.assert_allclose(c.distance, b.distance, atol=1e-6)
    np.testing.assert_allclose(c.normal, b.normal, atol=1e-3)
    np.testing.assert_allclose(c.velocity, b.velocity, atol=1e-6)


def test_the_preset_s_8_bit_codes_on_a_curve_round_trip_through_the_file(trained, tmp_path):
    """The articulated preset stores its table as ``int8-mu`` (8-bit codes on a mu-law curve):
    the trained network written so loads with that architecture and answers as the network in
    memory within its codes' steps; saved again, the file's table is the same."""
    assert ARTICULATED_PRESET.table_dtype == "int8-mu"
    _, result, _ = trained
    collider = result.collider
    arch = dataclasses.replace(collider.arch, table_dtype="int8-mu")
    info = dataclasses.replace(collider.info, settings={**collider.info.settings, "architecture": dataclasses.asdict(arch)})
    path = save_collider(ArticulatedNeuralCollider(info, collider.skin, collider.network), tmp_path / "mu.safetensors")
    loaded = load_collider(path)
    assert loaded.arch.table_dtype == "int8-mu" and loaded.tensors()["network.grid.table_codes"].dtype == np.int8
    points = np.random.default_rng(4).uniform(-0.1, 0.6, (2000, 3))
    a = collider.query(points, ("distance",), clip="reach", time=0.7).distance
    b = loaded.query(points, ("distance",), clip="reach", time=0.7).distance
    # Measured: median 0.14 mm, p99 1.1 mm of this small network's 8 bits (a point or two whose
    # union picks another part moves by centimetres).
    gap = np.abs(a - b)
    assert 0 < np.median(gap) < 5e-4 and np.percentile(gap, 99) < 3e-3, np.percentile(gap, [50, 99])
    again = load_collider(save_collider(loaded, tmp_path / "again.safetensors")).tensors()
    for key, value in loaded.tensors().items():
        if key.startswith("network.grid.table"):
            np.testing.assert_array_equal(again[key], value)


def test_the_fused_candidate_kernel_equals_the_numpy_rule(trained):
    skin, result, _ = trained
    collider = result.collider
    transforms = sample_poses(skin, 1, seed=11)[0]
    to_rest, _ = rest_maps(skin.skeleton, transforms)
    points = np.random.default_rng(4).uniform(-0.3, 0.8, (20_000, 3))
    args = (points, to_rest, collider.labels, collider.centre, collider.radius,
            allowed_labels(skin.skeleton.parents, True), collider.part_boxes)
    fused, reference = part_candidates(*args, fused=True), part_candidates(*args, fused=False)
    for a, b in zip(fused, reference):
        np.testing.assert_array_equal(a, b)
    assert set(np.unique(fused[0])) == set(range(len(points)))  # every point has a part
    seen = [labels_seen(points, to_rest, collider.labels, collider.centre, collider.radius, fused=f)
            for f in (True, False)]
    np.testing.assert_array_equal(seen[0], seen[1])


def _pose(transforms):
    from collider_contract import SkeletonPose

    return SkeletonPose(joint_transforms=transforms)


def _bent_elbow(skin, collider):
    """Posed vertices of the arm with the elbow bent 60 degrees, their rigid images through their
    dominant joints, and each vertex's own weights (J columns)."""
    own = np.zeros((len(skin.vertices), skin.skeleton.joint_count))
    for k in range(skin.joints.shape[1]):
        np.add.at(own, (np.arange(len(own)), skin.joints[:, k]), skin.weights[:, k])
    transforms, _ = pose_at(skin, "wave", 0.5)
    to_rest, posed = rest_maps(skin.skeleton, transforms)
    moved = skin_vertices(skin, transforms)
    dominant = np.argmax(own, axis=1)
    rigid = np.einsum("vab,vb->va", to_rest[dominant, :, :3], moved) + to_rest[dominant, :, 3]
    return moved, dominant, rigid, to_rest, posed, own


def test_the_skinning_carries_posed_vertices_back_to_the_rest_pose(trained):
    skin, result, _ = trained
    collider = result.collider
    field = collider.weights
    assert collider.arch.weight_blocks == len(field.block_joints) > 0
    # The weight field gives each rest vertex about its own weights.
    moved, _, rigid, _, posed, own = _bent_elbow(skin, collider)
    w = weights_at(skin.vertices, field, collider.centre, collider.radius, 3)
    assert np.abs(w - own).max() < 0.15 and np.abs(w - own).mean() < 0.01
    # A pose with the elbow bent 60 degrees: each posed vertex's rigid image (through its dominant
    # joint) misses its rest position by up to 20 mm where the skin blends; two fixed-point steps
    # through the skinning take a quarter of that off the worst and four fifths off the mean
    # (measured: p99 15.1 -> 4.1 mm, mean 0.94 -> 0.18 mm; more steps converge on, slowly:
    # docs/neural.md).
    carried, _ = skinned_rest(moved, rigid, posed, field, collider.centre, collider.radius, 2)
    reference, _ = skinned_rest(moved, rigid, posed, field, collider.centre, collider.radius, 2, fused=False)
    np.testing.assert_allclose(carried, reference, atol=1e-9)  # the numba pass, the numpy rule
    rigid_miss = np.linalg.norm(rigid - skin.vertices, axis=1)
    miss = np.linalg.norm(carried - skin.vertices, axis=1)
    assert np.percentile(rigid_miss, 99) > 1e-2  # the blend is there to undo
    assert np.percentile(miss, 99) < 0.35 * np.percentile(rigid_miss, 99), np.percentile(miss, 99)
    assert miss.mean() < 0.25 * rigid_miss.mean(), (miss.mean(), rigid_miss.mean())


def test_newton_steps_through_the_fine_weight_field_lower_the_map_s_floor(trained):
    skin, result, _ = trained
    collider = result.collider
    moved, dominant, rigid, to_rest, posed, _ = _bent_elbow(skin, collider)
    point = np.arange(len(moved))

    def miss(field, iterations, solver):
        keep, rest, _ = carry_to_rest(moved, point, dominant, rigid, to_rest, posed, field, collider.centre,
                                      collider.radius, iterations, solver)
        assert len(keep) == len(moved)  # every vertex's own candidate converged (or is kept)
        return np.linalg.norm(rest - skin.vertices, axis=1)

    coarse = weight_field(skin, collider.centre, collider.radius, collider.arch.weight_resolution)
    # The first model files' map: fixed-point steps through the 48^3 grid reach p99 0.70 mm, mean
    # 0.060 mm after 8 steps (4.1 / 0.18 after their 2); Newton steps through the same grid the same
    # (its floor). Newton through the fine blocks (96^3 here): p99 0.35, mean 0.028 mm (measured).
    old = miss(coarse, 8, "fixed-point")
    new = miss(collider.weights, collider.arch.skinning_iterations, "newton")
    assert np.percentile(old, 99) > 6e-4 and old.mean() > 5e-5, (np.percentile(old, 99), old.mean())
    assert np.percentile(new, 99) < 4.5e-4, np.percentile(new, 99)
    assert new.mean() < 0.6 * old.mean(), (new.mean(), old.mean())


def test_the_fused_newton_pass_equals_the_numpy_rule(trained):
    skin, result, _ = trained
    collider = result.collider
    field = collider.weights
    # Points in the +-10 mm band at a perturbed pose: fine blocks, the coarse grid and clamped
    # points beyond the cube alike.
    transforms = sample_poses(skin, 1, seed=17)[0]
    to_rest, posed = rest_maps(skin.skeleton, transforms)
    mesh_points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 4000, 1e-2, 8)
    points = np.concatenate([mesh_points, np.random.default_rng(5).uniform(-0.5, 1.0, (500, 3))])
    allowed = allowed_labels(skin.skeleton.parents, False)
    point, joint, rigid = part_candidates(points, to_rest, collider.labels, collider.centre, collider.radius,
                                          allowed, collider.part_boxes)
    args = (points, point, joint, rigid, to_rest, posed, field, collider.centre, collider.radius, 8, "newton")
    fused, reference = carry_to_rest(*args, fused=True), carry_to_rest(*args, fused=False)
    np.testing.assert_array_equal(fused[0], reference[0])
    np.testing.assert_allclose(fused[1], reference[1], atol=1e-9)
    np.testing.assert_allclose(fused[2], reference[2], rtol=1e-6, atol=1e-6)
    # The weights' derivative is the field's: central differences agree.
    y = skin.vertices[::7] + np.random.default_rng(6).normal(0, 2e-3, (len(skin.vertices[::7]), 3))
    _, dw = weights_and_gradient(y, field, collider.centre, collider.radius, 3)
    h = 1e-6
    for a in range(3):
        step = np.zeros(3)
        step[a] = h
        numeric = (weights_at(y + step, field, collider.centre, collider.radius, 3)
                   - weights_at(y - step, field, collider.centre, collider.radius, 3)) / (2 * h)
        # (a step across a cell face changes the slope: the few such points are left out)
        close = np.abs(numeric - dw[:, :, a]).max(axis=1) < 1e-3
        assert close.mean() > 0.97, close.mean()


def test_a_model_file_from_before_the_candidate_retry_answers_as_before(trained):
    skin, result, _ = trained
    collider = result.collider
    info = collider.info
    old_arch = {k: v for k, v in info.settings["architecture"].items()
                if k not in ("candidate_rule", "surface_offsets")}
    old_info = dataclasses.replace(info, settings={**info.settings, "architecture": old_arch})
    old = ArticulatedNeuralCollider.from_tensors(old_info, collider.tensors())
    old.patches = None  # its network's rows (the exact patches answer any file's points near the skin)
    assert old.arch.candidate_rule == "own-label" and old.anchors is None
    # Its answers are the first rule's: part_candidates, then carry_to_rest (no second pass, no
    # surface offsets).
    transforms = sample_poses(skin, 1, seed=23)[0]
    to_rest, posed = rest_maps(skin.skeleton, transforms)
    points = surface_band_points(Mesh(skin_vertices(skin, transforms), skin.faces, "posed"), 3000, 1e-2, 9)
    point, joint, rigid = part_candidates(points, to_rest, old.labels, old.centre, old.radius, old.allowed,
                                          old.part_boxes)
    keep, rest, _ = carry_to_rest(points, point, joint, rigid, to_rest, posed, old.weights, old.centre, old.radius,
                                  old.arch.skinning_iterations, old.arch.skinning_solver)
    distance, _ = old._part_values(rest, joint[keep], old.pose(None, _pose(transforms)).bias, False)
    expected = np.full(len(points), np.inf)
    np.minimum.at(expected, point[keep], distance)
    np.testing.assert_array_equal(old.query(points, "distance", joint_transforms=transforms).distance, expected)


def test_a_model_file_from_before_the_newton_map_loads_with_its_own_map(trained):
    skin, result, _ = trained
    collider = result.collider
    tensors = {k: v for k, v in collider.tensors().items() if not k.startswith(NETWORK_PREFIX + "weight_block")}
    info = collider.info
    old_arch = {k: v for k, v in info.settings["architecture"].items()
                if k not in ("skinning_solver", "fine_weight_resolution", "weight_blocks", "candidate_rule",
                             "surface_offsets")}
    old_info = dataclasses.replace(info, settings={**info.settings, "architecture": old_arch})
    old = ArticulatedNeuralCollider.from_tensors(old_info, tensors)
    assert old.arch.skinning_solver == "fixed-point" and not len(old.weights.block_joints)
    assert collider.arch.candidate_rule == "retry-labels" and old.arch.candidate_rule == "own-label"
    points = surface_band_points(Mesh(skin.vertices, skin.faces, "rest"), 500, 1e-3, 2)
    assert np.isfinite(old.query(points, "distance", clip="wave", time=0.5).distance).all()
    with pytest.raises(ValueError, match="skinning_solver must be one of fixed-point, newton"):
        ArticulatedGridArchitecture(skinning_solver="secant")
    with pytest.raises(ValueError, match="fine_weight_resolution must be a multiple of 4"):
        ArticulatedGridArchitecture(fine_weight_resolution=50)
