"""The error figures of a collider against the exact SDF, with the exact SDF's answers at a point
set computed once (a bench's candidates share them) and computed per call: the same figures."""

from __future__ import annotations

import numpy as np
import pytest

from collider_server.engine.meshes import ExactSDF, Mesh
from collider_server.making.bake import bake_collider
from collider_server.making.evaluation import error_figures, exact_reference
from collider_server.making.sampling import band_sets


def test_figures_from_a_shared_reference_are_the_figures_computed_afresh():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    mesh = Mesh(sphere.vertices, sphere.faces, "sphere")
    sdf = ExactSDF(mesh)
    points = band_sets(mesh, 3000, 7, 1.0)["band_10mm"]
    reference = exact_reference(sdf, points)
    for resolution in (12, 24):  # two colliders measured on one reference
        collider = bake_collider(mesh, "voxel", "sphere", resolution=resolution, show_progress=False, device="cpu")
        shared = error_figures(collider, sdf, points, reference=reference)
        afresh = error_figures(collider, sdf, points)
        assert shared == afresh
        assert shared["distance_mean_mm"] > 0 and shared["points"] == len(points)
    assert np.allclose(np.linalg.norm(reference.normal, axis=1), 1.0)
    # Another set's reference (a band mixed up with the other) is refused, not measured against.
    with pytest.raises(ValueError, match="other points"):
        error_figures(collider, sdf, points.copy(), reference=reference)
