"""4 x 4 transforms as a joint's translation, rotation and scale (TRS): the one decomposition
the character readers (glTF node matrices, USD joint matrices) share."""

from __future__ import annotations

import numpy as np

from ..engine.skinning import trs_matrices


def matrix_trs(m: np.ndarray, atol: float = 1e-6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(translation (3,), rotation (4,) unit quaternion (x, y, z, w), scale (3,))`` of a 4 x 4
    column-vector transform ``m`` = T R S, float64; a reflection becomes a negative x scale.
    ValueError when ``m`` is singular or holds a shear or projection, which TRS cannot (checked
    by rebuilding ``m`` to ``atol`` times its largest entry)."""
    m = np.asarray(m, dtype=np.float64)
    linear = m[:3, :3]
    scale = np.linalg.norm(linear, axis=0)
    if np.any(scale <= 0):
        raise ValueError("a singular matrix (a zero scale)")
    if np.linalg.det(linear) < 0:
        scale[0] = -scale[0]
    rotation = matrix_quaternion(linear / scale)
    translation = m[:3, 3].copy()
    rebuilt = trs_matrices(translation[None], rotation[None], scale[None])[0]
    if not np.allclose(rebuilt, m, atol=atol * max(1.0, float(np.abs(m).max()))):
        raise ValueError("a matrix with shear or projection, which a joint's TRS cannot hold")
    return translation, rotation, scale


def matrix_quaternion(r: np.ndarray) -> np.ndarray:
    """The unit quaternion (x, y, z, w) of a rotation matrix (3, 3) (Shepperd's method: the
    largest of the four candidates' divisors, so no division by a vanishing number)."""
    trace = np.trace(r)
    if trace > 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
    q = np.asarray(q, dtype=np.float64)
    return q / np.linalg.norm(q)
