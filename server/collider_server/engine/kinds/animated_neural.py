"""One network for a whole animation (kind ``neural`` with an ``animation``): keyframe feature
tables blended in time (:mod:`.neural_keyframes`), or a rest pose carried by deformation fields
(:mod:`.neural_deformed`).

``info.animation`` is the keyframes' :class:`~collider_contract.Timeline` (K frames evenly
spaced over the source animation's duration, its loop rule and speed bound; the source's own
frames and rate are in ``info.source``; a deformed network has one field per source frame), so
the time rule is the contract's: at time t, ``Timeline.locate`` gives the keyframe segment, the
fraction and the rate (0 where an end frame is held). Distance and spatial gradient in the
collider frame and units. The surface's velocity, collider units per second: for keyframe tables
its normal speed ``-df/dt`` along the unit normal (:func:`.animated_voxel.normal_velocity`, the
voxel keyframes' rule: an implicit surface does not say how its points slide along it, so no
tangential part); for a deformed rest pose the velocity of the material point, sliding included
(the deformation says where each point goes).

A deformed rest pose trained from a mesh's frames keeps them (``surface.frames``, float32, and
``surface.faces``): near the surface its points are answered on the exact patches
(:mod:`.patches`), the frames' faces, interpolated at the time, around the rest field's closest
point, as the articulated network answers a skin; a query of :func:`~.patches.near_points` or more
points first by the cells of the frames at the time (:func:`~.patches.pose_cells`), as the
articulated network's.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from collider_contract import Timeline

from ..animated_meshes import interpolate
from ..collider import ColliderInfo
from ..kept import Kept
from ..meshes import edge_index
from .animated_voxel import normal_velocity
from .neural import NeuralCollider
from .neural_deformed import DeformedGridArchitecture
from .neural_keyframes import KeyframeGridArchitecture
from .patches import (
    NEAR_CELL,
    PATCH_BAND,
    PATCH_CELL,
    PATCH_REACH,
    NearCells,
    PosedSurface,
    answer_near_first,
    answer_on_patches,
    near_points,
    patch_cells,
    pose_cells,
    posed_surface,
)

#: Times whose surface and cells a deformed network keeps (a batch's requests at a few times).
KEEP_TIMES = 4
#: The model file's names of the frames a deformed network keeps for its exact patches.
SURFACE_FRAMES, SURFACE_FACES = "surface.frames", "surface.faces"


class AnimatedNeuralCollider(NeuralCollider):
    """A trained 4D network (``info.settings["architecture"]`` a :class:`KeyframeGridArchitecture`
    or a :class:`DeformedGridArchitecture` with as many keyframes as ``info.animation`` has
    frames)."""

    def __init__(self, info: ColliderInfo, network, device: str | None = None):
        super().__init__(info, network, device)
        arch = self.architecture
        if not isinstance(arch, (KeyframeGridArchitecture, DeformedGridArchitecture)):
            raise ValueError(f"an animated neural collider needs a keyframe-grid or deformed-grid network, "
                             f"got encoding {arch.encoding!r}")
        #: The network answers the material velocity itself (a deformation), not df/dt.
        self._material_velocity = isinstance(arch, DeformedGridArchitecture)
        self.timeline = Timeline.from_dict(info.animation)
        if arch.keyframes != self.timeline.frames:
            raise ValueError(f"the network has {arch.keyframes} keyframes, but the animation "
                             f"has {self.timeline.frames} frames")
        #: The frames (F, v, 3) float32 and faces the exact patches answer on, or None (keyframe
        #: tables, files before them, or turned off): :meth:`keep_surface`.
        self.surface_frames: np.ndarray | None = None
        self.surface_faces: np.ndarray | None = None
        self.patches = None
        self.patch_band = 0.0
        #: The fewest points of a query answered near the surface by the cells of the frames at
        #: its time (:func:`~.patches.near_points`, with the frames kept), or None: never.
        self.near_points: int | None = None
        #: The surfaces and cells of the last times asked, by (segment, fraction, rate).
        self._surfaces: Kept[PosedSurface] = Kept(KEEP_TIMES)
        self._cells: Kept[NearCells] = Kept(KEEP_TIMES)

    def keep_surface(self, frames: np.ndarray, faces: np.ndarray) -> None:
        """Answer near the surface on the exact patches of this animation's ``frames`` (F, v, 3)
        (collider frame and units, one per keyframe: a deformed network's frames are its
        source's) and ``faces`` (f, 3); kept in the model file (float32)."""
        if not self._material_velocity:
            raise ValueError("only a deformed network answers on exact patches (its rest pose is its first frame)")
        frames = np.asarray(frames, np.float32)
        if frames.ndim != 3 or len(frames) != self.timeline.frames:
            raise ValueError(f"the surface needs one frame per keyframe ({self.timeline.frames}), got "
                             f"{list(frames.shape)}")
        self.surface_frames, self.surface_faces = frames, np.asarray(faces, np.int64)
        finest = 2.0 * float(self.network.radius) / self.architecture.max_resolution
        self.patches = patch_cells(frames[0].astype(np.float64), self.surface_faces, PATCH_REACH * finest,
                                   PATCH_CELL * finest)
        self.patch_band = PATCH_BAND * finest
        self._near_cell = NEAR_CELL * finest
        self.near_points = near_points(self.chunk_points)
        self._edges = edge_index(self.surface_faces)
        self._surfaces.clear()
        self._cells.clear()

    def _surface_at(self, k: int, s: float, rate: float) -> PosedSurface:
        """The frames' surface at segment ``k``, fraction ``s``, ``rate`` frames per second (kept
        for the last few times asked): vertices interpolated as the exact animated kind's, their
        velocities its segment's."""
        def build() -> PosedSurface:
            low, high = (self.surface_frames[k].astype(np.float64), self.surface_frames[k + 1].astype(np.float64))
            return posed_surface(interpolate(low, high, s), self.surface_faces, self._edges, (high - low) * rate)

        return self._surfaces.get((k, s, rate), build)

    def _cells_at(self, k: int, s: float, rate: float) -> NearCells:
        """The :func:`~.patches.pose_cells` of :meth:`_surface_at`'s surface (kept alike)."""
        return self._cells.get((k, s, rate), lambda: pose_cells(self._surface_at(k, s, rate), self.surface_faces,
                                                                self._edges, self.patch_band, self._near_cell))

    @property
    def keyframes(self) -> int:
        return self.timeline.frames

    @property
    def gradient_in_one_pass(self) -> bool:  # type: ignore[override]
        """With the exact patches the gradient costs little beside the distance (the patches take
        the rest field's anyway), and one pass answers a point's distance and normal by one rule."""
        return self.patches is not None

    def evaluate(self, local, want_gradient):
        distance, gradient, _ = self.evaluate_at(local, want_gradient, 0.0)
        return distance, gradient

    def evaluate_at(self, local, want_gradient, time):
        """A query of :attr:`near_points` or more points: those near the frames at the time in
        their clean cells by the frames themselves, the others through the network
        (:meth:`_through_network`); a smaller query all through the network."""
        if self.patches is None or self.near_points is None or len(local) < self.near_points:
            return self._through_network(local, want_gradient, time)
        segment = self.timeline.locate(0.0 if time is None else time)
        return answer_near_first(local, self._cells_at(*segment), self._surface_at(*segment), self.surface_faces,
                                 want_gradient,
                                 lambda rows, gradient: self._through_network(rows, gradient, time))

    def _through_network(self, local, want_gradient, time):
        """:meth:`evaluate_at` through the network (and its exact patches)."""
        torch = self._torch
        k, s, rate = self.timeline.locate(0.0 if time is None else time)
        x = torch.as_tensor(local, dtype=torch.float32, device=self._device)
        patched = self.patches is not None
        # A deformed network answers its rest points too (the patches' closest points).
        arguments = (x, k, s, rate, want_gradient) + ((True,) if patched else ())
        with torch.inference_mode():
            if self.network.can_fuse(x):
                answer = self.fused(lambda: self.network.query_at(*arguments))
            else:
                answer = self.network.query_at(*arguments)
        d, g, moving = answer[:3]
        distance = d.double().cpu().numpy()
        exact = self._on_patches(local, answer[3], (k, s, rate)) if patched else None
        if exact is not None:
            distance = np.where(exact.answered, exact.distance, distance)
        if not want_gradient:
            return distance, None, None
        gradient = self.across_plateaus(local, g.double().cpu().numpy(),
                                        lambda p: self._through_network(p, False, time)[0])
        moving = moving.double().cpu().numpy()  # the velocity (deformed) or df/dt (keyframes)
        velocity = moving if self._material_velocity else normal_velocity(gradient, moving)
        if exact is not None:
            gradient[exact.answered] = exact.normal[exact.answered]
            velocity[exact.answered] = exact.velocity[exact.answered]
        return distance, gradient, velocity

    def _on_patches(self, local, rest, segment) -> SimpleNamespace:
        """The exact patches' answers (:func:`~.patches.answer_on_patches`) of points ``local`` at
        keyframe ``segment`` (segment, fraction, rate), ``rest`` the network's rest points and its
        rest field's distance and gradient there: ``distance``, ``normal``, ``velocity`` and
        ``answered`` (where the patch, not the network, answers)."""
        rest_x, d0, g0 = (a.double().cpu().numpy() for a in rest)
        distance, normal, velocity, face = answer_on_patches(local, np.arange(len(local)), rest_x, d0, g0,
                                                             self.patch_band, self.patches, self._surface_at(*segment),
                                                             self.surface_faces)
        return SimpleNamespace(distance=distance, normal=normal, velocity=velocity, answered=face >= 0)

    def tensors(self):
        tensors = super().tensors()
        if self.surface_frames is not None:
            tensors[SURFACE_FRAMES] = self.surface_frames
            tensors[SURFACE_FACES] = self.surface_faces.astype(np.int32)
        return tensors

    @classmethod
    def from_tensors(cls, info, tensors, device=None):
        tensors = dict(tensors)
        frames, faces = tensors.pop(SURFACE_FRAMES, None), tensors.pop(SURFACE_FACES, None)
        if (frames is None) != (faces is None):
            raise ValueError(f"a model keeping its surface needs both {SURFACE_FRAMES!r} and {SURFACE_FACES!r}")
        collider = super().from_tensors(info, tensors, device)
        if frames is not None:
            collider.keep_surface(frames, faces)
        return collider
