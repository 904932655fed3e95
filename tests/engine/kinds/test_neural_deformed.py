"""The 4D neural collider as a rest pose carried by deformation fields (preset ``deformed``): the
warp is the numpy rule the fit uses, the normal is the direction of the composed network's gradient
(autograd and finite differences), the velocity moves with the material (the warp of the moved
point at the later time is the same rest point), the fused CPU kernel equals the torch path, the
identity deformation answers as the rest network, a uniform scale divides its distances by the
scale (the stretch correction), a degenerate warp stays finite, and the model file (the fit is
tested in tests/making/training/test_animated_training.py). Random networks with smooth random fields;
collider frame, metres, seconds."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from collider_contract import Timeline
from collider_server.engine.collider import ColliderInfo
from collider_server.engine.kinds import AnimatedNeuralCollider, grid_kernels
from collider_server.engine.kinds.neural import ANIMATED_PRESETS, PRESETS, architecture_dict, build_network
from collider_server.engine.kinds.neural_deformed import DeformedGridArchitecture, field_corners, trilinear
from collider_server.engine.kinds.neural_grid import GridArchitecture
from collider_server.engine.kinds.neural_keyframes import keyframe_segments
from collider_server.engine.modelfile import load_collider, save_collider

LO, HI = np.array([-0.12, -0.1, -0.08]), np.array([0.12, 0.1, 0.08])
CENTRE, RADIUS = 0.5 * (LO + HI), 0.12
SMALL = {"levels": 4, "features": 2, "base_resolution": 4, "max_resolution": 40, "table_log2": 10,
             "hidden_layers": 2, "hidden_width": 16, "keyframes": 4, "deformation_resolution": 6}
DURATION = 0.6
needs_numba = pytest.mark.skipif(not grid_kernels.available(), reason="numba is not installed")


def node_positions(resolution=SMALL["deformation_resolution"]):
    """(nodes, 3) normalised positions of a field's nodes, node i + s (j + s k): x fastest."""
    axis = np.linspace(-1.0, 1.0, resolution + 1)
    z, y, x = np.meshgrid(axis, axis, axis, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)


def random_network(seed=0, amplitude=0.08, **overrides):
    """A random rest network and, per keyframe, a smooth random field (a twist-like offset of up
    to ``amplitude`` normalised units, so the warp stays invertible)."""
    arch = DeformedGridArchitecture(**{**SMALL, **overrides})
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        network = build_network(arch, CENTRE, RADIUS)
        with torch.no_grad():
            network.table.normal_(0.0, 0.5)
            network.table.copy_(network.table.half().float())  # the file's float16
    nodes = node_positions(arch.deformation_resolution)
    rng = np.random.default_rng(seed)
    fields = []
    for _ in range(arch.keyframes):
        phase, scale = rng.uniform(0, 2 * np.pi, 3), rng.uniform(-1, 1, 3) * amplitude
        fields.append(np.stack([scale[0] * np.sin(2 * nodes[:, 2] + phase[0]),
                                scale[1] * np.sin(2 * nodes[:, 0] + phase[1]),
                                scale[2] * np.cos(2 * nodes[:, 1] + phase[2])], axis=1))
    with torch.no_grad():
        network.deformation.copy_(torch.from_numpy(np.stack(fields).astype(np.float32)))
    return network


def collider(network, loop=False, device="cpu"):
    arch = DeformedGridArchitecture(**{**SMALL, "keyframes": network.deformation.shape[0]})
    frames = arch.keyframes
    info = ColliderInfo(name="d", kind="neural", domain_min=LO.tolist(), domain_max=HI.tolist(),
                        settings={"architecture": architecture_dict(arch)},
                        animation=Timeline(frames, (frames - 1) / DURATION, loop).to_dict())
    return AnimatedNeuralCollider(info, network, device)


def points(n, seed):
    rng = np.random.default_rng(seed)
    return LO + rng.random((n, 3)) * (HI - LO)


def test_the_preset_is_the_static_grid_plus_one_field_per_frame():
    preset = ANIMATED_PRESETS["deformed"]
    assert preset.spatial() == PRESETS["grid"]  # the rest pose: the static preset
    arch = DeformedGridArchitecture(keyframes=61)
    assert arch.parameter_count() == GridArchitecture().parameter_count() + 61 * 17 ** 3 * 3
    with pytest.raises(ValueError, match="deformation_resolution must be a positive integer, got 0"):
        DeformedGridArchitecture(deformation_resolution=0)


def test_the_torch_warp_is_the_numpy_rule_of_the_fit():
    network = random_network()
    u = np.random.default_rng(1).uniform(-1.1, 1.1, (400, 3))  # some outside: clamped
    nodes, weight, dweight = trilinear(u, SMALL["deformation_resolution"])
    field = network.deformation[2].double().numpy()
    expected = u + (weight[..., None] * field[nodes]).sum(axis=1)
    expected_jacobian = np.eye(3) + np.einsum("ncd,nce->nde", field[nodes], dweight)
    inside = (np.abs(u) <= 1.0).all(axis=1)
    t_nodes, t_weight, t_dweight = field_corners(torch.from_numpy(u), SMALL["deformation_resolution"])
    rest, jacobian = network.warp(torch.from_numpy(u), network.deformation[2].double()[t_nodes], t_weight,
                                  t_dweight)
    assert np.array_equal(t_nodes.numpy(), nodes)
    np.testing.assert_allclose(rest.numpy(), expected, atol=1e-12)
    np.testing.assert_allclose(jacobian.numpy()[inside], expected_jacobian[inside], atol=1e-9)


@pytest.mark.parametrize("fused", [False, True])
def test_the_normal_is_the_composed_gradient_and_the_velocity_moves_with_the_material(fused):
    if fused and not grid_kernels.available():
        pytest.skip("numba is not installed")
    c = collider(random_network())
    c.network.fused = fused
    x = points(300, 2)
    t, dt = 0.23, 1e-4
    _, normal, velocity = c.evaluate_at(x, True, t)
    net = copy.deepcopy(c.network)
    net.fused = False  # the reference: torch ops, autograd reaches the points

    def composed(p, time):  # f0(X(p)) at one time, differentiable
        key, frac = keyframe_segments(np.full(len(p), time), DURATION, 4)
        u = (p - net.centre) / net.radius
        rest_u, _ = net.warp_at(u, torch.from_numpy(key), torch.from_numpy(frac))
        return rest_u, net.forward(net.centre + net.radius * rest_u)  # no time: the rest pose

    p = torch.from_numpy(x.astype(np.float64)).float().requires_grad_(True)
    _, g0 = composed(p, t)
    (grad,) = torch.autograd.grad(g0.sum(), p)
    expected = grad.numpy() / np.linalg.norm(grad.numpy(), axis=1, keepdims=True)
    np.testing.assert_allclose(normal, expected, atol=2e-4)
    # Finite differences of the composed distance along x.
    h = 1e-5
    with torch.no_grad():
        e = torch.zeros(1, 3)
        e[0, 0] = h
        fd = (composed(p + e, t)[1] - composed(p - e, t)[1]) / (2 * h)
    # float32 differences across the ReLUs' and the cells' kinks: nearly all, not all
    close = np.abs(fd.numpy() - grad.numpy()[:, 0]) < 5e-3 * np.abs(grad.numpy()).max()
    assert close.mean() > 0.98, close.mean()
    # A material point: where x goes in dt, the warp at t + dt finds the same rest point (in
    # float64, and a step short enough that few points cross a cell of the field).
    exact = copy.deepcopy(net).double()

    def rest_point(p, time):
        key, frac = keyframe_segments(np.full(len(p), time), DURATION, 4)
        u = (torch.from_numpy(p) - exact.centre) / exact.radius
        return exact.warp_at(u, torch.from_numpy(key), torch.from_numpy(frac))[0].numpy()

    before = rest_point(x, t)
    drift = np.linalg.norm(rest_point(x + velocity * dt, t + dt) - before, axis=1)
    still = np.linalg.norm(rest_point(x, t + dt) - before, axis=1)  # a point that does not move
    assert drift.max() < 1e-3 * still.max() and still.max() > 1e-6, (drift.max(), still.max())


@needs_numba
def test_the_fused_kernel_answers_as_the_torch_path():
    fused, plain = collider(random_network()), collider(random_network())
    plain.network.fused = False
    x = points(2000, 3)
    for t in (0.0, 0.11, 0.3, 0.6):
        (d1, n1, v1), (d2, n2, v2) = fused.evaluate_at(x, True, t), plain.evaluate_at(x, True, t)
        np.testing.assert_allclose(d1, d2, atol=3e-5, rtol=1e-4)
        # The kernel warps in float64, torch in float32: a point on a ReLU's kink may turn its
        # normal by a little (1 in 6,000 by 1.7e-4 seen); every other one agrees.
        for a, b in ((n1, n2), (v1, v2)):
            assert np.isclose(a, b, atol=3e-5, rtol=1e-4).all(axis=1).mean() > 0.998
            assert np.abs(a - b).max() < 1e-2
        np.testing.assert_allclose(fused.evaluate_at(x, False, t)[0], plain.evaluate_at(x, True, t)[0],
                                   atol=3e-5, rtol=1e-4)


def test_the_identity_deformation_answers_as_the_rest_network():
    c = collider(random_network(amplitude=0.0))
    x = points(500, 4)
    distance, normal, velocity = c.evaluate_at(x, True, 0.37)
    d0, g0 = c.network.value_and_gradient(torch.from_numpy(x.astype(np.float32)))
    np.testing.assert_allclose(distance, d0.numpy(), atol=1e-6)
    np.testing.assert_allclose(normal, g0.numpy() / np.linalg.norm(g0.numpy(), axis=1, keepdims=True), atol=1e-5)
    assert np.abs(velocity).max() == 0.0


@pytest.mark.parametrize("fused", [False, True])
def test_a_uniform_scale_divides_the_distance_by_the_scale(fused):
    """Fields that shrink the world by 1/a about the domain's centre (X = a u): the surface at rest
    is the world's scaled by a, so every distance is the rest one divided by a."""
    if fused and not grid_kernels.available():
        pytest.skip("numba is not installed")
    network = random_network(amplitude=0.0)
    network.fused = fused
    with torch.no_grad():  # a = 1.5 from frame 2
        network.deformation[2:] = torch.from_numpy((0.5 * node_positions()).astype(np.float32))
    c = collider(network)
    x = CENTRE + (points(500, 9) - CENTRE) * 0.6  # inside the domain once scaled
    distance, _, _ = c.evaluate_at(x, True, DURATION)  # the last frame
    rest = CENTRE + 1.5 * (x - CENTRE)
    with torch.no_grad():
        d0 = network.value_and_gradient(torch.from_numpy(rest.astype(np.float32)))[0].numpy()
    np.testing.assert_allclose(distance, d0 / 1.5, rtol=1e-4, atol=1e-7)


def test_a_degenerate_warp_answers_finite_distances_of_the_rest_sign():
    """Fields that flatten the world onto a plane (a fold no deformation has): J is singular, the
    answer stays finite and keeps the rest network's sign."""
    network = random_network(amplitude=0.0)
    nodes = node_positions()
    flatten = np.zeros_like(nodes)
    flatten[:, 2] = -nodes[:, 2]  # X_z = 0 everywhere
    with torch.no_grad():
        network.deformation[:] = torch.from_numpy(flatten.astype(np.float32))
    x = points(300, 10)
    rest = x.copy()
    rest[:, 2] = CENTRE[2]
    with torch.no_grad():
        d0 = network.value_and_gradient(torch.from_numpy(rest.astype(np.float32)))[0].numpy()
    clear = np.abs(d0) > 1e-6
    for fused in (False, True):
        network.fused = fused and grid_kernels.available()
        distance, normal, _ = collider(network).evaluate_at(x, True, 0.3)
        assert np.isfinite(distance).all() and np.isfinite(normal).all()
        assert np.array_equal(np.sign(distance[clear]), np.sign(d0[clear]))
        assert np.abs(distance).max() <= 10 * np.abs(d0).max() + 1e-9


@needs_numba
def test_cuda_answers_as_the_cpu(cuda):
    c = collider(random_network())
    g = collider(random_network(), device=cuda)
    x = points(3000, 7)
    for t in (0.0, 0.11, 0.59):
        for a, b in zip(c.evaluate_at(x, True, t), g.evaluate_at(x, True, t)):
            np.testing.assert_allclose(b, a, atol=3e-5, rtol=1e-4)


def test_a_saved_model_loads_and_answers_the_same(tmp_path):
    c = collider(random_network())
    loaded = load_collider(save_collider(c, tmp_path / "d.safetensors"))
    assert isinstance(loaded.architecture, DeformedGridArchitecture)
    x = points(500, 7)
    fields = ["distance", "normal", "contact", "velocity"]
    a, b = c.query(x, fields, time=0.33), loaded.query(x, fields, time=0.33)
    for field in fields:
        assert np.array_equal(getattr(a, field), getattr(b, field)), field
    assert np.abs(a.velocity).max() > 0


def test_a_plateau_of_the_rest_network_gets_the_normal_across_it():
    """The static rule for a vanishing gradient (test_neural_grid: central differences at half
    the finest cell) holds at any time of an animated network: the rest network
    radius * (relu(u_x - 0.2) + 0.05) under identity fields, asked in its plateau near the edge."""
    arch = DeformedGridArchitecture(levels=1, features=1, base_resolution=4, max_resolution=4, table_log2=10,
                                    hidden_layers=1, hidden_width=2, smooth=False, keyframes=2,
                                    deformation_resolution=2)
    network = build_network(arch, CENTRE, RADIUS)
    with torch.no_grad():
        network.table.copy_((-1.0 + 0.5 * (torch.arange(125) % 5)).float()[:, None])  # u_x
        network.body[0].weight.copy_(torch.tensor([[1.0], [0.0]]))
        network.body[0].bias.copy_(torch.tensor([-0.2, -1.0]))
        network.body[2].weight.copy_(torch.tensor([[1.0, 0.0]]))
        network.body[2].bias.copy_(torch.tensor([0.05]))
        network.deformation.zero_()
    info = ColliderInfo(name="p", kind="neural", domain_min=LO.tolist(), domain_max=HI.tolist(),
                        settings={"architecture": architecture_dict(arch)},
                        animation=Timeline(2, 1 / DURATION, False).to_dict())
    c = AnimatedNeuralCollider(info, network, "cpu")
    local = CENTRE + RADIUS * np.array([[0.1, 0.3, 0.1], [0.5, 0.3, 0.1]])
    _, gradient, _ = c.evaluate_at(local, True, 0.25)
    np.testing.assert_allclose(gradient, [[(0.1 + 0.25 - 0.2) / 0.5, 0, 0], [1, 0, 0]], atol=1e-5)
