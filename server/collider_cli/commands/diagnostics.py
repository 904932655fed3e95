"""What ``bake``, ``train`` and ``bench`` say about the mesh before they work and about the sign
after: the mesh check (:mod:`collider_server.making.mesh_check`) and the measured sign errors."""

from __future__ import annotations

import sys

#: Points of the +-1 mm band the closing sign check of ``bake`` and ``train`` measures (about a
#: second on the exact SDF; ``collider eval`` measures 100,000 per band).
SIGN_CHECK_POINTS = 20_000


def print_mesh_check(mesh, file=None):
    """Check ``mesh`` (placed), print what it is and what that means for the sign; return the
    :class:`~collider_server.making.mesh_check.MeshCheck`."""
    from collider_server.making.mesh_check import check_mesh

    check = check_mesh(mesh)
    for line in check.lines():
        print(line, file=file or sys.stdout)
    return check


def sign_check_line(collider, mesh, check=None) -> str:
    """Measure ``collider``'s sign errors in the +-1 mm band of ``mesh`` (its frame and units)
    and say so in one line (with the mesh's holes, when it has some)."""
    from collider_server.engine.meshes import ExactSDF
    from collider_server.making.evaluation import error_figures
    from collider_server.making.sampling import band_sets

    points = band_sets(mesh, SIGN_CHECK_POINTS, 0, collider.info.meters_per_unit)["band_1mm"]
    figures = error_figures(collider, ExactSDF(mesh), points)
    where = ""
    if check is not None and not check.watertight:
        where = f"; the mesh is not watertight ({check.summary()}): sign errors gather near its holes"
    return (f"sign errors: {figures['sign_errors_percent']:.2f} % of {SIGN_CHECK_POINTS:,} points in the +-1 mm "
            f"band (those farther than 0.2 mm from the surface; against the exact winding-number sign), "
            f"mean distance error {figures['distance_mean_mm']:.4f} mm{where}")
