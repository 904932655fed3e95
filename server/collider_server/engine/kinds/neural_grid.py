"""A multiresolution feature grid and a tiny MLP: the neural collider that trains in minutes and
answers fast on a CPU (and, being plain torch, on CUDA).

Network (``GridArchitecture``): ``u = (x - centre) / radius`` (collider frame to normalised
coordinates in [-1, 1]^3), then for each of ``levels`` grids of growing resolution ``r_l``
(geometric from ``base_resolution`` to ``max_resolution``) a feature vector of ``features`` values
interpolated from the 8 corners of the cell holding ``u``. Coarse levels whose ``(r + 1)^3``
corners fit in ``2^table_log2`` rows are dense (one row per corner); finer levels share a table of
``2^table_log2`` rows through a spatial hash (collisions are resolved by training: the near-surface
samples dominate). The interpolation weights are ``smoothstep`` (C1) when ``smooth`` is true, so
the features, and the normals built from them, are continuous across cell faces; plain trilinear
otherwise. The ``levels * features`` values go through ``hidden_layers`` ReLU layers of
``hidden_width`` and a linear output, times ``radius`` (distance in collider units).

The gradient is analytic (:meth:`GridSDF.value_and_gradient`): the interpolation weights'
derivatives times the table rows, pulled back through the MLP (ReLU masks) in one pass, no
autograd graph. It is written in differentiable torch ops, so training uses it for the normal
loss with a single backward pass; :meth:`GridSDF.forward` plus autograd is the slow, obviously
correct reference it is tested against.

Around the network: its shape is :mod:`.grid_architecture`'s, the table's storage in a model file
:mod:`.table_format`'s, the bridge to the fused CPU encoding :mod:`.fused_encoding`'s, the cells'
rules :mod:`.grid_cells`'.
"""

from __future__ import annotations

from functools import cache

import numpy as np

from . import grid_kernels
from .fused_encoding import KernelSpec, fused_encoding
from .grid_architecture import TABLE_DTYPES, GridArchitecture
from .grid_cells import cell_corners, dense_row, hashed_row
from .table_format import INT8_QUANTILE, pack_table, unpack_table

__all__ = ["INT8_QUANTILE", "TABLE_DTYPES", "GridArchitecture", "build_grid_network", "corner_rows",
           "fused_network_query", "grid_layout", "grid_network_class", "interpolate", "linear_layers", "mlp",
           "mlp_with_gradient", "pack_table", "unpack_table"]


def build_grid_network(arch: GridArchitecture, centre, radius: float):
    """The torch module for ``arch``; input collider-frame points (n, 3) float32, output (n,)."""
    return grid_network_class()(arch, centre, radius)


# -- the layout: which rows of the one table each level owns ------------------------------------

def grid_layout(arch: GridArchitecture) -> KernelSpec:
    """The levels of ``arch`` laid out in one table: each level's resolution, first row, row count
    and whether it is dense (numpy arrays, one entry per level; see :mod:`.grid_cells`)."""
    rows = np.asarray(arch.level_rows(), np.int64)
    offsets = np.concatenate([[0], np.cumsum(rows)[:-1]]).astype(np.int64)
    return KernelSpec(np.asarray(arch.resolutions(), np.int64), offsets, rows, np.asarray(arch.level_dense()),
                      arch.smooth, arch.levels, arch.features)


# -- the encoding (torch reference) -------------------------------------------------------------

def corner_rows(u, resolution, level_offset, level_rows, dense, smooth: bool):
    """Table rows, weights and weight derivatives of the 8 cell corners at every level.

    u : (n, 3) normalised coordinates (clamped into [-1, 1]); ``resolution`` (L,) float32,
    ``level_offset`` and ``level_rows`` (L,) int64, ``dense`` (L,) bool: the layout as tensors.
    Returns rows (n, L, 8) int64, weight (n, L, 8), dweight (n, L, 8, 3) (d weight / d u).
    """
    import torch

    ijk, weight, dweight = cell_corners(u, resolution, smooth)
    i, j, k = ijk[..., 0], ijk[..., 1], ijk[..., 2]
    dense_rows = dense_row(i, j, k, (resolution.long() + 1)[None, :, None])
    hashed_rows = hashed_row(i, j, k, level_rows[None, :, None])
    rows = torch.where(dense[None, :, None], dense_rows, hashed_rows) + level_offset[None, :, None]
    return rows, weight, dweight


def interpolate(values, weight, dweight, want_jacobian: bool):
    """Features (n, L, F) from the corner values (n, L, 8, F) and weights (n, L, 8) and, when
    asked, their Jacobian d features / d u (n, L, F, 3) from the weights' derivatives
    (n, L, 8, 3) (else None)."""
    import torch

    features = (weight[..., None] * values).sum(dim=2)
    if not want_jacobian:
        return features, None
    return features, torch.einsum("nlcf,nlcd->nlfd", values, dweight)


# -- the MLP ----------------------------------------------------------------------------------

def mlp(arch: GridArchitecture):
    """The MLP of ``arch``: ``hidden_layers`` ReLU layers of ``hidden_width`` on the
    ``levels * features`` inputs, then one linear output (a torch ``nn.Sequential``)."""
    from torch import nn

    layers: list[nn.Module] = []
    width = arch.levels * arch.features
    for _ in range(arch.hidden_layers):
        layers += [nn.Linear(width, arch.hidden_width), nn.ReLU()]
        width = arch.hidden_width
    layers.append(nn.Linear(width, 1))
    return nn.Sequential(*layers)


def linear_layers(body) -> list:
    """The ``nn.Linear`` layers of the MLP ``body``, input to output."""
    from torch import nn

    return [m for m in body if isinstance(m, nn.Linear)]


def mlp_with_gradient(body, features, radius, first_bias=None):
    """The MLP ``body`` on ``features`` (n, L, F): distance (n,) (the output times ``radius``)
    and d output / d features (n, L, F) (the ReLU masks kept from the forward pass).
    ``first_bias`` ((n, hidden_width) or (hidden_width,)), when given, is added to the first
    layer's pre-activation (the articulated network's per-part condition)."""
    from torch.nn.functional import linear as affine

    n = len(features)
    h = features.flatten(1)
    masks = []
    linears = linear_layers(body)
    for k, layer in enumerate(linears[:-1]):
        pre = affine(h, layer.weight, layer.bias)
        if k == 0 and first_bias is not None:
            pre = pre + first_bias
        mask = pre > 0
        masks.append(mask)
        h = pre * mask
    out = linears[-1]
    distance = affine(h, out.weight, out.bias).squeeze(-1) * radius
    # Backward through the MLP: d out / d features, (n, L * F).
    g = out.weight.expand(n, -1)
    for layer, mask in zip(reversed(linears[:-1]), reversed(masks)):
        g = (g * mask) @ layer.weight
    return distance, g.view(features.shape)


# -- the whole network in one fused CPU kernel ------------------------------------------------

def fused_network_query(network, x, want_gradient: bool, first_bias=None, part=None):
    """Distance (n,) and, when asked, gradient (n, 3) of the grid ``network`` at collider-frame
    points ``x`` (n, 3) by one fused CPU kernel for the whole network (numba; inference only,
    the query fast path). ``first_bias`` (hidden_width,) float32 numpy, when given, is added to
    the first layer's bias (the articulated network's per-part condition, :mod:`.neural_skinned`);
    with ``part`` (n,) int64 it is (P, hidden_width), one row per part, and point p takes row
    ``part[p]``."""
    import torch

    linears = linear_layers(network.body)
    u = ((x - network.centre) / network.radius).contiguous().numpy()
    weights = tuple(m.weight.detach().numpy() for m in linears[:-1])
    biases = tuple(m.bias.detach().numpy() for m in linears[:-1])
    part_biases = None
    if part is not None:
        part_biases = np.ascontiguousarray(biases[0] + first_bias, np.float32)
        part = np.ascontiguousarray(part, np.int64)
    elif first_bias is not None:
        biases = (np.ascontiguousarray(biases[0] + first_bias, np.float32),) + biases[1:]
    out = linears[-1]
    n = len(u)
    distance = np.empty(n, np.float32)
    gradient = np.empty((n if want_gradient else 0, 3), np.float32)
    spec = network.spec
    grid_kernels.network_query(u, network.table.detach().numpy(), spec.resolution, spec.offset, spec.rows,
                               spec.dense, spec.smooth, weights, biases, out.weight.detach().numpy()[0],
                               float(out.bias.detach()[0]), float(network.radius), want_gradient,
                               distance, gradient, part, part_biases)
    return torch.from_numpy(distance), (torch.from_numpy(gradient) if want_gradient else None)


# -- the module -------------------------------------------------------------------------------

@cache
def grid_network_class():
    """The torch module class of the grid network, ``GridSDF(arch, centre, radius)``: centre (3,)
    and radius of the normalisation, collider frame and units. Built on first use, so that
    importing the engine does not import torch."""
    import torch
    from torch import nn

    class GridSDF(nn.Module):
        def __init__(self, arch: GridArchitecture, centre, radius: float):
            super().__init__()
            spec = grid_layout(arch)
            self.register_buffer("centre", torch.as_tensor(np.asarray(centre, np.float32)))
            self.register_buffer("radius", torch.tensor(float(radius), dtype=torch.float32))
            # Derived from the architecture, not saved in the model file.
            self.register_buffer("resolution", torch.tensor(spec.resolution, dtype=torch.float32), persistent=False)
            self.register_buffer("level_offset", torch.tensor(spec.offset), persistent=False)
            self.register_buffer("level_rows", torch.tensor(spec.rows), persistent=False)
            self.register_buffer("dense", torch.tensor(spec.dense), persistent=False)
            # Small initial features (instant-NGP): the MLP starts from a near-constant input.
            self.table = nn.Parameter(torch.empty(int(spec.rows.sum()), arch.features).uniform_(-1e-4, 1e-4))
            self.body = mlp(arch)
            self.spec = spec
            #: Use the fused CPU kernels when they can run; False forces the torch reference.
            self.fused = True

        def corner_rows(self, u):
            """:func:`corner_rows` of this network's layout at normalised points ``u`` (n, 3)."""
            return corner_rows(u, self.resolution, self.level_offset, self.level_rows, self.dense, self.spec.smooth)

        def encode_parts(self, u, want_jacobian: bool):
            """Features (n, L, F) at normalised points ``u`` (n, 3) float32 and, when asked,
            their Jacobian d features / d u (n, L, F, 3) (else None).

            On a CPU with numba: the fused kernels (:mod:`.grid_kernels`; gradients flow to the
            table only). Otherwise, or with ``self.fused = False``: plain torch ops (the
            reference, and the CUDA path)."""
            if self.can_fuse(u):
                features, jacobian = fused_encoding(u.contiguous(), self.table, self.spec, want_jacobian)
                return features, (jacobian if want_jacobian else None)
            rows, weight, dweight = self.corner_rows(u)
            return interpolate(self.table[rows], weight, dweight, want_jacobian)

        def forward(self, x):
            u = (x - self.centre) / self.radius
            features, _ = self.encode_parts(u, False)
            return self.body(features.flatten(1)).squeeze(-1) * self.radius

        def can_fuse(self, x) -> bool:
            """Whether the fused CPU kernels serve points on ``x``'s device."""
            return self.fused and x.device.type == "cpu" and grid_kernels.available()

        def fused_query(self, x, want_gradient: bool, first_bias=None, part=None):
            """:func:`fused_network_query` of this network: distance (n,) and, when asked,
            gradient (n, 3) at collider-frame points ``x`` (n, 3); same values as
            :meth:`value_and_gradient`. ``first_bias``: the articulated network's per-part
            condition (:mod:`.neural_skinned`)."""
            return fused_network_query(self, x, want_gradient, first_bias, part)

        def value_and_gradient(self, x):
            """Distance (n,) and its gradient (n, 3) at collider-frame points ``x`` (n, 3).

            No autograd graph is needed (works under ``torch.inference_mode``); the ops are
            differentiable, so training backpropagates through the gradient in one pass.
            Outside [-1, 1]^3 the encoding is clamped: the gradient along a clamped axis is 0
            (the collider's domain box lies inside, and its own rule takes over beyond it).
            """
            u = (x - self.centre) / self.radius
            features, jacobian = self.encode_parts(u, True)  # (n, L, F), (n, L, F, 3)
            distance, g = self.head(features)
            # d distance / d x = radius * d mlp / d u * d u / d x = d mlp / d u.
            return distance, torch.einsum("nlf,nlfd->nd", g, jacobian)

        def head(self, features, first_bias=None):
            """:func:`mlp_with_gradient` of this network's MLP on ``features`` (n, L, F)."""
            return mlp_with_gradient(self.body, features, self.radius, first_bias)

    return GridSDF
