"""Training of the grid networks and the time-budget schedule: the default preset against the
old default (the paper's network) at an equal number of steps, and the clock logic with injected
times (no test here depends on the machine's speed)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from collider_server.engine.kinds.neural import DEFAULT_PRESET, PRESETS, GridArchitecture
from collider_server.making.evaluation import evaluate_collider
from collider_server.making.training import (
    DEFAULT_STEPS,
    VALIDATIONS_PER_BUDGET,
    RunClock,
    TrainConfig,
    cosine_learning_rate,
    train_neural,
)


@pytest.mark.slow
def test_default_preset_meets_a_bound_the_old_default_missed(load_shared_mesh):
    """The bunny, 300 steps of 4,096 points from 100k cached samples, in its own frame (metres).
    Measured on the loaded 2-core machine (docs/neural.md): the grid default 0.090 mm mean, 0.47 %
    sign errors, 7.8 deg normals in 163 s; the paper's network (the default before it) with the
    same steps, samples and batch 0.182 mm, 4.8 %, 8.6 deg in 534 s, so it misses these bounds
    even given 3.3x the time. (Training both here would take ~12 min of the suite's 5.)"""
    mesh = load_shared_mesh("stanford-bunny.obj")
    assert isinstance(PRESETS[DEFAULT_PRESET], GridArchitecture)
    config = TrainConfig(samples=100_000, steps=300, batch_size=4096, validate_every=100,
                         validation_points=2000, threads=1)
    result = train_neural(mesh, "bunny", config, show_progress=False)
    band = evaluate_collider(result.collider, mesh, points=4000, reconstruction=False,
                             show_progress=False)["band_1mm"]
    assert band["distance_mean_mm"] < 0.13, band
    assert band["sign_errors_percent"] < 1.5, band
    assert band["normal_mean_deg"] < 10.0, band


def test_clock_follows_steps_without_a_budget():
    clock = RunClock(TrainConfig(steps=1000, validate_every=250), start=100.0)
    assert clock.fraction(500, now=1e9) == 0.5  # the clock does not matter
    assert not clock.out_of_time(1e9)
    assert not clock.finished(999, 1e9) and clock.finished(1000, 100.0)
    assert [s for s in range(1, 1001) if clock.validation_due(s, 0.0)] == [250, 500, 750, 1000]
    assert RunClock(TrainConfig(), start=0.0).steps == DEFAULT_STEPS  # neither steps nor minutes


def test_a_budget_without_steps_runs_to_the_end_of_the_clock():
    clock = RunClock(TrainConfig(max_minutes=10.0), start=0.0)
    assert clock.steps is None
    assert clock.fraction(10 * DEFAULT_STEPS, now=60.0) == pytest.approx(0.1)  # only the clock counts
    assert not clock.finished(10 * DEFAULT_STEPS, 599.9) and clock.finished(1, 600.0)


def test_clock_follows_the_budget_and_steps_cap_it_when_given():
    clock = RunClock(TrainConfig(steps=20_000, max_minutes=10.0), start=0.0)
    assert clock.fraction(100, now=300.0) == 0.5  # half the time, far fewer than half the steps
    assert clock.fraction(15_000, now=60.0) == 0.75  # the steps, when further
    assert not clock.out_of_time(599.9) and clock.out_of_time(600.0)
    assert clock.finished(20_000, 60.0) and not clock.finished(19_999, 60.0)
    # Validations every budget / VALIDATIONS_PER_BUDGET seconds, whatever the step rate.
    interval = 600.0 / VALIDATIONS_PER_BUDGET
    assert not clock.validation_due(10, interval - 0.1) and clock.validation_due(10, interval)
    clock.validated(interval)
    assert not clock.validation_due(11, 1.5 * interval) and clock.validation_due(11, 2 * interval)


def test_a_resumed_run_goes_on_where_its_clock_was():
    """Started 300 s before it was resumed at t = 1000: half of a 10-minute budget is left, the
    schedule is half way, no validation is due at once and the bar starts at 300 s."""
    clock = RunClock(TrainConfig(max_minutes=10.0), start=700.0, now=1000.0)
    assert clock.fraction(0, 1000.0) == 0.5
    assert not clock.validation_due(1, 1000.1) and clock.finished(1, 1300.0)
    entered = []
    with clock.progress_bar("train", 0, 1000.0, enabled=False) as bar:
        bar.update = entered.append
        clock.advance(bar, 1000.5)
        assert entered == [] and clock.advance(bar, 1001.0) and entered == [1]
    assert clock.shown == 301


def test_progress_bar_counts_seconds_of_the_budget():
    updates = []
    bar = SimpleNamespace(update=updates.append)
    clock = RunClock(TrainConfig(max_minutes=1.0), start=0.0)
    moved = [clock.advance(bar, now) for now in (0.4, 1.2, 1.9, 30.5, 75.0)]  # past the budget: 60 s
    assert updates == [1, 29, 30] and sum(updates) == 60
    assert moved == [False, True, False, True, True]
    steps = RunClock(TrainConfig(steps=10), start=0.0)
    assert steps.advance(bar, 123.0) and updates[-1] == 1


def test_a_budget_is_used_to_its_end_and_the_summary_says_what_it_bought(analytic_shape):
    """A 3-second budget and no step count: the run trains until the clock ends (far more steps
    than a validation interval), validates its last step, and its summary names the budget."""
    sphere = analytic_shape("sphere").mesh
    small = {"levels": 4, "base_resolution": 4, "max_resolution": 32, "table_log2": 12}
    config = TrainConfig(preset="grid", architecture=small, samples=5000, batch_size=256,
                         validation_points=500, max_minutes=0.05, threads=1)
    result = train_neural(sphere, "s", config, show_progress=False)
    assert 3.0 <= result.seconds < 3.0 + 2.0  # the budget, plus at most the last step and validation
    assert result.history[-1]["step"] == result.steps > 30
    assert len(result.history) >= VALIDATIONS_PER_BUDGET // 2  # every 0.1 s, whatever the step rate
    best = min(result.history, key=lambda h: h["1mm"])
    assert (result.best_step, result.best_validation_mm) == (best["step"], best["1mm"])
    summary = result.summary()
    assert summary.startswith(f"the 0.05-minute budget bought {result.steps:,} steps (")
    assert f"best of {len(result.history)} validations: step {result.best_step:,}," in summary
    capped = train_neural(sphere, "s", TrainConfig(**{**config.__dict__, "steps": 7}), show_progress=False)
    assert summary.count("M samples") == (result.steps * 256 >= 1e6)
    assert capped.steps == 7 and capped.seconds < 3.0
    assert "7 steps (1,792 samples" in capped.summary() and "the step cap, reached after" in capped.summary()


def test_the_model_records_the_threads_that_trained_it(analytic_shape):
    """A grid network trains in the kernels' threads (torch keeps one): the model says so."""
    from collider_server.engine.kinds import grid_kernels

    sphere = analytic_shape("sphere").mesh
    small = {"levels": 4, "base_resolution": 4, "max_resolution": 32, "table_log2": 12}
    config = TrainConfig(preset="grid", architecture=small, samples=5000, steps=2, batch_size=256,
                         validation_points=500, threads=2)
    name = train_neural(sphere, "s", config, show_progress=False).collider.info.settings["training"]["device_name"]
    threads = grid_kernels.threads() if grid_kernels.available() else 2  # (numba: at most its cores)
    assert name.endswith(f"CPU, {threads} thread{'s' if threads > 1 else ''}"), name


def test_cosine_learning_rate_ends_at_the_final_rate():
    assert cosine_learning_rate(0.0, 1e-2, 1e-4) == pytest.approx(1e-2)
    assert cosine_learning_rate(1.0, 1e-2, 1e-4) == pytest.approx(1e-4)
    assert cosine_learning_rate(2.0, 1e-2, 1e-4) == pytest.approx(1e-4)
    assert 1e-4 < cosine_learning_rate(0.5, 1e-2, 1e-4) < 1e-2


def test_presets_choose_their_learning_rates_and_overrides_must_fit():
    assert TrainConfig(preset="grid").resolved_learning_rates() == (1e-2, 1e-4)
    assert TrainConfig(preset="paper-bunny").resolved_learning_rates() == (1e-3, 1e-5)
    assert TrainConfig(preset="grid", learning_rate=3e-3).resolved_learning_rates() == (3e-3, 1e-4)
    with pytest.raises(ValueError, match="do not fit preset 'grid'"):
        TrainConfig(preset="grid", architecture={"fourier_features": 8}).check()
    with pytest.raises(ValueError, match="learning_rate must be a finite number"):
        TrainConfig(learning_rate=float("nan")).check()


def test_a_grid_network_trains_and_saves(tmp_path, analytic_shape):
    from collider_server.engine.modelfile import load_collider, save_collider

    sphere = analytic_shape("sphere").mesh
    small = {"levels": 4, "base_resolution": 4, "max_resolution": 32, "table_log2": 12}
    result = train_neural(sphere, "s", TrainConfig(preset="grid", architecture=small, samples=5000, steps=20,
                                                   batch_size=512, validate_every=10, validation_points=500,
                                                   threads=1), show_progress=False)
    assert [h["step"] for h in result.history] == [10, 20]
    assert result.collider.info.settings["architecture"]["encoding"] == "grid"
    path = save_collider(result.collider, tmp_path / "s.safetensors")
    loaded = load_collider(path, "cpu")
    points = np.random.default_rng(0).uniform(-0.05, 0.05, (100, 3))
    np.testing.assert_allclose(loaded.query(points).distance, result.collider.query(points).distance, atol=1e-5)


def test_a_grid_network_trains_on_cuda_as_on_the_cpu(cuda, analytic_shape):
    """The same short run of the default preset's kind on CUDA (the torch path) and on the CPU
    (the fused kernels): both learn the sphere alike; the model records where it was trained."""
    sphere = analytic_shape("sphere").mesh
    small = {"levels": 6, "base_resolution": 8, "max_resolution": 96, "table_log2": 14}
    config = TrainConfig(preset="grid", architecture=small, samples=40_000, steps=300, batch_size=4096,
                         validate_every=100, validation_points=2000, threads=2)
    runs = {device: train_neural(sphere, "s", config, device=device, show_progress=False)
            for device in ("cpu", cuda)}
    assert runs[cuda].collider.info.settings["training"]["device"] == cuda
    assert runs[cuda].collider.info.settings["training"]["device_name"]
    cpu_mm, gpu_mm = runs["cpu"].best_validation_mm, runs[cuda].best_validation_mm
    assert gpu_mm < 2 * cpu_mm + 0.05, (cpu_mm, gpu_mm)
