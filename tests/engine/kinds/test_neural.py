"""The neural kind's plumbing (an untrained tiny network; accuracy of trained networks is tested
with training): shapes, the exact autograd gradient vs finite differences, presets, weights
that do not fit. Collider frame, metres."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from collider_server.engine.collider import ColliderInfo
from collider_server.engine.kinds.neural import PRESETS, Architecture, NeuralCollider, build_network

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
    ({"fourier_features": 0}, "fourier_features must be a positive integer"),
    ({"hidden_layers": 2.5}, "hidden_layers must be a positive integer"),
    ({"fourier_scale": -1.0}, "fourier_scale must be > 0"),
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


def test_presets_are_the_documented_ones():
    """docs/neural.md's preset table: shapes and parameter counts; ``grid`` is the default."""
    from collider_server.engine.kinds.neural import (
        ANIMATED_PRESETS,
        DEFAULT_ANIMATED_PRESET,
        DEFAULT_PRESET,
        GridArchitecture,
        KeyframeGridArchitecture,
    )

    assert DEFAULT_PRESET == "grid"
    assert PRESETS["paper-bunny"] == Architecture(128, 3, 256, 3.0)
    assert PRESETS["paper-dragon"] == Architecture(128, 8, 256, 3.0)
    assert PRESETS["fast"] == Architecture(64, 3, 128, 3.0)
    assert PRESETS["grid"] == GridArchitecture(levels=8, features=2, base_resolution=16, max_resolution=256,
                                               table_log2=17, hidden_layers=2, hidden_width=32, smooth=True,
                                               table_dtype="int8-mu", surface_rows=False)
    # The animated preset: the grid's levels and MLP, 2^16 float16 rows, 9 keyframe tables.
    assert ANIMATED_PRESETS["keyframes"] == KeyframeGridArchitecture(
        levels=8, features=2, base_resolution=16, max_resolution=256, table_log2=16, hidden_layers=2,
        hidden_width=32, smooth=True, table_dtype="float16", surface_rows=False, keyframes=9)
    assert DEFAULT_ANIMATED_PRESET == "keyframes"
    counts = {"grid": 1_446_741, "paper-bunny": 198_017, "paper-dragon": 526_977, "fast": 49_857}
    assert {name: arch.parameter_count() for name, arch in PRESETS.items()} == counts
    assert ANIMATED_PRESETS["keyframes"].parameter_count() == 7_109_365


@pytest.mark.parametrize("bad, message", [
    ({"fourier_features": 0}, "architecture fourier_features must be a positive integer, got 0"),
    ({"hidden_layers": 2.5}, "architecture hidden_layers must be a positive integer, got 2.5"),
    ({"hidden_width": "8"}, "architecture hidden_width must be a positive integer, got '8'"),
    ({"fourier_scale": -1.0}, "fourier_scale must be > 0, got -1.0"),
    ({"fourier_scale": 0.0}, "fourier_scale must be > 0, got 0.0"),
    ({"fourier_scale": float("nan")}, "fourier_scale must be > 0, got nan"),
])
def test_architecture_validation_messages(bad, message):
    with pytest.raises(ValueError) as error:
        Architecture(**bad)
    assert str(error.value) == message


def test_smallest_valid_architecture_is_accepted():
    """One of everything and any positive scale: a valid (if useless) network."""
    arch = Architecture(fourier_features=1, hidden_layers=1, hidden_width=1, fourier_scale=0.5)
    network = build_network(arch, [0.0, 0.0, 0.0], 1.0)
    # 3 x 1 Fourier matrix, 2 -> 1 ReLU layer (2 + 1), 1 -> 1 output (1 + 1).
    assert arch.parameter_count() == 3 + 3 + 2 == sum(p.numel() for p in network.parameters())


def test_fourier_matrix_is_drawn_with_the_given_scale():
    """B ~ N(0, fourier_scale^2) per entry (the paper's initialisation, normalised coordinates)."""
    import torch

    torch.manual_seed(0)
    for scale in (0.5, 3.0):
        network = build_network(Architecture(2000, 1, 4, scale), [0.0, 0.0, 0.0], 1.0)
        assert abs(float(network.fourier.std()) / scale - 1) < 0.05
        assert abs(float(network.fourier.mean())) < 0.05 * scale


def numpy_fourier_network(network, points):
    """The documented network, evaluated independently in float64: u = (x - centre) / radius,
    [cos(u B), sin(u B)], ReLU layers, linear output, times radius."""
    state = {k: v.detach().double().numpy() for k, v in network.state_dict().items()}
    u = (points - state["centre"]) / state["radius"]
    phase = u @ state["fourier"]
    h = np.concatenate([np.cos(phase), np.sin(phase)], axis=1)
    layers = sorted({int(k.split(".")[1]) for k in state if k.startswith("body.")})
    for index in layers[:-1]:
        h = np.maximum(h @ state[f"body.{index}.weight"].T + state[f"body.{index}.bias"], 0.0)
    last = layers[-1]
    return (h @ state[f"body.{last}.weight"].T + state[f"body.{last}.bias"])[:, 0] * state["radius"]


def test_fourier_network_is_the_documented_function(network_collider):
    points = inside_points(100, 6)
    expected = numpy_fourier_network(network_collider.network, points)
    distance, _ = network_collider.evaluate(points, False)
    np.testing.assert_allclose(distance, expected, rtol=1e-4, atol=1e-5 * np.abs(expected).max())
    assert np.ptp(expected) > 0  # a field worth comparing


def test_architecture_dict_round_trip():
    from collider_server.engine.kinds.neural import architecture_dict, architecture_from_dict

    for arch in PRESETS.values():
        stored = architecture_dict(arch)
        assert architecture_from_dict(stored) == arch
    fourier = Architecture(8, 2, 16, 1.0)
    assert "encoding" not in architecture_dict(fourier)  # Fourier files never carried one
    assert architecture_from_dict({**architecture_dict(fourier), "encoding": "fourier"}) == fourier
    assert architecture_dict(PRESETS["grid"])["encoding"] == "grid"


def test_from_tensors_messages(network_collider):
    tensors = network_collider.tensors()
    info = network_collider.info
    missing = dict(tensors)
    missing.pop("fourier")
    with pytest.raises(ValueError) as error:
        NeuralCollider.from_tensors(info, missing, "cpu")
    assert str(error.value).startswith("weights do not match the architecture {'fourier_features': ")
    assert ": expected {'fourier': (3, 8), 'centre': (3,), 'radius': (), " in str(error.value)
    assert ", found {'centre': (3,), 'radius': (), 'body.0.weight': " in str(error.value)
    for settings, reason in [({}, "'architecture'"),
                             ({"architecture": {"hidden_width": 4, "colour": 1}}, "colour"),
                             ({"architecture": None}, "NoneType")]:
        bad = ColliderInfo.from_dict({**info.to_dict(), "settings": settings})
        with pytest.raises(ValueError) as error:
            NeuralCollider.from_tensors(bad, tensors, "cpu")
        assert str(error.value).startswith("neural settings lack a valid architecture: ")
        assert reason in str(error.value)


def test_the_device_is_checked(network_collider):
    with pytest.raises(ValueError, match=r"^unknown device 'abacus'; use 'cpu', 'cuda' or 'auto'$"):
        NeuralCollider(network_collider.info, network_collider.network, "abacus")
    with pytest.raises(ValueError, match=r"^unknown device 'abacus'"):
        NeuralCollider.from_tensors(network_collider.info, network_collider.tensors(), "abacus")
    assert NeuralCollider.from_tensors(network_collider.info, network_collider.tensors(), "cpu").device == "cpu"


def test_weights_of_any_float_dtype_load_as_float32(tiny_neural_collider):
    """float64 weights load as float32, centre and radius (an off-origin box) included."""
    import torch

    shift = np.array([0.5, -0.25, 2.0])
    collider = tiny_neural_collider(LO + shift, HI + shift, seed=4)
    tensors = {k: v.astype(np.float64) for k, v in collider.tensors().items()}
    rebuilt = NeuralCollider.from_tensors(collider.info, tensors, "cpu")
    assert {v.dtype for v in rebuilt.network.state_dict().values()} == {torch.float32}
    np.testing.assert_allclose(rebuilt.network.centre.numpy(), shift, rtol=1e-6)
    assert float(rebuilt.network.radius) == pytest.approx(0.12, rel=1e-6)  # half the largest side
    points = inside_points(20, 7) + shift
    np.testing.assert_array_equal(rebuilt.query(points).distance, collider.query(points).distance)


def test_fourier_weights_are_float32(network_collider):
    """The model file holds float32 arrays: the Fourier matrix, the layers, centre and radius."""
    tensors = network_collider.tensors()
    assert {"fourier", "centre", "radius"} <= set(tensors)
    assert {v.dtype for v in tensors.values()} == {np.dtype(np.float32)}
