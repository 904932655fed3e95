"""The animated exact kind, measured on the shipped arm (examples/animations/arm.{obj,pc2},
models/arm.safetensors; metres, collider frame, seconds):

- its distances against an independent libigl evaluation (igl.signed_distance) of the linearly
  interpolated mesh at 5 random times between frames, 20,000 points each in the +-1 mm band;
- 1M points distance + normal + contact at one time (a new time each round, so nothing cached
  helps) against a static exact `mesh` collider of one frame, interleaved in 3 rounds.

    python benchmarks/animated_exact.py
"""
import os
import time
from pathlib import Path

import igl
import numpy as np

from collider_contract.point_cache import read_pc2
from collider_server.engine.meshes import Mesh
from collider_server.engine.modelfile import load_collider
from collider_server.making.animation_files import read_obj
from collider_server.making.bake import bake_collider

ROOT = Path(__file__).resolve().parents[1]
print(f"load average {os.getloadavg()[0]:.2f}")
mesh = read_obj(ROOT / "examples/animations/arm.obj")
frames = np.asarray(read_pc2(ROOT / "examples/animations/arm.pc2"), dtype=np.float64)
arm = load_collider(ROOT / "models/arm.safetensors")
info = arm.info.animation
rate, n = info["frame_rate_hz"], info["frames"]
rng = np.random.default_rng(7)
worst = 0.0
for t in rng.uniform(0, (n - 1) / rate, 5):
    pos = t * rate; k = min(int(pos), n - 2); u = pos - k
    v = (1 - u) * frames[k] + u * frames[k + 1]
    faces = mesh.faces.astype(np.int64)
    # points in the +-1 mm band: surface samples pushed along normals
    fi = rng.integers(0, len(faces), 20000); b = rng.dirichlet([1, 1, 1], 20000)
    p = np.einsum("nk,nkd->nd", b, v[faces[fi]])
    fn = np.cross(v[faces[fi, 1]] - v[faces[fi, 0]], v[faces[fi, 2]] - v[faces[fi, 0]])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    p = p + fn * rng.uniform(-1e-3, 1e-3, (20000, 1))
    ref = igl.signed_distance(p, v, faces)[0]
    got = arm.query(p, ["distance"], time=float(t)).distance
    worst = max(worst, float(np.abs(got - ref).max()))
print(f"exact animated arm vs libigl on the interpolated mesh, 5 random times x 20k points in +-1 mm: max |diff| {worst:.3g} m")
static = bake_collider(Mesh(frames[10].astype(np.float64), mesh.faces), "mesh", "arm10", show_progress=False)
pts = rng.uniform(arm.info.domain_min, arm.info.domain_max, (1_000_000, 3))
ta, ts = [], []
for r in range(3):
    s = time.perf_counter(); arm.query(pts, ["distance", "normal", "contact"], time=0.41 + 0.01 * r); ta.append(time.perf_counter() - s)
    s = time.perf_counter(); static.query(pts, ["distance", "normal", "contact"]); ts.append(time.perf_counter() - s)
ra = np.array(ta) / np.array(ts)
print(f"1M points d+n+c: animated {np.median(ta):.3f} s, static {np.median(ts):.3f} s, ratio median {np.median(ra):.2f}x (range {ra.min():.2f}-{ra.max():.2f}), 3 interleaved rounds, a new time each round")
print(f"load average {os.getloadavg()[0]:.2f}")
