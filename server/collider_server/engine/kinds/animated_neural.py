"""One network for a whole animation (kind ``neural`` with an ``animation``): keyframe feature
tables blended in time (:mod:`.neural_keyframes`).

``info.animation`` is the keyframes' :class:`~collider_contract.Timeline` (K frames evenly
spaced over the source animation's duration, its loop rule and speed bound; the source's own
frames and rate are in ``info.source``), so the time rule is the contract's: at time t,
``Timeline.locate`` gives the keyframe segment, the fraction and the rate (0 where an end frame is
held). Distance and spatial gradient in the collider frame and units; the surface's velocity is
its normal speed ``-df/dt`` along the unit normal (:func:`.animated_voxel.normal_velocity`, the
voxel keyframes' rule: an implicit surface does not say how its points slide along it, so no
tangential part), collider units per second.
"""

from __future__ import annotations

from collider_contract import Timeline

from ..collider import ColliderInfo
from .animated_voxel import normal_velocity
from .neural import NeuralCollider
from .neural_keyframes import KeyframeGridArchitecture


class AnimatedNeuralCollider(NeuralCollider):
    """A trained keyframe network (``info.settings["architecture"]`` a
    :class:`KeyframeGridArchitecture` with as many keyframes as ``info.animation`` has frames)."""

    def __init__(self, info: ColliderInfo, network, device: str | None = None):
        super().__init__(info, network, device)
        arch = self.architecture
        if not isinstance(arch, KeyframeGridArchitecture):
            raise ValueError(f"an animated neural collider needs a keyframe-grid network, got "
                             f"encoding {arch.encoding!r}")
        self.timeline = Timeline.from_dict(info.animation)
        if arch.keyframes != self.timeline.frames:
            raise ValueError(f"the network has {arch.keyframes} keyframe tables, but the animation "
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
                d, g, dt = self.fused(lambda: self.network.query_at(x, k, s, rate, want_gradient))
            else:
                d, g, dt = self.network.query_at(x, k, s, rate, want_gradient)
        distance = d.double().cpu().numpy()
        if not want_gradient:
            return distance, None, None
        gradient = g.double().cpu().numpy()
        return distance, gradient, normal_velocity(gradient, dt.double().cpu().numpy())
