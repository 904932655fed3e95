"""benchmarks/animated_neural.py: its voxel keyframe figures come from exact distances at the
cell corners around each point, not from a baked collider; they must be the baked collider's
answers (the shipped arm, a 24^3 x 5 keyframe bake, random times), and its accuracy figures must
see a wrong velocity."""

from __future__ import annotations

import numpy as np
from tests.conftest import REPO_ROOT, load_benchmark

from collider_server.making.animation_files import load_animation


def benchmark():
    return load_benchmark("animated_neural")


def arm():
    folder = REPO_ROOT / "examples" / "animations"
    return load_animation(folder / "arm.obj", folder / "arm.pc2", 24.0, loop=True)


def test_the_voxel_emulation_is_the_baked_voxel_collider():
    assert benchmark().check_voxel_emulation(arm(), seed=3) < 1e-6  # metres: float32 storage only


def test_accuracy_figures_see_the_surface_velocity():
    """The exact animated kind scores zero error everywhere; the same with its velocity doubled
    scores a normal speed error as large as the surface's speed."""
    from collider_server.making.bake import bake_animated_collider

    module = benchmark()
    animation = arm()
    exact = bake_animated_collider(animation, "mesh", "arm", show_progress=False)
    figures = module.accuracy(exact, animation, times=3, points=600, seed=5)
    assert figures["distance_max_mm"] < 1e-6 and figures["sign_errors_percent"] == 0.0
    assert figures["normal_speed_error_p99_mm_s"] < 1e-3
    evaluate_at = exact.evaluate_at
    exact.evaluate_at = lambda *a: (lambda d, g, v: (d, g, None if v is None else 2 * v))(*evaluate_at(*a))
    doubled = module.accuracy(exact, animation, times=3, points=600, seed=5)
    assert doubled["normal_speed_error_mean_mm_s"] > 10.0
    assert np.isclose(doubled["distance_mean_mm"], figures["distance_mean_mm"])
