"""Fused CPU kernels (numba) of the grid networks, gathered: the encoding for training
(:mod:`.encoding_kernels`), the query kernel (:mod:`.query_kernel`), the deformed network's warp
(:mod:`.warp_kernel`), and the kernels' thread count. Callers use ``grid_kernels.NAME``.

One pass per point computes, at every level, the 8 corner rows, their (smoothstep or trilinear)
weights and weight derivatives, and accumulates the features and their Jacobian: no (n, L, 8)
temporaries, which is what makes the pure-torch encoding memory-bound on a CPU (about 20 s per
1M points on 2 cores against well under 1 s here). The backward pass scatters the features' and
the Jacobian's gradients into the table, one level per thread (levels own disjoint rows, so no
two threads write the same row). The torch encoding in :mod:`.neural_grid` is the reference these
are tested against, and the path on CUDA.

Layout (shared with the torch code): ``u`` (n, 3) normalised coordinates; ``table`` (rows, F)
float32, level ``l`` at rows ``offset[l] : offset[l] + rows[l]``; a level's cells, corner rows
(dense or hashed) and weights follow :mod:`.grid_cells` (its numba helpers, compiled from the same
rules as the torch code's).
"""

from __future__ import annotations

from .grid_cells import numba

__all__ = ["available", "set_threads", "threads"]

if numba is not None:  # the kernels, gathered here (callers use grid_kernels.NAME)
    from .encoding_kernels import encode_keyframes, encode_keyframes_backward
    from .query_kernel import QUERY_BLOCK, QUERY_BUCKETS, network_query, network_query_timed
    from .warp_kernel import warp

    __all__ += ["QUERY_BLOCK", "QUERY_BUCKETS", "encode_keyframes",
                "encode_keyframes_backward", "network_query", "network_query_timed", "warp"]


def available() -> bool:
    """Whether the fused kernels can run (numba is installed)."""
    return numba is not None


def threads() -> int:
    """Threads of the kernels (numba's pool; 1 without numba, which runs no kernel)."""
    return numba.get_num_threads() if numba is not None else 1


def set_threads(threads: int) -> None:
    """Threads of the kernels (numba's pool; at most the cores numba found)."""
    if numba is not None:
        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
