"""benchmarks/large_errors.py sorts an articulated network's large errors into the map's and the
network's: it must answer each point through the query's own rows (its candidate rule, map and
surface offsets), or it describes a collider that is not the one served."""

from __future__ import annotations

import numpy as np
from tests.conftest import REPO_ROOT, load_benchmark

from collider_server.engine.meshes import Mesh
from collider_server.engine.modelfile import load_collider
from collider_server.engine.skinning import random_poses, skin_vertices
from collider_server.making.sampling import surface_band_points


def benchmark():
    return load_benchmark("large_errors")


def test_the_benchmark_answers_each_point_as_the_query_does():
    collider = load_collider(REPO_ROOT / "models" / "walker-neural.safetensors")
    collider.patches = None  # the network's answers, which the benchmark studies (the patches answer most exactly)
    assert collider.arch.surface_offsets  # the shipped walker's map has them: what a stale copy of the rows would miss
    transforms = random_poses(collider.skin, 1, 11).transforms[0]
    x = surface_band_points(Mesh(skin_vertices(collider.skin, transforms), collider.skin.faces, "posed"),
                            2000, 1e-3, 12)
    answer = benchmark().answer_by_rows(collider, x, transforms)
    served = collider.query(x, ("distance",), joint_transforms=transforms).distance
    np.testing.assert_allclose(answer.distance, served, rtol=0, atol=1e-9)  # metres
    assert np.array_equal(answer.distance, answer.row_distance[answer.chosen])
