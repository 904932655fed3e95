"""The 4D neural collider (keyframe feature tables blended in time): the analytic spatial
gradient and the exact time derivative against autograd and finite differences, the fused CPU
kernels (query and training) against the torch reference, the velocity rule, the time rule at the
ends, and the model file. Random networks with large random tables (so the encoding matters);
collider frame, metres, seconds."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from collider_contract import Timeline
from collider_server.engine.collider import ColliderInfo
from collider_server.engine.kinds import AnimatedNeuralCollider, grid_kernels
from collider_server.engine.kinds.neural import architecture_dict, architecture_from_dict, build_network
from collider_server.engine.kinds.neural_keyframes import KeyframeGridArchitecture, keyframe_segments
from collider_server.engine.modelfile import ModelFileError, load_collider, save_collider

LO, HI = np.array([-0.12, -0.1, -0.08]), np.array([0.12, 0.1, 0.08])
CENTRE, RADIUS = 0.5 * (LO + HI), 0.12
# Levels 0-1 dense, the finer ones hashed (collisions included); 4 keyframes over 0.6 s.
SMALL = {"levels": 4, "features": 2, "base_resolution": 4, "max_resolution": 40, "table_log2": 10,
             "hidden_layers": 2, "hidden_width": 16, "keyframes": 4}
DURATION = 0.6
needs_numba = pytest.mark.skipif(not grid_kernels.available(), reason="numba is not installed")


def random_network(seed=0, **overrides):
    arch = KeyframeGridArchitecture(**{**SMALL, **overrides})
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        network = build_network(arch, CENTRE, RADIUS)
        with torch.no_grad():
            network.table.normal_(0.0, 0.5)
            # float16-exact values: the model file stores the tables in float16.
            network.table.copy_(network.table.half().float())
    return network


def collider(network, loop=False, device="cpu"):
    arch = architecture_from_dict(architecture_dict(network_arch(network)))
    frames = arch.keyframes
    info = ColliderInfo(name="k", kind="neural", domain_min=LO.tolist(), domain_max=HI.tolist(),
                        settings={"architecture": architecture_dict(arch)},
                        animation=Timeline(frames, (frames - 1) / DURATION, loop).to_dict())
    return AnimatedNeuralCollider(info, network, device)


def network_arch(network):
    return KeyframeGridArchitecture(**{**SMALL, "keyframes": network.table.shape[0]})


def points(n, seed):
    rng = np.random.default_rng(seed)
    return LO + rng.random((n, 3)) * (HI - LO)


def test_parameters_and_memory():
    arch = KeyframeGridArchitecture(**SMALL)
    network = random_network()
    assert tuple(network.table.shape) == (4, sum(arch.level_rows()), 2)
    assert sum(p.numel() for p in network.parameters()) == arch.parameter_count()
    assert arch.parameter_count() == arch.spatial().parameter_count() + 3 * sum(arch.level_rows()) * 2


@pytest.mark.parametrize("fused", [False, True])
def test_gradient_and_time_derivative_match_autograd(fused):
    """One time (the query): the blended table's analytic gradient and the exact time derivative
    against autograd through the per-point forward, d/dt = d/d fraction * rate."""
    if fused and not grid_kernels.available():
        pytest.skip("numba is not installed")
    network = random_network()
    network.fused = fused
    x = torch.from_numpy(points(400, 1).astype(np.float32))
    k, s, rate = 1, 0.37, 5.0
    with torch.no_grad():
        distance, gradient, dtime = network.query_at(x, k, s, rate, True)
    network.fused = False
    xr = x.clone().requires_grad_(True)
    frac = torch.full((len(x),), s, requires_grad=True)
    reference = network(xr, torch.full((len(x),), k, dtype=torch.int64), frac)
    gx, gs = torch.autograd.grad(reference.sum(), (xr, frac))
    assert torch.allclose(distance, reference.detach(), atol=1e-6)
    assert torch.allclose(gradient, gx, atol=2e-5, rtol=1e-4)
    assert torch.allclose(dtime, gs * rate, atol=2e-5, rtol=1e-4)
    assert gx.abs().max() > 0.1 and (gs * rate).abs().max() > 0.01  # not trivially zero


@pytest.mark.parametrize("fused", [False, True])
def test_gradient_and_time_derivative_match_finite_differences(fused):
    """Through the collider: central differences of the distance in space (h = 1e-5 m) and in
    time (1e-4 s, inside one keyframe segment) against the gradient and -velocity . normal."""
    if fused and not grid_kernels.available():
        pytest.skip("numba is not installed")
    c = collider(random_network())
    c.network.fused = fused
    x = points(200, 2)
    t, dt, h = 0.27, 1e-4, 1e-5
    _d, g, v = c.evaluate_at(x, True, t)
    fd_t = (c.evaluate_at(x, False, t + dt)[0] - c.evaluate_at(x, False, t - dt)[0]) / (2 * dt)
    normal = g / np.linalg.norm(g, axis=1, keepdims=True)
    dfdt = -np.einsum("ij,ij->i", v, normal)
    # A few points sit on a ReLU kink between the two times: the bulk must agree closely.
    error = np.abs(dfdt - fd_t)
    assert np.percentile(error, 95) < 1e-2 * np.abs(fd_t).mean() and np.abs(fd_t).mean() > 1e-3
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        fd = (c.evaluate_at(x + step, False, t)[0] - c.evaluate_at(x - step, False, t)[0]) / (2 * h)
        # float32 distances: the difference quotient is good to ~1e-2 of a unit gradient.
        assert np.abs(fd - g[:, axis]).mean() < 2e-2, axis


@needs_numba
def test_fused_query_matches_the_torch_path():
    c = collider(random_network())
    x = points(3000, 3)
    for t in (0.0, 0.11, 0.3, 0.59):
        c.network.fused = True
        fused = c.evaluate_at(x, True, t)
        c.network.fused = False
        reference = c.evaluate_at(x, True, t)
        for a, b in zip(fused, reference):
            assert np.allclose(a, b, atol=2e-5, rtol=1e-4)
    c.network.fused = True
    distance, gradient, velocity = c.evaluate_at(x, False, 0.2)
    assert gradient is None and velocity is None
    assert np.allclose(distance, c.evaluate_at(x, True, 0.2)[0], atol=1e-6)


@needs_numba
def test_fused_training_kernels_match_the_torch_reference():
    """Per-point times (training): features, Jacobian and the tables' gradient of a loss that
    uses both, fused against torch."""
    network = random_network()
    rng = np.random.default_rng(4)
    x = torch.from_numpy(points(500, 5).astype(np.float32))
    key, frac = keyframe_segments(rng.uniform(0.0, DURATION, len(x)), DURATION, 4)
    key, frac = torch.from_numpy(key), torch.from_numpy(frac)
    grads = []
    for fused in (True, False):
        network.fused = fused
        network.zero_grad()
        distance, gradient = network.value_and_gradient(x, key, frac)
        (distance.sum() + (gradient ** 2).sum()).backward()
        grads.append((distance.detach(), gradient.detach(), network.table.grad.clone()))
    (d1, g1, t1), (d2, g2, t2) = grads
    assert torch.allclose(d1, d2, atol=1e-6)
    assert torch.allclose(g1, g2, atol=2e-5, rtol=1e-4)
    assert torch.allclose(t1, t2, atol=1e-4, rtol=1e-4)
    assert (t2[0] != 0).any() and (t2[3] != 0).any()  # every keyframe table is reached


@needs_numba
def test_cuda_answers_and_trains_as_the_cpu(cuda):
    """On CUDA (the torch path): distance, gradient and velocity at one time as the fused CPU
    kernel gives them, and, each point at its own time, the distance, gradient and the tables'
    gradient of a training loss as the CPU gives them."""
    c = collider(random_network())
    g = collider(random_network(), device=cuda)
    assert not g.network.can_fuse(torch.zeros(1, 3, device=cuda))
    x = points(3000, 7)
    for t in (0.0, 0.11, 0.3, 0.59):
        for a, b in zip(c.evaluate_at(x, True, t), g.evaluate_at(x, True, t)):
            np.testing.assert_allclose(b, a, atol=2e-5, rtol=1e-4)
    key, frac = keyframe_segments(np.random.default_rng(8).uniform(0.0, DURATION, len(x)), DURATION, 4)
    grads = []
    for network, device in ((c.network, "cpu"), (g.network, cuda)):
        network.table.requires_grad_(True)
        network.zero_grad()
        distance, gradient = network.value_and_gradient(
            torch.from_numpy(x.astype(np.float32)).to(device), torch.from_numpy(key).to(device),
            torch.from_numpy(frac).to(device))
        (distance.sum() + (gradient ** 2).sum()).backward()
        grads.append([t.detach().cpu() for t in (distance, gradient, network.table.grad)])
        network.table.requires_grad_(False)
    for a, b in zip(*grads):
        torch.testing.assert_close(b, a, atol=1e-4, rtol=1e-4)


def test_keyframe_segments_span_the_duration():
    key, frac = keyframe_segments(np.array([0.0, 0.1, 0.2, 0.59999, 0.6]), DURATION, 4)
    assert key.tolist() == [0, 0, 1, 2, 2]
    assert np.allclose(frac, [0.0, 0.5, 0.0, 1.0, 1.0], atol=1e-4)


def test_velocity_is_the_normal_speed_and_zero_where_an_end_frame_is_held():
    c = collider(random_network(), loop=False)
    x = points(300, 6)
    _d, g, v = c.evaluate_at(x, True, 0.3)
    normal = g / np.linalg.norm(g, axis=1, keepdims=True)
    tangential = v - np.einsum("ij,ij->i", v, normal)[:, None] * normal
    assert np.abs(tangential).max() < 1e-9 and np.abs(v).max() > 0.01
    for held in (-1.0, DURATION, 5.0):
        d_held, _, v_held = c.evaluate_at(x, True, held)
        assert np.abs(v_held).max() == 0.0
        end = 0.0 if held < 0 else DURATION
        # the end frame itself: the first or the last keyframe table
        assert np.allclose(d_held, c.evaluate_at(x, False, end - 1e-12 if end else 0.0)[0], atol=1e-5)
    looped = collider(random_network(), loop=True)
    assert np.allclose(looped.evaluate_at(x, False, 0.1 + DURATION)[0], looped.evaluate_at(x, False, 0.1)[0],
                       atol=1e-5)


def test_a_saved_model_loads_and_answers_the_same(tmp_path):
    c = collider(random_network())
    path = save_collider(c, tmp_path / "k.safetensors")
    loaded = load_collider(path)
    assert isinstance(loaded, AnimatedNeuralCollider) and loaded.animated
    assert loaded.info.animation["frames"] == 4 and loaded.info.animation["duration_s"] == pytest.approx(DURATION)
    x = points(500, 7)
    fields = ["distance", "normal", "contact", "velocity"]
    a = c.query(x, fields, time=0.33)
    b = loaded.query(x, fields, time=0.33)
    for field in fields:
        assert np.array_equal(getattr(a, field), getattr(b, field)), field
    assert np.abs(a.velocity).max() > 0


def test_a_model_whose_tables_do_not_fit_its_animation_is_refused(tmp_path):
    c = collider(random_network())
    c.info.animation = {**c.info.animation, "frames": 5}
    path = save_collider(c, tmp_path / "bad.safetensors")
    with pytest.raises(ModelFileError, match="4 keyframes, but the animation has 5 frames"):
        load_collider(path)


def test_a_query_without_time_is_refused():
    from collider_contract import QueryError

    with pytest.raises(QueryError, match="time"):
        collider(random_network()).query(points(3, 8), ["distance"])
