"""Training data: cached samples of the exact signed distance and gradient near the surface and
in the padded box, and the validation sets (mesh units and frame, seeded)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...engine.meshes import ExactSDF, Mesh
from ..bake import padded_box
from ..progress import progress
from ..sampling import band_sets, box_points, surface_points
from .config import TrainConfig


@dataclass
class TrainingData:
    """Cached samples: points (n, 3) float32, distance (n,) float32, gradient (n, 3) float32
    (exact unit gradient; only meaningful where ``near`` is True)."""

    points: np.ndarray
    distance: np.ndarray
    gradient: np.ndarray
    near: np.ndarray


def default_margin(mesh: Mesh, meters_per_unit: float) -> float:
    """5 % of the largest side, clamped to 5..10 mm (the paper's range), in mesh units."""
    side = float(np.ptp(mesh.vertices, axis=0).max())
    lo, hi = 0.005 / meters_per_unit, 0.010 / meters_per_unit
    return min(max(0.05 * side, lo), hi)


def make_training_data(mesh: Mesh, sdf: ExactSDF, config: TrainConfig, meters_per_unit: float,
                       show_progress: bool = True) -> TrainingData:
    """``config.samples`` points (mesh units and frame) and their exact distances and
    gradients: the near-surface share first (``near`` True), then uniform in the padded box."""
    rng = np.random.default_rng(config.seed)
    margin = config.margin_m / meters_per_unit if config.margin_m else default_margin(mesh, meters_per_unit)
    tight = config.tight_margin_m / meters_per_unit
    n_near = int(config.samples * config.near_fraction)
    n_tight = int(n_near * config.tight_fraction)
    surface, _ = surface_points(mesh, n_near, seed=config.seed + 11)
    noise = rng.uniform(-1.0, 1.0, (n_near, 3))
    noise[:n_tight] *= tight
    noise[n_tight:] *= margin
    lo, hi = padded_box(mesh, config.padding)
    points = np.concatenate([surface + noise, box_points(lo, hi, config.samples - n_near, config.seed + 12)])
    near = np.zeros(len(points), dtype=bool)
    near[:n_near] = True
    distance = np.empty(len(points))
    gradient = np.empty((len(points), 3))
    chunk = 100_000
    with progress(len(points), "exact SDF of samples", "pt", show_progress) as bar:
        for start in range(0, len(points), chunk):
            p = points[start : start + chunk]
            d, closest, face = sdf.query(p)
            distance[start : start + chunk] = d
            gradient[start : start + chunk] = sdf.gradient(p, d, closest, face)
            bar.update(len(p))
    return TrainingData(points.astype(np.float32), distance.astype(np.float32),
                        gradient.astype(np.float32), near)


def validation_sets(mesh: Mesh, sdf: ExactSDF, n: int, seed: int, meters_per_unit: float) -> dict:
    """Points in the +-1 mm and +-10 mm bands with their exact distances (float32)."""
    sets = band_sets(mesh, n, seed + 1, meters_per_unit)
    return {name[len("band_"):]: (p.astype(np.float32), sdf.signed_distance(p).astype(np.float32))
            for name, p in sets.items()}
