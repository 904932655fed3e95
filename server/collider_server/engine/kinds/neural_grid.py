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

import numpy as np

from . import grid_kernels
from .fused_encoding import KernelSpec, fused_encoding
from .grid_architecture import TABLE_DTYPES, GridArchitecture
from .grid_cells import cell_corners, dense_row, hashed_row
from .table_format import INT8_QUANTILE, pack_table, unpack_table

__all__ = ["INT8_QUANTILE", "TABLE_DTYPES", "GridArchitecture", "build_grid_network", "grid_network_class",
           "pack_table", "unpack_table"]


def build_grid_network(arch: GridArchitecture, centre, radius: float):
    """The torch module for ``arch``; input collider-frame points (n, 3) float32, output (n,)."""
    return grid_network_class(arch)(centre, radius)


def grid_network_class(arch: GridArchitecture):
    """The torch module class of ``arch``: ``GridSDF(centre, radius)``, centre (3,) and radius
    of the normalisation, collider frame and units."""
    import torch
    from torch import nn

    resolutions = arch.resolutions()
    rows = arch.level_rows()
    offsets = np.concatenate([[0], np.cumsum(rows)[:-1]])
    dense = arch.level_dense()

    class GridSDF(nn.Module):
        def __init__(self, centre, radius: float):
            super().__init__()
            self.register_buffer("centre", torch.as_tensor(np.asarray(centre, np.float32)))
            self.register_buffer("radius", torch.tensor(float(radius), dtype=torch.float32))
            # Derived from the architecture, not saved in the model file.
            self.register_buffer("resolution", torch.tensor(resolutions, dtype=torch.float32), persistent=False)
            self.register_buffer("level_offset", torch.tensor(offsets, dtype=torch.int64), persistent=False)
            self.register_buffer("level_rows", torch.tensor(rows, dtype=torch.int64), persistent=False)
            self.register_buffer("dense", torch.tensor(dense), persistent=False)
            # Small initial features (instant-NGP): the MLP starts from a near-constant input.
            self.table = nn.Parameter(torch.empty(sum(rows), arch.features).uniform_(-1e-4, 1e-4))
            layers: list[nn.Module] = []
            width = arch.levels * arch.features
            for _ in range(arch.hidden_layers):
                layers += [nn.Linear(width, arch.hidden_width), nn.ReLU()]
                width = arch.hidden_width
            layers.append(nn.Linear(width, 1))
            self.body = nn.Sequential(*layers)
            self.spec = KernelSpec(np.asarray(resolutions, np.int64), offsets.astype(np.int64),
                                    np.asarray(rows, np.int64), np.asarray(dense), arch.smooth,
                                    arch.levels, arch.features)
            #: Use the fused CPU kernels when they can run; False forces the torch reference.
            self.fused = True

        # -- encoding ------------------------------------------------------------------------

        def corner_rows(self, u):
            """Table rows, weights and weight derivatives of the 8 cell corners at every level.

            u : (n, 3) normalised coordinates (clamped into [-1, 1])
            Returns rows (n, L, 8) int64, weight (n, L, 8), dweight (n, L, 8, 3) (d weight / d u).
            """
            ijk, weight, dweight = cell_corners(u, self.resolution, arch.smooth)
            i, j, k = ijk[..., 0], ijk[..., 1], ijk[..., 2]
            dense_rows = dense_row(i, j, k, (self.resolution.long() + 1)[None, :, None])
            hashed_rows = hashed_row(i, j, k, self.level_rows[None, :, None])
            rows = torch.where(self.dense[None, :, None], dense_rows, hashed_rows) + self.level_offset[None, :, None]
            return rows, weight, dweight

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
            values = self.table[rows]  # (n, L, 8, F)
            features = (weight[..., None] * values).sum(dim=2)
            if not want_jacobian:
                return features, None
            return features, torch.einsum("nlcf,nlcd->nlfd", values, dweight)

        def forward(self, x):
            u = (x - self.centre) / self.radius
            features, _ = self.encode_parts(u, False)
            return self.body(features.flatten(1)).squeeze(-1) * self.radius

        # -- the analytic gradient -----------------------------------------------------------

        def fused_query(self, x, want_gradient: bool, first_bias=None, part=None):
            """Distance (n,) and, when asked, gradient (n, 3) at collider-frame points ``x``
            (n, 3) by one fused CPU kernel for the whole network (numba; inference only, the
            query fast path). Same values as :meth:`value_and_gradient`. ``first_bias``
            (hidden_width,) float32 numpy, when given, is added to the first layer's bias (the
            articulated network's per-part condition, :mod:`.neural_skinned`); with ``part`` (n,)
            int64 it is (P, hidden_width), one row per part, and point p takes row ``part[p]``."""
            linears = [m for m in self.body if isinstance(m, nn.Linear)]
            u = ((x - self.centre) / self.radius).contiguous().numpy()
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
            spec = self.spec
            grid_kernels.network_query(u, self.table.detach().numpy(), spec.resolution, spec.offset, spec.rows,
                                       spec.dense, spec.smooth, weights, biases, out.weight.detach().numpy()[0],
                                       float(out.bias.detach()[0]), float(self.radius), want_gradient,
                                       distance, gradient, part, part_biases)
            return torch.from_numpy(distance), (torch.from_numpy(gradient) if want_gradient else None)

        def can_fuse(self, x) -> bool:
            """Whether the fused CPU kernels serve points on ``x``'s device."""
            return self.fused and x.device.type == "cpu" and grid_kernels.available()

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
            """The MLP on ``features`` (n, L, F): distance (n,) (the output times the radius)
            and d output / d features (n, L, F) (the ReLU masks kept from the forward pass).
            ``first_bias`` ((n, hidden_width) or (hidden_width,)), when given, is added to the
            first layer's pre-activation (the articulated network's per-part condition)."""
            n = len(features)
            h = features.flatten(1)
            masks = []
            linears = [m for m in self.body if isinstance(m, nn.Linear)]
            for k, linear in enumerate(linears[:-1]):
                pre = torch.nn.functional.linear(h, linear.weight, linear.bias)
                if k == 0 and first_bias is not None:
                    pre = pre + first_bias
                mask = pre > 0
                masks.append(mask)
                h = pre * mask
            out = linears[-1]
            distance = torch.nn.functional.linear(h, out.weight, out.bias).squeeze(-1) * self.radius
            # Backward through the MLP: d out / d features, (n, L * F).
            g = out.weight.expand(n, -1)
            for linear, mask in zip(reversed(linears[:-1]), reversed(masks)):
                g = (g * mask) @ linear.weight
            return distance, g.view(n, arch.levels, arch.features)

    return GridSDF
