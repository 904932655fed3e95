"""The deformation fields of a ``deformed`` network (:mod:`...engine.kinds.neural_deformed`),
fitted to an animation's vertex correspondences: :func:`fit_deformation` at one resolution, and
:func:`fit_deformation_fields`, the preset's rule that picks the resolution by how far the fields
miss the frames."""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from ...engine.animated_meshes import AnimatedMesh
from ...engine.kinds.neural_deformed import trilinear
from ..progress import format_against, progress

#: Weight of the fields' smoothness (squared second differences of the nodes) against the
#: squared misfit at the surface samples, per sample per node: small, it only fills the nodes
#: no sample constrains (away from the surface) and leaves affine motion unpenalised.
SMOOTHNESS = 1e-4
#: Relative residual at which each frame's conjugate gradients stop.
CG_TOLERANCE = 1e-10
#: The deformed preset's field resolutions (cells per side), coarsest first: the fields take the
#: coarsest that misses no frame by more than RESIDUAL_BOUND_MM (99th percentile), else the finest
#: whose fields fit in FIELDS_BYTES_CAP (:func:`fit_deformation_fields`). A finer field follows a
#: larger bend (the spot cow's 30 degrees: 2.81 mm at 16^3, 0.81 mm at 32^3; docs/neural.md).
DEFORMATION_RESOLUTIONS = (16, 32)
RESIDUAL_BOUND_MM = 0.1
#: The most bytes the fields of every frame may take (float32) when a finer resolution is chosen.
FIELDS_BYTES_CAP = 16_000_000


@dataclass(frozen=True)
class DeformationFit:
    """Fitted fields (K, nodes, 3) float32 (normalised units) over the normalised domain
    ``centre``, ``radius`` at ``resolution`` cells per side; per frame, the largest and the
    99th-percentile distance (the animation's units) between where a fitted field sends a surface
    sample of that frame (its vertices and face centroids) and where it is in the rest pose (how
    well the fields follow the motion); and the frames whose solve did not converge."""

    fields: np.ndarray
    residual_max: np.ndarray
    residual_p99: np.ndarray
    centre: tuple
    radius: float
    resolution: int
    unconverged: tuple = ()

    def fits(self, centre, radius: float, resolution: int, frames: int) -> bool:
        """Whether these are the fields of a network of that domain, resolution and frames."""
        return (self.resolution == resolution and len(self.fields) == frames and self.radius == float(radius)
                and np.array_equal(np.asarray(self.centre), np.asarray(centre, np.float64)))

    def summary(self, meters_per_unit: float, bound_mm: float | None = None) -> str:
        """How far the fields miss, in millimetres: the worst frame's 99th percentile (written
        with the digits that show how it compares with ``bound_mm``, when given) and the max."""
        worst = int(self.residual_p99.argmax())
        to_mm = 1000.0 * meters_per_unit
        p99 = self.residual_p99[worst] * to_mm
        shown = f"{p99:.3f}" if bound_mm is None else format_against(p99, bound_mm)
        text = (f"{shown} mm (99th percentile, frame {worst}; max "
                f"{self.residual_max.max() * to_mm:.3f} mm)")
        if self.unconverged:
            text += f"; the solve of {len(self.unconverged)} frames did not converge (first: {self.unconverged[0]})"
        return text


def fit_deformation(animation: AnimatedMesh, centre, radius: float, resolution: int,
                    show_progress: bool = True, stop_above: float | None = None) -> DeformationFit:
    """Per frame k, the inverse deformation field ``W_k`` on a grid of ``resolution`` cells per
    side over the normalised domain (``u = (x - centre) / radius``): the least-squares fit of
    ``W_k(u_k) = u_0 - u_k`` at the frame's vertices and face centroids (frame 0, the rest pose,
    is the identity), smoothed by :data:`SMOOTHNESS`. Each frame starts its conjugate gradients
    from the previous frame's fit. With ``stop_above`` (the animation's units), the fit stops
    after the first frame it misses by more (99th percentile): the fields of the frames so far."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import cg

    centre = np.asarray(centre, np.float64)
    used = np.unique(animation.faces)
    side = resolution + 1
    nodes = side ** 3
    smooth = _second_differences(side)
    smooth = (smooth.T @ smooth).tocsr()

    def samples(frame: np.ndarray) -> np.ndarray:
        u = (frame - centre) / radius
        return np.concatenate([u[used], u[animation.faces].mean(axis=1)])

    rest = samples(animation.frames[0])
    count = len(animation.frames)
    fields = np.zeros((count, nodes, 3))
    residual_max, residual_p99 = np.zeros(count), np.zeros(count)
    unconverged: list[int] = []
    with progress(count, f"deformation fields of {count} frames ({resolution}^3)", "frame",
                  show_progress) as bar:
        for k, frame in enumerate(animation.frames):
            u = samples(frame)
            target = rest - u
            rows, weight, _ = trilinear(u, resolution)
            a = sp.csr_matrix((weight.ravel(), (np.repeat(np.arange(len(u)), 8), rows.ravel())),
                              shape=(len(u), nodes))
            system = (a.T @ a + SMOOTHNESS * len(u) / nodes * smooth).tocsr()
            jacobi = sp.diags(1.0 / np.maximum(system.diagonal(), 1e-30))
            for axis in range(3):
                start = fields[k - 1, :, axis] if k else None
                fields[k, :, axis], status = cg(system, a.T @ target[:, axis], x0=start, rtol=CG_TOLERANCE,
                                                maxiter=5000, M=jacobi)
                if status != 0 and (not unconverged or unconverged[-1] != k):
                    unconverged.append(k)
            miss = np.linalg.norm(a @ fields[k] - target, axis=1) * radius
            residual_max[k], residual_p99[k] = miss.max(), np.percentile(miss, 99)
            bar.update(1)
            if stop_above is not None and residual_p99[k] > stop_above:
                count = k + 1
                break
    return DeformationFit(fields[:count].astype(np.float32), residual_max[:count], residual_p99[:count],
                          tuple(centre.tolist()), float(radius), resolution, tuple(unconverged))


def fields_bytes(frames: int, resolution: int) -> int:
    """Bytes of the float32 fields of ``frames`` frames at ``resolution`` cells per side."""
    return frames * (resolution + 1) ** 3 * 3 * 4


def fit_deformation_fields(animation: AnimatedMesh, centre, radius: float, meters_per_unit: float,
                           show_progress: bool = True, resolutions=DEFORMATION_RESOLUTIONS,
                           bound_mm: float = RESIDUAL_BOUND_MM, cap_bytes: int = FIELDS_BYTES_CAP,
                           fitted: DeformationFit | None = None) -> DeformationFit:
    """The deformed preset's fields of ``animation`` (:func:`fit_deformation`'s arguments): of
    ``resolutions`` (coarsest first) whose fields of every frame take at most ``cap_bytes`` (the
    first whatever its size), the coarsest whose fit misses no frame by more than ``bound_mm``
    (99th percentile, millimetres), else the finest. A resolution that misses stops at the first
    frame it misses (its fit is not kept). ``fitted``, a whole fit of this domain already made
    (the preset trials'), stands for its resolution's."""
    frames = len(animation.frames)
    affordable = [r for r in resolutions if fields_bytes(frames, r) <= cap_bytes] or list(resolutions[:1])
    bound = bound_mm / (1000.0 * meters_per_unit)

    def fit_at(resolution: int, stop_above: float | None = None) -> DeformationFit:
        if fitted is not None and fitted.fits(centre, radius, resolution, frames):
            return fitted
        return fit_deformation(animation, centre, radius, resolution, show_progress, stop_above=stop_above)

    for resolution in affordable[:-1]:
        fit = fit_at(resolution, bound)
        if len(fit.fields) == frames and fit.residual_p99.max() <= bound:
            return fit
        if show_progress:
            print(f"deformation fit: {resolution}^3 fields miss frame {len(fit.fields) - 1} by "
                  f"{fit.summary(meters_per_unit, bound_mm)}, over {bound_mm:g} mm: {affordable[-1]}^3",
                  file=sys.stderr)
    return fit_at(affordable[-1])


def _second_differences(side: int):
    """(rows, side^3) sparse: the second difference of the nodes along each axis."""
    import scipy.sparse as sp

    index = np.arange(side ** 3).reshape(side, side, side)
    parts = []
    for axis in range(3):
        a = np.moveaxis(index, axis, 0)
        low, mid, high = a[:-2].ravel(), a[1:-1].ravel(), a[2:].ravel()
        m = len(mid)
        parts.append(sp.csr_matrix((np.tile([1.0, -2.0, 1.0], m),
                                    (np.repeat(np.arange(m), 3), np.stack([low, mid, high], 1).ravel())),
                                   shape=(m, side ** 3)))
    return sp.vstack(parts).tocsr()
