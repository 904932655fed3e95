"""The training loop: :func:`train_neural`."""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from collider_contract import Timeline

from ...engine.animated_meshes import AnimatedMesh
from ...engine.collider import ColliderInfo
from ...engine.kinds.animated_neural import AnimatedNeuralCollider
from ...engine.kinds.neural import ANIMATED_PRESETS, NeuralCollider, architecture_dict, build_network
from ...engine.kinds.neural_deformed import DeformedGridArchitecture
from ...engine.kinds.neural_keyframes import KeyframeGridArchitecture, keyframe_segments
from ...engine.meshes import ExactSDF, Mesh
from ..bake import animation_source, mesh_source, padded_box
from .checkpoints import (
    check_resumable,
    load_checkpoint,
    read_checkpoint_state,
    run_identity,
    save_checkpoint,
    save_tensors_atomically,
)
from .config import TrainConfig
from .data import (
    animated_validation_sets,
    make_animated_training_data,
    make_training_data,
    normalisation,
    validation_sets,
)
from .deformation import DeformationFit, fit_deformation
from .schedule import RunClock, cosine_learning_rate, make_optimizer, set_training_threads, training_threads


@dataclass
class TrainResult:
    """A finished run: the collider (best validated weights), the best +-1 mm validation error
    (mm), the steps and seconds of training (a resumed run's whole, not this process's), the
    validations, the settings, and when the best weights were validated (step, seconds)."""

    collider: NeuralCollider
    best_validation_mm: float
    steps: int
    seconds: float
    history: list = field(default_factory=list)
    config: TrainConfig = field(default_factory=TrainConfig)
    best_step: int = 0
    best_seconds: float = 0.0

    def summary(self) -> str:
        """What the run's budget bought, in one line: steps, samples and rate, why it stopped,
        and the best weights' validation error and when they were reached."""
        minutes = self.seconds / 60.0
        rate = self.steps / self.seconds if self.seconds > 0 else 0.0
        samples = self.steps * self.config.batch_size
        shown = f"{samples / 1e6:,.1f}M" if samples >= 1e6 else f"{samples:,}"
        bought = f"{self.steps:,} steps ({shown} samples, {rate:.0f} steps/s)"
        budget, cap = self.config.max_minutes, self.config.step_cap()
        if budget is None:
            head = f"{bought} in {minutes:.1f} min"
        elif cap is not None and self.steps >= cap and minutes < budget:
            head = f"{bought}: the step cap, reached after {minutes:.1f} of the {budget:g} minutes"
        else:
            head = f"the {budget:g}-minute budget bought {bought}"
        return (f"{head}; best mean error in the +-1 mm band {self.best_validation_mm:.4f} mm "
                f"(the best of {len(self.history)} validations: step {self.best_step:,}, "
                f"{self.best_seconds / 60:.1f} min)")


def check_preset(config: TrainConfig, animated: bool):
    """``config`` checked, and its architecture, which must be an animated one (keyframes or
    deformed) for an animation and a static one otherwise (ValueError naming the preset)."""
    config.check()
    arch = config.resolved_architecture()
    moving = isinstance(arch, (KeyframeGridArchitecture, DeformedGridArchitecture))
    if animated and not moving:
        raise ValueError(f"preset {config.preset!r} is static; an animation takes an animated preset "
                         f"({', '.join(sorted(ANIMATED_PRESETS))})")
    if isinstance(arch, DeformedGridArchitecture) and "keyframes" in config.architecture:
        raise ValueError(f"preset {config.preset!r} has one deformation field per frame of the animation; "
                         "keyframes (--keyframes) are the keyframes preset's")
    if not animated and moving:
        raise ValueError(f"preset {config.preset!r} is for an animation (--animation); a static mesh "
                         "takes a static preset")
    return arch


def train_neural(mesh: Mesh, name: str, config: TrainConfig, *, units: str = "m",
                 meters_per_unit: float = 1.0, transform: np.ndarray | None = None,
                 device: str | None = None, checkpoint: Path | None = None,
                 show_progress: bool = True) -> TrainResult:
    """Train a neural collider for ``mesh`` (its units and frame); returns the best checkpoint."""
    arch = check_preset(config, animated=False)

    def samples():
        sdf = ExactSDF(mesh)
        validation = validation_sets(mesh, sdf, config.validation_points, config.seed + 100, meters_per_unit)
        return (make_training_data(mesh, sdf, config, meters_per_unit, show_progress),
                {k: (p, d, ()) for k, (p, d) in validation.items()})

    info = ColliderInfo(name=name, kind="neural", domain_min=[], domain_max=[], units=units,
                        meters_per_unit=meters_per_unit, source=mesh_source(mesh, transform))
    return _train(mesh, info, config, arch, samples, lambda _: (), NeuralCollider,
                  run_identity(mesh, config, meters_per_unit), device, checkpoint, show_progress)


def train_animated_neural(animation: AnimatedMesh, name: str, config: TrainConfig, *, units: str = "m",
                          meters_per_unit: float = 1.0, transform: np.ndarray | None = None,
                          device: str | None = None, checkpoint: Path | None = None,
                          show_progress: bool = True, deformation: DeformationFit | None = None) -> TrainResult:
    """Train one network for the whole of ``animation`` (its units and frame; an animated preset):
    validation at random times against the exact interpolated mesh; returns the best checkpoint
    as an animated collider whose ``info.animation`` is the keyframes' timeline (the source's
    frames and rate in ``info.source``).

    Keyframe tables train on samples at random times, the exact interpolated mesh as truth. A
    deformed network fits its deformation fields to the frames (one per frame, before the clock)
    and trains its rest pose, the first frame, on that mesh's exact samples (box samples over
    every frame's box: where the deformation sends any point of the domain); ``deformation``, a
    fit of the same fields already made (:func:`choose_animated_preset`'s), is used as it is."""
    arch = check_preset(config, animated=True)
    timeline = animation.timeline
    duration = timeline.duration_s
    deformed = isinstance(arch, DeformedGridArchitecture)
    if deformed:
        arch = replace(arch, keyframes=timeline.frames)

    def inputs(times):
        """An animated network's per-sample inputs after the point: keyframe segment, fraction
        (none for a rest pose's samples, which have no time)."""
        import torch

        if times is None:
            return ()
        key, frac = keyframe_segments(times, duration, arch.keyframes)
        return torch.from_numpy(key), torch.from_numpy(frac)

    def samples():
        validation = animated_validation_sets(animation, config.validation_points, config.seed + 100,
                                              meters_per_unit)
        if deformed:
            rest = animation.frame(0)
            data = make_training_data(rest, ExactSDF(rest), config, meters_per_unit, show_progress,
                                      box=padded_box(animation, config.padding))
        else:
            data = make_animated_training_data(animation, config, meters_per_unit, show_progress)
        return data, {k: (p, d, inputs(t)) for k, (p, d, t) in validation.items()}

    def prepare(network, centre, radius):
        if not deformed:
            return
        import torch

        fit = deformation
        if fit is None or not fit.fits(centre, radius, arch.deformation_resolution, arch.keyframes):
            fit = fit_deformation(animation, centre, radius, arch.deformation_resolution, show_progress)
            if show_progress:
                print(f"deformation fit: the fields carry every frame's surface samples to the rest pose "
                      f"within {fit.summary(meters_per_unit)}", file=sys.stderr)
        network.deformation.copy_(torch.from_numpy(fit.fields))

    # The keyframes' own timeline: the same duration, loop and speed bound, K frames.
    keyed = Timeline(arch.keyframes, (arch.keyframes - 1) / duration, timeline.loop, timeline.max_surface_speed)
    info = ColliderInfo(name=name, kind="neural", domain_min=[], domain_max=[], units=units,
                        meters_per_unit=meters_per_unit, source=animation_source(animation, transform),
                        animation=keyed.to_dict())
    return _train(animation, info, config, arch, samples, inputs, AnimatedNeuralCollider,
                  run_identity(animation, config, meters_per_unit), device, checkpoint, show_progress, prepare)


def _train(shape, info: ColliderInfo, config: TrainConfig, arch, samples, inputs, collider_class, identity: dict,
           device: str | None, checkpoint: Path | None, show_progress: bool, prepare=None) -> TrainResult:
    """The loop of both: ``samples()`` makes the training data and the validation sets
    ``{band: (points, distance, inputs)}``; ``inputs(times)`` the network's per-sample inputs
    after the point (none for a static network); ``prepare(network, centre, radius)``, when
    given, sets what the network does not train (before the clock)."""
    import torch

    from ...engine.devices import resolve_device

    name, meters_per_unit = info.name, info.meters_per_unit
    device = resolve_device(device)
    torch.manual_seed(config.seed)
    if config.threads is not None:
        set_training_threads(arch, config.threads)
    lo, hi = padded_box(shape, config.padding)
    centre, radius = normalisation(shape, config.padding)
    network = build_network(arch, centre, radius)
    if prepare is not None:
        prepare(network, centre, radius)
    network = network.to(device)
    first_lr, last_lr = config.resolved_learning_rates()
    normal_weight = config.resolved_normal_weight()
    optimizer = make_optimizer(network, first_lr, fused=isinstance(arch, KeyframeGridArchitecture))

    data, validation = samples()
    points = torch.from_numpy(data.points).to(device)
    extra = tuple(a.to(device) for a in inputs(data.times))
    target = torch.from_numpy(data.distance).to(device)
    target_gradient = torch.from_numpy(data.gradient).to(device)
    near = torch.from_numpy(data.near).to(device)
    val = {k: (torch.from_numpy(p).to(device), torch.from_numpy(d).to(device), tuple(a.to(device) for a in e))
           for k, (p, d, e) in validation.items()}

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
    now = time.monotonic()
    started = now - state["seconds"]  # a resumed run's clock goes on where it was saved
    clock = RunClock(config, started, now)
    analytic = hasattr(network, "value_and_gradient")

    def evaluate() -> dict:
        network.eval()
        with torch.no_grad():
            errors = {k: float((network(p, *e) - d).abs().mean()) * to_mm for k, (p, d, e) in val.items()}
        network.train()
        return errors

    def status(rate: float, errors: dict | None, lr: float) -> str:
        shown = "val±1mm -" if errors is None else f"val±1mm {errors['1mm']:.4f}mm best {state['best_mm']:.4f}mm"
        return f"step {state['step']:,} ({rate:.0f}/s) {shown} lr {lr:.1e}"

    with clock.progress_bar(f"train {name}", state["step"], now, show_progress) as bar:
        last_loss, errors, lr = float("nan"), None, first_lr
        session = (time.monotonic(), state["step"])  # this process's start, for the step rate
        finished = clock.finished(state["step"], time.monotonic())  # a resumed run may be done
        while not finished:
            step = state["step"]
            now = time.monotonic()
            lr = cosine_learning_rate(clock.fraction(step, now), first_lr, last_lr)
            for group in optimizer.param_groups:
                group["lr"] = lr
            index = torch.randint(0, len(points), (config.batch_size,), generator=generator).to(device)
            x = points[index]
            x_inputs = tuple(a[index] for a in extra)
            mask = near[index]
            # The normal term lives on the near samples only; a batch without any (possible with
            # a small near_fraction) would make its mean, and the logged loss, NaN.
            want_normals = normal_weight > 0 and bool(mask.any())
            if want_normals and analytic:
                # The analytic gradient is made of differentiable ops: one backward pass.
                prediction, grad = network.value_and_gradient(x, *x_inputs)
            elif want_normals:
                x.requires_grad_(True)
                prediction = network(x, *x_inputs)
                (grad,) = torch.autograd.grad(prediction.sum(), x, create_graph=True)
            else:
                prediction = network(x, *x_inputs)
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
            finished = clock.finished(state["step"], now)  # the last step is always validated
            validating = finished or clock.validation_due(state["step"], now)
            if validating:
                errors = evaluate()
                state["history"].append({"step": state["step"], "loss": last_loss, **errors,
                                         "seconds": time.monotonic() - started})
                if errors["1mm"] < state["best_mm"]:
                    state["best_mm"] = errors["1mm"]
                    state["best_step"], state["best_seconds"] = state["step"], time.monotonic() - started
                    best_weights = {k: v.detach().cpu().clone() for k, v in network.state_dict().items()}
                    if checkpoint is not None:
                        save_tensors_atomically({k: v.contiguous() for k, v in best_weights.items()},
                                                checkpoint.with_name(checkpoint.name + ".best"))
                state["seconds"] = time.monotonic() - started
                if checkpoint is not None:
                    save_checkpoint(checkpoint, network, optimizer, state)
                clock.validated(time.monotonic())
            if clock.advance(bar, now) or validating:
                rate = (state["step"] - session[1]) / max(now - session[0], 1e-9)
                bar.set_postfix_str(status(rate, errors, lr), refresh=False)

    if best_weights is not None:
        network.load_state_dict(best_weights)
    seconds = state["seconds"] = time.monotonic() - started
    info.domain_min, info.domain_max = lo.tolist(), hi.tolist()
    info.settings = {
        "architecture": architecture_dict(arch),
        "parameters": arch.parameter_count(),
        "training": {**asdict(config), "steps_done": state["step"], "seconds": round(seconds, 1),
                     "device": device, "device_name": _device_name(device, arch),
                     "best_validation_1mm_mm": state["best_mm"]},
    }
    collider = collider_class(info, network.cpu(), device="cpu")
    return TrainResult(collider, state["best_mm"], state["step"], seconds, state["history"], config,
                       state.get("best_step", 0), state.get("best_seconds", 0.0))


def _device_name(device: str, arch) -> str:
    """The device, and on a CPU the threads that did the work (a grid network's are the
    kernels', torch having one: ``set_training_threads``)."""
    import platform

    import torch

    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    threads = training_threads(arch)
    return f"{platform.processor() or platform.machine()} CPU, {threads} thread{'s' if threads != 1 else ''}"
