"""The grid network (multiresolution feature grid + tiny MLP): the analytic gradient against
autograd and finite differences, the fused CPU kernels against the torch reference (values,
Jacobians, table gradients), dense and hashed levels, smoothstep continuity, the model file
(float16 table) and old files. Random networks here; the shipped models in test_real_meshes.
Collider frame, metres."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from collider_server.collider import ColliderInfo
from collider_server.kinds import grid_kernels
from collider_server.kinds.neural import (PRESETS, GridArchitecture, NeuralCollider, architecture_from_dict,
                                          build_network)

LO, HI = np.array([-0.12, -0.1, -0.08]), np.array([0.12, 0.1, 0.08])
CENTRE, RADIUS = 0.5 * (LO + HI), 0.12
# Small tables so that levels 0-1 are dense and the finer ones hashed (collisions included).
SMALL = dict(levels=4, features=2, base_resolution=4, max_resolution=40, table_log2=10,
             hidden_layers=2, hidden_width=16)
needs_numba = pytest.mark.skipif(not grid_kernels.available(), reason="numba is not installed")


def random_network(seed=0, table_scale=0.5, **overrides):
    """An untrained grid network with a large random table (so the encoding matters)."""
    arch = GridArchitecture(**{**SMALL, **overrides})
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        network = build_network(arch, CENTRE, RADIUS)
        with torch.no_grad():
            network.table.normal_(0.0, table_scale)
    return network


def points(n, seed, pad=0.0):
    rng = np.random.default_rng(seed)
    return torch.from_numpy((LO - pad + rng.random((n, 3)) * (HI - LO + 2 * pad)).astype(np.float32))


def test_levels_dense_then_hashed():
    arch = GridArchitecture(**SMALL)
    assert arch.resolutions() == [4, 9, 19, 40]
    assert arch.level_rows() == [125, 1000, 1024, 1024]  # 5^3 and 10^3 corners fit in 2^10 rows
    network = random_network()
    assert network.dense.tolist() == [True, True, False, False]
    assert sum(p.numel() for p in network.parameters()) == arch.parameter_count()


@pytest.mark.parametrize("smooth", [True, False])
def test_analytic_gradient_matches_autograd(smooth):
    network = random_network(smooth=smooth)
    network.fused = False  # the torch reference on both sides
    x = points(500, 1).requires_grad_(True)
    reference = network(x)
    (autograd,) = torch.autograd.grad(reference.sum(), x)
    with torch.inference_mode():
        distance, gradient = network.value_and_gradient(x.detach())
    torch.testing.assert_close(distance, reference.detach(), rtol=0, atol=1e-7)
    torch.testing.assert_close(gradient, autograd, rtol=1e-5, atol=1e-5)
    assert autograd.norm(dim=1).mean() > 0.1  # a gradient worth comparing


def test_analytic_gradient_matches_finite_differences():
    """Central differences of the float64 copy of the network (smoothstep: C1 features)."""
    network = random_network(seed=2)
    network.fused = False
    x = points(300, 3)
    _, gradient = network.value_and_gradient(x)
    net64 = copy.deepcopy(network).double()
    net64.fused = False
    x64, h = x.double(), 1e-7
    fd = torch.empty_like(x64)
    with torch.no_grad():
        for axis in range(3):
            step = torch.zeros(3, dtype=torch.float64)
            step[axis] = h
            fd[:, axis] = (net64(x64 + step) - net64(x64 - step)) / (2 * h)
    error = (gradient.double() - fd).norm(dim=1) / fd.norm(dim=1)
    # A ReLU kink or a cell face between x - h and x + h breaks a quotient now and then.
    assert error.median() < 1e-4 and (error < 1e-3).float().mean() > 0.97


@needs_numba
@pytest.mark.parametrize("smooth", [True, False])
def test_fused_kernels_match_the_torch_reference(smooth):
    network = random_network(seed=4, smooth=smooth)
    x = points(2000, 5, pad=0.05)  # some outside the [-1, 1] box: clamped encoding
    results = {}
    for fused in (False, True):
        network.fused = fused
        network.zero_grad()
        distance, gradient = network.value_and_gradient(x)
        features, _ = network.encode_parts((x - network.centre) / network.radius, False)
        target = torch.nn.functional.normalize(torch.ones(3), dim=0)
        loss = distance.square().sum() + (1 - torch.nn.functional.cosine_similarity(gradient, target[None])).sum()
        loss.backward()
        results[fused] = (distance.detach(), gradient.detach(), features.detach(), network.table.grad.clone(),
                          network.body[0].weight.grad.clone())
    for reference, fused in zip(results[False], results[True]):
        # float32 sums in another order (the kernels accumulate in float64): relative 1e-4.
        torch.testing.assert_close(fused, reference, rtol=0, atol=1e-4 * float(reference.abs().max()))


@needs_numba
@pytest.mark.parametrize("smooth", [True, False])
def test_fused_network_query_matches_the_torch_reference(smooth):
    """The query fast path (the whole network in one kernel) against the torch analytic path
    and autograd, points inside and outside the [-1, 1] box; distance only too."""
    network = random_network(seed=12, smooth=smooth, hidden_layers=3)
    network.fused = False
    x = points(3000, 13, pad=0.05)
    xr = x.clone().requires_grad_(True)
    reference = network(xr)
    (autograd,) = torch.autograd.grad(reference.sum(), xr)
    network.fused = True
    distance, gradient = network.fused_query(x, True)
    only, none = network.fused_query(x, False)
    assert none is None
    torch.testing.assert_close(distance, reference.detach(), rtol=0, atol=1e-5 * float(reference.abs().max()))
    torch.testing.assert_close(only, distance, rtol=0, atol=0)
    torch.testing.assert_close(gradient, autograd, rtol=0, atol=1e-4 * float(autograd.abs().max()))


@needs_numba
def test_fused_forward_matches_reference_on_the_default_preset():
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(11)
        network = build_network(PRESETS["grid"], CENTRE, RADIUS)
        with torch.no_grad():
            network.table.normal_(0.0, 0.1)
    x = points(5000, 6)
    with torch.inference_mode():
        network.fused = True
        fast = network.value_and_gradient(x)
        network.fused = False
        slow = network.value_and_gradient(x)
    torch.testing.assert_close(fast[0], slow[0], rtol=0, atol=1e-5 * float(slow[0].abs().max()))
    torch.testing.assert_close(fast[1], slow[1], rtol=0, atol=1e-4 * float(slow[1].abs().max()))


def test_smoothstep_makes_the_gradient_continuous_across_cell_faces():
    """Across a face of the coarsest cell the trilinear gradient jumps and the smoothstep one
    does not (its jump shrinks with the step)."""
    jumps = {}
    for smooth in (True, False):
        network = random_network(seed=7, smooth=smooth, levels=1, base_resolution=4, max_resolution=4)
        face_u = -0.5  # a cell face of the 4-cell grid over [-1, 1]
        x = torch.tensor([[face_u * RADIUS + CENTRE[0], 0.01, 0.02]] * 2, dtype=torch.float32)
        x[0, 0] -= 1e-5
        x[1, 0] += 1e-5
        with torch.inference_mode():
            _, gradient = network.value_and_gradient(x)
        jumps[smooth] = float((gradient[0] - gradient[1]).norm() / gradient.norm(dim=1).mean())
    assert jumps[True] < 1e-2 < jumps[False]


def test_model_file_stores_the_table_in_float16(tmp_path):
    from collider_server.modelfile import load_collider, save_collider

    network = random_network(seed=8)
    arch = GridArchitecture(**SMALL)
    info = ColliderInfo("g", "neural", LO.tolist(), HI.tolist(), settings={"architecture": arch.__dict__.copy()})
    collider = NeuralCollider(info, network, "cpu")
    assert collider.tensors()["table"].dtype == np.float16
    path = save_collider(collider, tmp_path / "g.safetensors")
    loaded = load_collider(path, "cpu")
    assert isinstance(loaded.architecture, GridArchitecture)
    assert loaded.network.table.dtype == torch.float32
    x = points(1000, 9).numpy().astype(np.float64)
    # float16 rounding of the table (relative 2^-11) moves distances by ~1e-3 of their range.
    before, after = collider.query(x).distance, loaded.query(x).distance
    assert 0 < np.abs(after - before).max() < 2e-3 * np.abs(before).max()


def test_architecture_from_dict_reads_old_and_new_files():
    old = {"fourier_features": 8, "hidden_layers": 2, "hidden_width": 16, "fourier_scale": 1.0}
    assert type(architecture_from_dict(old)).__name__ == "Architecture"
    assert architecture_from_dict({**SMALL, "encoding": "grid"}) == GridArchitecture(**SMALL)
    with pytest.raises(ValueError, match="table_dtype"):
        GridArchitecture(table_dtype="int8")
    with pytest.raises(ValueError, match="max_resolution"):
        GridArchitecture(base_resolution=64, max_resolution=32)


@pytest.mark.parametrize("name", ["bunny", "dragon"])
def test_shipped_grid_models_analytic_gradient_matches_autograd(name):
    """On each shipped grid model: the fused kernels, the torch analytic gradient and autograd
    through the torch forward agree (points in the model's domain)."""
    from collider_server.modelfile import load_collider
    from collider_server.repository import ModelRepository

    path = ModelRepository().path(name)
    if not path.is_file():
        pytest.skip(f"no shipped model at {path}")
    collider = load_collider(path, "cpu")
    if not isinstance(collider.architecture, GridArchitecture):
        pytest.skip(f"{name} is not a grid network")
    network = collider.network
    lo, hi = collider.domain_min, collider.domain_max
    x = torch.from_numpy((lo + np.random.default_rng(3).random((3000, 3)) * (hi - lo)).astype(np.float32))
    try:
        network.fused = False
        xr = x.clone().requires_grad_(True)
        with torch.enable_grad():
            reference = network(xr)
            (autograd,) = torch.autograd.grad(reference.sum(), xr)
        with torch.inference_mode():
            torch_path = network.value_and_gradient(x)
            network.fused = grid_kernels.available()
            fused_path = network.value_and_gradient(x)
            paths = [torch_path, fused_path]
            if grid_kernels.available():
                paths.append(network.fused_query(x, True))
    finally:
        network.fused = True
    for distance, gradient in paths:
        torch.testing.assert_close(distance, reference.detach(), rtol=0, atol=1e-6 * float(reference.abs().max()))
        torch.testing.assert_close(gradient, autograd, rtol=0, atol=1e-4 * float(autograd.abs().max()))
