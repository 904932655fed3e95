"""What the union's boundary costs per frame or pose (seconds, on the shared meshes; mesh units).

For each mesh: the self-intersection test alone (every frame pays it), the whole union
(:func:`collider_server.engine.union.union_surface`: the test, the regions, the cut cells and
their winding numbers; the winding number's hierarchy built beforehand, since the sign needs it
anyway), and what an ExactSDF costs to build before its first answer without the union (libigl's
AABB tree and the winding number's hierarchy), all interleaved over ``ROUNDS`` rounds, the best
of each. Then a 20k-point signed distance query (uniform in the mesh's box) against the union
and against the mesh itself (libigl's tree and the winding number, as before the union).

Meshes: spot (5.9k faces), two spots crossing (11.7k), four spots crossing (23k), the bunny
(69k), the dragon (100k, 25 crossing pairs), two bunnies crossing (139k): the copies moved by a
quarter of the mesh's size, written as one mesh (a skin folding into itself, in bulk).

    python benchmarks/union_cost.py
"""
import os
import time
from pathlib import Path

import igl
import numpy as np

from collider_server.engine.intersections import self_intersections
from collider_server.engine.meshes import ExactSDF, Mesh, edge_index
from collider_server.engine.union import union_surface
from collider_server.making.mesh_files import load_mesh

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "meshes"
ROUNDS = 2


def copies(mesh: Mesh, n: int) -> Mesh:
    """``n`` copies of ``mesh``, each moved by a quarter of its size from the last, as one mesh."""
    shift = 0.25 * np.ptp(mesh.vertices, axis=0).max() * np.array([1.0, 0.2, 0.1])
    return Mesh(np.concatenate([mesh.vertices + k * shift for k in range(n)]),
                np.concatenate([mesh.faces + k * len(mesh.vertices) for k in range(n)]), f"{n} x {mesh.name}")


def plain_build(mesh: Mesh) -> None:
    """What an ExactSDF built before its first answer without the union."""
    tree = igl.AABB()
    tree.init(mesh.vertices, mesh.faces)
    winding = igl.FastWindingNumberBVH()
    winding.init(mesh.vertices, mesh.faces, 2)


def best(f):
    started = time.perf_counter()
    out = f()
    return time.perf_counter() - started, out


spot, bunny, dragon = (load_mesh(SHARED / f"{n}.obj") for n in ("spot", "stanford-bunny", "dragon"))
meshes = [spot, copies(spot, 2), copies(spot, 4), bunny, dragon, copies(bunny, 2)]
print(f"load average {os.getloadavg()[0]:.2f} (2 cores, shared)")
print("| mesh | faces | crossing pairs | test s | union s | cut faces | dropped faces | union triangles "
      "| ExactSDF build without union s | 20k query union / mesh s |")
print("|---|---|---|---|---|---|---|---|---|---|")
rng = np.random.default_rng(0)
for mesh in meshes:
    sdf = ExactSDF(mesh)
    sdf.winding_number(mesh.vertices[:1])  # the hierarchy, built once (the sign needs it anyway)
    edges = edge_index(mesh.faces)
    test, union, build = [], [], []
    for _ in range(ROUNDS):
        seconds, found = best(lambda m=mesh: self_intersections(m.vertices, m.faces))
        test.append(seconds)
        seconds, result = best(lambda m=mesh, s=sdf, e=edges: union_surface(m.vertices, m.faces, s.winding_number, e))
        union.append(seconds)
        build.append(best(lambda m=mesh: plain_build(m))[0])
    lo, hi = mesh.bounds
    points = rng.uniform(lo, hi, (20_000, 3))
    sdf.union  # noqa: B018 -- built before the timing (a frame's first query pays it, measured above)
    query_union = best(lambda s=sdf, p=points: s.query(p))[0]
    tree = igl.AABB()
    tree.init(mesh.vertices, mesh.faces)
    query_mesh = best(lambda m=mesh, s=sdf, t=tree, p=points: (t.squared_distance(m.vertices, m.faces, p),
                                                               s.winding_number(p)))[0]
    cut, dropped, triangles = ((result.cut_faces, result.dropped_faces, len(result.faces))
                               if result is not None else ("-", "-", "-"))
    print(f"| {mesh.name} | {len(mesh.faces):,} | {len(found)} | {min(test):.3f} | {min(union):.3f} | {cut} | "
          f"{dropped} | {triangles} | {min(build):.3f} | {query_union:.2f} / {query_mesh:.2f} |", flush=True)
print(f"load average {os.getloadavg()[0]:.2f}")
