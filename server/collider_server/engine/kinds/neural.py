"""The ``neural`` kind: a network that maps a point to its signed distance, and its normal, the
exact gradient of the network: by autograd for the paper's network (this module), analytic for
the default multiresolution grid network (:mod:`.neural_grid`, fused on a CPU by
:mod:`.grid_kernels`).

The paper's network, an MLP with a trainable Fourier-feature layer:

Network: ``u = (x - centre) / radius`` (collider frame to normalised coordinates), features
``[cos(u B), sin(u B)]`` with ``B`` a trainable 3 x K matrix, then L ReLU layers of width H and a
linear output; the output is multiplied by ``radius`` so distances come out in collider units.
The normalisation makes one set of presets work for meshes of any size and unit; the paper's
``B ~ N(0, 32^2)`` per metre on a ~0.1 m bunny corresponds to ``fourier_scale`` ~ 3.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..collider import Collider, ColliderInfo
from ..devices import resolve_device
from . import grid_kernels
from .grid_architecture import require_integers
from .neural_deformed import DeformedGridArchitecture, build_deformed_network
from .neural_grid import GridArchitecture, build_grid_network, pack_table, unpack_table
from .neural_keyframes import KeyframeGridArchitecture, build_keyframe_network


@dataclass(frozen=True)
class Architecture:
    """Shape of the network.

    fourier_features : K, columns of B (the encoding has 2K values)
    hidden_layers : L, ReLU layers
    hidden_width : H, units per ReLU layer
    fourier_scale : standard deviation of B's initialisation, in normalised coordinates
    """

    fourier_features: int = 128
    hidden_layers: int = 3
    hidden_width: int = 256
    fourier_scale: float = 3.0

    def __post_init__(self):
        require_integers(self, ("fourier_features", "hidden_layers", "hidden_width"))
        if not (self.fourier_scale > 0):
            raise ValueError(f"fourier_scale must be > 0, got {self.fourier_scale}")

    def parameter_count(self) -> int:
        k2, h = 2 * self.fourier_features, self.hidden_width
        return 3 * self.fourier_features + (k2 * h + h) + (self.hidden_layers - 1) * (h * h + h) + h + 1


#: Every preset ``collider train --preset`` offers. The paper's architectures (its experiments: a
#: Fourier-feature layer, then fully connected layers of 256 units, 4 for the bunny, 8 for the
#: dragon; here 3 and 8 hidden, K = 128 features) stay unchanged for reproduction; the grid
#: presets (:mod:`.neural_grid`) are ours, chosen by measurement (docs/neural.md).
PRESETS: dict[str, Architecture | GridArchitecture] = {
    "paper-bunny": Architecture(128, 3, 256, 3.0),
    "paper-dragon": Architecture(128, 8, 256, 3.0),
    # Ours: narrower, trains several times faster on a CPU.
    "fast": Architecture(64, 3, 128, 3.0),
    # Twice the default rows per hashed level, stored in 8 bits: the file of 2^16 float16 rows,
    # fewer hash collisions (docs/neural.md, "8-bit tables"); the codes on a mu-law curve, which
    # a large mesh's network needs ("8-bit codes on a curve").
    "grid": GridArchitecture(table_log2=17, table_dtype="int8-mu"),
}

#: The presets of an animation (``collider train --animation``), apart: a static mesh cannot use
#: them (ours, docs/neural.md): keyframe tables blended in time (any motion), or the rest pose's
#: grid carried by fitted deformation fields (a smooth deformation: a twist, a squash).
ANIMATED_PRESETS: dict[str, KeyframeGridArchitecture | DeformedGridArchitecture] = {
    "keyframes": KeyframeGridArchitecture(),
    # The rest pose's grid as the static preset's (docs/neural.md, "8-bit tables").
    "deformed": DeformedGridArchitecture(table_log2=PRESETS["grid"].table_log2,
                                         table_dtype=PRESETS["grid"].table_dtype),
}

#: The animated preset for any motion: ``collider train --animation`` takes it when none is named
#: and it measures better than ``deformed`` after a short trial of each
#: (``making.training.choose_animated_preset``), or when ``--keyframes`` is given.
DEFAULT_ANIMATED_PRESET = "keyframes"

#: The preset ``collider train`` uses when none is named.
DEFAULT_PRESET = "grid"


def architecture_from_dict(values: dict) -> Architecture | GridArchitecture:
    """The architecture stored in a model's ``settings["architecture"]`` (files written before
    the grid encoding have no ``encoding`` key: they are Fourier networks)."""
    values = dict(values)
    for cls in (GridArchitecture, KeyframeGridArchitecture, DeformedGridArchitecture):
        if values.get("encoding") == cls.ENCODING:
            return cls(**values)
    values.pop("encoding", None)
    return Architecture(**values)


def architecture_dict(arch: Architecture | GridArchitecture) -> dict:
    """``arch`` as stored in a model file."""
    return asdict(arch)


def build_network(arch: Architecture | GridArchitecture, centre, radius: float):
    """The torch module for ``arch``; input collider-frame points (n, 3) float32, output (n,)."""
    if isinstance(arch, KeyframeGridArchitecture):
        return build_keyframe_network(arch, centre, radius)
    if isinstance(arch, DeformedGridArchitecture):
        return build_deformed_network(arch, centre, radius)
    if isinstance(arch, GridArchitecture):
        return build_grid_network(arch, centre, radius)
    import torch
    from torch import nn

    class FourierSDF(nn.Module):
        def __init__(self):
            super().__init__()
            self.register_buffer("centre", torch.as_tensor(np.asarray(centre, np.float32)))
            self.register_buffer("radius", torch.tensor(float(radius), dtype=torch.float32))
            self.fourier = nn.Parameter(torch.randn(3, arch.fourier_features) * arch.fourier_scale)
            layers: list[nn.Module] = []
            width = 2 * arch.fourier_features
            for _ in range(arch.hidden_layers):
                layers += [nn.Linear(width, arch.hidden_width), nn.ReLU()]
                width = arch.hidden_width
            layers.append(nn.Linear(width, 1))
            self.body = nn.Sequential(*layers)

        def forward(self, x):
            u = (x - self.centre) / self.radius
            phase = u @ self.fourier
            features = torch.cat([torch.cos(phase), torch.sin(phase)], dim=-1)
            return self.body(features).squeeze(-1) * self.radius

    return FourierSDF()


#: Below this length (distance per unit of the network's frame; a true SDF's is 1) a network's
#: gradient counts as vanished.
PLATEAU_GRADIENT = 1e-6


def across_plateaus(points, gradient, distance_at, step: float, lo, hi):
    """``gradient`` (m, 3) at ``points`` (m, 3) with the rows where the network's own gradient
    vanishes replaced by central differences of ``distance_at(rows, probes)`` (the rows' indices
    (k,), their probes (6k, 3): six per row, +x +y +z -x -y -z, ``step`` from the point, clamped
    to the box ``lo``-``hi``; returns the 6k distances), in the points' frame and units.

    A ReLU network can learn a plateau: a region where every unit of a layer is off and the
    output is a constant, there the bias (the 30-minute bunny of 2026-11-27: a slab ~0.05 mm
    thick at 0.27 mm outside the surface, 0.3 % of the +-1 mm band; the 30-minute walker of
    2026-12-05: 3.8 % of its band points). Its gradient there is exactly zero and the normal would
    be the fallback's guess; the differences across the slab give the surface's direction. Rows
    whose differences vanish too (a true extremum) keep their zero gradient for the caller's
    fallback. The one rule of every neural kind (static, animated, articulated)."""
    flat = np.flatnonzero(np.einsum("ij,ij->i", gradient, gradient) < PLATEAU_GRADIENT ** 2)
    if not len(flat):
        return gradient
    offsets = np.concatenate([np.eye(3) * step, -np.eye(3) * step])  # +x +y +z -x -y -z
    probes = np.clip(points[flat][:, None, :] + offsets[None], lo, hi)
    d = np.asarray(distance_at(flat, probes.reshape(-1, 3))).reshape(len(flat), 6)
    span = probes[:, :3] - probes[:, 3:]  # (k, 3, 3): the clamped steps, per axis
    gradient = gradient.copy()
    gradient[flat] = (d[:, :3] - d[:, 3:]) / np.maximum(np.einsum("kii->ki", span), 1e-30)
    return gradient


class NeuralCollider(Collider):
    """A trained :func:`build_network`; ``info.settings["architecture"]`` holds its shape."""

    kind = "neural"
    chunk_points = 65_536

    def __init__(self, info: ColliderInfo, network, device: str | None = None):
        super().__init__(info)
        import torch

        self._device = resolve_device(device)
        self.network = network.to(self._device).eval()
        for parameter in self.network.parameters():
            parameter.requires_grad_(False)
        self._torch = torch

    @property
    def device(self) -> str:
        return self._device

    @property
    def architecture(self) -> Architecture | GridArchitecture:
        return architecture_from_dict(self.info.settings["architecture"])

    def evaluate(self, local, want_gradient):
        distance, gradient = self._network_evaluate(local, want_gradient)
        if want_gradient:
            gradient = self.across_plateaus(local, gradient, lambda p: self._network_evaluate(p, False)[0])
        return distance, gradient

    def across_plateaus(self, local, gradient, distance_at):
        """``gradient`` (m, 3) at collider-frame points ``local`` with its plateaus crossed
        (:func:`across_plateaus`: central differences of ``distance_at``, collider-frame points ->
        distances, at half the finest cell: the grid's; a Fourier network: 1/256 of the radius)."""
        step = float(self.network.radius) / getattr(self.architecture, "max_resolution", 256)
        return across_plateaus(local, gradient, lambda rows, probes: distance_at(probes), step,
                               self.domain_min, self.domain_max)

    def _network_evaluate(self, local, want_gradient):
        torch = self._torch
        x = torch.as_tensor(local, dtype=torch.float32, device=self._device)
        if hasattr(self.network, "can_fuse") and self.network.can_fuse(x):
            # The CPU fast path: one fused kernel for the whole network (grid_kernels).
            d, g = self.fused(lambda: self.network.fused_query(x, want_gradient))
            return d.double().numpy(), (g.double().numpy() if want_gradient else None)
        if not want_gradient:
            with torch.inference_mode():
                return self.network(x).double().cpu().numpy(), None
        if hasattr(self.network, "value_and_gradient"):  # analytic: no autograd graph
            with torch.inference_mode():
                d, g = self.network.value_and_gradient(x)
            return d.double().cpu().numpy(), g.double().cpu().numpy()
        with torch.enable_grad():
            x.requires_grad_(True)
            d = self.network(x)
            (g,) = torch.autograd.grad(d.sum(), x)
        return d.detach().double().cpu().numpy(), g.double().cpu().numpy()

    def fused(self, kernel):
        """``kernel()`` (a fused numba kernel) on as many threads as torch is given (the
        service's --compute-threads, a simulator's)."""
        torch = self._torch
        threads = torch.get_num_threads()
        grid_kernels.set_threads(threads)
        try:
            return kernel()
        finally:
            if torch.get_num_threads() != threads:
                # numba's OpenMP pool, started by the first kernel of the process, sets the
                # process-wide OpenMP thread count to every core, torch's included: give it back
                # (`collider serve --compute-threads 1` computed on 2 threads after it).
                torch.set_num_threads(threads)

    def tensors(self):
        tensors = {k: v.detach().cpu().numpy() for k, v in self.network.state_dict().items()}
        arch = self.architecture
        if isinstance(arch, GridArchitecture):
            tensors.update(pack_table(tensors.pop("table"), arch))  # a smaller file; docs/neural.md
        return tensors

    @classmethod
    def from_tensors(cls, info, tensors, device=None):
        import torch

        try:
            arch = architecture_from_dict(info.settings["architecture"])
        except (KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"neural settings lack a valid architecture: {exc}") from None
        tensors = unpack_table(tensors, arch) if isinstance(arch, GridArchitecture) else dict(tensors)
        if np.shape(tensors.get("radius")) == (1,):
            # Files written before scalars kept their shape hold the radius as (1,).
            tensors["radius"] = np.asarray(tensors["radius"]).reshape(())
        # The initial weights (and the placeholder centre and radius) are overwritten below: draw
        # them from a forked generator, so that loading a model leaves the caller's torch random
        # stream (a seeded simulation) as it was.
        with torch.random.fork_rng(devices=[]):
            network = build_network(arch, np.zeros(3), 1.0)
        expected = {k: tuple(v.shape) for k, v in network.state_dict().items()}
        found = {k: tuple(v.shape) for k, v in tensors.items()}
        if expected != found:
            raise ValueError(
                f"weights do not match the architecture {asdict(arch)}: "
                f"expected {expected}, found {found}"
            )
        # load_state_dict copies into the float32 parameters and buffers: float32 in memory
        # whatever the stored dtype (a float16 feature table).
        network.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in tensors.items()})
        return cls(info, network, device)
