"""How a model file stores a grid network's feature table (``GridArchitecture.table_dtype``):
float16, float32, or 8 bits (the hashed levels as int8 codes with one scale per level and
feature, on a straight line (``int8``) or a mu-law curve (``int8-mu``), the dense levels as
float16). :func:`pack_table` writes, :func:`unpack_table` reads."""

from __future__ import annotations

import numpy as np

from .grid_architecture import GridArchitecture

#: The quantile of a hashed level's |feature values| that its 8-bit codes reach (``int8``); the
#: rarer larger values are clipped to it. Scaling by the maximum instead left most values a
#: coarser step (docs/neural.md: "8-bit tables").
INT8_QUANTILE = 0.999
#: The mu of ``int8-mu``'s curve: a code's step grows with its value, from 0.18 of the straight
#: line's at zero to 3 times it at the largest. A table's values crowd near zero (a fifth of a
#: trained walker's codes are within 2 steps of it), where the finer steps take two thirds off the
#: error the 8 bits add (docs/neural.md, "8-bit codes on a curve"; mu 5-40 alike).
INT8_MU = 15.0
#: The 8-bit table formats: each's mu (0: the straight line).
_CURVES = {"int8": 0.0, "int8-mu": INT8_MU}


def pack_table(table: np.ndarray, arch: GridArchitecture) -> dict[str, np.ndarray]:
    """The feature table (..., rows, F) float32 as a model file stores it (``arch.table_dtype``):
    ``{"table": ...}`` in float16 or float32, or for ``int8`` the dense levels' rows as float16
    (``table_dense``: the coarse levels, few rows, to which the distance is most sensitive) and
    the hashed levels' rows as int8 codes (``table_codes``) times one float32 scale per level and
    feature (``table_scales`` (hashed levels, F)): the value is ``code * scale`` (``int8``; for
    ``int8-mu`` :func:`_decode`'s curve through the same ends), the scale the level's
    :data:`INT8_QUANTILE` of |value| / 127. :func:`unpack_table` inverts it."""
    if arch.table_dtype not in _CURVES:
        return {"table": table.astype(arch.table_dtype)}
    mu = _CURVES[arch.table_dtype]
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
        steps = _encode(flat / np.where(peak > 0, peak, 1.0), mu)
        coded = (np.abs(steps - np.rint(steps)) < 1e-3).all(axis=0)
        scale = np.where(coded, peak, scale)
        scale = np.where(scale > 0, scale, np.float32(1.0))  # an all-zero level: any scale
        codes.append(np.rint(_encode(block / scale, mu)).astype(np.int8))
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
    if arch.table_dtype not in _CURVES:
        return tensors
    mu = _CURVES[arch.table_dtype]
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
            table[..., rows, :] = _decode(codes[..., code_at:code_at + n, :], mu) * scales[level]
            code_at += n
            level += 1
    tensors["table"] = table
    return tensors


def _level_slices(arch: GridArchitecture) -> list[tuple[slice, bool]]:
    """Each level's rows of the table and whether the level is dense."""
    stops = np.cumsum(arch.level_rows())
    return [(slice(int(stop - n), int(stop)), dense)
            for stop, n, dense in zip(stops, arch.level_rows(), arch.level_dense())]


def _encode(steps: np.ndarray, mu: float) -> np.ndarray:
    """Values in straight-line steps (value / scale) to codes before rounding, in [-127, 127]:
    the same for ``mu`` 0, else on the mu-law curve through (0, 0) and (127, 127)."""
    steps = np.clip(steps, -127.0, 127.0)
    if not mu:
        return steps
    return np.sign(steps) * (127.0 * np.log1p(mu * np.abs(steps) / 127.0) / np.log1p(mu))


def _decode(codes: np.ndarray, mu: float) -> np.ndarray:
    """:func:`_encode`'s inverse, float32: int8 codes to straight-line steps."""
    if not mu:
        return codes.astype(np.float32)
    codes = codes.astype(np.float64)  # float64, so that code 127 is 127.0 exactly (saving again keeps the scale)
    return (np.sign(codes) * (127.0 / mu) * np.expm1(np.abs(codes) * (np.log1p(mu) / 127.0))).astype(np.float32)
