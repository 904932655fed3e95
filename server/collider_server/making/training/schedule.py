"""The schedule of a training run: steps or the clock, whichever ends first (the learning rate,
the progress bar and the validations follow it), the optimiser and the CPU threads."""

from __future__ import annotations

import math

from ...engine.kinds.neural import GridArchitecture
from ..progress import progress
from .config import VALIDATIONS_PER_BUDGET, TrainConfig


def set_training_threads(arch, threads: int) -> None:
    """``threads`` CPU threads for the run. A grid network spends them in the fused encoding
    kernels; its MLP is too small for torch's OpenMP to gain anything, and on a shared machine
    OpenMP threads that wait for a preempted sibling made a step 14x slower (586 against 42 ms
    measured with 2 against 1 torch threads under load), so torch gets one."""
    import torch

    from ...engine.kinds import grid_kernels

    if _in_kernels(arch):
        torch.set_num_threads(1)
        grid_kernels.set_threads(threads)
    else:
        torch.set_num_threads(threads)


def training_threads(arch) -> int:
    """The CPU threads a run of ``arch`` computes with (``set_training_threads``'s, or the
    defaults): the kernels' for a grid network, else torch's."""
    import torch

    from ...engine.kinds import grid_kernels

    return grid_kernels.threads() if _in_kernels(arch) else torch.get_num_threads()


def _in_kernels(arch) -> bool:
    """Whether a run of ``arch`` computes in the fused grid kernels."""
    from ...engine.kinds import grid_kernels

    return isinstance(arch, GridArchitecture) and grid_kernels.available()


def make_optimizer(network, learning_rate: float, fused: bool = False):
    """Adam; a grid network's feature table in its own group (instant-NGP's settings: the
    table's rows see sparse, noisy gradients, so a small eps and a short second-moment memory).
    ``fused``: torch's fused Adam, one kernel over each tensor (the keyframe tables' millions of
    parameters: 40 against 465 ms a step for 12M on one thread, measured; the default walks them
    in several passes)."""
    import torch

    def is_table(name: str) -> bool:  # the static network's, or one inside a larger module
        return name == "table" or name.endswith(".table")

    table = [p for n, p in network.named_parameters() if is_table(n)]
    others = [p for n, p in network.named_parameters() if not is_table(n)]
    if not table:
        return torch.optim.Adam(others, lr=learning_rate)
    return torch.optim.Adam([{"params": table}, {"params": others}], lr=learning_rate,
                            betas=(0.9, 0.99), eps=1e-15, fused=fused or None)


def cosine_learning_rate(fraction: float, first: float, last: float) -> float:
    """Cosine decay from ``first`` (fraction 0) to ``last`` (fraction 1)."""
    fraction = min(max(fraction, 0.0), 1.0)
    return last + 0.5 * (first - last) * (1 + math.cos(math.pi * fraction))


class RunClock:
    """Where a run is, by steps or, with ``max_minutes``, by the clock (whichever ends first):
    the learning-rate schedule, the progress bar (seconds of the budget, not a step count that a
    time-bounded run never reaches), the validation times and the stop follow it. A budget with
    no step count has no step cap: the run trains until the clock ends. Times are
    ``time.monotonic()`` values passed in, so the logic is testable without waiting; ``start``
    is when the run's training began (earlier than now for a resumed run, so its budget and
    schedule go on where they were)."""

    def __init__(self, config: TrainConfig, start: float, now: float | None = None):
        self.steps = config.step_cap()
        self.validate_every = config.validate_every
        self.budget_s = None if config.max_minutes is None else 60.0 * config.max_minutes
        self.start = start
        self.last_validation = start if now is None else now
        self.shown = 0

    def fraction(self, step: int, now: float) -> float:
        """Share of the run done: steps or the budget's time, whichever is further."""
        done = 0.0 if self.steps is None else step / self.steps
        if self.budget_s is not None:
            done = max(done, (now - self.start) / self.budget_s)
        return min(done, 1.0)

    def out_of_time(self, now: float) -> bool:
        return self.budget_s is not None and now - self.start >= self.budget_s

    def out_of_steps(self, step: int) -> bool:
        return self.steps is not None and step >= self.steps

    def finished(self, step: int, now: float) -> bool:
        return self.out_of_steps(step) or self.out_of_time(now)

    def validation_due(self, step: int, now: float) -> bool:
        """Every ``validate_every`` steps; with a budget, every 1/VALIDATIONS_PER_BUDGET of it
        instead (a slow machine still picks its best weights among as many candidates)."""
        if self.budget_s is None:
            return step % self.validate_every == 0
        return now - self.last_validation >= self.budget_s / VALIDATIONS_PER_BUDGET

    def validated(self, now: float) -> None:
        self.last_validation = now

    def progress_bar(self, desc: str, step: int, now: float, enabled: bool):
        """A bar in steps, or in seconds of the budget when the run has one; a resumed run's bar
        starts where the run is."""
        if self.budget_s is None:
            bar = progress(self.steps, desc, "step", enabled)
            self.shown = step
        else:
            bar = progress(int(round(self.budget_s)), desc, "s", enabled)
            self.shown = int(min(max(now - self.start, 0.0), self.budget_s))
        return _started(bar, self.shown)

    def advance(self, bar, now: float) -> bool:
        """Move ``bar`` to the run's position (one step, or the seconds elapsed); whether it
        moved."""
        if self.budget_s is None:
            bar.update(1)
            self.shown += 1
            return True
        elapsed = int(min(now - self.start, self.budget_s))
        if elapsed > self.shown:
            bar.update(elapsed - self.shown)
            self.shown = elapsed
            return True
        return False


class _started:
    """``progress(...)`` entered already advanced by ``done`` (a resumed run)."""

    def __init__(self, bar, done: int):
        self._bar, self._done = bar, done

    def __enter__(self):
        handle = self._bar.__enter__()
        if self._done:
            handle.update(self._done)
        return handle

    def __exit__(self, *exc):
        return self._bar.__exit__(*exc)
