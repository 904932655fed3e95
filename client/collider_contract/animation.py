"""How an animated collider runs in time: one rule for the engine, the service and the SDK.

An animated collider has ``frames`` (F >= 2) keyframes at ``frame_rate_hz``: frame ``k`` is at
``t = k / frame_rate_hz`` seconds, the last at ``duration_s = (F - 1) / frame_rate_hz``. Between
two frames the surface is their linear interpolation (an animated mesh: of its vertex positions,
the ground truth at any time; a voxel collider: of its keyframe grids).

Before 0 and after ``duration_s``:

- ``loop``: the time wraps modulo ``duration_s`` (an animation that loops without a jump ends on
  the frame it starts with);
- clamp (``loop`` false): the first or last frame is held and the surface's own velocity is zero.

Segments are right-continuous: a time in ``[k / rate, (k + 1) / rate)`` lies in segment ``k``
(frames ``k`` and ``k + 1``), so the velocity at a keyframe is that of the segment after it; at
the end of a clamped animation the last frame is held (velocity zero), a looping one starts over.

:class:`Timeline` is this rule; ``ModelInfo.animation`` (a dict: ``frames``, ``frame_rate_hz``,
``duration_s``, ``loop``, ``max_surface_speed``) is its wire form.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: The highest frame rate an animation may have, frames per second. A surface's velocity is its
#: displacement per frame times the rate and travels as float32: at 1e300 fps any motion overflows
#: it (an answer with no finite velocity), while no simulation or capture runs near a million.
MAX_FRAME_RATE_HZ = 1e6


def is_frame_rate(value) -> bool:
    """Whether ``value`` is a frame rate an animation may have: a number (not a bool) in
    ``(0, MAX_FRAME_RATE_HZ]`` frames per second."""
    return (not isinstance(value, bool) and isinstance(value, (int, float))
            and 0 < value <= MAX_FRAME_RATE_HZ)


@dataclass(frozen=True)
class Timeline:
    """When an animated collider's frames are, and what happens beyond them.

    frames : F >= 2 keyframes
    frame_rate_hz : keyframes per second, in (0, :data:`MAX_FRAME_RATE_HZ`]
    loop : wrap beyond the ends (True) or hold the end frames (False)
    max_surface_speed : the fastest any point of the surface moves, collider units per second (an
        upper bound: the fastest vertex of the animation); 0 when unknown
    """

    frames: int
    frame_rate_hz: float
    loop: bool = False
    max_surface_speed: float = 0.0

    def __post_init__(self):
        if isinstance(self.frames, bool) or not isinstance(self.frames, int) or self.frames < 2:
            raise ValueError(f"an animation needs at least 2 frames, got {self.frames!r}")
        rate = self.frame_rate_hz
        if not is_frame_rate(rate):
            raise ValueError(f"the frame rate must be a number of frames per second in (0, "
                             f"{MAX_FRAME_RATE_HZ:g}], got {rate!r}")
        if not isinstance(self.loop, bool):
            raise ValueError(f"loop must be true or false, got {self.loop!r}")
        speed = self.max_surface_speed
        if isinstance(speed, bool) or not isinstance(speed, (int, float)) or not (
                math.isfinite(speed) and speed >= 0):
            raise ValueError(f"max_surface_speed must be a finite number >= 0, got {speed!r}")

    @classmethod
    def of_clip(cls, duration_s: float, loop: bool, max_surface_speed: float = 0.0) -> Timeline:
        """A skinned model's clip as a timeline: the same time rule over its ``duration_s``
        seconds (> 0), two frames spanning it (a clip's keys are its own: only
        :attr:`duration_s`, :attr:`loop` and :attr:`max_surface_speed` mean anything here)."""
        if isinstance(duration_s, bool) or not isinstance(duration_s, (int, float)) or not (
                math.isfinite(duration_s) and duration_s > 0):
            raise ValueError(f"a clip's duration must be a number of seconds > 0, got {duration_s!r}")
        return cls(2, 1.0 / duration_s, loop, max_surface_speed)

    @property
    def duration_s(self) -> float:
        """Seconds from the first frame to the last: ``(frames - 1) / frame_rate_hz``."""
        return (self.frames - 1) / self.frame_rate_hz

    def with_loop(self, loop: bool | None) -> Timeline:
        """This timeline with ``loop`` overridden (None: as it is)."""
        if loop is None or loop == self.loop:
            return self
        return Timeline(self.frames, self.frame_rate_hz, bool(loop), self.max_surface_speed)

    def local_time(self, t: float) -> float:
        """``t`` (seconds) in ``[0, duration_s]``: wrapped when looping, clamped otherwise."""
        duration = self.duration_s
        if self.loop:
            return t % duration  # Python's modulo: in [0, duration) for negative t too
        return min(max(t, 0.0), duration)

    def held(self, t: float) -> bool:
        """Whether an end frame is held at ``t``: clamped, at or beyond the last frame or before
        the first (the surface's own velocity is then zero)."""
        return not self.loop and (t < 0.0 or t >= self.duration_s)

    def locate(self, t: float) -> tuple[int, float, float]:
        """Where ``t`` (seconds) falls: ``(k, u, rate)``, segment ``k`` in ``0 .. frames - 2``,
        the fraction ``u`` in ``[0, 1]`` of the way from frame ``k`` to ``k + 1``, and ``rate``,
        d(u)/dt in 1/s: ``frame_rate_hz`` while the animation runs, 0 where an end frame is held.
        Positions are ``(1 - u) x_k + u x_{k+1}``, velocities ``rate (x_{k+1} - x_k)``."""
        if self.held(t):
            return (0, 0.0, 0.0) if t < 0.0 else (self.frames - 2, 1.0, 0.0)
        k, u = segment_at(self.local_time(t) * self.frame_rate_hz, self.frames)
        return k, u, float(self.frame_rate_hz)

    def to_dict(self) -> dict:
        """The wire form: ``ModelInfo.animation``."""
        return {"frames": self.frames, "frame_rate_hz": float(self.frame_rate_hz),
                "duration_s": self.duration_s, "loop": self.loop,
                "max_surface_speed": float(self.max_surface_speed)}

    @classmethod
    def from_dict(cls, data: dict) -> Timeline:
        """The timeline of ``ModelInfo.animation`` (``duration_s`` is derived, not read); a
        ValueError names what is wrong."""
        if not isinstance(data, dict):
            raise ValueError(f"animation must be a map, got {type(data).__name__}")
        missing = [k for k in ("frames", "frame_rate_hz", "loop") if k not in data]
        if missing:
            raise ValueError(f"animation lacks {missing}")
        return cls(data["frames"], data["frame_rate_hz"], data["loop"],
                   data.get("max_surface_speed", 0.0))


def segment_at(position: float, frames: int) -> tuple[int, float]:
    """The segment of a fractional frame ``position`` (frame k at k) of an animation of
    ``frames`` frames: ``(k, u)``, ``k`` in ``0 .. frames - 2`` and ``u`` in ``[0, 1]`` of the way
    from frame ``k`` to ``k + 1`` (the last frame is segment ``frames - 2`` at ``u = 1``)."""
    k = min(int(math.floor(position)), frames - 2)
    return k, min(max(position - k, 0.0), 1.0)
