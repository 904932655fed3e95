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
"""

from __future__ import annotations

from collider_contract import Timeline

from ..collider import ColliderInfo
from .animated_voxel import normal_velocity
from .neural import NeuralCollider
from .neural_deformed import DeformedGridArchitecture
from .neural_keyframes import KeyframeGridArchitecture


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

    @property
    def keyframes(self) -> int:
        return self.timeline.frames

    def evaluate(self, local, want_gradient):
        distance, gradient, _ = self.evaluate_at(local, want_gradient, 0.0)
        return distance, gradient

    def evaluate_at(self, local, want_gradient, time):
        torch = self._torch
        k, s, rate = self.timeline.locate(0.0 if time is None else time)
        x = torch.as_tensor(local, dtype=torch.float32, device=self._device)
        with torch.inference_mode():
            if self.network.can_fuse(x):
                d, g, moving = self.fused(lambda: self.network.query_at(x, k, s, rate, want_gradient))
            else:
                d, g, moving = self.network.query_at(x, k, s, rate, want_gradient)
        distance = d.double().cpu().numpy()
        if not want_gradient:
            return distance, None, None
        gradient = self.across_plateaus(local, g.double().cpu().numpy(),
                                        lambda p: self.evaluate_at(p, False, time)[0])
        moving = moving.double().cpu().numpy()  # the velocity (deformed) or df/dt (keyframes)
        if self._material_velocity:
            return distance, gradient, moving
        return distance, gradient, normal_velocity(gradient, moving)
