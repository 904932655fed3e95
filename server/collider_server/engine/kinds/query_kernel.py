"""The fused CPU query kernel (numba) of a grid network: encoding, ReLU MLP forward and backward
in one pass over blocks of points (inference only; :func:`network_query` and its animated twin
:func:`network_query_timed`). The torch network in :mod:`.neural_grid` is its reference. Part of
the kernels :mod:`.grid_kernels` gathers; the cells' rules are :mod:`.grid_cells`'."""

from __future__ import annotations

import numpy as np

# Absolute imports: benchmarks/neural_query.py --kernel-from loads a copy of this file by path.
from collider_server.engine.kinds.grid_cells import numba

if numba is not None:
    from collider_server.engine.kinds.grid_cells import axis_jit, cell_rows_jit, trilerp_jit

    _jit = numba.njit(cache=True, fastmath=False, nogil=True)

    @numba.njit(cache=True, fastmath=True, nogil=True)
    def _encode_block(ub, m, table, dtable, resolution, offset, rows, dense, smooth, want_jacobian,
                      corner_rows, weights, feature, jac, dfeature):
        """The encoding of a block's ``m`` points ``ub`` (3, block) float32: columns ``0:m`` of
        ``feature`` (L * F, block), when ``want_jacobian`` its Jacobian ``jac`` (3, L * F, block)
        and, when ``dtable`` (the table's time derivative, an animated network's) has rows,
        ``dfeature`` (L * F, block), the encoding of ``dtable``. Level by level, each loop over the block's points
        innermost so that the compiler vectorises it (gathers of the table rows):
        first the cells' corner rows (``corner_rows`` (8, block)) and per-axis weights and
        derivatives (``weights`` (6, block)), then per feature the corners read and
        interpolated axis by axis."""
        width = table.shape[1]
        timed = dtable.shape[0] > 0
        for level in range(resolution.shape[0]):
            r = resolution[level]
            o, level_rows, level_dense = offset[level], rows[level], dense[level]
            for q in range(m):
                # float64 here: a float32 cell position would cost the gradient ~1e-4 of itself
                cx, wx, dx = axis_jit(ub[0, q], r, smooth)
                cy, wy, dy = axis_jit(ub[1, q], r, smooth)
                cz, wz, dz = axis_jit(ub[2, q], r, smooth)
                weights[0, q], weights[1, q], weights[2, q] = wx, wy, wz
                weights[3, q], weights[4, q], weights[5, q] = dx, dy, dz
                c0, c1, c2, c3, c4, c5, c6, c7 = cell_rows_jit(cx, cy, cz, r, level_rows, level_dense)
                corner_rows[0, q], corner_rows[1, q], corner_rows[2, q], corner_rows[3, q] = o + c0, o + c1, o + c2, o + c3
                corner_rows[4, q], corner_rows[5, q], corner_rows[6, q], corner_rows[7, q] = o + c4, o + c5, o + c6, o + c7
            for f in range(width):
                i = level * width + f
                for q in range(m):
                    value, gx, gy, gz = trilerp_jit(
                        table[corner_rows[0, q], f], table[corner_rows[1, q], f], table[corner_rows[2, q], f],
                        table[corner_rows[3, q], f], table[corner_rows[4, q], f], table[corner_rows[5, q], f],
                        table[corner_rows[6, q], f], table[corner_rows[7, q], f],
                        weights[0, q], weights[1, q], weights[2, q])
                    feature[i, q] = value
                    if want_jacobian:
                        jac[0, i, q] = gx * weights[3, q]
                        jac[1, i, q] = gy * weights[4, q]
                        jac[2, i, q] = gz * weights[5, q]
                if timed:
                    for q in range(m):
                        dfeature[i, q] = trilerp_jit(
                            dtable[corner_rows[0, q], f], dtable[corner_rows[1, q], f], dtable[corner_rows[2, q], f],
                            dtable[corner_rows[3, q], f], dtable[corner_rows[4, q], f], dtable[corner_rows[5, q], f],
                            dtable[corner_rows[6, q], f], dtable[corner_rows[7, q], f],
                            weights[0, q], weights[1, q], weights[2, q])[0]

    #: Points per block of the query kernel: the MLP runs on a block at a time, its inner loops
    #: over the block's points (contiguous, so the compiler vectorises them).
    QUERY_BLOCK = 64
    #: Buckets per side of the cube the query kernel sorts its points into first.
    QUERY_BUCKETS = 32

    @_jit
    def _bucket_order(u):
        """A permutation of the points grouping them by cell of a QUERY_BUCKETS^3 grid over
        [-1, 1]^3 (a counting sort, O(n)): points processed together then read nearby table rows,
        which stay in cache; random input order is otherwise twice as slow (measured)."""
        n = u.shape[0]
        side = QUERY_BUCKETS
        key = np.empty(n, np.int64)
        count = np.zeros(side * side * side + 1, np.int64)
        for p in range(n):
            cell = 0
            for axis in range(3):
                c = int((min(max(u[p, axis], -1.0), 1.0) + 1.0) * 0.5 * side)
                cell = cell * side + min(c, side - 1)
            key[p] = cell
            count[cell + 1] += 1
        for cell in range(side * side * side):
            count[cell + 1] += count[cell]
        order = np.empty(n, np.int64)
        for p in range(n):
            order[count[key[p]]] = p
            count[key[p]] += 1
        return order

    @numba.njit(cache=True, fastmath=True, nogil=True)
    def _multiply_add(matrix, source, target):
        """``target[r] += sum_c matrix[r, c] * source[c]`` for the rows ``r`` of ``matrix`` (the
        rows of ``source`` and ``target`` are a block's points): eight sources per pass over a
        target row, so that each load and store of it carries eight multiply-adds."""
        rows, cols = matrix.shape
        block = target.shape[1]
        for r in range(rows):
            t = target[r]
            c = 0
            while c + 8 <= cols:
                m0, m1, m2, m3 = matrix[r, c], matrix[r, c + 1], matrix[r, c + 2], matrix[r, c + 3]
                m4, m5, m6, m7 = matrix[r, c + 4], matrix[r, c + 5], matrix[r, c + 6], matrix[r, c + 7]
                s0, s1, s2, s3 = source[c], source[c + 1], source[c + 2], source[c + 3]
                s4, s5, s6, s7 = source[c + 4], source[c + 5], source[c + 6], source[c + 7]
                for q in range(block):
                    t[q] += (m0 * s0[q] + m1 * s1[q] + m2 * s2[q] + m3 * s3[q]
                             + m4 * s4[q] + m5 * s5[q] + m6 * s6[q] + m7 * s7[q])
                c += 8
            while c < cols:
                mc, sc = matrix[r, c], source[c]
                for q in range(block):
                    t[q] += mc * sc[q]
                c += 1

    @numba.njit(cache=True, fastmath=True, nogil=True)
    def _query_block(u, order, start, m, table, dtable, resolution, offset, rows, dense, smooth, weights,
                     biases, sizes, w_out, b_out, scale, want_gradient, distance, gradient, dtime, part,
                     part_biases, ub, corner_rows, corner_weights, feature, dfeature, jac, act, g, g_next, out,
                     part_row):
        """One block of ``network_query_timed``: its ``m`` points from ``start`` in ``order``,
        with the scratch arrays of its run (``part_row`` (block,): the points' parts); the hidden
        layers packed (:func:`_packed_layers`)."""
        depth = weights.shape[0]
        n_in = feature.shape[0]
        block = out.shape[0]
        for q in range(m):
            p = order[start + q]
            ub[0, q], ub[1, q], ub[2, q] = u[p, 0], u[p, 1], u[p, 2]
        _encode_block(ub, m, table, dtable, resolution, offset, rows, dense, smooth, want_gradient,
                      corner_rows, corner_weights, feature, jac, dfeature)
        # MLP forward, activations kept for the backward pass.
        for k in range(depth):
            w = weights[k, :sizes[k, 0], :sizes[k, 1]]
            for o in range(w.shape[0]):
                act[k, o, :] = biases[k, o]
            if k == 0 and part.shape[0] > 0:  # each point's own first bias (its part's)
                for q in range(m):
                    part_row[q] = part[order[start + q]]
                for o in range(w.shape[0]):  # the block's points innermost, as every loop here
                    a = act[0, o]
                    for q in range(m):
                        a[q] = part_biases[part_row[q], o]
            _multiply_add(w, feature if k == 0 else act[k - 1], act[k])
            for o in range(w.shape[0]):
                s = act[k, o]
                for q in range(block):
                    s[q] = max(s[q], np.float32(0.0))
        last = act[depth - 1]
        out[:] = b_out
        for i in range(sizes[depth - 1, 0]):
            for q in range(block):
                out[q] += w_out[i] * last[i, q]
        for q in range(m):
            distance[order[start + q]] = out[q] * scale
        if not want_gradient:
            return
        # Backward: d output / d activation, layer by layer (ReLU masks), then the encoding.
        for i in range(sizes[depth - 1, 0]):
            g[i, :] = w_out[i]
        for k in range(depth - 1, -1, -1):
            w = weights[k, :sizes[k, 0], :sizes[k, 1]]
            for o in range(w.shape[0]):
                go = g[o]
                for q in range(block):
                    if act[k, o, q] <= 0.0:
                        go[q] = 0.0
            g_next[:w.shape[1], :] = 0.0
            _multiply_add(w.T, g, g_next)
            g[:w.shape[1], :] = g_next[:w.shape[1], :]
        # d output / d u = g . jac, summed over the inputs with the points innermost (into g_next).
        grad_u = g_next[:3]
        grad_u[:] = 0.0
        for i in range(n_in):
            for axis in range(3):
                row, jrow = grad_u[axis], jac[axis, i]
                gi = g[i]
                for q in range(block):
                    row[q] += gi[q] * jrow[q]
        for q in range(m):
            p = order[start + q]
            gradient[p, 0] = grad_u[0, q]
            gradient[p, 1] = grad_u[1, q]
            gradient[p, 2] = grad_u[2, q]
        if dtable.shape[0] > 0:
            for q in range(m):
                gt = 0.0
                for i in range(n_in):
                    gt += g[i, q] * dfeature[i, q]
                dtime[order[start + q]] = gt * scale

    def network_query_timed(u, table, dtable, resolution, offset, rows, dense, smooth, weights, biases, w_out,
                            b_out, scale, want_gradient, distance, gradient, dtime, part=None, part_biases=None):
        """The whole network at normalised points ``u`` (n, 3), fused: encoding, ReLU MLP
        (``weights[k]`` (out, in), ``biases[k]`` (out,)), linear output ``w_out`` (in,),
        ``b_out``; ``distance`` (n,) = output * ``scale``; when ``want_gradient``, ``gradient``
        (n, 3) = d output / d u (the MLP backward through the ReLU masks, times the encoding's
        Jacobian), and when ``dtable`` (the table's time derivative, same shape; (0, F) for a
        static network) has rows, ``dtime`` (n,) = d distance / dt = ``scale`` * d output /
        d features . the encoding of ``dtable``. Points sorted by bucket (``_bucket_order``), then
        in blocks of QUERY_BLOCK points (``_query_block``): the encoding, the MLP forward and
        backward for the whole block, each loop's point index innermost (float32 SIMD); scratch
        arrays allocated once per run of blocks. Inference only. With ``part`` (n,) int64 and
        ``part_biases`` (P, out of the first layer) float32, point p's first layer takes the bias
        ``part_biases[part[p]]`` in place of ``biases[0]`` (the articulated network's parts in one
        call, :mod:`.neural_skinned`)."""
        if part is None:
            part = np.zeros(0, np.int64)
            part_biases = np.zeros((0, weights[0].shape[0]), np.float32)
        # Scratch arrays once per run of blocks (not per block). numba's static schedule hands each
        # thread a contiguous share of the runs, so their number does not balance the threads: the
        # points cost alike.
        blocks = (len(u) + QUERY_BLOCK - 1) // QUERY_BLOCK
        packed, packed_biases, sizes = _packed_layers(weights, biases)
        _network_query(u, table, dtable, resolution, offset, rows, dense, smooth, packed, packed_biases, sizes,
                       w_out, b_out, scale, want_gradient, distance, gradient, dtime, part, part_biases,
                       min(blocks, 8 * numba.get_num_threads()))

    def _packed_layers(weights, biases):
        """The hidden layers ``weights[k]`` (out, in) and ``biases[k]`` (out,) in one array each:
        ``(weights (depth, most out, most in), biases (depth, most out), sizes (depth, 2) int64:
        each layer's (out, in))``, zero beyond each layer's own size, which the kernel never
        reads. One type for every depth: numba compiles the kernel once (a tuple of arrays is a
        type per length, each compiled anew: ~15-25 s of CPU each)."""
        depth = len(weights)
        sizes = np.array([w.shape for w in weights], dtype=np.int64).reshape(depth, 2)
        dtype = np.result_type(*weights)
        packed = np.zeros((depth, int(sizes[:, 0].max()), int(sizes[:, 1].max())), dtype)
        packed_biases = np.zeros((depth, int(sizes[:, 0].max())), np.result_type(*biases))
        for k, (w, b) in enumerate(zip(weights, biases)):
            packed[k, :w.shape[0], :w.shape[1]] = w
            packed_biases[k, :len(b)] = b
        return packed, packed_biases, sizes

    @numba.njit(cache=True, fastmath=True, nogil=True, parallel=True)
    def _network_query(u, table, dtable, resolution, offset, rows, dense, smooth, weights, biases, sizes,
                       w_out, b_out, scale, want_gradient, distance, gradient, dtime, part, part_biases, runs):
        """``network_query_timed`` in ``runs`` runs of blocks, the hidden layers packed
        (:func:`_packed_layers`)."""
        n = u.shape[0]
        n_in = resolution.shape[0] * table.shape[1]
        depth = weights.shape[0]
        widest = max(n_in, 3)  # (g_next's first 3 rows hold the gradient at the end)
        for k in range(depth):
            widest = max(widest, sizes[k, 0])
        block = QUERY_BLOCK
        order = _bucket_order(u)
        blocks = (n + block - 1) // block
        for run in numba.prange(runs):
            ub = np.empty((3, block), np.float32)
            corner_rows = np.zeros((8, block), np.int64)
            corner_weights = np.zeros((6, block), np.float32)
            feature = np.zeros((n_in, block), np.float32)
            dfeature = np.zeros((n_in if dtable.shape[0] > 0 else 0, block), np.float32)
            jac = np.zeros((3, n_in, block), np.float32)
            act = np.zeros((depth, widest, block), np.float32)
            g = np.zeros((widest, block), np.float32)
            g_next = np.zeros((widest, block), np.float32)
            out = np.empty(block, np.float32)
            part_row = np.empty(block, np.int64)
            for b in range(run * blocks // runs, (run + 1) * blocks // runs):
                _query_block(u, order, b * block, min(n, b * block + block) - b * block, table, dtable,
                             resolution, offset, rows, dense, smooth, weights, biases, sizes, w_out, b_out,
                             scale, want_gradient, distance, gradient, dtime, part, part_biases, ub, corner_rows,
                             corner_weights,
                             feature, dfeature, jac, act, g, g_next, out, part_row)

    def network_query(u, table, resolution, offset, rows, dense, smooth, weights, biases, w_out, b_out,
                      scale, want_gradient, distance, gradient, part=None, part_biases=None):
        """``network_query_timed`` of a static network (no time derivative)."""
        network_query_timed(u, table, np.zeros((0, table.shape[1]), table.dtype), resolution, offset, rows,
                            dense, smooth, weights, biases, w_out, b_out, scale, want_gradient, distance,
                            gradient, np.zeros(0, np.float32), part, part_biases)
