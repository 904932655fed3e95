"""What a training run is asked to do: :class:`TrainConfig`, with the preset's learning rates
and normal weight."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from ...engine.kinds.neural import ANIMATED_PRESETS, DEFAULT_PRESET, PRESETS, Architecture, GridArchitecture
from ...engine.kinds.neural_keyframes import KeyframeGridArchitecture

#: Adam's learning rate, initial and final (cosine decay), per kind of network: feature tables
#: learn best at the large rate instant-NGP uses; the paper's MLP at 1e-3.
LEARNING_RATES = {"fourier": (1e-3, 1e-5), "grid": (1e-2, 1e-4)}
#: Weight of the 1 - cos(normal) term per kind of network (docs/neural.md has the measurements).
NORMAL_WEIGHTS = {"fourier": 0.05, "grid": 0.1}
#: With a time budget, validations per run (plus one at the end): the best weights are chosen
#: among these whatever the speed of the machine.
VALIDATIONS_PER_BUDGET = 30
#: Steps of a run given neither a time budget nor a step count.
DEFAULT_STEPS = 20_000
#: The keyframes preset's warm start: the share of the run (its steps or its budget, whichever ends
#: it) that trains the preset's static grid on the animation's first frame before the keyframe
#: tables start from it (docs/neural.md, "Why the keyframe tables learn slower").
WARM_START_SHARE = 0.1


@dataclass
class TrainConfig:
    """Training settings; lengths in the mesh's units unless the name says metres.

    margin_m / tight_margin_m : near-surface noise widths in metres (converted with
    ``meters_per_unit``); None for margin_m means 5 % of the largest side clamped to 5..10 mm.
    steps / max_minutes : a cap on optimiser steps and a time budget in minutes; the run ends at
    whichever comes first. With a budget and no steps given there is no step cap (the run uses
    the whole budget); with neither, DEFAULT_STEPS.
    """

    preset: str = DEFAULT_PRESET
    samples: int = 1_000_000
    near_fraction: float = 0.8
    tight_fraction: float = 0.5
    margin_m: float | None = None
    tight_margin_m: float = 0.0015
    padding: float = 0.1
    batch_size: int = 8192
    steps: int | None = None
    learning_rate: float | None = None  # None: the preset's (LEARNING_RATES)
    final_learning_rate: float | None = None
    normal_weight: float | None = None  # None: the preset's (NORMAL_WEIGHTS)
    validate_every: int = 500
    validation_points: int = 20_000
    max_minutes: float | None = None
    seed: int = 0
    threads: int | None = None
    architecture: dict = field(default_factory=dict)
    #: The keyframes preset's warm start (a share of the run in [0, 1), 0: none); None: WARM_START_SHARE.
    warm_start: float | None = None

    def resolved_architecture(self) -> Architecture | GridArchitecture:
        presets = {**PRESETS, **ANIMATED_PRESETS}
        if self.preset not in presets:
            raise ValueError(f"unknown preset {self.preset!r}; choose one of {sorted(presets)}")
        preset = presets[self.preset]
        try:
            return type(preset)(**{**asdict(preset), **self.architecture})
        except TypeError as exc:  # an override the preset's kind of network does not have
            raise ValueError(f"architecture overrides {sorted(self.architecture)} do not fit preset "
                             f"{self.preset!r}: {exc}") from None

    def _encoding(self) -> str:
        return "grid" if isinstance({**PRESETS, **ANIMATED_PRESETS}.get(self.preset), GridArchitecture) else "fourier"

    def resolved_learning_rates(self) -> tuple[float, float]:
        """(initial, final) learning rate: the given ones, else the preset kind's defaults."""
        first, last = LEARNING_RATES[self._encoding()]
        return (first if self.learning_rate is None else self.learning_rate,
                last if self.final_learning_rate is None else self.final_learning_rate)

    def step_cap(self) -> int | None:
        """The step count the run stops at, or None when only the clock ends it."""
        if self.steps is None and self.max_minutes is None:
            return DEFAULT_STEPS
        return self.steps

    def resolved_warm_start(self) -> float:
        """The share of the run that trains the static grid on the first frame before the keyframe
        tables (the keyframes preset's warm start): the given one, else WARM_START_SHARE; 0 for
        any other preset."""
        if not isinstance(self.resolved_architecture(), KeyframeGridArchitecture):
            return 0.0
        return WARM_START_SHARE if self.warm_start is None else self.warm_start

    def resolved_normal_weight(self) -> float:
        return NORMAL_WEIGHTS[self._encoding()] if self.normal_weight is None else self.normal_weight

    def check(self) -> None:
        if self.samples < 1000:
            raise ValueError(f"samples must be >= 1000, got {self.samples}")
        if not 0 <= self.near_fraction <= 1 or not 0 <= self.tight_fraction <= 1:
            raise ValueError("near_fraction and tight_fraction must be in [0, 1]")
        if (self.steps is not None and self.steps < 1) or self.batch_size < 1:
            raise ValueError("steps and batch_size must be >= 1")
        if self.max_minutes is not None and not (math.isfinite(self.max_minutes) and self.max_minutes > 0):
            raise ValueError(f"max_minutes must be a finite number > 0 (None: no limit), got {self.max_minutes}")
        for name in ("learning_rate", "final_learning_rate"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value}")
        if self.normal_weight is not None and not (math.isfinite(self.normal_weight) and self.normal_weight >= 0):
            # a negative weight would train normals to point away
            raise ValueError(f"normal_weight must be a finite number >= 0, got {self.normal_weight}")
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"threads must be >= 1, got {self.threads}")
        if self.validate_every < 1 or self.validation_points < 1:
            raise ValueError("validate_every and validation_points must be >= 1")
        if self.warm_start is not None and not (math.isfinite(self.warm_start) and 0 <= self.warm_start < 1):
            raise ValueError(f"warm_start must be a share of the run in [0, 1) (None: the preset's), got {self.warm_start}")
        if not (math.isfinite(self.padding) and self.padding >= 0):
            raise ValueError(f"padding must be a finite number >= 0, got {self.padding}")
        self.resolved_architecture()
