"""Which animated preset an animation trains (``collider train --animation`` without
``--preset``): :func:`choose_animated_preset` trains each candidate briefly and takes the one
that measures better, rather than judging a preset by a threshold on one of its parts (the
deformation fit's miss, which on a cow bending by 30 degrees sat at its 0.1 mm bound and chose
the worse preset: issue 34)."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace

from ...engine.animated_meshes import AnimatedMesh, ExactAtTimes
from ..evaluation import animated_error_figures
from ..sampling import random_times
from .config import TrainConfig
from .data import normalisation
from .deformation import DEFORMATION_RESOLUTIONS, DeformationFit, fit_deformation
from .loop import train_animated_neural

#: The candidates, in the order they are measured (the first wins a tie).
CANDIDATES = ("deformed", "keyframes")
#: Steps of each candidate's trial (fewer when the run itself has fewer): a few hundred, where the
#: presets' errors already differ as they do after minutes (issue 34's cow: 0.039 against 0.104 mm).
TRIAL_STEPS = 300
#: Samples of a trial's training set (at most the run's): the exact distances cost more than the steps.
TRIAL_SAMPLES = 100_000
#: With a time budget, each trial trains at most this share of it (the whole choice is charged to it).
TRIAL_SHARE = 0.1
#: Held-out random times and points per time (+-1 mm band) every candidate is measured on.
TRIAL_TIMES = 8
TRIAL_POINTS = 1000


@dataclass(frozen=True)
class TrialFigures:
    """One candidate's trial: steps trained and, at the held-out points, the mean distance error
    (mm) and the sign errors beyond 0.2 mm (percent) in the +-1 mm band; of the steps, those of
    the keyframes preset's warm start (the static grid on the first frame, as the run trains it)."""

    preset: str
    steps: int
    mean_mm: float
    sign_percent: float
    warm_steps: int = 0

    def text(self) -> str:
        return f"{self.mean_mm:.3f} mm mean / {self.sign_percent:.2f} % sign after {self.steps} steps"


@dataclass(frozen=True)
class PresetChoice:
    """The animated preset :func:`choose_animated_preset` picked, why (one line), every
    candidate's figures, the seconds the choice took, and the deformation fit it made (the preset
    rule's coarsest resolution; a deformed run reuses it where the rule takes that resolution)."""

    preset: str
    reason: str
    trials: tuple[TrialFigures, ...]
    seconds: float
    fit: DeformationFit | None = None


def better(trials) -> TrialFigures:
    """The trial that measured better: the lower mean distance error in the +-1 mm band (the
    figure training validates by; sign errors go with it), the first on a tie."""
    return min(trials, key=lambda trial: trial.mean_mm)


def choose_animated_preset(animation: AnimatedMesh, config: TrainConfig, meters_per_unit: float,
                           device: str | None = None, show_progress: bool = True,
                           trial_steps: int = TRIAL_STEPS) -> PresetChoice:
    """Train each of :data:`CANDIDATES` for ``trial_steps`` steps (``config``'s settings,
    fewer samples; each within :data:`TRIAL_SHARE` of ``config.max_minutes``; each as its run
    will train, the keyframes preset with its warm start over the trial's steps) on ``animation``
    (its units and frame), measure every one at the same held-out points and times
    (:data:`TRIAL_TIMES` random times, :data:`TRIAL_POINTS` +-1 mm band points each, seeds apart
    from training's) and take the :func:`better`."""
    started = time.monotonic()
    steps = min(trial_steps, config.step_cap() or trial_steps)
    trial_config = replace(config, steps=steps, samples=min(config.samples, TRIAL_SAMPLES), architecture={},
                           validation_points=min(config.validation_points, 2000),
                           max_minutes=None if config.max_minutes is None else config.max_minutes * TRIAL_SHARE)
    held_out = random_times(animation.timeline, TRIAL_TIMES, config.seed + 300)
    exact = ExactAtTimes(animation, keep=1)
    if show_progress:
        print(f"measuring presets {' and '.join(CANDIDATES)}: {steps} steps each, then the better trains",
              file=sys.stderr)
    trials, fit = [], None
    for preset in CANDIDATES:
        extra = {}
        trial = replace(trial_config, preset=preset)
        if preset == "deformed":
            # The trial's fields are the preset rule's coarsest (DEFORMATION_RESOLUTIONS): a few
            # hundred steps end far above either floor, and a finer fit takes minutes (the spot
            # cow's 32^3: 6 on a loaded machine), spent only by a run that trains the preset.
            fit = fit_deformation(animation, *normalisation(animation, config.padding), DEFORMATION_RESOLUTIONS[0],
                                  show_progress)
            extra["deformation"] = fit
            trial = replace(trial, architecture={"deformation_resolution": fit.resolution})
        result = train_animated_neural(animation, f"{preset} (trial)", trial,
                                       meters_per_unit=meters_per_unit, device=device,
                                       show_progress=show_progress, **extra)
        band = animated_error_figures(result.collider, animation, held_out, TRIAL_POINTS, config.seed + 300,
                                      sets=("band_1mm",), exact=exact)["band_1mm"]
        trials.append(TrialFigures(preset, result.steps, band["distance_mean_mm"], band["sign_errors_percent"],
                                   result.warm_steps))
    chosen = better(trials)
    others = ", ".join(f"{t.preset} {t.mean_mm:.3f} / {t.sign_percent:.2f} %" for t in trials if t is not chosen)
    seconds = time.monotonic() - started
    # The deformed preset's floor, known before any step: how far its fields miss the frames.
    floor = ("" if fit is None else
             f"deformed's {fit.resolution}^3 fields miss the frames by {fit.summary(meters_per_unit)}; ")
    reason = (f"preset {chosen.preset}: {chosen.text()}, {others} (+-1 mm band, {TRIAL_TIMES} held-out times; "
              f"{floor}measured in {seconds:.0f} s; --preset to choose)")
    return PresetChoice(chosen.preset, reason, tuple(trials), seconds, fit if chosen.preset == "deformed" else None)


def remaining_minutes(config: TrainConfig, choice: PresetChoice) -> float | None:
    """The run's budget (minutes) once the choice's time is charged to it: at least half of it is
    left to the run (a budget too small for the trials' data still trains)."""
    if config.max_minutes is None:
        return None
    return max(config.max_minutes - choice.seconds / 60.0, 0.5 * config.max_minutes)
