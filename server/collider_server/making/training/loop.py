"""The training loop: :func:`train_neural`."""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from collider_contract import Timeline

from ...engine.animated_meshes import AnimatedMesh
from ...engine.collider import ColliderInfo
from ...engine.kinds.animated_neural import AnimatedNeuralCollider
from ...engine.kinds.neural import ANIMATED_PRESETS, PRESETS, NeuralCollider, architecture_dict, build_network
from ...engine.kinds.neural_deformed import DeformedGridArchitecture
from ...engine.kinds.neural_keyframes import KeyframeGridArchitecture, keyframe_segments, keyframe_weights
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
from .deformation import DeformationFit, fit_deformation, fit_deformation_fields
from .schedule import RunClock, cosine_learning_rate, make_optimizer, set_training_threads, training_threads

#: A deformed network keeps its source's frames (float32) for its exact patches where they take
#: no more than this (bytes): the spot bend's 25 frames take 0.9 MB, the shipped twisting bunny's
#: 61 frames of 36,000 vertices 26 MB.
SURFACE_MAX_BYTES = 16_000_000


@dataclass
class TrainResult:
    """A finished run: the collider (best validated weights), the best +-1 mm validation error
    (mm), the steps and seconds of training (a resumed run's whole, not this process's), the
    validations, the settings, when the best weights were validated (step, seconds), and the
    steps of a keyframes run's warm start (the static grid on the first frame; among ``steps``)."""

    collider: NeuralCollider
    best_validation_mm: float
    steps: int
    seconds: float
    history: list = field(default_factory=list)
    config: TrainConfig = field(default_factory=TrainConfig)
    best_step: int = 0
    best_seconds: float = 0.0
    warm_steps: int = 0

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
        if self.warm_steps:
            head += f" (the first {self.warm_steps:,} on the first frame: the warm start)"
        return (f"{head}; best mean error in the +-1 mm band {self.best_validation_mm:.4f} mm "
                f"(the best of {len(self.history)} validations: step {self.best_step:,}, "
                f"{self.best_seconds / 60:.1f} min)")


def check_preset(config: TrainConfig, animated: bool):
    """``config`` checked, and its architecture, which must be an animated one (keyframes or
    deformed) for an animation and a static one otherwise (ValueError naming the preset)."""
    preset = {**PRESETS, **ANIMATED_PRESETS}.get(config.preset)
    if "deformation_resolution" in config.architecture and preset is not None \
            and not isinstance(preset, DeformedGridArchitecture):
        raise ValueError(f"preset {config.preset!r} has no deformation fields; their resolution "
                         "(--deformation-resolution) is the deformed preset's")
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
    deformed network fits its deformation fields to the frames (one per frame, before the clock;
    at the resolution ``config.architecture`` names, else the one the preset's rule picks,
    :func:`fit_deformation_fields`, which the run's settings then name) and trains its rest pose, the first frame, on that mesh's exact samples (box samples over
    every frame's box: where the deformation sends any point of the domain); ``deformation``, a
    fit of the same fields already made (:func:`choose_animated_preset`'s), is used as it is."""
    arch = check_preset(config, animated=True)
    timeline = animation.timeline
    duration = timeline.duration_s
    deformed = isinstance(arch, DeformedGridArchitecture)
    if deformed:
        arch = replace(arch, keyframes=timeline.frames)
        if "deformation_resolution" not in config.architecture:  # the preset's rule picks it
            centre, radius = normalisation(animation, config.padding)
            deformation = fit_deformation_fields(animation, centre, radius, meters_per_unit, show_progress,
                                                 fitted=deformation)
            # The run's settings (its checkpoint's identity, the model's) say which it took.
            config = replace(config, architecture={**config.architecture,
                                                   "deformation_resolution": deformation.resolution})
            arch = replace(arch, deformation_resolution=deformation.resolution)

    def inputs(times):
        """An animated network's per-sample inputs after the point: keyframe segment, fraction
        (none for a rest pose's samples, which have no time)."""
        import torch

        if times is None:
            return ()
        key, frac = keyframe_segments(times, duration, arch.keyframes)
        return torch.from_numpy(key), torch.from_numpy(frac)

    def first_frame():
        """The first frame's exact samples, box samples over every frame's box (the deformed
        preset's rest pose; the keyframes preset's warm start)."""
        rest = animation.frame(0)
        return make_training_data(rest, ExactSDF(rest), config, meters_per_unit, show_progress,
                                  box=padded_box(animation, config.padding))

    def samples():
        validation = animated_validation_sets(animation, config.validation_points, config.seed + 100,
                                              meters_per_unit)
        if deformed:
            data = first_frame()
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
            print(f"deformation fit: the {fit.resolution}^3 fields carry every frame's surface samples to the "
                  f"rest pose within {fit.summary(meters_per_unit)}", file=sys.stderr)
        network.deformation.copy_(torch.from_numpy(fit.fields))

    # The keyframes' own timeline: the same duration, loop and speed bound, K frames.
    keyed = Timeline(arch.keyframes, (arch.keyframes - 1) / duration, timeline.loop, timeline.max_surface_speed)
    info = ColliderInfo(name=name, kind="neural", domain_min=[], domain_max=[], units=units,
                        meters_per_unit=meters_per_unit, source=animation_source(animation, transform),
                        animation=keyed.to_dict())
    result = _train(animation, info, config, arch, samples, inputs, AnimatedNeuralCollider,
                    run_identity(animation, config, meters_per_unit), device, checkpoint, show_progress, prepare,
                    first_frame)
    if deformed:  # its frames: near the surface it answers on their exact patches
        size = animation.frames.size * 4
        kept = size <= SURFACE_MAX_BYTES
        if kept:
            result.collider.keep_surface(animation.frames, animation.faces)
        if show_progress:
            told = ("kept in the file: near the surface it answers on their faces (exact patches)" if kept
                    else f"not kept (over {SURFACE_MAX_BYTES / 1e6:.0f} MB): the network answers everywhere")
            print(f"its {len(animation.frames)} frames ({size / 1e6:.1f} MB in float32) {told}", file=sys.stderr)
    return result


#: The phases of a keyframes run with a warm start (``TrainConfig.warm_start``), as a checkpoint
#: and the progress bar name them: the static grid on the first frame, then the keyframe tables.
WARM_PHASE, KEYFRAME_PHASE = "first frame", "keyframes"


@dataclass
class Batches:
    """What one phase of a run trains on (tensors on the run's device): the samples' points (n, 3),
    per-sample network inputs after the point, exact distances (n,), unit gradients (n, 3) and
    near mask (n,)."""

    points: Any
    inputs: tuple
    target: Any
    target_gradient: Any
    near: Any

    @classmethod
    def of(cls, data, inputs: tuple, device: str) -> Batches:
        import torch

        return cls(torch.from_numpy(data.points).to(device), tuple(a.to(device) for a in inputs),
                   torch.from_numpy(data.distance).to(device), torch.from_numpy(data.gradient).to(device),
                   torch.from_numpy(data.near).to(device))


def sdf_loss(prediction, target, gradient, target_gradient, near, radius: float, normal_weight: float):
    """The training loss of every network: the L1 of the distance ``prediction`` (m,) against
    ``target`` (m,) over the normalisation ``radius``, plus ``normal_weight`` times ``1 - cos``
    between the network's ``gradient`` (m, 3) and ``target_gradient`` (m, 3) on the ``near`` (m,)
    samples; ``gradient`` None: the distance term alone."""
    import torch

    loss = (prediction - target).abs().mean() / radius
    if gradient is not None:
        cosine = torch.nn.functional.cosine_similarity(gradient[near], target_gradient[near], dim=1)
        loss = loss + normal_weight * (1 - cosine).mean()
    return loss


def train_step(network, optimizer, batches: Batches, index, radius: float, normal_weight: float) -> float:
    """One optimiser step of ``network`` on the samples ``index`` (int64 tensor) of ``batches``:
    L1 on the distance over the normalisation ``radius``, plus ``normal_weight`` times ``1 -
    cos`` between the network's gradient and the exact one on the near samples. Returns the loss."""
    import torch

    x = batches.points[index]
    x_inputs = tuple(a[index] for a in batches.inputs)
    mask = batches.near[index]
    # The normal term lives on the near samples only; a batch without any (possible with
    # a small near_fraction) would make its mean, and the logged loss, NaN.
    want_normals = normal_weight > 0 and bool(mask.any())
    if want_normals and hasattr(network, "value_and_gradient"):
        # The analytic gradient is made of differentiable ops: one backward pass.
        prediction, grad = network.value_and_gradient(x, *x_inputs)
    elif want_normals:
        x.requires_grad_(True)
        prediction = network(x, *x_inputs)
        (grad,) = torch.autograd.grad(prediction.sum(), x, create_graph=True)
    else:
        prediction = network(x, *x_inputs)
    loss = sdf_loss(prediction, batches.target[index], grad if want_normals else None,
                    batches.target_gradient[index], mask, radius, normal_weight)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    return float(loss.detach())


def _train(shape, info: ColliderInfo, config: TrainConfig, arch, samples, inputs, collider_class, identity: dict,
           device: str | None, checkpoint: Path | None, show_progress: bool, prepare=None,
           first_frame=None) -> TrainResult:
    """The loop of both: ``samples()`` makes the training data and the validation sets
    ``{band: (points, distance, inputs)}``; ``inputs(times)`` the network's per-sample inputs
    after the point (none for a static network); ``prepare(network, centre, radius)``, when
    given, sets what the network does not train (before the clock); ``first_frame()``, the
    first frame's samples, which a keyframes run's warm start trains the static grid on.

    The warm start (``config.resolved_warm_start()`` > 0, keyframe tables only): until that
    share of the run (:meth:`RunClock.fraction`) the static grid of the keyframe network
    (``arch.spatial()``) trains on the first frame; then every keyframe table starts from its
    table and the MLP is kept (:func:`keyframe_weights`), with a fresh Adam, and the tables
    train on. Validated at random times throughout (a static grid is the keyframe network of
    equal tables); its best weights and the checkpoint name their phase, so that a run resumes
    in either."""
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
    keyframed = isinstance(arch, KeyframeGridArchitecture)
    optimizer = make_optimizer(network, first_lr, fused=keyframed)

    # A checkpoint of another run is refused before the samples are made.
    saved = read_checkpoint_state(checkpoint) if checkpoint is not None and checkpoint.is_file() else None
    if saved is not None:
        check_resumable(checkpoint, saved.get("run"), identity)
    share = config.resolved_warm_start()
    phase = None  # a static network's run has one phase; a keyframes run names its own
    if keyframed:  # a checkpoint written before the warm start (no phase) holds keyframe tables
        phase = saved.get("phase", KEYFRAME_PHASE) if saved is not None else (
            WARM_PHASE if share > 0 else KEYFRAME_PHASE)
    warming = phase == WARM_PHASE
    trained, trained_optimizer = network, optimizer  # the network this phase trains, and its Adam
    if warming:
        trained = build_network(arch.spatial(), centre, radius).to(device)
        trained_optimizer = make_optimizer(trained, first_lr)  # the static grid's, as its own runs

    data, validation = samples()
    batches = Batches.of(data, inputs(data.times), device)
    if warming:
        main_batches, batches = batches, Batches.of(first_frame(), (), device)
    val = {k: (torch.from_numpy(p).to(device), torch.from_numpy(d).to(device), tuple(a.to(device) for a in e))
           for k, (p, d, e) in validation.items()}

    state = {"step": 0, "seconds": 0.0, "best_mm": math.inf, "history": [], "run": identity}
    if phase is not None:
        state["phase"] = phase
    best_weights = None
    if saved is not None:
        state = load_checkpoint(checkpoint, trained, trained_optimizer)
        shown_phase = f" in its {phase} phase" if phase is not None and share > 0 else ""
        print(f"resuming {checkpoint} at step {state['step']}{shown_phase} (same mesh, settings and architecture)",
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

    def model_weights() -> dict:
        """The model's weights as they stand: the keyframe network's (a static grid's in every table)."""
        weights = trained.state_dict()
        return keyframe_weights(weights, arch.keyframes) if warming else weights

    def evaluate() -> dict:
        trained.eval()
        with torch.no_grad():  # a static grid answers every time alike
            errors = {k: float(((trained(p) if warming else trained(p, *e)) - d).abs().mean()) * to_mm
                      for k, (p, d, e) in val.items()}
        trained.train()
        return errors

    def status(rate: float, errors: dict | None, lr: float) -> str:
        shown = "val±1mm -" if errors is None else f"val±1mm {errors['1mm']:.4f}mm best {state['best_mm']:.4f}mm"
        named = f"{state['phase']}: " if share > 0 and "phase" in state else ""
        return f"{named}step {state['step']:,} ({rate:.0f}/s) {shown} lr {lr:.1e}"

    with clock.progress_bar(f"train {name}", state["step"], now, show_progress) as bar:
        last_loss, errors, lr = float("nan"), None, first_lr
        session = (time.monotonic(), state["step"])  # this process's start, for the step rate
        finished = clock.finished(state["step"], time.monotonic())  # a resumed run may be done
        while not finished:
            step = state["step"]
            now = time.monotonic()
            fraction = clock.fraction(step, now)
            if warming and fraction >= share:
                # The warm start: every keyframe table from the static grid's, its MLP kept.
                network.load_state_dict(model_weights())
                trained, trained_optimizer, batches, warming = network, optimizer, main_batches, False
                state["phase"], state["warm_steps"] = KEYFRAME_PHASE, step
            lr = cosine_learning_rate(fraction, first_lr, last_lr)
            for group in trained_optimizer.param_groups:
                group["lr"] = lr
            index = torch.randint(0, len(batches.points), (config.batch_size,), generator=generator).to(device)
            last_loss = train_step(trained, trained_optimizer, batches, index, radius, normal_weight)
            state["step"] = step + 1
            now = time.monotonic()
            finished = clock.finished(state["step"], now)  # the last step is always validated
            validating = finished or clock.validation_due(state["step"], now)
            if validating:
                errors = evaluate()
                state["history"].append({"step": state["step"], "loss": last_loss, **errors,
                                         "seconds": time.monotonic() - started,
                                         **({"phase": state["phase"]} if "phase" in state else {})})
                if errors["1mm"] < state["best_mm"]:
                    state["best_mm"] = errors["1mm"]
                    state["best_step"], state["best_seconds"] = state["step"], time.monotonic() - started
                    best_weights = {k: v.detach().cpu().clone() for k, v in model_weights().items()}
                    if checkpoint is not None:
                        save_tensors_atomically({k: v.contiguous() for k, v in best_weights.items()},
                                                checkpoint.with_name(checkpoint.name + ".best"))
                state["seconds"] = time.monotonic() - started
                if checkpoint is not None:
                    save_checkpoint(checkpoint, trained, trained_optimizer, state)
                clock.validated(time.monotonic())
            if clock.advance(bar, now) or validating:
                rate = (state["step"] - session[1]) / max(now - session[0], 1e-9)
                bar.set_postfix_str(status(rate, errors, lr), refresh=False)

    network.load_state_dict(best_weights if best_weights is not None else model_weights())
    seconds = state["seconds"] = time.monotonic() - started
    info.domain_min, info.domain_max = lo.tolist(), hi.tolist()
    warm_steps = state.get("warm_steps", state["step"] if warming else 0)
    info.settings = {
        "architecture": architecture_dict(arch),
        "parameters": arch.parameter_count(),
        "training": {**asdict(config), "steps_done": state["step"], "seconds": round(seconds, 1),
                     "device": device, "device_name": _device_name(device, arch),
                     "best_validation_1mm_mm": state["best_mm"],
                     **({"warm_start_steps": warm_steps} if keyframed else {})},
    }
    collider = collider_class(info, network.cpu(), device="cpu")
    return TrainResult(collider, state["best_mm"], state["step"], seconds, state["history"], config,
                       state.get("best_step", 0), state.get("best_seconds", 0.0), warm_steps)


def _device_name(device: str, arch) -> str:
    """The device, and on a CPU the threads that did the work (a grid network's are the
    kernels', torch having one: ``set_training_threads``)."""
    import platform

    import torch

    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    threads = training_threads(arch)
    return f"{platform.processor() or platform.machine()} CPU, {threads} thread{'s' if threads != 1 else ''}"
