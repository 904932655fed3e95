"""The neural kind's plumbing (an untrained tiny network; accuracy of trained networks is tested
with training): shapes, the exact autograd gradient vs finite differences, presets, weights
that do not fit. Collider frame, metres."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from collider_server.collider import ColliderInfo
from collider_server.kinds.neural import PRESETS, Architecture, NeuralCollider, build_network

LO, HI = np.array([-0.12, -0.1, -0.08]), np.array([0.12, 0.1, 0.08])


@pytest.fixture
def network_collider(tiny_neural_collider):
    return tiny_neural_collider(LO, HI, seed=1, fourier_scale=2.0)


def inside_points(n, seed):
    return LO + np.random.default_rng(seed).random((n, 3)) * (HI - LO)


def test_presets_match_the_paper():
    """NOTES.md: the paper's bunny has 198,017 parameters; the dragon 8 hidden layers (~527k)."""
    assert PRESETS["paper-bunny"].parameter_count() == 198_017
    assert PRESETS["paper-dragon"] == Architecture(128, 8, 256, PRESETS["paper-dragon"].fourier_scale)
    for arch in PRESETS.values():
        network = build_network(arch, [0.0, 0.0, 0.0], 0.1)
        assert sum(p.numel() for p in network.parameters()) == arch.parameter_count()
        if isinstance(arch, Architecture):
            assert network.fourier.requires_grad  # the Fourier layer is trainable


@pytest.mark.parametrize("bad, message", [
    (dict(fourier_features=0), "fourier_features must be a positive integer"),
    (dict(hidden_layers=2.5), "hidden_layers must be a positive integer"),
    (dict(fourier_scale=-1.0), "fourier_scale must be > 0"),
])
def test_architecture_validation(bad, message):
    with pytest.raises(ValueError, match=message):
        Architecture(**bad)


def test_shapes_and_dtypes(network_collider):
    points = inside_points(37, 0)
    distance, gradient = network_collider.evaluate(points, True)
    assert distance.shape == (37,) and gradient.shape == (37, 3)
    assert distance.dtype == np.float64 and gradient.dtype == np.float64
    only, none = network_collider.evaluate(points, False)
    assert none is None
    np.testing.assert_array_equal(only, distance)
    result = network_collider.query(points, ["distance", "normal", "contact", "collides"])
    assert result.distance.shape == (37,) and result.normal.shape == (37, 3)
    np.testing.assert_allclose(result.normal, gradient / np.linalg.norm(gradient, axis=1, keepdims=True),
                               atol=1e-6)


def test_gradient_matches_finite_differences(network_collider):
    """Autograd (float32) vs central differences of the same network in float64."""
    import torch

    points = inside_points(200, 2)
    _, gradient = network_collider.evaluate(points, True)
    net64 = copy.deepcopy(network_collider.network).double()
    h = 1e-6
    fd = np.empty_like(points)
    with torch.no_grad():
        for axis in range(3):
            step = np.zeros(3)
            step[axis] = h
            up = net64(torch.from_numpy(points + step)).numpy()
            down = net64(torch.from_numpy(points - step)).numpy()
            fd[:, axis] = (up - down) / (2 * h)
    scale = np.linalg.norm(fd, axis=1)
    error = np.linalg.norm(gradient - fd, axis=1) / scale
    # A ReLU kink between p - h and p + h breaks a difference quotient now and then.
    assert np.median(error) < 1e-4 and (error < 1e-3).mean() > 0.97


def test_network_works_in_normalised_coordinates(tiny_neural_collider):
    """The same weights over a box twice as large give twice the distance at the scaled point
    (the output is multiplied by the radius): presets fit meshes of any size and unit."""
    small = tiny_neural_collider(LO, HI, seed=3)
    large = tiny_neural_collider(2 * LO, 2 * HI, seed=3)
    points = inside_points(50, 4)
    np.testing.assert_allclose(large.query(2 * points).distance, 2 * small.query(points).distance,
                               rtol=1e-5, atol=1e-7)


def test_from_tensors_rejects_weights_of_another_architecture(network_collider):
    tensors = network_collider.tensors()
    info = network_collider.info
    rebuilt = NeuralCollider.from_tensors(info, tensors, "cpu")
    points = inside_points(20, 5)
    np.testing.assert_array_equal(rebuilt.query(points).distance, network_collider.query(points).distance)
    wider = ColliderInfo.from_dict({**info.to_dict(), "settings": {"architecture": {
        **info.settings["architecture"], "hidden_width": 32}}})
    with pytest.raises(ValueError, match="weights do not match the architecture"):
        NeuralCollider.from_tensors(wider, tensors, "cpu")
    missing = dict(tensors)
    missing.pop("fourier")
    with pytest.raises(ValueError, match="weights do not match the architecture"):
        NeuralCollider.from_tensors(info, missing, "cpu")
    no_arch = ColliderInfo.from_dict({**info.to_dict(), "settings": {}})
    with pytest.raises(ValueError, match="lack a valid architecture"):
        NeuralCollider.from_tensors(no_arch, tensors, "cpu")


def test_loading_leaves_the_callers_random_stream_alone(network_collider):
    import torch

    torch.manual_seed(7)
    expected = torch.rand(4)
    torch.manual_seed(7)
    NeuralCollider.from_tensors(network_collider.info, network_collider.tensors(), "cpu")
    assert torch.equal(torch.rand(4), expected)


def test_parameters_are_frozen_for_queries(network_collider):
    assert not any(p.requires_grad for p in network_collider.network.parameters())
    assert not network_collider.network.training
