"""Training data: cached samples of the exact signed distance and gradient near the surface and
in the padded box, and the validation sets (mesh units and frame, seeded)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...engine.animated_meshes import AnimatedMesh, ExactAtTimes
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
    #: An animation's samples: each one's time, seconds in [0, duration] (float64); None: static.
    times: np.ndarray | None = None


def normalisation(shape: Mesh | AnimatedMesh, padding: float) -> tuple[np.ndarray, float]:
    """The centre (3,) and radius of a network's normalised coordinates ``u = (x - centre) /
    radius`` for ``shape`` (its units and frame): the padded box's centre and half its largest
    side, so that the box lies in [-1, 1]^3."""
    lo, hi = padded_box(shape, padding)
    return 0.5 * (lo + hi), 0.5 * float((hi - lo).max())


def default_margin(mesh: Mesh | AnimatedMesh, meters_per_unit: float) -> float:
    """5 % of the largest side, clamped to 5..10 mm (the paper's range), in mesh units."""
    vertices = mesh.frames[0] if isinstance(mesh, AnimatedMesh) else mesh.vertices
    side = float(np.ptp(vertices, axis=0).max())
    lo, hi = 0.005 / meters_per_unit, 0.010 / meters_per_unit
    return min(max(0.05 * side, lo), hi)


def make_training_data(mesh: Mesh, sdf: ExactSDF, config: TrainConfig, meters_per_unit: float,
                       show_progress: bool = True, box=None) -> TrainingData:
    """``config.samples`` points (mesh units and frame) and their exact distances and
    gradients: the near-surface share first (``near`` True), then uniform in ``box`` (lo, hi;
    default the mesh's padded box)."""
    margin = config.margin_m / meters_per_unit if config.margin_m else default_margin(mesh, meters_per_unit)
    points, near = sample_points(mesh, config.samples, config, margin, meters_per_unit, config.seed,
                                 padded_box(mesh, config.padding) if box is None else box)
    distance = np.empty(len(points))
    gradient = np.empty((len(points), 3))
    chunk = 100_000
    with progress(len(points), "exact SDF of samples", "pt", show_progress) as bar:
        for start in range(0, len(points), chunk):
            p = points[start : start + chunk]
            distance[start : start + chunk], gradient[start : start + chunk] = exact_values(sdf, p)
            bar.update(len(p))
    return TrainingData(points.astype(np.float32), distance.astype(np.float32),
                        gradient.astype(np.float32), near)


def sample_points(mesh: Mesh, n: int, config: TrainConfig, margin: float, meters_per_unit: float, seed: int,
                  box) -> tuple[np.ndarray, np.ndarray]:
    """``n`` sample points (float64, mesh units and frame): ``config.near_fraction`` of them near
    ``mesh``'s surface (surface samples plus uniform noise within ``margin``, a share
    ``tight_fraction`` within ``tight_margin_m``) first, the rest uniform in ``box`` (lo, hi);
    and the mask of the near ones."""
    rng = np.random.default_rng(seed)
    tight = config.tight_margin_m / meters_per_unit
    n_near = int(n * config.near_fraction)
    n_tight = int(n_near * config.tight_fraction)
    surface, _ = surface_points(mesh, n_near, seed=seed + 11)
    noise = rng.uniform(-1.0, 1.0, (n_near, 3))
    noise[:n_tight] *= tight
    noise[n_tight:] *= margin
    lo, hi = box
    points = np.concatenate([surface + noise, box_points(lo, hi, n - n_near, seed + 12)])
    near = np.zeros(len(points), dtype=bool)
    near[:n_near] = True
    return points, near


def exact_values(sdf: ExactSDF, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact signed distance (n,) and unit gradient (n, 3) at ``points``."""
    d, closest, face = sdf.query(points)
    return d, sdf.gradient(points, d, closest, face)


#: Samples per distinct time of an animation's training set: each time costs an exact SDF (an
#: AABB tree of the interpolated mesh), so times are shared by a few thousand points, and there
#: are many of them (250 for the default million samples) at random, not at the frames; at least
#: MIN_TIMES (a small set with a few times only would fit those times and no other).
SAMPLES_PER_TIME = 4000
MIN_TIMES = 64


def make_animated_training_data(animation: AnimatedMesh, config: TrainConfig, meters_per_unit: float,
                                show_progress: bool = True) -> TrainingData:
    """``config.samples`` points (the animation's units and frame) at random times, uniform over
    its duration (seconds), with the exact distances and gradients of the interpolated mesh at
    their time (:class:`ExactAtTimes`): per time, near-surface samples first, then uniform in the
    padded box of every frame."""
    margin = config.margin_m / meters_per_unit if config.margin_m else default_margin(animation, meters_per_unit)
    box = padded_box(animation, config.padding)
    count = max(min(MIN_TIMES, config.samples // 100), config.samples // SAMPLES_PER_TIME, 2)
    sizes = np.full(count, config.samples // count)
    sizes[: config.samples - sizes.sum()] += 1
    parts = []
    with progress(config.samples, f"exact SDF of samples at {count} times", "pt", show_progress) as bar:
        for (t, sdf, seed), n in zip(random_times(animation, count, config.seed, 1000), sizes, strict=True):
            points, near = sample_points(sdf.mesh, int(n), config, margin, meters_per_unit, seed, box)
            distance, gradient = exact_values(sdf, points)
            parts.append((points, distance, gradient, near, np.full(len(points), t)))
            bar.update(int(n))
    points, distance, gradient, near, when = (np.concatenate(a) for a in zip(*parts))
    return TrainingData(points.astype(np.float32), distance.astype(np.float32), gradient.astype(np.float32),
                        near, when)


def animated_validation_sets(animation: AnimatedMesh, n: int, seed: int, meters_per_unit: float,
                             times: int = 16) -> dict:
    """Points in the +-1 mm and +-10 mm bands at ``times`` random times (seconds, uniform over the
    duration; ``n`` points per band in all): ``{band: (points float32, distance float32, times
    float64)}``, exact distances of the interpolated mesh at each point's time."""
    per_time = max(1, n // times)
    parts: dict[str, list] = {}
    for t, sdf, seed_at in random_times(animation, times, seed, 10):
        for name, p in band_sets(sdf.mesh, per_time, seed_at, meters_per_unit).items():
            parts.setdefault(name[len("band_"):], []).append((p, sdf.signed_distance(p), np.full(len(p), t)))
    return {name: (np.concatenate([a[0] for a in sets]).astype(np.float32),
                   np.concatenate([a[1] for a in sets]).astype(np.float32),
                   np.concatenate([a[2] for a in sets]))
            for name, sets in parts.items()}


def random_times(animation: AnimatedMesh, count: int, seed: int, stride: int):
    """``count`` times (seconds, uniform over the animation's duration, drawn with ``seed``),
    each as ``(t, exact SDF of the interpolated mesh at t, t's own seed)``: the i-th time's seed
    is ``seed + stride * (i + 1)``, so that every time samples its points independently."""
    when = np.random.default_rng(seed).uniform(0.0, animation.timeline.duration_s, count)
    exact = ExactAtTimes(animation, keep=1)
    for i, t in enumerate(when):
        sdf, _, _ = exact.at(float(t))
        yield t, sdf, seed + stride * (i + 1)


def validation_sets(mesh: Mesh, sdf: ExactSDF, n: int, seed: int, meters_per_unit: float) -> dict:
    """Points in the +-1 mm and +-10 mm bands with their exact distances (float32)."""
    sets = band_sets(mesh, n, seed + 1, meters_per_unit)
    return {name[len("band_"):]: (p.astype(np.float32), sdf.signed_distance(p).astype(np.float32))
            for name, p in sets.items()}
