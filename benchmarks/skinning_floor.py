"""The error floor of kind ``neural-skinned``'s map from a posed point to the rest pose, which no
training removes: the *exact* SDF of the rest mesh read through the map (no network), against
the exact skinned kind (the union of the posed skin) at that pose. What is left is the map's
share of the error.

Poses: ``--clip-times`` random times of the walker's clips and ``--poses`` random poses off the
clips (every joint's local rotation turned by up to 15 degrees); ``--points`` points each in the
+-1 mm band of the posed surface. Candidates per point as the query takes them (the label grid);
the minimum over them. Per variant: mean / p99 / max distance error (mm) and sign errors (%),
clip times and off-clip poses apart. Variants (``--variants``), interleaved per pose:

- ``fp2-w48``: two fixed-point steps ``x_rest <- M(x_rest)^-1 x`` through the 48^3 uint8 weight
  grid (the map of the first model files)
- ``newton-w48``: damped Newton on ``M(y) y = x`` with the weight grid's derivative
- ``newton-w96``: the same through a finer dense weight grid (benchmark only: 7.3 MB, too big to
  ship; says what a finer field would buy)
- ``newton-b96`` / ``fp2-b96``: through the 48^3 grid and blocks of a 96^3 grid near the rest
  surface (:func:`weight_field`, what a model holds with ``fine_weight_resolution`` 96)
- ``newton-surface``: the weights of the closest rest surface point (barycentric), exact on the
  surface (finite-difference derivative; benchmark only)
- a ``+metric`` suffix: the distance divided by the stretch along the normal, ``d_rest / |J^-T
  grad d_rest|`` (J the map's Jacobian at the rest point)

Each grid variant is measured with every candidate rule of ``--rules`` (``own-label``,
``retry-labels``: the architecture's ``candidate_rule``, :func:`parts_through_skinning`), a row
each, with the mean candidates per point kept; ``newton-surface`` takes the own-label candidates.

    python benchmarks/skinning_floor.py
    python benchmarks/skinning_floor.py --variants fp2-w48 newton-w48 newton-w48+metric --points 2000
    python benchmarks/skinning_floor.py --variants newton-b128 --rules own-label retry-labels
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[1] / "server"), str(Path(__file__).resolve().parents[1] / "client")]

from collider_server.engine.kinds import neural_skinned as ns
from collider_server.engine.meshes import ExactSDF, Mesh, barycentric
from collider_server.engine.skinning import pose_at, skin_vertices
from collider_server.making.sampling import surface_band_points
from collider_server.making.skinned import skinned_collider
from collider_server.making.training.articulated import FINE_WEIGHT_BAND_CELLS, sample_poses
from collider_server.making.training.data import normalisation
from collider_server.making.walker import make_walker

VARIANTS = ("fp2-w48", "fp2-w48+metric", "newton-w48", "newton-w48+metric", "fp2-b96", "newton-b96",
            "newton-b96+metric", "newton-w96", "newton-w96+metric", "newton-surface", "newton-surface+metric")


def surface_weights(rest_sdf: ExactSDF, skin, joints: int):
    """A weight function of rest points: the closest rest surface point's barycentric blend of its
    triangle's vertex weights, and its derivative by central differences (h = 0.2 mm)."""

    def dense(y):
        _, closest, face = rest_sdf.query(y)
        tri = skin.faces[face]
        bary = barycentric(closest, skin.vertices[tri])
        out = np.zeros((len(y), joints))
        rows = np.arange(len(y))
        for c in range(3):
            for k in range(skin.joints.shape[1]):
                np.add.at(out, (rows, skin.joints[tri[:, c], k]), bary[:, c] * skin.weights[tri[:, c], k])
        return out

    def weights(y):
        h = 2e-4
        w = dense(y)
        dw = np.empty(w.shape + (3,))
        for a in range(3):
            step = np.zeros(3)
            step[a] = h
            dw[:, :, a] = (dense(y + step) - dense(y - step)) / (2 * h)
        return w, dw

    return weights


def grid_weights(grid, centre, radius, joints: int):
    def weights(y):
        return ns.weights_and_gradient(y, grid, centre, radius, joints)

    return weights


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS))
    parser.add_argument("--clip-times", type=int, default=3)
    parser.add_argument("--poses", type=int, default=3)
    parser.add_argument("--points", type=int, default=5000)
    parser.add_argument("--iterations", type=int, default=8, help="Newton steps")
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--rules", nargs="+", default=["own-label"], choices=ns.CANDIDATE_RULES,
                        help="candidate rules, each grid variant with each")
    args = parser.parse_args()
    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    skin = make_walker().skin()
    joints = skin.skeleton.joint_count
    exact = skinned_collider(skin, "walker", loop=True)
    rest_mesh = Mesh(skin.vertices, skin.faces, "rest")
    rest_sdf = ExactSDF(rest_mesh)
    centre, radius = normalisation(rest_mesh, 0.1)
    arch = ns.ArticulatedGridArchitecture(joints=joints)
    cell = 2.0 * radius / arch.label_resolution
    labels = ns.part_labels(skin, centre, radius, arch.label_resolution, band=3.0 * cell)
    boxes = ns.part_boxes(skin, cell)
    allowed = ns.allowed_labels(skin.skeleton.parents, False)
    weight_functions = {}
    for variant in args.variants:
        source = variant.split("+")[0].split("-")[1]
        if source in weight_functions:
            continue
        if source == "surface":
            weight_functions[source] = (None, surface_weights(rest_sdf, skin, joints))
        else:
            started = time.perf_counter()
            resolution = int(source[1:])
            if source.startswith("w"):  # a dense grid
                grid = ns.weight_field(skin, centre, radius, resolution)
            else:  # the 48^3 grid and blocks of a finer one near the surface
                grid = ns.weight_field(skin, centre, radius, 48, resolution,
                                       FINE_WEIGHT_BAND_CELLS * 2.0 * radius / resolution)
            size = sum(a.nbytes for a in grid)
            print(f"weight field {source}: {size / 1e6:.2f} MB ({len(grid.block_joints)} blocks), built in "
                  f"{time.perf_counter() - started:.0f} s")
            weight_functions[source] = (grid, grid_weights(grid, centre, radius, joints))

    rng = np.random.default_rng(args.seed)
    poses = []
    for _ in range(args.clip_times):
        clip = skin.clips[rng.integers(len(skin.clips))]
        poses.append(("clip", pose_at(skin, clip.name, rng.uniform(0.0, clip.duration_s))[0]))
    poses += [("off", t) for t in sample_poses(skin, args.poses, args.seed + 5, perturbed_share=1.0)]
    rows = [(v, rule) for v in args.variants for rule in (["own-label"] if "surface" in v else args.rules)]
    errors = {(row, kind): [] for row in rows for kind in ("clip", "off")}
    signs = {(row, kind): [] for row in rows for kind in ("clip", "off")}
    candidates = {(row, kind): [] for row in rows for kind in ("clip", "off")}
    seconds = dict.fromkeys(rows, 0.0)
    truths: dict = {"clip": [], "off": []}
    for p, (kind, transforms) in enumerate(poses):
        mesh = Mesh(skin_vertices(skin, transforms), skin.faces, "posed")
        points = surface_band_points(mesh, args.points, 1e-3, args.seed + 100 + p)
        truth = exact.query(points, "distance", joint_transforms=transforms).distance
        truths[kind].append(np.abs(truth))
        to_rest, posed = ns.rest_maps(skin.skeleton, transforms)
        point, _, rigid = ns.part_candidates(points, to_rest, labels, centre, radius, allowed, boxes)
        for variant, rule in rows:
            started = time.perf_counter()
            method, source = variant.split("+")[0].split("-")
            metric = variant.endswith("+metric")
            grid, weights = weight_functions[source]
            if source != "surface":  # the query's rule (its numba passes)
                solver, steps = ("fixed-point", 2) if method == "fp2" else ("newton", args.iterations)
                at, _, rest, _ = ns.parts_through_skinning(points, to_rest, posed, labels, centre, radius, allowed,
                                                           boxes, grid, steps, solver, rule)
            else:
                rest, _, ok = ns.newton_rest(points[point], rigid, posed, weights, args.iterations)
                # The minimum over the candidates kept (converged; all, where none did).
                keep = ok | ~np.bincount(point, ok, len(points)).astype(bool)[point]
                at, rest = point[keep], rest[keep]
            seconds[variant, rule] += time.perf_counter() - started
            d, closest, face = rest_sdf.query(rest)
            if metric:
                g = rest_sdf.gradient(rest, d, closest, face)
                w, dw = weights(rest)
                jacobian = ns.skinning_jacobian(rest, posed, w, dw)
                d = d / np.linalg.norm(np.linalg.solve(np.swapaxes(jacobian, 1, 2), g[..., None])[..., 0], axis=1)
            best = np.full(len(points), np.inf)
            np.minimum.at(best, at, d)
            errors[(variant, rule), kind].append(np.abs(best - truth))
            signs[(variant, rule), kind].append(np.sign(best) != np.sign(truth))
            candidates[(variant, rule), kind].append(len(at) / len(points))
        print(f"pose {p + 1}/{len(poses)} ({kind}) done, load {os.getloadavg()[0]:.2f}", flush=True)
    print(f"{'variant':36s} {'clip times: mean / p99 / max mm, sign % (beyond 0.2 mm), candidates':66s} "
          f"{'off the clips':66s} map s")
    for row in rows:
        line = f"{row[0] + ' ' + row[1]:36s}"
        for kind in ("clip", "off"):
            e = np.concatenate(errors[row, kind]) * 1e3
            wrong = np.concatenate(signs[row, kind])
            clear = np.concatenate(truths[kind]) > 2e-4
            line += (f" {e.mean():7.4f} / {np.percentile(e, 99):6.3f} / {e.max():7.2f}, {wrong.mean() * 100:5.2f} % "
                     f"({wrong[clear].mean() * 100:5.2f} %), {np.mean(candidates[row, kind]):.3f}").ljust(67)
        print(line + f" {seconds[row]:.1f}")
    print(f"load average at end: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
