"""The bridge from torch to the fused numba encoding (:mod:`.encoding_kernels`): an autograd
function whose forward runs the kernel and whose backward scatters the gradients into the
feature tables (the positions are data, not parameters: no gradient flows to them). One bridge
for the static network (one table) and the keyframe network (K tables, each point at its own
time)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import grid_kernels


@dataclass(frozen=True)
class KernelSpec:
    """The grid layout as the fused kernels take it (numpy arrays; see :mod:`.grid_cells`)."""

    resolution: np.ndarray
    offset: np.ndarray
    rows: np.ndarray
    dense: np.ndarray
    smooth: bool
    levels: int
    features: int


def _encoding_function():
    import torch

    class FusedEncoding(torch.autograd.Function):
        """The numba keyframe encoding as an autograd function: gradients reach the tables."""

        @staticmethod
        def forward(ctx, u, key, frac, tables, spec: KernelSpec, want_jacobian: bool):
            u_np = u.detach().numpy()
            n = len(u_np)
            features = np.empty((n, spec.levels, spec.features), np.float32)
            jacobian = np.empty((n if want_jacobian else 0, spec.levels, spec.features, 3), np.float32)
            grid_kernels.encode_keyframes(u_np, key.numpy(), frac.numpy(), tables.detach().numpy(),
                                          spec.resolution, spec.offset, spec.rows, spec.dense, spec.smooth,
                                          want_jacobian, features, jacobian)
            ctx.save_for_backward(u, key, frac, tables)
            ctx.spec, ctx.want_jacobian = spec, want_jacobian
            return torch.from_numpy(features), torch.from_numpy(jacobian)

        @staticmethod
        def backward(ctx, grad_features, grad_jacobian):
            # Autograd hands zeros for an output the loss does not use (materialised gradients),
            # so both are tensors; without a Jacobian the second has 0 rows, like the output.
            u, key, frac, tables = ctx.saved_tensors
            spec = ctx.spec
            grad_tables = np.zeros(tuple(tables.shape), np.float32)
            grid_kernels.encode_keyframes_backward(
                u.detach().numpy(), key.numpy(), frac.numpy(), spec.resolution, spec.offset, spec.rows,
                spec.dense, spec.smooth, grad_features.contiguous().numpy(), grad_jacobian.contiguous().numpy(),
                ctx.want_jacobian, grad_tables)
            return None, None, None, torch.from_numpy(grad_tables), None, None

    return FusedEncoding


_function = None


def fused_encoding(u, tables, spec: KernelSpec, want_jacobian: bool, key=None, frac=None):
    """Features (n, L, F) float32 of normalised points ``u`` (n, 3) (torch, CPU, contiguous) and
    their Jacobian d features / d u (n, L, F, 3) (0 rows unless ``want_jacobian``) by the fused
    kernels, differentiable with respect to the tables: ``tables`` (rows, F), or (K, rows, F)
    keyframe tables with point i at segment ``key[i]`` (int64) and fraction ``frac[i]``
    (float32) between tables ``key[i]`` and ``key[i] + 1``."""
    global _function
    if _function is None:  # built on first use: the module imports without torch
        _function = _encoding_function()
    if key is None:  # one table: every point in it (segment 0, fraction 0 reads table 0 only)
        import torch

        key, frac = torch.zeros(len(u), dtype=torch.int64), torch.zeros(len(u), dtype=torch.float32)
        tables = tables.unsqueeze(0)
    return _function.apply(u, key, frac, tables, spec, want_jacobian)
