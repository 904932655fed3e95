"""Train a ``neural`` collider from a mesh (the paper's recipe, with a few additions).

Data: exact signed distances (float64, libigl closest point + fast winding number sign) at
``samples`` points: ``near_fraction`` near the surface (surface samples plus uniform noise within
``margin``; a share ``tight_fraction`` of those within ``tight_margin``, the band where collisions
are decided) and the rest uniform in the padded domain box. The set is computed once and cached
(cheaper than fresh samples each epoch and it converged as well in our runs).

Loss: L1 on the distance (the paper's choice), plus, when ``normal_weight > 0``, ``1 - cos`` between
the network's gradient and the exact gradient (direction to the closest point) on the near
samples: distance accuracy and normal accuracy are separate goals, and the normal term is what
makes the ReLU network's gradient smooth. Adam with a cosine learning-rate decay; the checkpoint
with the best validation error in the +-1 mm band is kept; runs resume from their checkpoint
(safetensors, no pickle); deterministic under ``seed`` on one device.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..engine.collider import ColliderInfo
from ..engine.kinds.neural import (
    DEFAULT_PRESET,
    PRESETS,
    Architecture,
    GridArchitecture,
    NeuralCollider,
    architecture_dict,
    build_network,
)
from ..engine.meshes import ExactSDF, Mesh
from .bake import mesh_source, padded_box
from .progress import progress
from .sampling import box_points, surface_band_points, surface_points

#: Adam's learning rate, initial and final (cosine decay), per kind of network: feature tables
#: learn best at the large rate instant-NGP uses; the paper's MLP at 1e-3.
LEARNING_RATES = {"fourier": (1e-3, 1e-5), "grid": (1e-2, 1e-4)}
#: Weight of the 1 - cos(normal) term per kind of network (docs/neural.md has the measurements).
NORMAL_WEIGHTS = {"fourier": 0.05, "grid": 0.1}
#: With a time budget, validations per run (plus one at the end): the best weights are chosen
#: among these whatever the speed of the machine.
VALIDATIONS_PER_BUDGET = 30


@dataclass
class TrainConfig:
    """Training settings; lengths in the mesh's units unless the name says metres.

    margin_m / tight_margin_m : near-surface noise widths in metres (converted with
    ``meters_per_unit``); None for margin_m means 5 % of the largest side clamped to 5..10 mm.
    """

    preset: str = DEFAULT_PRESET
    samples: int = 1_000_000
    near_fraction: float = 0.8
    tight_fraction: float = 0.5
    margin_m: float | None = None
    tight_margin_m: float = 0.0015
    padding: float = 0.1
    batch_size: int = 8192
    steps: int = 20_000
    learning_rate: float | None = None  # None: the preset's (LEARNING_RATES)
    final_learning_rate: float | None = None
    normal_weight: float | None = None  # None: the preset's (NORMAL_WEIGHTS)
    validate_every: int = 500
    validation_points: int = 20_000
    max_minutes: float | None = None
    seed: int = 0
    threads: int | None = None
    architecture: dict = field(default_factory=dict)

    def resolved_architecture(self) -> Architecture | GridArchitecture:
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; choose one of {sorted(PRESETS)}")
        preset = PRESETS[self.preset]
        try:
            return type(preset)(**{**asdict(preset), **self.architecture})
        except TypeError as exc:  # an override the preset's kind of network does not have
            raise ValueError(f"architecture overrides {sorted(self.architecture)} do not fit preset "
                             f"{self.preset!r}: {exc}") from None

    def _encoding(self) -> str:
        return "grid" if isinstance(PRESETS.get(self.preset), GridArchitecture) else "fourier"

    def resolved_learning_rates(self) -> tuple[float, float]:
        """(initial, final) learning rate: the given ones, else the preset kind's defaults."""
        first, last = LEARNING_RATES[self._encoding()]
        return (first if self.learning_rate is None else self.learning_rate,
                last if self.final_learning_rate is None else self.final_learning_rate)

    def resolved_normal_weight(self) -> float:
        return NORMAL_WEIGHTS[self._encoding()] if self.normal_weight is None else self.normal_weight

    def check(self) -> None:
        if self.samples < 1000:
            raise ValueError(f"samples must be >= 1000, got {self.samples}")
        if not 0 <= self.near_fraction <= 1 or not 0 <= self.tight_fraction <= 1:
            raise ValueError("near_fraction and tight_fraction must be in [0, 1]")
        if self.steps < 1 or self.batch_size < 1:
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
        if not (math.isfinite(self.padding) and self.padding >= 0):
            raise ValueError(f"padding must be a finite number >= 0, got {self.padding}")
        self.resolved_architecture()


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
    sets = {}
    for label, band_m in (("1mm", 1e-3), ("10mm", 1e-2)):
        p = surface_band_points(mesh, n, band_m / meters_per_unit, seed=seed + (1 if label == "1mm" else 2))
        sets[label] = (p.astype(np.float32), sdf.signed_distance(p).astype(np.float32))
    return sets


# -- checkpoints (safetensors: weights, Adam state, progress; no pickle) --------------------------

def save_checkpoint(path: Path, network, optimizer, state: dict) -> None:
    import torch

    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in network.state_dict().items()}
    for index, param_state in optimizer.state_dict()["state"].items():
        for key, value in param_state.items():
            value = value if torch.is_tensor(value) else torch.tensor(value)  # Adam's step count
            tensors[f"adam.{index}.{key}"] = value.detach().cpu().contiguous()
    save_tensors_atomically(tensors, path, metadata={"state": json.dumps(state)})


def save_tensors_atomically(tensors: dict, path: Path, metadata: dict | None = None) -> None:
    """Write a safetensors file so that a run killed mid-write leaves the previous file intact
    (a resumed run reads it back)."""
    from safetensors.torch import save_file

    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=metadata)
    os.replace(tmp, path)


def read_checkpoint_state(path: Path) -> dict:
    """The progress state saved in a checkpoint's metadata (ValueError naming the file)."""
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as fh:
            state = json.loads((fh.metadata() or {})["state"])
    except Exception as exc:  # safetensors' own error type, JSON errors, a missing "state"
        raise ValueError(f"{path}: not a readable training checkpoint ({type(exc).__name__}: "
                         f"{exc}); delete it to start over") from None
    if not isinstance(state, dict):
        raise ValueError(f"{path}: not a readable training checkpoint (state is not an object)")
    return state


def load_checkpoint(path: Path, network, optimizer) -> dict:
    """Restore ``network`` and ``optimizer`` from ``path``; returns the saved progress state.

    Raises ValueError naming the file when it is unreadable or was written for another
    architecture (a stale checkpoint of an earlier run under the same name)."""
    from safetensors.torch import load_file

    state = read_checkpoint_state(path)
    try:
        tensors = load_file(str(path))
    except Exception as exc:  # safetensors' own error type
        raise ValueError(f"{path}: not a readable training checkpoint ({type(exc).__name__}: "
                         f"{exc}); delete it to start over") from None
    weights = {k[6:]: v for k, v in tensors.items() if k.startswith("model.")}
    expected = {k: tuple(v.shape) for k, v in network.state_dict().items()}
    found = {k: tuple(v.shape) for k, v in weights.items()}
    if found != expected:
        differ = sorted(set(found) ^ set(expected)) or [
            k for k in sorted(expected) if found[k] != expected[k]]
        key = differ[0]
        raise ValueError(f"{path}: checkpoint of another network architecture ({key}: checkpoint "
                         f"{found.get(key, 'absent')}, this run {expected.get(key, 'absent')}); "
                         "delete it or pass another --checkpoint")
    network.load_state_dict(weights)
    opt_state = optimizer.state_dict()
    restored: dict = {}
    for key, value in tensors.items():
        if key.startswith("adam."):
            _, index, name = key.split(".", 2)
            restored.setdefault(int(index), {})[name] = value
    opt_state["state"] = restored
    optimizer.load_state_dict(opt_state)
    return state


# -- what a checkpoint belongs to ------------------------------------------------------------------

#: Settings a resumed run may change: they say how long and how often, not what is learnt.
RESUMABLE_SETTINGS = frozenset({"steps", "max_minutes", "threads", "validate_every"})


def run_identity(mesh: Mesh, config: TrainConfig, meters_per_unit: float) -> dict:
    """What a checkpoint must match to be resumed: the placed mesh's content (sha256 of its
    vertices and faces, so a rescaled or rotated file differs), the settings that shape the
    training, and the architecture."""
    import hashlib

    digest = hashlib.sha256()
    for array in (np.ascontiguousarray(mesh.vertices, dtype=np.float64),
                  np.ascontiguousarray(mesh.faces, dtype=np.int64)):
        digest.update(array.tobytes())
    settings = {k: v for k, v in asdict(config).items() if k not in RESUMABLE_SETTINGS}
    return {"mesh": mesh.name, "mesh_sha256": digest.hexdigest(), "meters_per_unit": meters_per_unit,
            "settings": settings, "architecture": asdict(config.resolved_architecture())}


def identity_differences(saved: dict | None, current: dict) -> list[str]:
    """Human-readable differences between a checkpoint's identity and this run's (empty: same)."""
    if not saved:
        return ["it records no mesh, settings or architecture (written by an older version)"]
    differs = []
    if (saved.get("mesh_sha256"), saved.get("meters_per_unit")) != (current["mesh_sha256"], current["meters_per_unit"]):
        differs.append(f"mesh differs (checkpoint: {saved.get('mesh')} sha256 {str(saved.get('mesh_sha256'))[:12]}, "
                       f"this run: {current['mesh']} sha256 {current['mesh_sha256'][:12]})")
    for group in ("settings", "architecture"):
        old, new = saved.get(group, {}), current[group]
        keys = sorted(k for k in set(old) | set(new) if json.dumps(old.get(k)) != json.dumps(new.get(k)))
        if keys:
            differs.append(f"{group} differ: " + ", ".join(f"{k} {old.get(k)!r} -> {new.get(k)!r}" for k in keys))
    return differs


def check_resumable(path: Path, saved: dict | None, current: dict) -> None:
    """Raise ValueError naming what differs when the checkpoint at ``path`` is another run's."""
    differs = identity_differences(saved, current)
    if differs:
        raise ValueError(f"{path}: checkpoint of another run, not resumed: {'; '.join(differs)}; "
                         "delete it or pass another --checkpoint")


def set_training_threads(arch, threads: int) -> None:
    """``threads`` CPU threads for the run. A grid network spends them in the fused encoding
    kernels; its MLP is too small for torch's OpenMP to gain anything, and on a shared machine
    OpenMP threads that wait for a preempted sibling made a step 14x slower (586 against 42 ms
    measured with 2 against 1 torch threads under load), so torch gets one."""
    import torch

    from ..engine.kinds import grid_kernels

    if isinstance(arch, GridArchitecture) and grid_kernels.available():
        torch.set_num_threads(1)
        grid_kernels.set_threads(threads)
    else:
        torch.set_num_threads(threads)


# -- the schedule: steps or the clock, whichever ends first ------------------------------------

def make_optimizer(network, learning_rate: float):
    """Adam; a grid network's feature table in its own group (instant-NGP's settings: the
    table's rows see sparse, noisy gradients, so a small eps and a short second-moment memory)."""
    import torch

    table = [p for n, p in network.named_parameters() if n == "table"]
    others = [p for n, p in network.named_parameters() if n != "table"]
    if not table:
        return torch.optim.Adam(others, lr=learning_rate)
    return torch.optim.Adam([{"params": table}, {"params": others}], lr=learning_rate,
                            betas=(0.9, 0.99), eps=1e-15)


def cosine_learning_rate(fraction: float, first: float, last: float) -> float:
    """Cosine decay from ``first`` (fraction 0) to ``last`` (fraction 1)."""
    fraction = min(max(fraction, 0.0), 1.0)
    return last + 0.5 * (first - last) * (1 + math.cos(math.pi * fraction))


class RunClock:
    """Where a run is, by steps or, with ``max_minutes``, by the clock (whichever ends first):
    the learning-rate schedule, the progress bar (seconds of the budget, not a step count that a
    time-bounded run never reaches) and the validation times follow it. Times are
    ``time.monotonic()`` values passed in, so the logic is testable without waiting."""

    def __init__(self, config: TrainConfig, start: float):
        self.steps = config.steps
        self.validate_every = config.validate_every
        self.budget_s = None if config.max_minutes is None else 60.0 * config.max_minutes
        self.start = start
        self.last_validation = start
        self.shown = 0

    def fraction(self, step: int, now: float) -> float:
        """Share of the run done: steps, or the budget's time when that is further."""
        done = step / self.steps
        if self.budget_s is not None:
            done = max(done, (now - self.start) / self.budget_s)
        return min(done, 1.0)

    def out_of_time(self, now: float) -> bool:
        return self.budget_s is not None and now - self.start >= self.budget_s

    def validation_due(self, step: int, now: float) -> bool:
        """Every ``validate_every`` steps; with a budget, every 1/VALIDATIONS_PER_BUDGET of it
        instead (a slow machine still picks its best weights among as many candidates)."""
        if self.budget_s is None:
            return step % self.validate_every == 0
        return now - self.last_validation >= self.budget_s / VALIDATIONS_PER_BUDGET

    def validated(self, now: float) -> None:
        self.last_validation = now

    def progress_bar(self, desc: str, step: int, enabled: bool):
        """A bar in steps, or in seconds of the budget when the run has one."""
        if self.budget_s is None:
            bar = progress(self.steps, desc, "step", enabled)
            self.shown = step
            return _started(bar, step)
        return progress(int(round(self.budget_s)), desc, "s", enabled)

    def advance(self, bar, now: float) -> None:
        """Move ``bar`` to the run's position (one step, or the seconds elapsed)."""
        if self.budget_s is None:
            bar.update(1)
            return
        elapsed = int(min(now - self.start, self.budget_s))
        if elapsed > self.shown:
            bar.update(elapsed - self.shown)
            self.shown = elapsed


class _started:
    """``progress(...)`` entered already advanced by ``step`` (a resumed run)."""

    def __init__(self, bar, step: int):
        self._bar, self._step = bar, step

    def __enter__(self):
        handle = self._bar.__enter__()
        handle.update(self._step)
        return handle

    def __exit__(self, *exc):
        return self._bar.__exit__(*exc)


# -- the loop -----------------------------------------------------------------------------------

@dataclass
class TrainResult:
    collider: NeuralCollider
    best_validation_mm: float
    steps: int
    seconds: float
    history: list = field(default_factory=list)


def train_neural(mesh: Mesh, name: str, config: TrainConfig, *, units: str = "m",
                 meters_per_unit: float = 1.0, transform: np.ndarray | None = None,
                 device: str | None = None, checkpoint: Path | None = None,
                 show_progress: bool = True) -> TrainResult:
    """Train a neural collider for ``mesh`` (its units and frame); returns the best checkpoint."""
    import torch

    from ..engine.devices import resolve_device

    config.check()
    device = resolve_device(device)
    torch.manual_seed(config.seed)
    arch = config.resolved_architecture()
    if config.threads is not None:
        set_training_threads(arch, config.threads)
    lo, hi = padded_box(mesh, config.padding)
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float((hi - lo).max())
    network = build_network(arch, centre, radius).to(device)
    first_lr, last_lr = config.resolved_learning_rates()
    normal_weight = config.resolved_normal_weight()
    optimizer = make_optimizer(network, first_lr)

    sdf = ExactSDF(mesh)
    data = make_training_data(mesh, sdf, config, meters_per_unit, show_progress)
    validation = validation_sets(mesh, sdf, config.validation_points, config.seed + 100, meters_per_unit)
    points = torch.from_numpy(data.points).to(device)
    target = torch.from_numpy(data.distance).to(device)
    target_gradient = torch.from_numpy(data.gradient).to(device)
    near = torch.from_numpy(data.near).to(device)
    val = {k: (torch.from_numpy(p).to(device), torch.from_numpy(d).to(device)) for k, (p, d) in validation.items()}

    identity = run_identity(mesh, config, meters_per_unit)
    state = {"step": 0, "seconds": 0.0, "best_mm": math.inf, "history": [], "run": identity}
    best_weights = None
    if checkpoint is not None and checkpoint.is_file():
        check_resumable(checkpoint, read_checkpoint_state(checkpoint).get("run"), identity)
        state = load_checkpoint(checkpoint, network, optimizer)
        print(f"resuming {checkpoint} at step {state['step']} (same mesh, settings and architecture)",
              file=sys.stderr)
        best_path = checkpoint.with_name(checkpoint.name + ".best")
        if best_path.is_file():
            from safetensors.torch import load_file
            best_weights = load_file(str(best_path))

    generator = torch.Generator(device="cpu").manual_seed(config.seed + state["step"])
    to_mm = 1000.0 * meters_per_unit
    started = time.monotonic() - state["seconds"]
    clock = RunClock(config, time.monotonic())
    analytic = hasattr(network, "value_and_gradient")

    def evaluate() -> dict:
        network.eval()
        with torch.no_grad():
            errors = {k: float((network(p) - d).abs().mean()) * to_mm for k, (p, d) in val.items()}
        network.train()
        return errors

    with clock.progress_bar(f"train {name}", state["step"], show_progress) as bar:
        last_loss = float("nan")
        while state["step"] < config.steps:
            step = state["step"]
            now = time.monotonic()
            lr = cosine_learning_rate(clock.fraction(step, now), first_lr, last_lr)
            for group in optimizer.param_groups:
                group["lr"] = lr
            index = torch.randint(0, len(points), (config.batch_size,), generator=generator).to(device)
            x = points[index]
            mask = near[index]
            # The normal term lives on the near samples only; a batch without any (possible with
            # a small near_fraction) would make its mean, and the logged loss, NaN.
            want_normals = normal_weight > 0 and bool(mask.any())
            if want_normals and analytic:
                # The analytic gradient is made of differentiable ops: one backward pass.
                prediction, grad = network.value_and_gradient(x)
            elif want_normals:
                x.requires_grad_(True)
                prediction = network(x)
                (grad,) = torch.autograd.grad(prediction.sum(), x, create_graph=True)
            else:
                prediction = network(x)
            loss = (prediction - target[index]).abs().mean() / radius
            if want_normals:
                cosine = torch.nn.functional.cosine_similarity(grad[mask], target_gradient[index][mask], dim=1)
                loss = loss + normal_weight * (1 - cosine).mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            last_loss = float(loss.detach())
            state["step"] = step + 1
            now = time.monotonic()
            clock.advance(bar, now)
            done = state["step"] >= config.steps
            out_of_time = clock.out_of_time(now)
            if clock.validation_due(state["step"], now) or done or out_of_time:
                errors = evaluate()
                state["history"].append({"step": state["step"], "loss": last_loss, **errors,
                                         "seconds": time.monotonic() - started})
                if errors["1mm"] < state["best_mm"]:
                    state["best_mm"] = errors["1mm"]
                    best_weights = {k: v.detach().cpu().clone() for k, v in network.state_dict().items()}
                    if checkpoint is not None:
                        save_tensors_atomically({k: v.contiguous() for k, v in best_weights.items()},
                                                checkpoint.with_name(checkpoint.name + ".best"))
                bar.set_postfix_str(f"step {state['step']} loss {last_loss:.2e} val±1mm {errors['1mm']:.4f}mm "
                                    f"val±10mm {errors['10mm']:.4f}mm best {state['best_mm']:.4f}mm lr {lr:.1e}")
                state["seconds"] = time.monotonic() - started
                if checkpoint is not None:
                    save_checkpoint(checkpoint, network, optimizer, state)
                clock.validated(time.monotonic())
            if out_of_time:
                break

    if best_weights is not None:
        network.load_state_dict(best_weights)
    seconds = time.monotonic() - started
    info = ColliderInfo(
        name=name, kind="neural", domain_min=lo.tolist(), domain_max=hi.tolist(), units=units,
        meters_per_unit=meters_per_unit, source=mesh_source(mesh, transform),
        settings={
            "architecture": architecture_dict(arch),
            "parameters": arch.parameter_count(),
            "training": {**asdict(config), "steps_done": state["step"], "seconds": round(seconds, 1),
                         "device": device, "device_name": _device_name(device),
                         "best_validation_1mm_mm": state["best_mm"]},
        },
    )
    collider = NeuralCollider(info, network.cpu(), device="cpu")
    return TrainResult(collider, state["best_mm"], state["step"], seconds, state["history"])


def _device_name(device: str) -> str:
    import platform

    import torch

    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    return f"{platform.processor() or platform.machine()} CPU, {torch.get_num_threads()} threads"
