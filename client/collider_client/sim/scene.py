"""Scene files: TOML declaring the cloth, the colliders and the effects to simulate.

Units are in the key names (``_m``, ``_s``, ``_kg_m2``, ``_deg``). Frames: the world frame has
gravity along -z by default; a collider's ``position_m``/``rotation_deg`` place its frame in the
world (collider -> world). An animated collider is asked at the simulation time plus its
``time_offset_s``, looping or clamping as its model was baked unless ``loop`` says otherwise; a
skinned one likewise, in its ``clip`` (left out: its first);
``make`` is the command that makes a model the repository does not ship. Only the tables under
``[effects]`` that a file declares are simulated.
Every error names the file and the key (:mod:`.tables`); colliders' placement and motion are
:mod:`.motion`'s.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .motion import ColliderSpec, Motion
from .tables import SceneError, Table

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10
    import tomli as tomllib

#: The scenes shipped with the package (``collider simulate NAME`` finds them).
SCENES_DIR = Path(__file__).resolve().parents[1] / "scenes"


def shipped_scenes() -> list[str]:
    """Names of the scenes shipped with the package (``collider simulate NAME`` finds them)."""
    return sorted(p.stem for p in SCENES_DIR.glob("*.toml"))


def resolve_scene(name_or_path: str) -> Path:
    """The scene file ``name_or_path``, or the shipped scene of that name; FileNotFoundError
    listing the shipped scenes otherwise."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    shipped = SCENES_DIR / f"{name_or_path}.toml"
    if shipped.is_file():
        return shipped
    raise FileNotFoundError(f"no scene file {name_or_path!r}; shipped scenes: "
                            f"{', '.join(shipped_scenes())}")


EFFECTS = ("gravity", "wind", "damping", "stretch", "shear", "bend", "pins", "collisions",
           "friction")


@dataclass
class ClothSpec:
    """A W x H grid of vertices (quads) in the plane through ``origin_m`` spanned by ``axes``."""

    width: int
    height: int
    spacing_m: float
    origin_m: np.ndarray
    axes: str  # "xy" (horizontal), "xz" or "yz" (vertical)
    density_kg_m2: float


@dataclass
class Scene:
    path: Path
    name: str
    duration_s: float
    dt_s: float
    frame_every: int
    preview_frames: list[int]
    cloth: ClothSpec
    colliders: list[ColliderSpec]
    effects: dict[str, dict[str, Any]]

    @property
    def steps(self) -> int:
        return int(round(self.duration_s / self.dt_s))

    def has(self, effect: str) -> bool:
        return effect in self.effects

    @property
    def up(self) -> np.ndarray:
        """(3,) float64 unit vector, world frame: the scene's up, minus gravity's direction
        (+z when the scene declares no gravity, or a zero one). The PNG preview draws along it."""
        g = np.asarray(self.effects.get("gravity", {}).get("acceleration_m_s2", (0.0, 0.0, 0.0)),
                       dtype=np.float64)
        norm = float(np.linalg.norm(g))
        return -g / norm if norm > 0 else np.array([0.0, 0.0, 1.0])


# -- the scene -----------------------------------------------------------------------------------

def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file. Raises :class:`SceneError` (a ValueError) or
    FileNotFoundError. Model names are checked later against the repository or server."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such scene file")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{path}: not valid TOML: {exc}") from None
    root = Table(data, "", path)

    run = root.table("scene", required=True)
    name = run.string("name", default=path.stem)
    duration_s = run.number("duration_s", required=True, positive=True)
    dt_s = run.number("dt_s", required=True, positive=True)
    if dt_s > duration_s:
        run.fail("dt_s", f"is longer than duration_s ({dt_s} > {duration_s})")
    frame_every = run.number("frame_every_steps", default=100, integer=True, minimum=1)
    preview = run.get("preview_frames", [0, -1])
    if not isinstance(preview, list) or not all(isinstance(i, int) and not isinstance(i, bool)
                                                for i in preview):
        run.fail("preview_frames", f"must be a list of frame indices (negative from the end), got {preview!r}")
    run.done()

    c = root.table("cloth", required=True)
    cloth = ClothSpec(
        width=c.number("width", required=True, integer=True, minimum=2, maximum=4096),
        height=c.number("height", required=True, integer=True, minimum=2, maximum=4096),
        spacing_m=c.number("spacing_m", required=True, positive=True),
        origin_m=c.vector("origin_m", default=[0.0, 0.0, 0.0]),
        axes=c.string("axes", default="xy", choices=("xy", "xz", "yz")),
        density_kg_m2=c.number("density_kg_m2", default=0.5, positive=True),
    )
    c.done()

    colliders = []
    entries = root.get("colliders", [])
    if not isinstance(entries, list):
        root.fail("colliders", "must be an array of tables ([[colliders]])")
    for i, entry in enumerate(entries):
        t = Table(entry, f"colliders[{i}]", path)
        model = t.string("model", required=True)
        position = t.vector("position_m", default=[0.0, 0.0, 0.0])
        rotation = t.vector("rotation_deg", default=[0.0, 0.0, 0.0])
        motion = _motion(t.table("motion"))
        time_offset = t.number("time_offset_s", default=0.0)
        loop = t.boolean("loop")
        clip = t.string("clip")
        make = t.string("make")
        t.done()
        colliders.append(ColliderSpec(model, position, rotation, motion, float(time_offset), loop,
                                      make, clip))

    effects_table = root.table("effects", required=True)
    effects: dict[str, dict[str, Any]] = {}
    for effect in EFFECTS:
        settings = effects_table.table(effect)
        if settings is not None:
            effects[effect] = _EFFECT_READERS[effect](settings, cloth)
            settings.done()
    effects_table.done()
    root.done()

    scene = Scene(path, name, duration_s, dt_s, frame_every, preview, cloth, colliders, effects)
    _check_consistency(scene)
    return scene


def check_models(scene: Scene, infos: dict) -> None:
    """Refuse, naming the file and key, colliders whose model is not among ``infos`` (name ->
    ModelInfo; the collider's ``make`` says how to make it), animation keys on a static model
    and a ``clip`` that is not the model's (or on a model without a skeleton)."""
    missing = [i for i, spec in enumerate(scene.colliders) if spec.model not in infos]
    if missing:
        spec = scene.colliders[missing[0]]
        hint = (f"; make it with: {spec.make}" if spec.make else "")
        raise SceneError(f"{scene.path}: colliders[{missing[0]}].model: no model named "
                         f"{spec.model!r} (available: {sorted(infos) or 'none'}){hint}")
    for i, spec in enumerate(scene.colliders):
        info = infos[spec.model]
        if info.skinned:
            try:
                info.clip_timeline(spec.clip)
            except ValueError as error:
                raise SceneError(f"{scene.path}: colliders[{i}].clip: {error}") from None
            continue
        if spec.clip is not None:
            raise SceneError(f"{scene.path}: colliders[{i}].clip: model {spec.model!r} is not "
                             "skinned (the key applies to skinned models)")
        if info.animated:
            continue
        for key, given in (("time_offset_s", spec.time_offset_s != 0.0), ("loop", spec.loop is not None)):
            if given:
                raise SceneError(f"{scene.path}: colliders[{i}].{key}: model {spec.model!r} is "
                                 "not animated (the key applies to animated and skinned models)")


def _motion(t: Table | None) -> Motion:
    """A collider's [colliders.motion] table (it names its own keys in errors)."""
    if t is None:
        return Motion()
    kind = t.string("kind", default="static", choices=("static", "velocity", "keyframes"))
    motion = Motion(kind=kind)
    if kind == "velocity":
        motion.velocity_m_s = t.vector("velocity_m_s", default=[0.0, 0.0, 0.0])
        motion.angular_velocity_deg_s = t.vector("angular_velocity_deg_s", default=[0.0, 0.0, 0.0])
    elif kind == "keyframes":
        times = t.get("times_s", required=True)
        if (not isinstance(times, list) or len(times) < 2 or any(
                isinstance(v, bool) or not isinstance(v, (int, float)) for v in times)):
            t.fail("times_s", f"must be a list of at least 2 numbers, got {times!r}")
        times = np.asarray(times, dtype=np.float64)
        if np.any(np.diff(times) <= 0):
            t.fail("times_s", f"must increase strictly, got {times.tolist()}")
        motion.times_s = times
        for key in ("positions_m", "rotations_deg"):
            value = t.get(key, [[0.0, 0.0, 0.0]] * len(times))
            try:
                array = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError):
                t.fail(key, f"must be a list of [x, y, z] lists, got {value!r}")
            if array.shape != (len(times), 3) or not np.isfinite(array).all():
                t.fail(key, f"must hold {len(times)} finite [x, y, z] rows (one per time), "
                            f"got shape {array.shape}")
            setattr(motion, key, array)
    t.done()
    return motion


def _gravity(t, cloth):
    return {"acceleration_m_s2": t.vector("acceleration_m_s2", default=[0.0, 0.0, -9.81])}


def _wind(t, cloth):
    return {"velocity_m_s": t.vector("velocity_m_s", required=True),
            "drag_1_s": t.number("drag_1_s", default=1.0, minimum=0.0)}


def _damping(t, cloth):
    return {"coefficient_1_s": t.number("coefficient_1_s", required=True, minimum=0.0)}


def _spring(t, cloth):
    return {"stiffness_n_m": t.number("stiffness_n_m", required=True, positive=True)}


def _pins(t, cloth):
    corners = t.get("corners", [])
    valid = ("top-left", "top-right", "bottom-left", "bottom-right")
    if not isinstance(corners, list) or any(c not in valid for c in corners):
        t.fail("corners", f"must be a list of {list(valid)}, got {corners!r}")
    vertices = t.get("vertices", [])
    if not isinstance(vertices, list) or any(
            not (isinstance(v, list) and len(v) == 2 and all(isinstance(i, int) for i in v))
            for v in vertices):
        t.fail("vertices", f"must be a list of [column, row] integer pairs, got {vertices!r}")
    for col, row in vertices:
        if not (0 <= col < cloth.width and 0 <= row < cloth.height):
            t.fail("vertices", f"[{col}, {row}] is outside the {cloth.width} x {cloth.height} cloth")
    if not corners and not vertices:
        t.fail("corners", "pins need at least one of corners or vertices")
    return {"corners": corners, "vertices": vertices}


def _collisions(t, cloth):
    return {"eps_m": t.number("eps_m", default=1e-3, positive=True)}


def _friction(t, cloth):
    return {"coefficient": t.number("coefficient", required=True, minimum=0.0),
            "restitution": t.number("restitution", default=0.0, minimum=0.0, maximum=1.0)}


_EFFECT_READERS = {"gravity": _gravity, "wind": _wind, "damping": _damping, "stretch": _spring,
                   "shear": _spring, "bend": _spring, "pins": _pins, "collisions": _collisions,
                   "friction": _friction}


def _check_consistency(scene: Scene) -> None:
    path = scene.path
    if scene.colliders and not scene.has("collisions"):
        raise SceneError(f"{path}: colliders are declared but [effects.collisions] is absent; "
                         "add it or remove the [[colliders]]")
    if scene.has("collisions") and not scene.colliders:
        raise SceneError(f"{path}: effects.collisions needs at least one [[colliders]] entry")
    if scene.has("friction") and not scene.has("collisions"):
        raise SceneError(f"{path}: effects.friction needs effects.collisions")
    _check_stability(scene)


def stability_limits(scene: Scene) -> dict[str, float]:
    """The largest safe ``dt_s`` (seconds) of each declared effect that limits it.

    - springs (stretch, shear, bend): explicit integration is stable while dt < 2 / omega_max;
      the stiffest grid mode is about (4 per declared spring family) * k / m;
    - damping and wind drag both scale the velocity by ``1 - (c + drag) dt`` per step: above
      ``dt = 1 / (c + drag)`` the factor turns negative and the velocity flips sign every step
      (above twice that it grows without bound: positions reached 1e36 m).
    """
    limits = {}
    mass = scene.cloth.density_kg_m2 * scene.cloth.spacing_m ** 2
    k_total = sum(4.0 * scene.effects[s]["stiffness_n_m"] for s in ("stretch", "shear", "bend")
                  if scene.has(s))
    if k_total:
        limits["springs"] = 2.0 / math.sqrt(k_total / mass)
    rate = (scene.effects["damping"]["coefficient_1_s"] if scene.has("damping") else 0.0) + (
        scene.effects["wind"]["drag_1_s"] if scene.has("wind") else 0.0)
    if rate > 0:
        limits["damping and wind drag"] = 1.0 / rate
    return limits


def _check_stability(scene: Scene) -> None:
    """Refuse, before the run, a dt_s beyond any declared effect's stability limit."""
    path = scene.path
    limits = stability_limits(scene)
    dt_drag = limits.get("damping and wind drag")
    if dt_drag is not None and scene.dt_s > dt_drag:
        raise SceneError(
            f"{path}: scene.dt_s = {scene.dt_s} is unstable for effects.damping.coefficient_1_s + "
            f"effects.wind.drag_1_s = {1.0 / dt_drag:g} 1/s (the velocity factor 1 - rate * dt "
            f"must stay >= 0): use dt_s <= {dt_drag:.3g} s or a smaller coefficient")
    mass = scene.cloth.density_kg_m2 * scene.cloth.spacing_m ** 2
    k_total = sum(4.0 * scene.effects[s]["stiffness_n_m"] for s in ("stretch", "shear", "bend")
                  if scene.has(s))
    if k_total:
        dt_max = limits["springs"]
        if scene.dt_s >= dt_max:
            raise SceneError(
                f"{path}: scene.dt_s = {scene.dt_s} is unstable for these springs (vertex mass "
                f"{mass:.3g} kg from cloth.density_kg_m2, stiffness sum {k_total / 4:g} N/m): "
                f"use dt_s < {dt_max:.3g}, softer springs or a denser cloth")


