"""Training the articulated network of a skinned character (kind ``neural-skinned``,
:mod:`collider_server.engine.kinds.neural_skinned`): :func:`train_articulated`.

Data: poses of the skeleton (:func:`sample_poses`: the rest pose, random times of the clips, and
random times with every joint's local rotation turned by up to ``perturb_deg`` about a random
axis), at each the skin posed by linear blend skinning and its exact signed distance and gradient
(:class:`~collider_server.engine.meshes.ExactSDF`, the exact ``skinned`` kind's truth) at
``samples / poses`` points drawn as a static mesh's are (near the posed surface, then uniform in
its padded box). Each sample keeps its candidate parts (``parts_through_skinning``: the rule the
query uses) with its point in each part's rest frame and the pose's codes.

Loss per batch: the distance is the minimum over a sample's candidates of the shared network's
value (what the query answers), L1 against the truth, plus ``normal_weight`` (1 - cos) between the
chosen part's gradient, taken through its rigid map, and the exact gradient on the near samples.
Adam with the grid presets' rates and cosine decay, the clock of :class:`.schedule.RunClock`; the
weights with the best mean error in the +-1 mm band of held-out poses are kept. No checkpoint to
resume from (a run is minutes).
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ...engine.kinds.neural import PRESETS
from ...engine.kinds.neural_skinned import (
    NO_PART,
    ArticulatedGridArchitecture,
    ArticulatedNeuralCollider,
    allowed_labels,
    build_articulated_network,
    dilated_labels,
    part_boxes,
    part_labels,
    parts_through_skinning,
    pose_codes,
    rest_maps,
    surface_anchors,
    surface_offsets,
    weight_field,
)
from ...engine.meshes import ExactSDF, Mesh
from ...engine.skinning import PERTURB_DEG, Skin, random_poses, skin_vertices
from ..bake import padded_box
from ..progress import progress
from ..sampling import surface_band_points
from .config import TrainConfig
from .data import default_margin, exact_values, normalisation, sample_points
from .loop import sdf_loss
from .schedule import RunClock, cosine_learning_rate, make_optimizer, set_training_threads

#: The preset ``collider train CHARACTER`` uses: the static ``grid`` preset's field (2^17 rows
#: per hashed level in 8 bits, stored as that preset stores them: codes on the mu-law curve)
#: shared by the parts; the map to the rest pose by 8 damped Newton steps through the 48^3 weight
#: grid and blocks of a 128^3 one near the rest surface (the walker's floor without a network:
#: docs/neural.md); a point none of whose candidates reaches a root tried again with the parts the
#: label grid names at its rigid images (``retry-labels``); the label grid dilated by a cell where
#: that lowers the map's floor (:func:`choose_label_dilation`).
ARTICULATED_PRESET = ArticulatedGridArchitecture(skinning_solver="newton", skinning_iterations=8,
                                                 fine_weight_resolution=128, candidate_rule="retry-labels",
                                                 surface_offsets=True, table_dtype=PRESETS["grid"].table_dtype)
#: The fine weight field's blocks reach this many fine cells beyond the rest surface.
FINE_WEIGHT_BAND_CELLS = 1.0
#: The label dilations (cells, :func:`dilated_labels`) a training chooses between, and by how
#: much the wider must lower the map's floor to be taken: it costs the query 1.35-1.6x (the rows
#: a point 1.0-1.2 -> 1.6-1.8). Measured (docs/neural.md, "A dilated label grid"): CesiumMan's and
#: the RiggedFigure's floors fall 44-56 %, the walker's 3 %.
LABEL_DILATIONS = (0, 1)
DILATION_GAIN = 0.2
#: Poses off the clips (where a point's part goes missing) and points of each that measure it.
DILATION_POSES = 8
DILATION_POINTS = 2000
#: Training poses and validation poses of a run (the rest pose is one of the training poses).
TRAIN_POSES = 240
VALIDATION_POSES = 12


def sample_poses(skin: Skin, count: int, seed: int, perturb_deg: float = PERTURB_DEG,
                 perturbed_share: float = 0.5) -> np.ndarray:
    """(count, J, 4, 4) float64 joint transforms (collider frame): :func:`~collider_server.engine.
    skinning.random_poses` (random clip times, the last ``perturbed_share`` of them with every
    joint's local rotation turned by up to ``perturb_deg``)."""
    return random_poses(skin, count, seed, perturb_deg, perturbed_share).transforms


@dataclass
class ArticulatedSamples:
    """Samples of several poses with their candidate parts (float32 unless said).

    distance (n,), gradient (n, 3), near (n,) bool: the exact truth per sample
    start (n,) int64, count (n,) int64: each sample's rows of the candidate arrays
    rest (m, 3), joint (m,) int64, pose (m,) int64, to_rest (m, 3, 3): each candidate's rest-pose
    point, part, pose and the linear part of its map to the rest pose (the gradient's pull-back)
    codes (P, J, C): the poses' part codes
    """

    distance: np.ndarray
    gradient: np.ndarray
    near: np.ndarray
    start: np.ndarray
    count: np.ndarray
    rest: np.ndarray
    joint: np.ndarray
    pose: np.ndarray
    to_rest: np.ndarray
    codes: np.ndarray


def make_samples(skin: Skin, poses: np.ndarray, per_pose: int, point_sampler, arch, centre, radius: float,
                 labels: np.ndarray, boxes: np.ndarray, weights: tuple, show_progress: bool,
                 what: str, anchors=None, sets: np.ndarray | None = None) -> ArticulatedSamples:
    """:class:`ArticulatedSamples` of ``per_pose`` points at each pose: ``point_sampler(mesh,
    seed)`` -> (points (k, 3), near (k,) bool) on the posed mesh; ``weights``: the weight grid
    (:func:`weight_field`) the query carries points through, with each pose's
    :func:`surface_offsets` where ``anchors`` (:func:`surface_anchors`) are given; ``sets``: the
    label grid's set codes (:func:`dilated_labels`) where it has them."""
    skeleton = skin.skeleton
    allowed = allowed_labels(skeleton.parents, arch.neighbours, sets)
    parts = {k: [] for k in ("distance", "gradient", "near", "count", "rest", "joint", "pose", "to_rest")}
    codes = []
    with progress(len(poses), what, "pose", show_progress) as bar:
        for p, transforms in enumerate(poses):
            mesh = Mesh(skin_vertices(skin, transforms), skin.faces, "posed")
            points, near = point_sampler(mesh, p)
            distance, gradient = exact_values(ExactSDF(mesh), points)
            to_rest, posed = rest_maps(skeleton, transforms)
            offsets = None if anchors is None else surface_offsets(anchors, weights, skin, posed[:, :3, :])
            point, joint, rest, inverse = parts_through_skinning(
                points, to_rest, posed, labels, centre, radius, allowed, boxes, weights, arch.skinning_iterations,
                arch.skinning_solver, arch.candidate_rule, offsets=offsets)
            order = np.argsort(point, kind="stable")
            parts["distance"].append(distance)
            parts["gradient"].append(gradient)
            parts["near"].append(near)
            parts["count"].append(np.bincount(point, minlength=len(points)))
            parts["rest"].append(rest[order])
            parts["joint"].append(joint[order])
            parts["pose"].append(np.full(len(point), p, np.int64))
            parts["to_rest"].append(inverse[order])
            codes.append(pose_codes(skeleton, transforms, arch.pose_slots))
            bar.update(1)
    joined = {k: np.concatenate(v) for k, v in parts.items()}
    count = joined["count"].astype(np.int64)
    return ArticulatedSamples(
        joined["distance"].astype(np.float32), joined["gradient"].astype(np.float32), joined["near"],
        np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64), count,
        joined["rest"].astype(np.float32), joined["joint"], joined["pose"],
        joined["to_rest"].astype(np.float32), np.stack(codes))


def rest_tables(skin: Skin, arch, centre, radius: float):
    """The rest pose's tables of ``arch`` over the cube ``centre +- radius`` (collider units):
    ``(labels, boxes, weights, anchors)``: the label grid (:func:`part_labels`, undilated), the
    part boxes, the weight field (:func:`weight_field`) and its surface anchors (None without
    ``surface_offsets``)."""
    cell = 2.0 * radius / arch.label_resolution
    labels = part_labels(skin, centre, radius, arch.label_resolution, band=3.0 * cell)
    weights = weight_field(skin, centre, radius, arch.weight_resolution, arch.fine_weight_resolution,
                           band=FINE_WEIGHT_BAND_CELLS * 2.0 * radius / max(arch.fine_weight_resolution, 1))
    anchors = surface_anchors(skin, weights, centre, radius) if arch.surface_offsets else None
    return labels, part_boxes(skin, cell), weights, anchors


def choose_label_dilation(skin: Skin, arch, centre, radius: float, labels: np.ndarray, boxes: np.ndarray,
                          weights, anchors, rest_sdf, band: float, seed: int) -> tuple[int, str]:
    """Which of :data:`LABEL_DILATIONS` the label grid ``labels`` (:func:`part_labels`) gets, and
    why in one line: the map's floor (the exact rest SDF ``rest_sdf`` read through ``arch``'s map
    with ``weights`` and the surface ``anchors``, the least over each point's candidate rows)
    against the exact posed skin at :data:`DILATION_POSES` poses off the clips,
    :data:`DILATION_POINTS` points each in the +-``band`` band (collider units); the wider
    dilation where it lowers the mean by :data:`DILATION_GAIN` or more."""
    poses = sample_poses(skin, DILATION_POSES, seed + 31, perturbed_share=1.0)
    truths = []
    for p, transforms in enumerate(poses):
        mesh = Mesh(skin_vertices(skin, transforms), skin.faces, "posed")
        points = surface_band_points(mesh, DILATION_POINTS, band, seed + 40 + p)
        to_rest, posed = rest_maps(skin.skeleton, transforms)
        offsets = None if anchors is None else surface_offsets(anchors, weights, skin, posed[:, :3, :])
        truths.append((points, ExactSDF(mesh).query(points)[0], to_rest, posed, offsets))
    floors, rows = [], []
    for cells in LABEL_DILATIONS:
        dilated, sets, _ = dilated_labels(labels, arch.joints, cells)
        allowed = allowed_labels(skin.skeleton.parents, arch.neighbours, sets)
        errors, count = [], 0
        for points, truth, to_rest, posed, offsets in truths:
            point, _, rest, _ = parts_through_skinning(points, to_rest, posed, dilated, centre, radius, allowed, boxes,
                                                       weights, arch.skinning_iterations, arch.skinning_solver,
                                                       arch.candidate_rule, offsets=offsets)
            least = np.full(len(points), np.inf)
            np.minimum.at(least, point, rest_sdf.query(rest)[0])
            errors.append(np.abs(least - truth))
            count += len(point)
        floors.append(float(np.concatenate(errors).mean()))
        rows.append(count / sum(len(t[0]) for t in truths))
    best = 0
    for k in range(1, len(LABEL_DILATIONS)):
        if floors[k] <= (1.0 - DILATION_GAIN) * floors[best]:
            best = k
    # band is 1 mm in collider units: floor / band is the floor in millimetres.
    figures = "; ".join(f"{cells} {'cell' if cells == 1 else 'cells'} {floor / band:.3f} mm, {r:.2f} rows a point"
                        for cells, floor, r in zip(LABEL_DILATIONS, floors, rows))
    return LABEL_DILATIONS[best], (f"label dilation {LABEL_DILATIONS[best]} (the map's floor, mean in the +-1 mm "
                                   f"band at {DILATION_POSES} poses off the clips: {figures})")


class _Batches:
    """The samples as torch tensors, and the network's answer at a set of them (the minimum over
    each sample's candidates, and the chosen candidate's gradient through its rigid map)."""

    def __init__(self, samples: ArticulatedSamples):
        import torch

        self.torch = torch
        t = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in asdict(samples).items()}
        self.__dict__.update(t)
        self.parts = samples.codes.shape[1]

    def answer(self, network, index, want_gradient: bool):
        """Distance (b,) at samples ``index`` (b,) int64, and (when asked) the world gradient of
        each sample's chosen candidate (b, 3)."""
        torch = self.torch
        count = self.count[index]
        owner = torch.repeat_interleave(torch.arange(len(index)), count)
        first = torch.repeat_interleave(self.start[index] - (torch.cumsum(count, 0) - count), count)
        rows = first + torch.arange(len(owner))
        rest, joint, pose = self.rest[rows], self.joint[rows], self.pose[rows]
        code = self.codes[pose, joint]
        if want_gradient:
            d, g = network.value_and_gradient(rest, joint, code)
        else:
            d, g = network(rest, joint, code), None
        best = torch.full((len(index),), math.inf).scatter_reduce(0, owner, d, "amin", include_self=True)
        if not want_gradient:
            return best, None
        chosen = d.detach() <= best.detach()[owner]
        # One chosen row per sample (the last of equal ones): its gradient through the rigid map.
        pick = torch.zeros(len(index), dtype=torch.int64).index_put_((owner[chosen],), torch.nonzero(chosen)[:, 0])
        world = torch.einsum("nb,nba->na", g[pick], self.to_rest[rows[pick]])
        return best, world


@dataclass
class ArticulatedResult:
    """A finished run: the collider (best validated weights), its validation error (mm, +-1 mm
    band of the held-out poses), steps, seconds, the validations."""

    collider: ArticulatedNeuralCollider
    best_validation_mm: float
    steps: int
    seconds: float
    history: list = field(default_factory=list)
    data_seconds: float = 0.0

    def summary(self) -> str:
        rate = self.steps / self.seconds if self.seconds > 0 else 0.0
        return (f"{self.steps:,} steps in {self.seconds / 60:.1f} min ({rate:.0f} steps/s, after "
                f"{self.data_seconds:.0f} s of exact samples); best mean error in the +-1 mm band of "
                f"{VALIDATION_POSES} held-out poses {self.best_validation_mm:.4f} mm")


def train_articulated(skin: Skin, name: str, config: TrainConfig, *, arch: ArticulatedGridArchitecture | None = None,
                      poses: int | None = None, units: str = "m", meters_per_unit: float = 1.0, loop: bool = True,
                      source: dict | None = None, show_progress: bool = True,
                      label_dilation: int | None = None, say=None) -> ArticulatedResult:
    """Train the articulated network of ``skin`` (its units and frame) for ``config``'s budget
    (``max_minutes`` / ``steps``, ``samples`` over ``poses`` poses (default :data:`TRAIN_POSES`,
    fewer for fewer than 2,000 samples a pose), ``batch_size``, learning
    rates, ``normal_weight``, ``seed``, ``threads``; its ``preset`` is not used: ``arch``,
    default :data:`ARTICULATED_PRESET` with the skeleton's joints; ``label_dilation``: the label
    grid's (cells), None: chosen by :func:`choose_label_dilation`, its reason kept in the model's
    training settings and passed to ``say`` (a callable taking the line) as soon as it is known; so
    are the label cells the dilation could not code, ``label_cells_uncoded``, said where there are
    any)."""
    import torch

    from ..skinned import skinned_collider

    config.check()
    if poses is None:  # each pose costs an exact SDF: a few thousand samples share one
        poses = min(TRAIN_POSES, max(8, config.samples // 2000))
    arch = replace(arch or ARTICULATED_PRESET, joints=skin.skeleton.joint_count)
    if config.threads is not None:
        set_training_threads(arch, config.threads)
    torch.manual_seed(config.seed)
    exact = skinned_collider(skin, name, loop=loop, padding=config.padding, units=units,
                             meters_per_unit=meters_per_unit, source=source)
    rest = Mesh(skin.vertices, skin.faces, name)
    centre, radius = normalisation(rest, config.padding)
    # The network keeps its cube in float32: the tables the samples are carried through are built
    # on that cube, as the trained model's query builds them (else rows near a cell face differ).
    centre, radius = np.float32(centre).astype(np.float64), float(np.float32(radius))
    began = time.monotonic()
    labels, boxes, weights, anchors = rest_tables(skin, arch, centre, radius)
    arch = replace(arch, weight_blocks=len(weights.block_joints))
    band = 1e-3 / meters_per_unit
    dilation_choice = None
    if label_dilation is None:
        label_dilation, dilation_choice = choose_label_dilation(skin, arch, centre, radius, labels, boxes, weights,
                                                                anchors, ExactSDF(rest), band, config.seed)
        if say is not None:
            say(dilation_choice)
    arch = replace(arch, label_dilation=label_dilation)
    labels, sets, uncoded = dilated_labels(labels, arch.joints, arch.label_dilation)
    if uncoded and say is not None:  # a skeleton of many joints leaves few codes (255 - J)
        say(f"label dilation {arch.label_dilation}: {uncoded:,} cells near a part boundary keep their own label "
            f"(the grid's {NO_PART - arch.joints} set codes ran out): a point there lacks the parts around it")

    margin = config.margin_m / meters_per_unit if config.margin_m else default_margin(rest, meters_per_unit)
    per_pose = max(config.samples // poses, 100)
    train_poses = np.concatenate([skin.skeleton.rest_world()[None],
                                  sample_poses(skin, poses - 1, config.seed)])

    def training_points(mesh, p):
        return sample_points(mesh, per_pose, config, margin, meters_per_unit, config.seed + 1000 + p,
                             padded_box(mesh, config.padding))

    per_validation = max(config.validation_points // VALIDATION_POSES, 100)

    def validation_points(mesh, p):
        points = surface_band_points(mesh, per_validation, band, config.seed + 500 + p)
        return points, np.ones(len(points), bool)

    data = _Batches(make_samples(skin, train_poses, per_pose, training_points, arch, centre, radius, labels,
                                 boxes, weights, show_progress, "exact SDF at training poses", anchors, sets))
    held_out = sample_poses(skin, VALIDATION_POSES, config.seed + 77)
    val = _Batches(make_samples(skin, held_out, per_validation, validation_points, arch, centre, radius,
                                labels, boxes, weights, show_progress, "exact SDF at validation poses", anchors, sets))
    data_seconds = time.monotonic() - began

    network = build_articulated_network(arch, centre, radius)
    network.set_rest_tables(labels, sets, boxes, weights)
    first_lr, last_lr = config.resolved_learning_rates()
    normal_weight = config.resolved_normal_weight()
    optimizer = make_optimizer(network, first_lr)
    generator = torch.Generator().manual_seed(config.seed)
    to_mm = 1000.0 * meters_per_unit
    n = len(data.distance)
    val_index = torch.arange(len(val.distance))

    def validate() -> float:
        network.eval()
        with torch.no_grad():
            d, _ = val.answer(network, val_index, False)
        network.train()
        return float((d - val.distance).abs().mean()) * to_mm

    step, best_mm, best_weights, history = 0, math.inf, None, []
    started = time.monotonic()
    clock = RunClock(config, started, started)
    with clock.progress_bar(f"train {name}", 0, started, show_progress) as bar:
        finished = False
        while not finished:
            lr = cosine_learning_rate(clock.fraction(step, time.monotonic()), first_lr, last_lr)
            for group in optimizer.param_groups:
                group["lr"] = lr
            index = torch.randint(0, n, (config.batch_size,), generator=generator)
            near = data.near[index]
            want_normals = normal_weight > 0 and bool(near.any())
            prediction, gradient = data.answer(network, index, want_normals)
            loss = sdf_loss(prediction, data.distance[index], gradient if want_normals else None,
                            data.gradient[index], near, radius, normal_weight)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            step += 1
            now = time.monotonic()
            finished = clock.finished(step, now)
            if finished or clock.validation_due(step, now):
                error = validate()
                history.append({"step": step, "loss": float(loss.detach()), "1mm": error,
                                "seconds": time.monotonic() - started})
                if error < best_mm:
                    best_mm = error
                    best_weights = {k: v.detach().clone() for k, v in network.state_dict().items()}
                clock.validated(time.monotonic())
                bar.set_postfix_str(f"step {step:,} val±1mm {error:.4f}mm best {best_mm:.4f}mm lr {lr:.1e}",
                                    refresh=False)
            clock.advance(bar, now)
    if best_weights is not None:
        network.load_state_dict(best_weights)
    seconds = time.monotonic() - started
    info = exact.info
    info.kind = ArticulatedNeuralCollider.kind
    info.settings = {**info.settings, "architecture": asdict(arch), "parameters": arch.parameter_count(),
                     "training": {**asdict(config), "poses": poses, "perturb_deg": PERTURB_DEG,
                                  "label_dilation_choice": dilation_choice, "label_cells_uncoded": uncoded,
                                  "steps_done": step, "seconds": round(seconds, 1),
                                  "best_validation_1mm_mm": best_mm}}
    collider = ArticulatedNeuralCollider(info, skin, network.eval(), device="cpu")
    if show_progress:
        print(f"trained {name}: {step:,} steps, best validation {best_mm:.4f} mm", file=sys.stderr)
    return ArticulatedResult(collider, best_mm, step, seconds, history, data_seconds)
