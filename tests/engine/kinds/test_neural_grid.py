"""The grid network (multiresolution feature grid + tiny MLP): the analytic gradient against
autograd and finite differences, the fused CPU kernels against the torch reference (values,
Jacobians, table gradients), dense and hashed levels, smoothstep continuity, the model file
(float16 and 8-bit tables) and old files, the normal across a plateau. Random networks here; the
shipped models in test_real_meshes. Collider frame, metres."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from collider_server.engine.collider import ColliderInfo
from collider_server.engine.kinds import grid_kernels
from collider_server.engine.kinds.neural import (
    PRESETS,
    GridArchitecture,
    NeuralCollider,
    architecture_from_dict,
    build_network,
)

LO, HI = np.array([-0.12, -0.1, -0.08]), np.array([0.12, 0.1, 0.08])
CENTRE, RADIUS = 0.5 * (LO + HI), 0.12
# Small tables so that levels 0-1 are dense and the finer ones hashed (collisions included).
SMALL = {"levels": 4, "features": 2, "base_resolution": 4, "max_resolution": 40, "table_log2": 10,
             "hidden_layers": 2, "hidden_width": 16}
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
@pytest.mark.parametrize("smooth, features, n", [(True, 2, 3000), (False, 2, 3000), (True, 3, 3000),
                                                 (True, 2, 1), (True, 2, 65)])
def test_fused_network_query_matches_the_torch_reference(smooth, features, n):
    """The query fast path (the whole network in one kernel: points sorted into buckets, blocks
    of 64) against the torch analytic path and autograd, points inside and outside the [-1, 1]
    box, in random order, a partial last block, the two-feature fast path and the general one;
    distance only too."""
    network = random_network(seed=12, smooth=smooth, hidden_layers=3, features=features)
    network.fused = False
    x = points(n, 13, pad=0.05)
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
def test_fused_network_query_takes_each_point_s_row_of_the_part_bias_table():
    """The articulated network's parts in one call (:mod:`.neural_skinned`): point p's first
    layer takes row ``part[p]`` of a bias table, against the torch path with that bias per point;
    in random order, a partial last block."""
    network = random_network(seed=21, hidden_layers=2, features=2)
    x = points(3001, 22, pad=0.05)
    width = network.body[0].out_features
    table = (torch.randn(5, width, generator=torch.Generator().manual_seed(23)) * 0.5).numpy()
    part = np.random.default_rng(24).integers(0, 5, len(x))
    u = (x - network.centre) / network.radius
    features, jacobian = network.encode_parts(u, True)
    reference, g = network.head(features, torch.from_numpy(table)[part])
    expected = torch.einsum("nlf,nlfd->nd", g, jacobian)
    distance, gradient = network.fused_query(x, True, table, part)
    torch.testing.assert_close(distance, reference, rtol=0, atol=1e-5 * float(reference.abs().max()))
    torch.testing.assert_close(gradient, expected, rtol=0, atol=1e-4 * float(expected.abs().max()))
    one, _ = network.fused_query(x, True, table[0])  # one bias for all: another answer
    assert (one - distance).abs().max() > 1e-3 * float(reference.abs().max())


@needs_numba
def test_fused_network_query_of_the_smallest_network():
    """One level of one feature and an MLP one unit wide: fewer inputs and units than the
    gradient's three components (the kernel keeps them in its scratch rows)."""
    network = random_network(seed=3, levels=1, features=1, hidden_layers=1, hidden_width=1,
                             base_resolution=8, max_resolution=8)
    with torch.no_grad():  # a positive pre-activation, so the one ReLU passes the gradient
        network.body[0].bias.fill_(5.0)
    network.fused = False
    x = points(200, 5)
    xr = x.clone().requires_grad_(True)
    reference = network(xr)
    (autograd,) = torch.autograd.grad(reference.sum(), xr)
    network.fused = True
    distance, gradient = network.fused_query(x, True)
    torch.testing.assert_close(distance, reference.detach(), rtol=0, atol=1e-5 * float(reference.abs().max()))
    torch.testing.assert_close(gradient, autograd, rtol=0, atol=1e-4 * float(autograd.abs().max()))
    assert float(autograd.abs().max()) > 0


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
    from collider_server.engine.modelfile import load_collider, save_collider

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


def test_int8_table_codes_the_hashed_levels_and_keeps_the_dense_ones_in_float16():
    """``table_dtype="int8"``: the hashed levels' rows become 8-bit codes times a scale per level
    and feature (the 99.9th percentile of |value| / 127: within half a step of the value,
    clipped above it), the dense levels' rows float16; unpacking rebuilds the table in level
    order, for one table (rows, F) or keyframe tables (K, rows, F)."""
    from collider_server.engine.kinds.neural_grid import INT8_QUANTILE, pack_table, unpack_table

    arch = GridArchitecture(**SMALL, table_dtype="int8")
    rows, dense = arch.level_rows(), arch.level_dense()
    assert dense == [True, True, False, False]
    rng = np.random.default_rng(4)
    for shape in [(sum(rows), 2), (3, sum(rows), 2)]:
        table = rng.normal(0.0, 0.5, shape).astype(np.float32)
        table[..., -1, 0] = 40.0  # an outlier of the finest level: clipped, not the scale
        packed = pack_table(table, arch)
        assert sorted(packed) == ["table_codes", "table_dense", "table_scales"]
        assert packed["table_dense"].dtype == np.float16 and packed["table_dense"].shape[-2] == 125 + 1000
        assert packed["table_codes"].dtype == np.int8 and packed["table_codes"].shape[-2] == 2 * 1024
        assert packed["table_scales"].shape == (2, 2)
        back = unpack_table({**packed, "other": np.zeros(1)}, arch)
        assert sorted(back) == ["other", "table"] and back["table"].shape == shape
        np.testing.assert_array_equal(back["table"][..., :1125, :], table[..., :1125, :].astype(np.float16))
        start = 1125
        for level in range(2):
            block, got = table[..., start:start + 1024, :], back["table"][..., start:start + 1024, :]
            step = np.quantile(np.abs(block).reshape(-1, 2), INT8_QUANTILE, axis=0) / 127
            np.testing.assert_allclose(packed["table_scales"][level], step, rtol=1e-6)
            inside = np.abs(block) <= 127 * step
            assert inside.mean() > 0.99
            assert (np.abs(got - block)[inside] <= 0.5 * np.broadcast_to(step, block.shape)[inside] + 1e-7).all()
            np.testing.assert_allclose(np.abs(got[~inside]), np.broadcast_to(127 * step, block.shape)[~inside], rtol=1e-6)
            start += 1024
        assert back["table"][..., -1, 0].max() < 40.0  # clipped
        # Loading and saving again keeps the codes and scales (the table is on its own steps).
        again = pack_table(back["table"], arch)
        for key in packed:
            np.testing.assert_array_equal(again[key], packed[key])
    # The float formats are one array, as before.
    plain = pack_table(table[0], GridArchitecture(**SMALL))
    assert list(plain) == ["table"] and plain["table"].dtype == np.float16
    # Every level hashed (64 rows: not even 5^3 corners fit): no dense rows, float16 all the same.
    hashed = GridArchitecture(**{**SMALL, "table_log2": 6}, table_dtype="int8")
    assert not any(hashed.level_dense())
    table = rng.normal(0.0, 0.5, (sum(hashed.level_rows()), 2)).astype(np.float32)
    packed = pack_table(table, hashed)
    assert packed["table_dense"].dtype == np.float16 and packed["table_dense"].shape == (0, 2)
    assert packed["table_codes"].shape == table.shape and packed["table_scales"].shape == (4, 2)
    back = unpack_table(packed, hashed)["table"]
    step = np.repeat(packed["table_scales"], hashed.level_rows(), axis=0)
    inside = np.abs(table) <= 127 * step  # (clipped beyond the 99.9th percentile)
    assert inside.mean() > 0.95 and (np.abs(back - table)[inside] <= 0.5 * step[inside] + 1e-7).all()


def test_int8_mu_codes_lie_on_the_curve_and_err_less_where_values_crowd_near_zero():
    """``table_dtype="int8-mu"``: the same arrays as ``int8`` (dense levels float16, codes and one
    scale per hashed level and feature), the codes on the mu-law curve through 0 and the scale's
    127 steps: a code's value is ``127 * scale * expm1(|code| / 127 * log1p(mu)) / mu``. On values
    crowded near zero as a trained table's (Laplace), it errs less than the straight line, and
    loading and saving again changes nothing."""
    from collider_server.engine.kinds.neural_grid import pack_table, unpack_table
    from collider_server.engine.kinds.table_format import INT8_MU

    line, curve = (GridArchitecture(**SMALL, table_dtype=dtype) for dtype in ("int8", "int8-mu"))
    rng = np.random.default_rng(5)
    table = rng.laplace(0.0, 0.05, (sum(line.level_rows()), 2)).astype(np.float32)
    packed = pack_table(table, curve)
    assert {k: v.dtype for k, v in packed.items()} == {k: v.dtype for k, v in pack_table(table, line).items()}
    np.testing.assert_array_equal(packed["table_scales"], pack_table(table, line)["table_scales"])
    back = unpack_table(packed, curve)["table"]
    hashed = slice(125 + 1000, None)
    codes = packed["table_codes"].astype(np.float64)
    scale = np.repeat(packed["table_scales"], 1024, axis=0)
    expected = np.sign(codes) * 127 * scale * np.expm1(np.abs(codes) / 127 * np.log1p(INT8_MU)) / INT8_MU
    np.testing.assert_allclose(back[hashed], expected, rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(back[:1125], table[:1125].astype(np.float16))
    error_curve = np.abs(back[hashed] - table[hashed]).mean()
    error_line = np.abs(unpack_table(pack_table(table, line), line)["table"][hashed] - table[hashed]).mean()
    assert error_curve < 0.7 * error_line, (error_curve, error_line)
    again = pack_table(back, curve)
    for key in packed:
        np.testing.assert_array_equal(again[key], packed[key])


@pytest.mark.parametrize("damage, message", [
    (lambda t: t.pop("table_scales"), "table_scales is missing"),
    (lambda t: t.update(table_codes=t["table_codes"][:-1]), "the int8 table does not fit the architecture"),
    (lambda t: t.update(table_codes=t["table_codes"].astype(np.int16)), "found float16 .*, int16 "),
    (lambda t: t.update(table_scales=t["table_scales"][:1]), "the int8 table does not fit"),
])
def test_int8_model_file_round_trip_and_damaged_files(tmp_path, damage, message):
    """A network saved with an int8 table loads (float32 in memory) and answers as the original
    to within its codes' steps; a file whose parts do not fit says which."""
    from collider_server.engine.modelfile import load_collider, save_collider

    network = random_network(seed=8)
    arch = GridArchitecture(**SMALL, table_dtype="int8")
    info = ColliderInfo("g", "neural", LO.tolist(), HI.tolist(), settings={"architecture": arch.__dict__.copy()})
    collider = NeuralCollider(info, network, "cpu")
    tensors = collider.tensors()
    assert "table" not in tensors and tensors["table_codes"].dtype == np.int8
    loaded = load_collider(save_collider(collider, tmp_path / "g.safetensors"), "cpu")
    assert loaded.network.table.dtype == torch.float32
    x = points(1000, 9).numpy().astype(np.float64)
    before, after = collider.query(x).distance, loaded.query(x).distance
    # 8-bit steps (~1/100 of a hashed level's spread) move distances by ~1 % of their range.
    assert 0 < np.abs(after - before).max() < 3e-2 * np.abs(before).max()
    damage(tensors)
    with pytest.raises(ValueError, match=message):
        NeuralCollider.from_tensors(info, tensors)


def plateau_network():
    """A real network with a plateau: one dense level whose feature is u_x (trilinear, exact),
    one hidden unit relu(u_x - 0.2), output radius * (relu(u_x - 0.2) + 0.05): for u_x < 0.2
    every unit is off, the distance is the constant 0.05 radius and the gradient exactly zero
    (what a trained ReLU network can learn; the 30-minute bunny of 2026-11-27 did)."""
    arch = GridArchitecture(levels=1, features=1, base_resolution=4, max_resolution=4, table_log2=10,
                            hidden_layers=1, hidden_width=2, smooth=False)
    network = build_network(arch, CENTRE, RADIUS)
    with torch.no_grad():
        i = torch.arange(125) % 5
        network.table.copy_((-1.0 + 0.5 * i).float()[:, None])  # corner i of 5 along x: u_x
        network.body[0].weight.copy_(torch.tensor([[1.0], [0.0]]))
        network.body[0].bias.copy_(torch.tensor([-0.2, -1.0]))
        network.body[2].weight.copy_(torch.tensor([[1.0, 0.0]]))
        network.body[2].bias.copy_(torch.tensor([0.05]))
    info = ColliderInfo("plateau", "neural", LO.tolist(), HI.tolist(), settings={"architecture": arch.__dict__.copy()})
    return NeuralCollider(info, network, "cpu")


def test_normal_across_a_plateau_comes_from_differences_at_half_the_finest_cell():
    """Where the network's gradient vanishes (a ReLU plateau), the normal is the direction of the
    central differences at half the finest cell (here radius / 4: u_x +-0.25): within that of the
    plateau's edge it points across it (+x); deeper in, the differences vanish too and the
    collider's zero-gradient fallback (away from the domain centre) stands; elsewhere the
    analytic gradient is untouched."""
    collider = plateau_network()
    u_x = np.array([0.1, -0.04, 0.5, -0.6])  # in the plateau near its edge (twice), active, deep in
    local = CENTRE + np.stack([u_x * RADIUS, np.full(4, 0.3 * RADIUS), np.full(4, 0.1 * RADIUS)], axis=1)
    distance, gradient = collider.evaluate(local, True)
    np.testing.assert_allclose(distance, RADIUS * (np.maximum(u_x - 0.2, 0.0) + 0.05), rtol=1e-5)
    # Central differences of radius * relu(u_x - 0.2) over u_x +-0.25, per collider unit:
    expected_x = [(0.1 + 0.25 - 0.2) / 0.5, (-0.04 + 0.25 - 0.2) / 0.5, 1.0, 0.0]
    np.testing.assert_allclose(gradient[:, 0], expected_x, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(gradient[:, 1:], 0.0, atol=1e-6)
    normal = collider.query(local, ["normal"]).normal
    np.testing.assert_allclose(normal[:3], [[1.0, 0.0, 0.0]] * 3, atol=1e-6)
    away = (local[3] - CENTRE) / np.linalg.norm(local[3] - CENTRE)
    np.testing.assert_allclose(normal[3], away, atol=1e-6)  # the fallback's guess, as before


def test_architecture_from_dict_reads_old_and_new_files():
    old = {"fourier_features": 8, "hidden_layers": 2, "hidden_width": 16, "fourier_scale": 1.0}
    assert type(architecture_from_dict(old)).__name__ == "Architecture"
    assert architecture_from_dict({**SMALL, "encoding": "grid"}) == GridArchitecture(**SMALL)
    with pytest.raises(ValueError, match="table_dtype"):
        GridArchitecture(table_dtype="int4")
    with pytest.raises(ValueError, match="max_resolution"):
        GridArchitecture(base_resolution=64, max_resolution=32)


@pytest.mark.parametrize("name", ["bunny", "dragon"])
def test_shipped_grid_models_analytic_gradient_matches_autograd(name):
    """On each shipped grid model: the fused kernels, the torch analytic gradient and autograd
    through the torch forward agree (points in the model's domain)."""
    from collider_server.engine.modelfile import load_collider
    from collider_server.engine.repository import ModelRepository

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


@pytest.mark.parametrize("bad, message", [
    ({"levels": 0}, "architecture levels must be a positive integer, got 0"),
    ({"features": True}, "architecture features must be a positive integer, got True"),
    ({"base_resolution": 1.5}, "architecture base_resolution must be a positive integer, got 1.5"),
    ({"max_resolution": -4}, "architecture max_resolution must be a positive integer, got -4"),
    ({"table_log2": "16"}, "architecture table_log2 must be a positive integer, got '16'"),
    ({"hidden_layers": 0}, "architecture hidden_layers must be a positive integer, got 0"),
    ({"hidden_width": None}, "architecture hidden_width must be a positive integer, got None"),
    ({"base_resolution": 64, "max_resolution": 32}, "max_resolution (32) must be >= base_resolution (64)"),
    ({"table_log2": 25}, "table_log2 must be <= 24 (16M rows per level), got 25"),
    ({"table_dtype": "int4"}, "table_dtype must be one of 'float16', 'float32', 'int8', 'int8-mu', got 'int4'"),
    ({"encoding": "fourier"}, "a GridArchitecture has encoding 'grid', got 'fourier'"),
])
def test_grid_architecture_validation_messages(bad, message):
    with pytest.raises(ValueError) as error:
        GridArchitecture(**bad)
    assert str(error.value) == message


def test_grid_architecture_bounds_are_inclusive():
    """The limits themselves are valid: one of everything, max == base, 2^24 rows, float32."""
    tiny = GridArchitecture(levels=1, features=1, base_resolution=1, max_resolution=1, table_log2=1,
                            hidden_layers=1, hidden_width=1)
    assert tiny.resolutions() == [1]
    assert tiny.level_rows() == [2]  # 2^3 corners do not fit in 2^1 rows: hashed
    # 2 table rows x 1 feature, 1 -> 1 ReLU layer (1 + 1), 1 -> 1 output (1 + 1).
    assert tiny.parameter_count() == 2 + 2 + 2
    network = build_network(tiny, CENTRE, RADIUS)
    assert sum(p.numel() for p in network.parameters()) == 6
    assert network.dense.tolist() == [False]
    assert GridArchitecture(table_log2=24).level_rows()[-1] == 2**24
    assert GridArchitecture(base_resolution=32, max_resolution=32, levels=3).resolutions() == [32, 32, 32]
    assert GridArchitecture(table_dtype="float32").table_dtype == "float32"


@pytest.mark.parametrize("levels, base, top, expected", [
    (1, 16, 256, [16]),
    (2, 4, 9, [4, 9]),
    (3, 16, 144, [16, 48, 144]),  # growth 3
    (5, 16, 256, [16, 32, 64, 128, 256]),
    (3, 10, 20, [10, 14, 20]),  # 10 * sqrt(2) = 14.14 rounds to 14
])
def test_resolutions_grow_geometrically(levels, base, top, expected):
    assert GridArchitecture(levels=levels, base_resolution=base, max_resolution=top).resolutions() == expected


@pytest.mark.parametrize("arch, expected", [
    # cap 2^16; r = 16: 17^3 = 4913 corners fit (dense); r = 32: share 2^16 / 16 = 2^12, raised to
    # 2^14; r = 64: share 2^14; r = 128: the whole 2^16.
    ({"levels": 4, "base_resolution": 16, "max_resolution": 128, "table_log2": 16}, [4913, 16384, 16384, 65536]),
    # cap 2^18; r = 48: share 2^18 / 9 = 29127.1, down to the power of two 2^14; r = 144: 2^18.
    ({"levels": 3, "base_resolution": 16, "max_resolution": 144, "table_log2": 18}, [4913, 16384, 262144]),
    # cap 2^18; r = 64: share 2^18 / 4 = 2^16 (65^3 corners do not fit).
    ({"levels": 3, "base_resolution": 32, "max_resolution": 128, "table_log2": 18}, [16384, 65536, 262144]),
    # cap 2^13 below the 2^14 floor: never more than the cap.
    ({"levels": 2, "base_resolution": 32, "max_resolution": 64, "table_log2": 13}, [8192, 8192]),
])
def test_surface_rows_grow_like_the_surface(arch, expected):
    """``surface_rows``: hashed levels get cap * (r / r_max)^2 rows, rounded down to a power of
    two, at least 2^14 and at most the cap; dense levels keep one row per corner."""
    grid = GridArchitecture(surface_rows=True, hidden_layers=1, hidden_width=4, **arch)
    assert grid.level_rows() == expected
    plain = GridArchitecture(surface_rows=False, hidden_layers=1, hidden_width=4, **arch)
    assert plain.level_rows() == [min((r + 1) ** 3, 2 ** arch["table_log2"]) for r in plain.resolutions()]
    network = build_network(grid, CENTRE, RADIUS)
    assert tuple(network.table.shape) == (sum(expected), grid.features)
    assert sum(p.numel() for p in network.parameters()) == grid.parameter_count()


def numpy_grid_features(arch, table, u):
    """The encoding as documented (grid_kernels' layout), independently in float64: per level,
    the cell holding the clamped point, smoothstep or trilinear weights of its 8 corners, rows
    ``i + (r+1) (j + (r+1) k)`` (dense) or ``(i P0 ^ j P1 ^ k P2) & (rows - 1)`` (hashed)."""
    table = np.asarray(table, np.float64)
    u = np.clip(np.asarray(u, np.float64), -1.0, 1.0)
    features = np.zeros((len(u), arch.levels, arch.features))
    offset = 0
    for level, (r, rows) in enumerate(zip(arch.resolutions(), arch.level_rows())):
        position = (u + 1.0) * 0.5 * r
        cell = np.minimum(np.floor(position), r - 1).astype(np.int64)
        t = position - cell
        w1 = t * t * (3 - 2 * t) if arch.smooth else t
        for corner in range(8):
            bits = np.array([corner & 1, (corner >> 1) & 1, (corner >> 2) & 1])
            weight = np.prod(np.where(bits == 1, w1, 1 - w1), axis=1)
            i, j, k = (cell + bits).T
            if (r + 1) ** 3 <= rows:
                row = i + (r + 1) * (j + (r + 1) * k)
            else:
                row = (i * 1 ^ j * 2_654_435_761 ^ k * 805_459_861) & (rows - 1)
            features[:, level] += weight[:, None] * table[offset + row]
        offset += rows
    return features


def numpy_grid_network(network, arch, x):
    """The whole documented network in float64: normalise, encode, ReLU MLP, times radius."""
    state = {k: v.detach().double().numpy() for k, v in network.state_dict().items()}
    u = (np.asarray(x, np.float64) - state["centre"]) / state["radius"]
    h = numpy_grid_features(arch, state["table"], u).reshape(len(u), -1)
    layers = sorted({int(k.split(".")[1]) for k in state if k.startswith("body.")})
    for index in layers[:-1]:
        h = np.maximum(h @ state[f"body.{index}.weight"].T + state[f"body.{index}.bias"], 0.0)
    last = layers[-1]
    return (h @ state[f"body.{last}.weight"].T + state[f"body.{last}.bias"])[:, 0] * state["radius"]


@pytest.mark.parametrize("smooth", [True, False])
def test_encoding_is_the_documented_layout(smooth):
    """Features from the torch reference and the fused kernels against an independent numpy
    evaluation of the documented grid (dense and hashed levels, points beyond [-1, 1])."""
    arch = GridArchitecture(**{**SMALL, "smooth": smooth})
    network = random_network(seed=14, smooth=smooth)
    x = points(400, 15, pad=0.03)
    u = (x - network.centre) / network.radius
    expected = numpy_grid_features(arch, network.table.detach().numpy(), u.numpy())
    for fused in ([False, True] if grid_kernels.available() else [False]):
        network.fused = fused
        with torch.no_grad():
            features, _ = network.encode_parts(u, False)
        np.testing.assert_allclose(features.numpy(), expected, rtol=0, atol=1e-5)


def test_grid_collider_answers_the_documented_network():
    """A grid NeuralCollider's distances (the query path, fused where it can be) equal the
    documented network evaluated in numpy; its architecture reads back from the settings."""
    arch = GridArchitecture(**{**SMALL, "hidden_layers": 1})
    network = random_network(seed=16, hidden_layers=1)
    with torch.no_grad():
        network.body[0].bias.uniform_(-0.5, 0.5)
    info = ColliderInfo("g", "neural", LO.tolist(), HI.tolist(), settings={"architecture": arch.__dict__.copy()})
    collider = NeuralCollider(info, network, "cpu")
    assert collider.architecture == arch and collider.device == "cpu"
    x = points(300, 17).numpy().astype(np.float64)
    expected = numpy_grid_network(network, arch, x)
    assert np.ptp(expected) > 0
    gradients = []
    for fused in (True, False):  # the fused query path, and the torch one (CUDA's)
        network.fused = fused
        for want_gradient in (False, True):
            distance, gradient = collider.evaluate(x, want_gradient)
            assert distance.dtype == np.float64 and distance.shape == (300,)
            np.testing.assert_allclose(distance, expected, rtol=0, atol=1e-5 * np.abs(expected).max())
            assert (gradient is not None) == want_gradient
        gradients.append(gradient)
    assert gradients[1].dtype == np.float64 and gradients[1].shape == (300, 3)
    np.testing.assert_allclose(gradients[0], gradients[1], rtol=0, atol=1e-4 * np.abs(gradients[1]).max())


def test_the_fused_kernels_serve_cpu_points_unless_switched_off():
    """They can run exactly when numba (a serve dependency) is installed."""
    import importlib.util

    assert grid_kernels.available() == (importlib.util.find_spec("numba") is not None)
    network = random_network()
    x = points(4, 18)
    assert network.can_fuse(x) == grid_kernels.available()
    network.fused = False
    assert not network.can_fuse(x)


def test_a_new_network_starts_from_small_features():
    """instant-NGP's initialisation: table entries uniform in [-1e-4, 1e-4] (the MLP starts
    from a near-constant input); a float32 table stays float32 in the model's tensors."""
    arch = GridArchitecture(**{**SMALL, "table_dtype": "float32"})
    torch.manual_seed(0)
    network = build_network(arch, CENTRE, RADIUS)
    table = network.table.detach()
    assert float(table.abs().max()) <= 1e-4 and float(table.abs().max()) > 0.9e-4
    assert abs(float(table.mean())) < 1e-5 and float(table.std()) > 0.5e-4
    info = ColliderInfo("g", "neural", LO.tolist(), HI.tolist(), settings={"architecture": arch.__dict__.copy()})
    tensors = NeuralCollider(info, network, "cpu").tensors()
    assert tensors["table"].dtype == np.float32
    assert set(tensors) == {"centre", "radius", "table", "body.0.weight", "body.0.bias", "body.2.weight",
                            "body.2.bias", "body.4.weight", "body.4.bias"}
    np.testing.assert_array_equal(tensors["centre"], CENTRE.astype(np.float32))
    assert tensors["radius"].shape == () and float(tensors["radius"]) == np.float32(RADIUS)


@needs_numba
def test_kernel_threads_are_bounded_by_the_cores_numba_found():
    import numba

    before = numba.get_num_threads()
    try:
        grid_kernels.set_threads(10**6)  # more than there are: all numba found, no error
        assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS
        grid_kernels.set_threads(0)  # fewer than one: one
        assert numba.get_num_threads() == 1
        grid_kernels.set_threads(1.0)
        assert numba.get_num_threads() == 1
    finally:
        numba.set_num_threads(before)


@needs_numba
@pytest.mark.parametrize("loss", ["distance", "gradient", "features"])
def test_fused_table_gradient_of_partial_losses(loss):
    """The table gradient through the fused encoding when the loss uses only the distance (no
    Jacobian asked), only the gradient (the features' gradient is zero) or only the features
    of a call that also asked for the Jacobian: the torch reference's, every time."""
    network = random_network(seed=19, levels=2, max_resolution=9)
    x = points(300, 20, pad=0.02)
    grads = {}
    for fused in (False, True):
        network.fused = fused
        network.zero_grad()
        if loss == "distance":
            value = network(x).square().sum()
        elif loss == "gradient":
            value = network.value_and_gradient(x)[1][:, 0].sum()
        else:
            value = network.encode_parts((x - network.centre) / network.radius, True)[0].sum()
        value.backward()
        grads[fused] = network.table.grad.clone()
    assert grads[False].abs().max() > 0
    torch.testing.assert_close(grads[True], grads[False], rtol=0, atol=1e-5 * float(grads[False].abs().max()))


@pytest.mark.parametrize("smooth", [True, False])
def test_gradient_on_the_faces_of_the_normalised_cube(smooth):
    """Points exactly on u = +-1 (the encoding's own box; inside, not clamped): the derivative
    along that axis counts, as autograd's and the fused kernels' do."""
    network = random_network(seed=21, smooth=smooth)
    network.fused = False
    centre, radius = network.centre, network.radius
    x = points(60, 22)
    for row in range(60):
        axis, sign = row % 3, (1.0 if row % 2 else -1.0)
        x[row, axis] = centre[axis] + sign * radius
    u = (x - centre) / radius
    assert (u.abs() == 1.0).any(dim=1).all()
    xr = x.clone().requires_grad_(True)
    (autograd,) = torch.autograd.grad(network(xr).sum(), xr)
    with torch.no_grad():
        _, gradient = network.value_and_gradient(x)
    torch.testing.assert_close(gradient, autograd, rtol=1e-5, atol=1e-5)
    if not smooth:  # (smoothstep's derivative is 0 at a cell's end anyway)
        assert autograd[u.abs() == 1.0].abs().min() > 0  # the face derivative is not dropped
    if grid_kernels.available():
        network.fused = True
        _, fused = network.fused_query(x, True)
        torch.testing.assert_close(fused, gradient, rtol=0, atol=1e-4 * float(gradient.abs().max()))


def test_the_collider_queries_through_the_fused_network_kernel_on_a_cpu():
    """docs/neural.md, query fast path: on a CPU with numba a grid collider's answers are the
    fused whole-network kernel's (bit for bit); with it switched off, the torch analytic path,
    which needs no autograd graph (it answers inside torch.inference_mode)."""
    arch = GridArchitecture(**SMALL)
    network = random_network(seed=23)
    info = ColliderInfo("g", "neural", LO.tolist(), HI.tolist(), settings={"architecture": arch.__dict__.copy()})
    collider = NeuralCollider(info, network, "cpu")
    x = points(200, 24)
    if grid_kernels.available():
        distance, gradient = collider.evaluate(x.numpy().astype(np.float64), True)
        kernel_distance, kernel_gradient = network.fused_query(x, True)
        np.testing.assert_array_equal(distance, kernel_distance.numpy())
        np.testing.assert_array_equal(gradient, kernel_gradient.numpy())
    network.fused = False
    with torch.inference_mode():
        distance, gradient = collider.evaluate(x.numpy().astype(np.float64), True)
        reference = network.value_and_gradient(x)
    np.testing.assert_array_equal(distance, reference[0].numpy())
    np.testing.assert_array_equal(gradient, reference[1].numpy())


@pytest.mark.skipif(not grid_kernels.available(), reason="numba is not installed")
def test_the_first_fused_query_keeps_the_thread_counts_it_was_given():
    """In a fresh process (numba's OpenMP pool starts with the first kernel): torch keeps the
    thread count set before the query (the pool's start set it to every core), and the
    OpenMP wait policy is the engine's passive one (idle threads sleep instead of spinning)."""
    import subprocess
    import sys
    from pathlib import Path

    models = Path(__file__).resolve().parents[3] / "models"
    code = ("import os, collider_server, torch, numpy as np\n"
            "torch.set_num_threads(1)\n"
            "from collider_server.engine.modelfile import load_collider\n"
            f"c = load_collider({str(models / 'bunny.safetensors')!r}, 'cpu')\n"
            "c.query(np.zeros((100, 3)), ['distance', 'normal'])\n"
            "print(torch.get_num_threads(), os.environ['OMP_WAIT_POLICY'])\n")
    env = {k: v for k, v in __import__("os").environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["1", "PASSIVE"]


@pytest.mark.parametrize("name", ["bunny", "dragon"])
def test_shipped_grid_models_answer_on_cuda_as_on_the_cpu(name, cuda):
    """A shipped grid model loaded on CUDA (the torch path) answers distance, normal and contact
    as on the CPU (the fused kernel): collider frame, points over the whole domain."""
    from collider_server.engine.modelfile import load_collider
    from collider_server.engine.repository import ModelRepository

    path = ModelRepository().path(name)
    if not path.is_file():
        pytest.skip(f"no shipped model at {path}")
    cpu, gpu = load_collider(path, "cpu"), load_collider(path, cuda)
    assert gpu.device.startswith("cuda") and not gpu.network.can_fuse(torch.zeros(1, 3, device=cuda))
    lo, hi = cpu.domain_min, cpu.domain_max
    points = lo + np.random.default_rng(5).random((50_000, 3)) * (hi - lo)
    a, b = (c.query(points, ["distance", "normal", "contact"]) for c in (cpu, gpu))
    scale = float(np.abs(a.distance).max())
    np.testing.assert_allclose(b.distance, a.distance, rtol=0, atol=1e-5 * scale)
    np.testing.assert_allclose(b.contact, a.contact, rtol=0, atol=1e-4 * scale)  # |d| x normal's
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a.normal, b.normal), -1, 1)))
    assert np.percentile(angle, 99.9) < 0.05, np.percentile(angle, [50, 99.9, 100])


def test_a_fourier_network_answers_on_cuda_as_on_the_cpu(tiny_neural_collider, cuda):
    """The paper's network (autograd normal) on CUDA against the CPU, same weights."""
    lo, hi = [-0.1, -0.1, -0.1], [0.1, 0.1, 0.1]
    cpu = tiny_neural_collider(lo, hi, seed=4)
    gpu = tiny_neural_collider(lo, hi, seed=4, device=cuda)
    points = np.random.default_rng(6).uniform(-0.1, 0.1, (20_000, 3))
    a, b = (c.query(points, ["distance", "normal", "contact"]) for c in (cpu, gpu))
    np.testing.assert_allclose(b.distance, a.distance, rtol=0, atol=1e-5)
    np.testing.assert_allclose(b.normal, a.normal, rtol=0, atol=1e-3)
    np.testing.assert_allclose(b.contact, a.contact, rtol=0, atol=1e-5)
