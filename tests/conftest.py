"""Shared fixtures: the test meshes folder, procedural shapes with analytic SDFs, small colliders.

Nothing here imports torch or ``collider_server`` at module import time (client tests check that
the client stays light); heavy imports happen inside the fixtures that need them.

Units: metres. Frames: every procedural shape is centred at the origin of its own frame.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
#: The shared real meshes (never copied into the repository); tests skip when absent.
MESHES_DIR = REPO_ROOT.parent / "shared" / "data" / "meshes"


def shared_mesh_path(name: str) -> Path:
    """Path of ``MESHES_DIR/name`` (e.g. "stanford-bunny.obj"); skips the test when absent."""
    path = MESHES_DIR / name
    if not path.is_file():
        pytest.skip(f"shared test mesh {path} is absent")
    return path


@functools.cache
def _load_shared_mesh(name: str):
    from collider_server.making.mesh_files import load_mesh

    return load_mesh(MESHES_DIR / name)


@pytest.fixture(scope="session")
def meshes_dir() -> Path:
    """The shared meshes folder; skips when it is absent."""
    if not MESHES_DIR.is_dir():
        pytest.skip(f"shared test meshes folder {MESHES_DIR} is absent")
    return MESHES_DIR


@pytest.fixture(scope="session")
def load_shared_mesh() -> Callable:
    """``load_shared_mesh("stanford-bunny.obj")`` -> :class:`collider_server.engine.meshes.Mesh`
    (cached for the session); skips when the file is absent."""

    def load(name: str):
        shared_mesh_path(name)
        return _load_shared_mesh(name)

    return load


@pytest.fixture(scope="session")
def built_once(tmp_path_factory) -> Callable:
    """``built_once(name, build)`` -> a folder that ``build(folder)`` filled, built once per test
    run: under ``-n`` (pytest-xdist) the first worker that asks builds it under a file lock in the
    run's temporary folder, which every worker shares, and the others wait for it (a quick bench
    or a trained model, made twice on two workers, took twice the CPU of a busy CI host). A build
    that raised is built again by the next worker that asks. Never change what other tests read
    in it (a collider cache inside may gain entries)."""
    import os
    import shutil

    from filelock import FileLock

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's folder; each worker's own is popen-gwN inside it

    def get(name: str, build: Callable[[Path], None]) -> Path:
        folder, done = root / name, root / f"{name}.built"
        with FileLock(str(root / f"{name}.lock")):
            if not done.is_file():
                shutil.rmtree(folder, ignore_errors=True)  # what a failed build left
                folder.mkdir()
                build(folder)
                done.touch()
        return folder

    return get


def load_benchmark(name: str):
    """The script ``benchmarks/<name>.py`` as a module (the scripts are not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO_ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_collider(*args):
    """``collider ARGS`` run in this process, as ``python -m collider_cli`` runs it: a
    ``subprocess.CompletedProcess`` with its exit status, stdout and stderr. For a test of a
    command (its options, output and status), not of a process (signals, a pasted line): a
    subprocess spends about 4 s of CPU importing torch before it starts. Warnings print to stderr
    as in a fresh interpreter; the CPU threads a training run sets (torch's, the kernels') are
    restored for the tests after it."""
    import contextlib
    import io
    import subprocess
    import warnings

    import torch

    from collider_cli import main
    from collider_server.engine.kinds import grid_kernels

    threads = torch.get_num_threads(), grid_kernels.threads()
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
            warnings.resetwarnings()
            warnings.simplefilter("default")
            try:
                code = main([str(a) for a in args])
            except SystemExit as exc:  # argparse's refusals exit 2
                code = exc.code
    finally:
        torch.set_num_threads(threads[0])
        grid_kernels.set_threads(threads[1])
    return subprocess.CompletedProcess(["collider", *map(str, args)], code, out.getvalue(), err.getvalue())


#: The public RiggedSimple glTF character (a cylinder bending at its one inner joint).
CHARACTER = REPO_ROOT / "tests" / "data" / "gltf" / "RiggedSimple.gltf"


@pytest.fixture(scope="session")
def trained_character(built_once) -> dict:
    """``collider train RiggedSimple.gltf --name cylinder-neural --fit-size 1.0`` for 20 steps (8,000
    samples, batches of 1,024, one thread), run in this process once per test run:
    ``{"models": folder holding cylinder-neural.safetensors, "code": exit code, "out": stdout,
    "err": stderr}``. Copy the model file before anything writes into it (``collider eval``)."""
    import contextlib
    import io
    import json

    def train(folder: Path) -> None:
        from collider_cli import main

        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(["train", str(CHARACTER), "--name", "cylinder-neural", "--fit-size", "1.0", "--steps",
                         "20", "--samples", "8000", "--batch-size", "1024", "--threads", "1", "--models",
                         str(folder / "models"), "--quiet"])
        (folder / "run.json").write_text(json.dumps({"code": code, "out": out.getvalue(), "err": err.getvalue()}))

    folder = built_once("trained-character", train)
    return {"models": folder / "models", **json.loads((folder / "run.json").read_text())}


# -- devices ---------------------------------------------------------------------------------


def _skip_without_cuda() -> None:
    import torch

    if not torch.cuda.is_available():
        pytest.skip("no CUDA GPU on this machine (CI has none: these run on a lent GPU, docs/neural.md)")


@pytest.fixture(params=["cpu", "cuda"])
def device(request) -> str:
    """Each torch device: "cpu" always, "cuda" only when a CUDA GPU is present."""
    if request.param == "cuda":
        _skip_without_cuda()
    return request.param


@pytest.fixture
def cuda() -> str:
    """"cuda", for a test that compares a CUDA GPU's answers with the CPU's; skipped without one."""
    _skip_without_cuda()
    return "cuda"


# -- procedural shapes with analytic signed distances ----------------------------------------


@dataclass(frozen=True)
class Shape:
    """A procedural solid with its exact SDF.

    mesh : :class:`collider_server.engine.meshes.Mesh`, a high-resolution triangulation (metres)
    sdf : (n, 3) float64 points -> (n,) float64 signed distance, negative inside
    gradient : (n, 3) float64 points -> (n, 3) unit outward SDF gradient
    sample : (n, seed) -> (n, 3) float64 points near the surface where the SDF is smooth
        (off the medial axis), for accuracy checks
    facet_error : bound on |mesh SDF - analytic SDF|, metres (the triangulation's deviation)
    edge_length : longest mesh edge, metres
    """

    name: str
    mesh: object
    sdf: Callable
    gradient: Callable
    sample: Callable
    facet_error: float
    edge_length: float


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _mesh(tri, name: str):
    from collider_server.engine.meshes import Mesh

    return Mesh(np.asarray(tri.vertices, np.float64), np.asarray(tri.faces, np.int64), name)


def _longest_edge(mesh) -> float:
    tri = mesh.vertices[mesh.faces]
    return float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max())


SPHERE_RADIUS = 0.1
BOX_HALF = np.array([0.1, 0.05, 0.075])
TORUS_MAJOR, TORUS_MINOR = 0.1, 0.03


def make_sphere() -> Shape:
    import trimesh

    mesh = _mesh(trimesh.creation.icosphere(subdivisions=5, radius=SPHERE_RADIUS), "sphere")

    def sdf(p):
        return np.linalg.norm(p, axis=1) - SPHERE_RADIUS

    def sample(n, seed):
        rng = np.random.default_rng(seed)
        return _unit(rng.normal(size=(n, 3))) * (SPHERE_RADIUS + rng.uniform(-0.02, 0.02, n))[:, None]

    # A face of an inscribed icosphere sags below the sphere by about e^2 / (6 r) at its centre
    # (e the edge, r the radius); bound it by e^2 / (5 r).
    edge = _longest_edge(mesh)
    return Shape("sphere", mesh, sdf, _unit, sample, edge**2 / (5 * SPHERE_RADIUS), edge)


def make_box() -> Shape:
    import trimesh

    mesh = _mesh(trimesh.creation.box(extents=2 * BOX_HALF), "box")

    def sdf(p):
        q = np.abs(p) - BOX_HALF
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        return outside + np.minimum(q.max(axis=1), 0.0)

    def gradient(p):
        q = np.abs(p) - BOX_HALF
        sign = np.where(p < 0, -1.0, 1.0)
        out = np.maximum(q, 0.0)
        is_out = (q > 0).any(axis=1)
        g = np.zeros_like(p)
        g[is_out] = _unit(out[is_out]) * sign[is_out]
        inner = ~is_out
        axis = q[inner].argmax(axis=1)
        g[np.flatnonzero(inner), axis] = sign[inner, axis]
        return g

    def sample(n, seed):
        # Points over the inner 60 % of each face, +-8 mm along its normal (off the medial
        # surface), plus points outside the corners and edges where the SDF is round.
        rng = np.random.default_rng(seed)
        n_face = n - n // 4
        axis = rng.integers(0, 3, n_face)
        side = rng.choice([-1.0, 1.0], n_face)
        p = rng.uniform(-0.6, 0.6, (n_face, 3)) * BOX_HALF
        p[np.arange(n_face), axis] = side * (BOX_HALF[axis] + rng.uniform(-0.008, 0.008, n_face))
        corner = rng.choice([-1.0, 1.0], (n // 4, 3)) * BOX_HALF
        away = np.abs(rng.normal(size=(n // 4, 3))) * np.sign(corner)
        corner_points = corner + _unit(away) * rng.uniform(0.002, 0.02, n // 4)[:, None]
        return np.concatenate([p, corner_points])

    return Shape("box", mesh, sdf, gradient, sample, 1e-12, _longest_edge(mesh))


def make_torus() -> Shape:
    """A torus around the z axis."""
    import trimesh

    tri = trimesh.creation.torus(TORUS_MAJOR, TORUS_MINOR, major_sections=128, minor_sections=64)
    mesh = _mesh(tri, "torus")

    def tube(p):
        rho = np.linalg.norm(p[:, :2], axis=1)
        return rho, np.stack([rho - TORUS_MAJOR, p[:, 2]], axis=1)

    def sdf(p):
        return np.linalg.norm(tube(p)[1], axis=1) - TORUS_MINOR

    def gradient(p):
        rho, q = tube(p)
        q = _unit(q)
        return np.stack([q[:, 0] * p[:, 0] / rho, q[:, 0] * p[:, 1] / rho, q[:, 1]], axis=1)

    def sample(n, seed):
        rng = np.random.default_rng(seed)
        theta, phi = rng.uniform(0, 2 * np.pi, (2, n))
        r = TORUS_MINOR + rng.uniform(-0.01, 0.01, n)
        rho = TORUS_MAJOR + r * np.cos(phi)
        return np.stack([rho * np.cos(theta), rho * np.sin(theta), r * np.sin(phi)], axis=1)

    # Sagitta of the major and minor polygons.
    facet = TORUS_MAJOR * (1 - np.cos(np.pi / 128)) + TORUS_MINOR * (1 - np.cos(np.pi / 64))
    return Shape("torus", mesh, sdf, gradient, sample, 1.5 * facet + 1e-6, _longest_edge(mesh))


SHAPE_MAKERS = {"sphere": make_sphere, "box": make_box, "torus": make_torus}


@functools.cache
def procedural_shape(name: str) -> Shape:
    """The procedural :class:`Shape` ``name`` ("sphere", "box", "torus"), cached."""
    return SHAPE_MAKERS[name]()


#: Voxel resolution of the small procedural colliders (fast to bake, still accurate).
TEST_VOXEL_RESOLUTION = 64


@functools.cache
def _baked(shape_name: str, kind: str, resolution: int):
    from collider_server.making.bake import bake_collider

    return bake_collider(procedural_shape(shape_name).mesh, kind, f"{shape_name}-{kind}",
                         resolution=resolution, device="cpu", show_progress=False)


def make_neural_collider(domain_min, domain_max, *, seed: int = 0, device: str = "cpu",
                         name: str = "tiny", fourier_features: int = 8, hidden_layers: int = 2,
                         hidden_width: int = 16, fourier_scale: float = 1.0, grid: bool = False):
    """An untrained (randomly initialised, seeded) small :class:`NeuralCollider` over the box
    ``[domain_min, domain_max]`` (collider frame, metres): for plumbing tests, not accuracy.
    ``grid``: a small grid-encoded network (the default preset's kind, with its CPU fused
    kernels), its feature table filled with values large enough to vary the field."""
    import torch

    from collider_server.engine.collider import ColliderInfo
    from collider_server.engine.kinds.neural import Architecture, NeuralCollider, build_network
    from collider_server.engine.kinds.neural_grid import GridArchitecture

    if grid:
        arch = GridArchitecture(levels=4, max_resolution=32, table_log2=12,
                                hidden_layers=hidden_layers, hidden_width=hidden_width)
    else:
        arch = Architecture(fourier_features, hidden_layers, hidden_width, fourier_scale)
    lo, hi = np.asarray(domain_min, np.float64), np.asarray(domain_max, np.float64)
    info = ColliderInfo(name, "neural", lo.tolist(), hi.tolist(),
                        settings={"architecture": arch.__dict__.copy()})
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        network = build_network(arch, 0.5 * (lo + hi), 0.5 * float((hi - lo).max()))
        if grid:
            with torch.no_grad():
                network.table.uniform_(-0.5, 0.5)
    return NeuralCollider(info, network, device)


@pytest.fixture(scope="session")
def shape_collider() -> Callable:
    """``shape_collider("sphere", "voxel")`` -> a CPU collider of that procedural shape, shared
    by the session (do not mutate it). Kinds: voxel (64^3), mesh, kdtree, and neural / grid (a
    tiny untrained Fourier / grid network over the voxel kind's padded domain)."""

    def get(shape_name: str, kind: str, resolution: int = TEST_VOXEL_RESOLUTION):
        if kind in ("neural", "grid"):
            box = _baked(shape_name, "kdtree", resolution)
            return make_neural_collider(box.domain_min, box.domain_max, grid=kind == "grid",
                                        name=f"{shape_name}-{kind}")
        return _baked(shape_name, kind, resolution)

    return get


@pytest.fixture
def small_sphere_model(tmp_path) -> Path:
    """A saved 32^3 voxel sphere (radius 0.1 m) in a fresh model repository ``tmp_path/models``;
    returns the file path (``.../models/sphere.safetensors``)."""
    import trimesh

    from collider_server.engine.modelfile import save_collider
    from collider_server.making.bake import bake_collider

    mesh = _mesh(trimesh.creation.icosphere(subdivisions=3, radius=SPHERE_RADIUS), "sphere")
    collider = bake_collider(mesh, "voxel", "sphere", resolution=32, show_progress=False, device="cpu")
    return save_collider(collider, tmp_path / "models" / "sphere.safetensors")


@pytest.fixture(scope="session")
def analytic_shape() -> Callable:
    """``analytic_shape("sphere" | "box" | "torus")`` -> :class:`Shape` (mesh + exact SDF)."""
    return procedural_shape


@pytest.fixture(scope="session")
def tiny_neural_collider() -> Callable:
    """:func:`make_neural_collider`: ``tiny_neural_collider(domain_min, domain_max, seed=0,
    device="cpu", ...)`` -> an untrained small NeuralCollider (plumbing tests only)."""
    return make_neural_collider


def closest_point_brute_force(triangles: np.ndarray, point: np.ndarray) -> tuple[float, np.ndarray]:
    """Slow, obviously correct reference: the closest point to ``point`` (3,) over every one of
    ``triangles`` (f, 3, 3), by Ericson's Voronoi-region test per triangle (Real-Time Collision
    Detection, 5.1.5), float64. Returns ``(distance, closest (3,))``.

    (trimesh.triangles.closest_point is not used: on thin triangles it can return a point on an
    edge although an interior point is closer.)"""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    p = np.asarray(point, np.float64)[None, :]
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c

    def dot(u, v):
        return np.einsum("ij,ij->i", u, v)

    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        on_ab = a + (d1 / (d1 - d3))[:, None] * ab
        on_ac = a + (d2 / (d2 - d6))[:, None] * ac
        on_bc = b + ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None] * (c - b)
        denom = 1.0 / (va + vb + vc)
        inside = a + (vb * denom)[:, None] * ab + (vc * denom)[:, None] * ac
    conditions = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
    ]
    choices = [a, b, on_ab, c, on_ac, on_bc]
    closest = inside.copy()
    for condition, choice in reversed(list(zip(conditions, choices))):  # first match wins
        closest[condition] = choice[condition]
    distance = np.linalg.norm(closest - p, axis=1)
    best = int(np.nanargmin(distance))
    return float(distance[best]), closest[best]


@pytest.fixture(scope="session")
def brute_force_closest_point() -> Callable:
    """:func:`closest_point_brute_force`: ``(triangles (f, 3, 3), point (3,)) -> (distance,
    closest (3,))``, the slow reference for exact-distance tests."""
    return closest_point_brute_force
