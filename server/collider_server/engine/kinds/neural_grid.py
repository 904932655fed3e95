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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np

from . import grid_kernels

#: The 8 corners of a cell as 0/1 offsets along x, y, z (bit 0: x): (8, 3).
CORNERS = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=np.int64)

#: Primes of the spatial hash (Teschner et al. 2003, as in instant-NGP); the first is 1 so that
#: neighbouring cells along x land in neighbouring rows.
HASH_PRIMES = (1, 2_654_435_761, 805_459_861)


#: How a model file may store the feature table (``GridArchitecture.table_dtype``).
TABLE_DTYPES = ("float16", "float32", "int8")

#: The quantile of a hashed level's |feature values| that its 8-bit codes reach (``int8``); the
#: rarer larger values are clipped to it. Scaling by the maximum instead left most values a
#: coarser step (docs/neural.md: "8-bit tables").
INT8_QUANTILE = 0.999


@dataclass(frozen=True)
class GridArchitecture:
    """Shape of a grid network (see the module docstring).

    levels : L, grids of growing resolution
    features : F, values per grid corner
    base_resolution, max_resolution : cells per side of the coarsest and finest grid over [-1, 1]
    table_log2 : rows per level, log2 (a level with more corners is hashed into that many rows)
    hidden_layers, hidden_width : the MLP after the encoding
    smooth : smoothstep interpolation weights (continuous normals) instead of trilinear
    surface_rows : hashed levels' rows grow like r^2 up to ``2^table_log2`` (see level_rows)
    table_dtype : how the feature table is stored in the model file: "float16", "float32", or
        "int8": the hashed levels as 8-bit codes with one scale per level and feature, the dense
        (coarse) levels as float16 (see :func:`pack_table`); computation is float32 either way
    """

    levels: int = 8
    features: int = 2
    base_resolution: int = 16
    max_resolution: int = 256
    table_log2: int = 16
    hidden_layers: int = 2
    hidden_width: int = 32
    smooth: bool = True
    table_dtype: str = "float16"
    surface_rows: bool = False
    encoding: str = "grid"
    #: The ``encoding`` of this class of architecture (a subclass has its own).
    ENCODING: ClassVar[str] = "grid"

    def __post_init__(self):
        for name in ("levels", "features", "base_resolution", "max_resolution", "table_log2",
                     "hidden_layers", "hidden_width"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"architecture {name} must be a positive integer, got {value!r}")
        if self.max_resolution < self.base_resolution:
            raise ValueError(f"max_resolution ({self.max_resolution}) must be >= base_resolution "
                             f"({self.base_resolution})")
        if self.table_log2 > 24:
            raise ValueError(f"table_log2 must be <= 24 (16M rows per level), got {self.table_log2}")
        if self.table_dtype not in TABLE_DTYPES:
            raise ValueError(f"table_dtype must be one of {', '.join(map(repr, TABLE_DTYPES))}, "
                             f"got {self.table_dtype!r}")
        if self.encoding != self.ENCODING:
            raise ValueError(f"a {type(self).__name__} has encoding {self.ENCODING!r}, got {self.encoding!r}")

    def grid(self) -> GridArchitecture:
        """The plain grid of this architecture (a subclass's own fields dropped): the static
        network an animated one is built on."""
        return GridArchitecture(**{f.name: getattr(self, f.name) for f in fields(GridArchitecture)
                                   if f.name != "encoding"})

    def resolutions(self) -> list[int]:
        """Cells per side of each level, coarse to fine."""
        if self.levels == 1:
            return [self.base_resolution]
        growth = (self.max_resolution / self.base_resolution) ** (1.0 / (self.levels - 1))
        return [int(round(self.base_resolution * growth ** level)) for level in range(self.levels)]

    def level_rows(self) -> list[int]:
        """Rows of each level's table: its corners when they fit (dense), else the level's hash
        table: ``2^table_log2`` rows, or with ``surface_rows`` rows growing like the number of
        cells a surface crosses (r^2), ``2^table_log2`` at the finest level, a power of two
        and at least ``2^14``: the fine levels, where the surface detail is, get the memory."""
        cap = 2 ** self.table_log2
        rows = []
        for r in self.resolutions():
            hashed = cap
            if self.surface_rows:
                share = cap * (r / self.max_resolution) ** 2
                hashed = min(cap, max(2 ** 14, 2 ** int(math.floor(math.log2(share)))))
            rows.append(min((r + 1) ** 3, hashed))
        return rows

    def level_dense(self) -> list[bool]:
        """Whether each level is dense (one row per corner) rather than hashed."""
        return [(r + 1) ** 3 <= n for r, n in zip(self.resolutions(), self.level_rows())]

    def parameter_count(self) -> int:
        width = self.levels * self.features
        mlp = 0
        for _ in range(self.hidden_layers):
            mlp += width * self.hidden_width + self.hidden_width
            width = self.hidden_width
        return sum(self.level_rows()) * self.features + mlp + width + 1


def pack_table(table: np.ndarray, arch: GridArchitecture) -> dict[str, np.ndarray]:
    """The feature table (..., rows, F) float32 as a model file stores it (``arch.table_dtype``):
    ``{"table": ...}`` in float16 or float32, or for ``int8`` the dense levels' rows as float16
    (``table_dense``: the coarse levels, few rows, to which the distance is most sensitive) and
    the hashed levels' rows as int8 codes (``table_codes``) times one float32 scale per level and
    feature (``table_scales`` (hashed levels, F)): the value is ``code * scale``, the scale the
    level's :data:`INT8_QUANTILE` of |value| / 127. :func:`unpack_table` inverts it."""
    if arch.table_dtype != "int8":
        return {"table": table.astype(arch.table_dtype)}
    dense_rows, codes, scales = [], [], []
    for rows, dense in _level_slices(arch):
        block = table[..., rows, :]
        if dense:
            dense_rows.append(block.astype(np.float16))
            continue
        flat = np.abs(block).reshape(-1, block.shape[-1])
        scale = np.quantile(flat, INT8_QUANTILE, axis=0).astype(np.float32) / 127
        # A table that was loaded from 8 bits is kept on its own steps (its largest value is code
        # 127), so that loading and saving again changes nothing.
        peak = flat.max(axis=0) / np.float32(127)
        steps = flat / np.where(peak > 0, peak, 1.0)
        coded = (np.abs(steps - np.rint(steps)) < 1e-3).all(axis=0)
        scale = np.where(coded, peak, scale)
        scale = np.where(scale > 0, scale, np.float32(1.0))  # an all-zero level: any scale
        codes.append(np.clip(np.rint(block / scale), -127, 127).astype(np.int8))
        scales.append(scale)
    features = table.shape[-1]
    return {"table_dense": np.concatenate(dense_rows, axis=-2) if dense_rows
            else np.zeros((*table.shape[:-2], 0, features), np.float16),
            "table_codes": np.concatenate(codes, axis=-2) if codes
            else np.zeros((*table.shape[:-2], 0, features), np.int8),
            "table_scales": np.asarray(scales, np.float32).reshape(len(scales), features)}


def unpack_table(tensors: dict[str, np.ndarray], arch: GridArchitecture) -> dict[str, np.ndarray]:
    """A copy of ``tensors`` with the table as :func:`pack_table` stored it turned back into
    ``"table"`` (..., rows, F) float32. Raises ValueError when the stored parts do not fit ``arch``."""
    tensors = dict(tensors)
    if arch.table_dtype != "int8":
        return tensors
    try:
        dense = np.asarray(tensors.pop("table_dense"))
        codes = np.asarray(tensors.pop("table_codes"))
        scales = np.asarray(tensors.pop("table_scales"))
    except KeyError as exc:
        raise ValueError(f"an int8 table needs table_dense, table_codes and table_scales; "
                         f"{exc.args[0]} is missing") from None
    levels = _level_slices(arch)
    hashed = [rows for rows, is_dense in levels if not is_dense]
    expected_dense = sum(rows.stop - rows.start for rows, is_dense in levels if is_dense)
    expected_codes = sum(rows.stop - rows.start for rows in hashed)
    features = arch.features
    if (codes.dtype != np.int8 or dense.ndim < 2 or codes.ndim != dense.ndim
            or dense.shape[-2:] != (expected_dense, features) or codes.shape[-2:] != (expected_codes, features)
            or dense.shape[:-2] != codes.shape[:-2] or scales.shape != (len(hashed), features)):
        raise ValueError(f"the int8 table does not fit the architecture: expected (..., {expected_dense}, "
                         f"{features}) dense rows, (..., {expected_codes}, {features}) int8 codes and "
                         f"({len(hashed)}, {features}) scales, found {dense.dtype} {dense.shape}, "
                         f"{codes.dtype} {codes.shape}, {scales.shape}")
    dense, scales = dense.astype(np.float32), scales.astype(np.float32)
    table = np.empty((*dense.shape[:-2], expected_dense + expected_codes, features), np.float32)
    dense_at = code_at = level = 0
    for rows, is_dense in levels:
        n = rows.stop - rows.start
        if is_dense:
            table[..., rows, :] = dense[..., dense_at:dense_at + n, :]
            dense_at += n
        else:
            table[..., rows, :] = codes[..., code_at:code_at + n, :] * scales[level]
            code_at += n
            level += 1
    tensors["table"] = table
    return tensors


def _level_slices(arch: GridArchitecture) -> list[tuple[slice, bool]]:
    """Each level's rows of the table and whether the level is dense."""
    stops = np.cumsum(arch.level_rows())
    return [(slice(int(stop - n), int(stop)), dense)
            for stop, n, dense in zip(stops, arch.level_rows(), arch.level_dense())]


@dataclass(frozen=True)
class _KernelSpec:
    """The grid layout as the fused kernels take it (numpy arrays)."""

    resolution: np.ndarray
    offset: np.ndarray
    rows: np.ndarray
    dense: np.ndarray
    smooth: bool
    levels: int
    features: int


def _fused_encoding_class():
    import torch

    class FusedEncoding(torch.autograd.Function):
        """The numba encoding as an autograd function: gradients reach the table (the positions
        are data, not parameters, so none flows to ``u``)."""

        @staticmethod
        def forward(ctx, u, table, spec: _KernelSpec, want_jacobian: bool):
            u_np = u.detach().numpy()
            n = len(u_np)
            features = np.empty((n, spec.levels, spec.features), np.float32)
            jacobian = np.empty((n if want_jacobian else 0, spec.levels, spec.features, 3), np.float32)
            grid_kernels.encode(u_np, table.detach().numpy(), spec.resolution, spec.offset, spec.rows,
                                spec.dense, spec.smooth, want_jacobian, features, jacobian)
            ctx.save_for_backward(u, table)
            ctx.spec, ctx.want_jacobian = spec, want_jacobian
            return torch.from_numpy(features), torch.from_numpy(jacobian)

        @staticmethod
        def backward(ctx, grad_features, grad_jacobian):
            # Autograd hands zeros for an output the loss does not use (materialised gradients),
            # so both are tensors; without a Jacobian the second has 0 rows, like the output.
            u, table = ctx.saved_tensors
            spec = ctx.spec
            grad_table = np.zeros(tuple(table.shape), np.float32)
            grid_kernels.encode_backward(u.detach().numpy(), spec.resolution, spec.offset, spec.rows,
                                         spec.dense, spec.smooth, grad_features.contiguous().numpy(),
                                         grad_jacobian.contiguous().numpy(), ctx.want_jacobian, grad_table)
            return None, torch.from_numpy(grad_table), None, None

    return FusedEncoding


class _LazyFusedEncoding:
    """Builds the autograd function on first use (the module imports without torch)."""

    _cls = None

    def apply(self, *args):
        if self._cls is None:
            type(self)._cls = _fused_encoding_class()
        return self._cls.apply(*args)


_FusedEncoding = _LazyFusedEncoding()


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
            self.register_buffer("corners", torch.from_numpy(CORNERS), persistent=False)
            self.register_buffer("primes", torch.tensor(HASH_PRIMES, dtype=torch.int64), persistent=False)
            # Small initial features (instant-NGP): the MLP starts from a near-constant input.
            self.table = nn.Parameter(torch.empty(sum(rows), arch.features).uniform_(-1e-4, 1e-4))
            layers: list[nn.Module] = []
            width = arch.levels * arch.features
            for _ in range(arch.hidden_layers):
                layers += [nn.Linear(width, arch.hidden_width), nn.ReLU()]
                width = arch.hidden_width
            layers.append(nn.Linear(width, 1))
            self.body = nn.Sequential(*layers)
            self.spec = _KernelSpec(np.asarray(resolutions, np.int64), offsets.astype(np.int64),
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
            # [-1, 1] -> [0, r] grid coordinates of every level: (n, L, 3).
            unit = ((u.clamp(-1.0, 1.0) + 1.0) * 0.5)[:, None, :]
            position = unit * self.resolution[None, :, None]
            cell = position.floor().clamp_(max=self.resolution[None, :, None] - 1)
            t = position - cell
            if arch.smooth:  # smoothstep: C1 across cell faces
                w1 = t * t * (3.0 - 2.0 * t)
                dw1 = 6.0 * t * (1.0 - t)
            else:
                w1 = t
                dw1 = torch.ones_like(t)
            dw1 = dw1 * (0.5 * self.resolution)[None, :, None]  # d position / d u
            # Per axis, weight of the low (0) and high (1) corner: (n, L, 3, 2).
            w = torch.stack([1.0 - w1, w1], dim=-1)
            dw = torch.stack([-dw1, dw1], dim=-1)
            ox, oy, oz = self.corners[:, 0], self.corners[:, 1], self.corners[:, 2]
            wx, wy, wz = w[:, :, 0, ox], w[:, :, 1, oy], w[:, :, 2, oz]  # (n, L, 8)
            weight = wx * wy * wz
            dweight = torch.stack([dw[:, :, 0, ox] * wy * wz, wx * dw[:, :, 1, oy] * wz,
                                   wx * wy * dw[:, :, 2, oz]], dim=-1)
            # Integer corner coordinates (n, L, 8, 3) and their rows, dense or hashed.
            ijk = cell.long()[:, :, None, :] + self.corners[None, None]
            side = (self.resolution.long() + 1)[None, :, None]
            dense_row = ijk[..., 0] + side * (ijk[..., 1] + side * ijk[..., 2])
            hashed = (ijk[..., 0] * self.primes[0]) ^ (ijk[..., 1] * self.primes[1]) ^ (ijk[..., 2] * self.primes[2])
            hashed = hashed & (self.level_rows[None, :, None] - 1)
            rows = torch.where(self.dense[None, :, None], dense_row, hashed) + self.level_offset[None, :, None]
            # Clamped axes do not move the encoding: their derivative is 0 (as autograd has it).
            dweight = dweight * (u.abs() <= 1.0).to(u.dtype)[:, None, None, :]
            return rows, weight, dweight

        def encode_parts(self, u, want_jacobian: bool):
            """Features (n, L, F) at normalised points ``u`` (n, 3) float32 and, when asked,
            their Jacobian d features / d u (n, L, F, 3) (else None).

            On a CPU with numba: the fused kernels (:mod:`.grid_kernels`; gradients flow to the
            table only). Otherwise, or with ``self.fused = False``: plain torch ops (the
            reference, and the CUDA path)."""
            if self.can_fuse(u):
                features, jacobian = _FusedEncoding.apply(u.contiguous(), self.table, self.spec, want_jacobian)
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

        def fused_query(self, x, want_gradient: bool, first_bias=None):
            """Distance (n,) and, when asked, gradient (n, 3) at collider-frame points ``x``
            (n, 3) by one fused CPU kernel for the whole network (numba; inference only, the
            query fast path). Same values as :meth:`value_and_gradient`. ``first_bias``
            (hidden_width,) float32 numpy, when given, is added to the first layer's bias (the
            articulated network's per-part condition, :mod:`.neural_skinned`)."""
            linears = [m for m in self.body if isinstance(m, nn.Linear)]
            u = ((x - self.centre) / self.radius).contiguous().numpy()
            weights = tuple(m.weight.detach().numpy() for m in linears[:-1])
            biases = tuple(m.bias.detach().numpy() for m in linears[:-1])
            if first_bias is not None:
                biases = (np.ascontiguousarray(biases[0] + first_bias, np.float32),) + biases[1:]
            out = linears[-1]
            n = len(u)
            distance = np.empty(n, np.float32)
            gradient = np.empty((n if want_gradient else 0, 3), np.float32)
            spec = self.spec
            grid_kernels.network_query(u, self.table.detach().numpy(), spec.resolution, spec.offset, spec.rows,
                                       spec.dense, spec.smooth, weights, biases, out.weight.detach().numpy()[0],
                                       float(out.bias.detach()[0]), float(self.radius), want_gradient,
                                       distance, gradient)
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
