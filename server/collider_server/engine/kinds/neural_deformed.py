"""A rest pose and its deformation: the 4D network of an animated ``neural`` collider whose
animation deforms smoothly (a twist, a squash, a breath), one network for the whole animation.

Network (``DeformedGridArchitecture``): the static grid network of :mod:`.neural_grid`, trained on
the animation's **rest pose** (its first frame), and for every frame k of the animation an
**inverse deformation field** ``W_k``: on a grid of ``deformation_resolution`` cells per side over
the collider's domain (normalised coordinates ``u``, trilinear), the offset that carries a point
of frame k to where the same material point is in the rest pose, ``X = u + W_k(u)``. Between
frames k and k + 1 (fraction ``s``) the field is ``(1 - s) W_k + s W_{k+1}``, the rule the
animation's own vertices follow. The fields are fitted to the animation's vertex
correspondences (a least-squares fit, :func:`fit_deformation`), not trained.

With ``f0`` the rest pose's network, ``J = dX/du`` (3 x 3) and ``G = J^T grad f0(X)`` (the gradient
of ``f0(X(u))``), in the collider frame and units:

- distance ``f0(X) |grad f0(X)| / |G|``: ``f0(X(u))`` is a signed distance scaled by the
  deformation's stretch across the surface, ``|J^T n0|`` with ``n0`` the rest normal, and dividing
  by it undoes that to first order (exact on the surface, the error of second order in the
  distance, as Taubin's first-order distance); where the deformation is the identity (the rest
  frame) the answer is the rest network's own;
- normal ``G / |G|``;
- velocity: the velocity of the material point at the query point, ``-J^-1 dX/dt`` (the
  fields' difference times the frame rate): the full velocity, sliding included, as the exact
  kind's, not only the normal speed.

A query is at one time: the two fields are blended once per call, then the warp, its Jacobian and
the velocity run in one fused CPU kernel (:func:`.grid_kernels.warp`) and the rest network as the
static one (the fused CPU kernel), or both as torch ops (CUDA, the reference). ``forward(x)`` and
``value_and_gradient(x)`` without a time are the rest pose's (training); ``forward(x, key,
frac)`` is the deformed distance of points each at its own time (validation).

Where the warp degenerates (a fold the fields cannot follow, forced with ``--preset deformed``),
the stretch is held within [1/10, 10] and a rest gradient of zero leaves it at 1: the answer
stays finite and of the right sign.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from . import grid_kernels
from .grid_architecture import require_integers
from .grid_cells import cell_corners, dense_row
from .neural_grid import GridArchitecture, grid_network_class

#: The stretch's bounds: beyond them the warp is degenerate, not a deformation of the surface.
STRETCH_BOUNDS = (0.1, 10.0)


@dataclass(frozen=True)
class DeformedGridArchitecture(GridArchitecture):
    """A :class:`GridArchitecture` for the rest pose (the ``deformed`` preset: the static
    preset's levels, MLP and 2^17 rows per hashed level in 8 bits) and ``keyframes`` inverse
    deformation fields, one per frame of the animation (the training sets it), of
    ``deformation_resolution`` cells per side."""

    keyframes: int = 2
    deformation_resolution: int = 16
    encoding: str = "deformed-grid"
    ENCODING: ClassVar[str] = "deformed-grid"

    def __post_init__(self):
        super().__post_init__()
        require_integers(self, ("keyframes",), least=2)
        require_integers(self, ("deformation_resolution",))

    def spatial(self) -> GridArchitecture:
        """The rest pose's static grid (same levels, rows and MLP)."""
        return self.grid()

    def field_nodes(self) -> int:
        """Nodes of one deformation field: ``(deformation_resolution + 1)^3``."""
        return (self.deformation_resolution + 1) ** 3

    def parameter_count(self) -> int:
        return super().parameter_count() + self.keyframes * self.field_nodes() * 3


def trilinear(u: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nodes (n, 8) int64, weights (n, 8) and weight derivatives d weight / d u (n, 8, 3) of the
    trilinear interpolation at normalised points ``u`` (n, 3) (clamped into [-1, 1]) on a grid of
    ``resolution`` cells per side over [-1, 1]^3, node ``(i, j, k)`` at row ``i + s (j + s k)``,
    ``s = resolution + 1``: float64 numpy, the network's warp (:func:`field_corners`) on arrays
    (the fit uses it)."""
    import torch

    u = torch.from_numpy(np.asarray(u, np.float64))
    return tuple(a.numpy() for a in field_corners(u, resolution))


def field_corners(u, resolution: int):
    """Nodes (n, 8) int64, weights (n, 8) and d weights / d u (n, 8, 3) of a deformation grid of
    ``resolution`` cells per side at normalised points ``u`` (n, 3) (torch, clamped into
    [-1, 1]): :func:`.grid_cells.cell_corners` at one trilinear level, nodes in a dense table."""
    import torch

    ijk, weight, dweight = cell_corners(u, torch.tensor([resolution], dtype=u.dtype, device=u.device), False)
    ijk, weight, dweight = ijk[:, 0], weight[:, 0], dweight[:, 0]
    return dense_row(ijk[..., 0], ijk[..., 1], ijk[..., 2], resolution + 1), weight, dweight


def build_deformed_network(arch: DeformedGridArchitecture, centre, radius: float):
    """The torch module for ``arch`` (centre (3,) and radius: the normalisation, collider frame
    and units); see the module docstring."""
    import torch

    base = grid_network_class()
    resolution = arch.deformation_resolution

    class DeformedGridSDF(base):
        """``deformation``: (K, nodes, 3) inverse deformation fields (normalised units; a buffer,
        fitted, saved in the model file); everything else as the static GridSDF (the rest pose)."""

        def __init__(self):
            super().__init__(arch.spatial(), centre, radius)
            self.register_buffer("deformation", torch.zeros(arch.keyframes, arch.field_nodes(), 3))

        # -- the warp ---------------------------------------------------------------------------

        def warp(self, u, values, weight, dweight):
            """Rest-pose points ``X`` (n, 3) and ``J = dX/du`` (n, 3, 3) (row: X's component) from
            the corner values (n, 8, 3) of the field at normalised points ``u`` (n, 3)."""
            offset = (weight[..., None] * values).sum(dim=1)
            jacobian = torch.einsum("ncd,nce->nde", values, dweight)
            return u + offset, jacobian + torch.eye(3, dtype=u.dtype, device=u.device)

        def warp_at(self, u, key, frac):
            """:meth:`warp` with point i at keyframe segment ``key[i]``, fraction ``frac[i]``."""
            nodes, weight, dweight = field_corners(u, resolution)
            s = frac[:, None, None]
            values = (1.0 - s) * self.deformation[key[:, None], nodes] + s * self.deformation[key[:, None] + 1, nodes]
            return self.warp(u, values, weight, dweight)

        def deformed(self, x, rest_u, jacobian, fused: bool, rest_answers: bool = False):
            """Distance (n,) and the gradient of ``f0(X(x))`` (n, 3) at collider-frame points ``x``
            whose rest-pose points are ``rest_u`` (normalised) and ``J = jacobian``; with
            ``rest_answers`` also ``(rest point (n, 3), the rest field's distance (n,) and gradient
            (n, 3) there)``, collider frame, else None."""
            rest_x = self.centre + self.radius * rest_u
            if fused:
                d0, g0 = self.fused_query(rest_x, True)
            else:
                d0, g0 = self.value_and_gradient(rest_x)
            g = torch.einsum("nca,nc->na", jacobian, g0)
            rest_norm = g0.norm(dim=1)
            stretch = torch.where(rest_norm > 1e-12, g.norm(dim=1) / rest_norm.clamp_min(1e-12), 1.0)  # |J^T n0|
            return d0 / stretch.clamp(*STRETCH_BOUNDS), g, ((rest_x, d0, g0) if rest_answers else None)

        # -- many times (validation) ------------------------------------------------------------

        def forward(self, x, key=None, frac=None):
            """Distance (n,) at collider-frame points ``x`` (n, 3): of the rest pose without
            ``key`` (training), else of the animation, point i at keyframe segment ``key[i]`` and
            fraction ``frac[i]``."""
            if key is None:
                return super().forward(x)
            rest_u, jacobian = self.warp_at((x - self.centre) / self.radius, key, frac)
            return self.deformed(x, rest_u, jacobian, False)[0]

        # -- one time (queries) -----------------------------------------------------------------

        def query_at(self, x, k: int, s: float, rate: float, want_gradient: bool, rest_answers: bool = False):
            """Distance (n,), and when ``want_gradient`` the unit normal (n, 3) and the velocity of
            the material point at each point (n, 3, collider units per second), at collider-frame
            points ``x`` (n, 3) at one time (frame segment ``k``, fraction ``s``, ``rate`` frames
            per second, 0 where an end frame is held); with ``rest_answers`` a fourth item, the
            rest points and the rest field's distance and gradient there (:meth:`deformed`). Fused
            on a CPU (numba), else torch ops."""
            low, high = self.deformation[k], self.deformation[k + 1]
            field, dfield = low + s * (high - low), (high - low) * rate
            u = (x - self.centre) / self.radius
            fused = self.can_fuse(x)
            if fused:
                rest_u, jacobian, velocity = self._fused_warp(u, field, dfield, want_gradient)
            else:
                nodes, weight, dweight = field_corners(u, resolution)
                rest_u, jacobian = self.warp(u, field[nodes], weight, dweight)
                if want_gradient:  # d X / dt at fixed x; the material point (X fixed) moves at -J^-1 dX/dt
                    rest_rate = (weight[..., None] * dfield[nodes]).sum(dim=1)
                    velocity = -torch.linalg.solve_ex(jacobian, rest_rate)[0]  # no raise where J is singular
            distance, g, rest = self.deformed(x, rest_u, jacobian, fused, rest_answers)
            if not want_gradient:
                return distance, None, None, rest
            return distance, g / g.norm(dim=1, keepdim=True).clamp_min(1e-12), velocity * self.radius, rest

        def _fused_warp(self, u, field, dfield, want_velocity: bool):
            n = len(u)
            rest = np.empty((n, 3), np.float32)
            jacobian = np.empty((n, 3, 3), np.float32)
            velocity = np.empty((n if want_velocity else 0, 3), np.float32)
            grid_kernels.warp(u.contiguous().numpy(), field.contiguous().numpy(), dfield.contiguous().numpy(),
                              resolution, want_velocity, rest, jacobian, velocity)
            return torch.from_numpy(rest), torch.from_numpy(jacobian), torch.from_numpy(velocity)

    return DeformedGridSDF()
