"""Keyframe feature grids: the 4D network of an animated ``neural`` collider (one network for a
whole animation).

Network (``KeyframeGridArchitecture``): the spatial grid of :mod:`.neural_grid` (levels, corners,
smoothstep weights, dense or hashed rows: one layout) with ``keyframes`` (K) feature tables
instead of one, keyframe j at ``j / (K - 1)`` of the animation's duration. At a time between
keyframes k and k + 1 (fraction ``s``) the features are ``(1 - s) T_k(x) + s T_{k+1}(x)``: two
table reads per corner, then the same small MLP as the static network. So in the collider frame:

- the spatial gradient is analytic, as for the static network (the blended table's);
- the time derivative is exact: ``df/dt = radius * dMLP/dfeatures . (T_{k+1}(x) - T_k(x)) * rate``
  (``rate`` = keyframes per second, 0 where the timeline holds an end frame), in collider units
  per second.

A query is at one time: the two tables are blended into one (and their difference into a
time-derivative table) once per call, then the static fused CPU kernel runs with that table
(:func:`.grid_kernels.network_query_timed`, which also sums the time derivative), or the same in
torch ops (CUDA, the reference). Training sees every sample at its own time:
:meth:`KeyframeGridSDF.value_and_gradient` with per-point keyframes and fractions (fused CPU
kernels :func:`.grid_kernels.encode_keyframes` and its backward, or torch ops).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from . import grid_kernels
from .fused_encoding import fused_encoding
from .grid_architecture import require_integers
from .neural_grid import GridArchitecture, grid_network_class, interpolate, linear_layers


@dataclass(frozen=True)
class KeyframeGridArchitecture(GridArchitecture):
    """A :class:`GridArchitecture` whose table is repeated ``keyframes`` times (K >= 2 tables,
    evenly spaced from the first frame of the animation to its last); the other fields as
    there: 2^16 float16 rows per hashed level (2^14 rows train twice as many steps in the same
    minutes but reached less: on the bending arm, 30 quiet minutes on 2 threads, 0.053 against
    0.046 mm mean; docs/neural.md). The static preset's 2^17 rows in 8 bits (the deformed
    preset's too) were not measured on keyframe tables."""

    keyframes: int = 9
    table_log2: int = 16
    encoding: str = "keyframe-grid"
    ENCODING: ClassVar[str] = "keyframe-grid"

    def __post_init__(self):
        super().__post_init__()
        require_integers(self, ("keyframes",), least=2)

    def spatial(self) -> GridArchitecture:
        """The static grid of one keyframe (same levels, rows and MLP)."""
        return self.grid()

    def parameter_count(self) -> int:
        table = sum(self.level_rows()) * self.features
        return super().parameter_count() + (self.keyframes - 1) * table


def keyframe_segments(times, duration_s: float, keyframes: int):
    """Keyframe segment (int64) and fraction (float32) of animation times ``times`` (seconds,
    numpy, in [0, duration_s]) with ``keyframes`` keyframes evenly spaced over the duration."""
    position = np.clip(np.asarray(times, np.float64) / duration_s, 0.0, 1.0) * (keyframes - 1)
    key = np.minimum(np.floor(position).astype(np.int64), keyframes - 2)
    return key, (position - key).astype(np.float32)


def keyframe_weights(static_weights: dict, keyframes: int) -> dict:
    """A keyframe network's weights (``state_dict``) that answer as the static grid network of
    ``static_weights`` (its ``spatial()`` grid) does at every time: its (rows, F) table in each of
    the ``keyframes`` tables (K, rows, F), its MLP and normalisation as they are (the keyframes
    preset's warm start, ``making.training``)."""
    return {name: value.unsqueeze(0).repeat(keyframes, 1, 1) if name == "table" else value
            for name, value in static_weights.items()}


def build_keyframe_network(arch: KeyframeGridArchitecture, centre, radius: float):
    """The torch module for ``arch`` (centre (3,) and radius: the normalisation, collider frame
    and units); see the module docstring."""
    import torch
    from torch import nn

    base = grid_network_class()

    class KeyframeGridSDF(base):
        """``table``: (K, rows, F) keyframe tables; everything else as the static GridSDF."""

        def __init__(self):
            super().__init__(arch.spatial(), centre, radius)
            rows = self.table.shape[0]
            self.table = nn.Parameter(torch.empty(arch.keyframes, rows, arch.features).uniform_(-1e-4, 1e-4))

        # -- many times (training) ---------------------------------------------------------

        def encode_at(self, u, key, frac, want_jacobian: bool):
            """Features (n, L, F) at normalised points ``u`` (n, 3), point i at keyframe segment
            ``key[i]`` (int64) and fraction ``frac[i]`` (float32), and when asked their Jacobian
            d features / d u (n, L, F, 3) (else None). Fused on a CPU with numba, else torch."""
            if self.can_fuse(u):
                features, jacobian = fused_encoding(u.contiguous(), self.table, self.spec, want_jacobian,
                                                    key.contiguous(), frac.contiguous())
                return features, (jacobian if want_jacobian else None)
            rows, weight, dweight = self.corner_rows(u)
            b = frac[:, None, None, None]
            index = key[:, None, None]
            values = (1.0 - b) * self.table[index, rows] + b * self.table[index + 1, rows]  # (n, L, 8, F)
            return interpolate(values, weight, dweight, want_jacobian)

        def forward(self, x, key, frac):
            """Distance (n,) at collider-frame points ``x`` (n, 3), each at its own time."""
            features, _ = self.encode_at((x - self.centre) / self.radius, key, frac, False)
            return self.body(features.flatten(1)).squeeze(-1) * self.radius

        def value_and_gradient(self, x, key, frac):
            """Distance (n,) and spatial gradient (n, 3), each point at its own time;
            differentiable (training's normal loss backpropagates through it)."""
            features, jacobian = self.encode_at((x - self.centre) / self.radius, key, frac, True)
            distance, g = self.head(features)
            return distance, torch.einsum("nlf,nlfd->nd", g, jacobian)

        # -- one time (queries) -----------------------------------------------------------

        def tables_at(self, k: int, s: float, rate: float):
            """The table at fraction ``s`` of keyframe segment ``k`` and its time derivative
            (``rate`` keyframes per second): two (rows, F) tensors."""
            low, high = self.table[k], self.table[k + 1]
            return low + s * (high - low), (high - low) * rate

        def query_at(self, x, k: int, s: float, rate: float, want_gradient: bool):
            """Distance (n,), and when ``want_gradient`` the spatial gradient (n, 3) and the
            time derivative d distance / dt (n,) (collider units per second), at collider-frame
            points ``x`` (n, 3) at one time (keyframe segment ``k``, fraction ``s``, ``rate``)."""
            table, dtable = self.tables_at(k, s, rate)
            u = (x - self.centre) / self.radius
            if self.can_fuse(x):
                return self._fused_query_at(u, table, dtable, want_gradient)
            rows, weight, dweight = self.corner_rows(u)
            values = table[rows]  # (n, L, 8, F)
            features = (weight[..., None] * values).sum(dim=2)
            if not want_gradient:
                return self.body(features.flatten(1)).squeeze(-1) * self.radius, None, None
            distance, g = self.head(features)
            gradient = torch.einsum("nlf,nlcf,nlcd->nd", g, values, dweight)
            dfeatures = (weight[..., None] * dtable[rows]).sum(dim=2)
            return distance, gradient, (g * dfeatures).sum(dim=(1, 2)) * self.radius

        def _fused_query_at(self, u, table, dtable, want_gradient: bool):
            linears = linear_layers(self.body)
            out = linears[-1]
            n = len(u)
            distance = np.empty(n, np.float32)
            gradient = np.empty((n if want_gradient else 0, 3), np.float32)
            dtime = np.empty(n if want_gradient else 0, np.float32)
            dtable = dtable.detach().contiguous().numpy()
            if not want_gradient:
                dtable = dtable[:0]
            spec = self.spec
            grid_kernels.network_query_timed(
                u.contiguous().numpy(), table.detach().contiguous().numpy(), dtable, spec.resolution, spec.offset,
                spec.rows, spec.dense, spec.smooth, tuple(m.weight.detach().numpy() for m in linears[:-1]),
                tuple(m.bias.detach().numpy() for m in linears[:-1]), out.weight.detach().numpy()[0],
                float(out.bias.detach()[0]), float(self.radius), want_gradient, distance, gradient, dtime)
            if not want_gradient:
                return torch.from_numpy(distance), None, None
            return torch.from_numpy(distance), torch.from_numpy(gradient), torch.from_numpy(dtime)

    return KeyframeGridSDF()
