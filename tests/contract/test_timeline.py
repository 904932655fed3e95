"""The time rule of animated colliders (collider_contract.animation.Timeline): frame k at
k / rate, linear between frames, right-continuous segments, loop wraps and clamp holds with zero
velocity; its wire form and its refusals. Seconds; no torch."""

from __future__ import annotations

import re

import pytest

from collider_contract import ModelInfo, Timeline
from collider_contract.animation import MAX_FRAME_RATE_HZ


def test_frames_segments_and_rates():
    line = Timeline(5, 4.0)  # frames at 0, .25, .5, .75, 1.0 s
    assert line.duration_s == 1.0 and not line.loop
    assert line.locate(0.0) == (0, 0.0, 4.0)
    assert line.locate(0.25) == (1, 0.0, 4.0)  # a keyframe starts the segment after it
    k, u, rate = line.locate(0.6)
    assert (k, rate) == (2, 4.0) and u == pytest.approx(0.4)
    assert line.locate(0.999999)[0] == 3


def test_clamp_holds_the_ends_with_zero_rate():
    line = Timeline(5, 4.0, loop=False)
    assert line.locate(-3.0) == (0, 0.0, 0.0)
    assert line.locate(1.0) == (3, 1.0, 0.0)  # the end: the last frame, held
    assert line.locate(7.5) == (3, 1.0, 0.0)
    assert line.held(1.0) and line.held(-0.1) and not line.held(0.0) and not line.held(0.99)
    assert line.local_time(7.5) == 1.0 and line.local_time(-1.0) == 0.0


def test_loop_wraps_by_the_duration():
    line = Timeline(5, 4.0, loop=True)
    assert line.locate(1.0) == (0, 0.0, 4.0)  # the end is the start again
    k, u, rate = line.locate(2.6)
    assert (k, rate) == (2, 4.0) and u == pytest.approx(0.4)
    k, u, _ = line.locate(-0.4)  # 0.6 s into the loop
    assert k == 2 and u == pytest.approx(0.4)
    assert not line.held(99.0) and line.local_time(-0.4) == pytest.approx(0.6)


def test_overriding_loop_keeps_the_rest():
    line = Timeline(5, 4.0, loop=False, max_surface_speed=2.5)
    looped = line.with_loop(True)
    assert looped.loop and looped.max_surface_speed == 2.5 and looped.frames == 5
    assert line.with_loop(None) is line and line.with_loop(False) is line


def test_wire_form_round_trips_through_model_info():
    line = Timeline(25, 24.0, loop=True, max_surface_speed=0.9)
    data = line.to_dict()
    assert data == {"frames": 25, "frame_rate_hz": 24.0, "duration_s": 1.0, "loop": True,
                    "max_surface_speed": 0.9}
    info = ModelInfo.from_dict({"name": "arm", "kind": "mesh", "animation": data})
    assert info.animated and info.timeline == line
    assert ModelInfo(name="still", kind="mesh").timeline is None


@pytest.mark.parametrize("args, message", [
    ((1, 24.0), "at least 2 frames"),
    ((True, 24.0), "at least 2 frames"),
    ((5, 0.0), "frame rate must be a number of frames per second in (0, 1e+06]"),
    ((5, -24.0), "frame rate must be a number of frames per second in (0, 1e+06]"),
    ((5, float("nan")), "frame rate must be a number of frames per second in (0, 1e+06]"),
    ((5, float("inf")), "frame rate must be a number of frames per second in (0, 1e+06]"),
    ((5, 24.0, "yes"), "loop must be true or false"),
    ((5, 24.0, False, -1.0), "max_surface_speed must be"),
])
def test_refusals(args, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        Timeline(*args)


def test_a_malformed_wire_form_is_refused():
    with pytest.raises(ValueError, match=r"animation lacks \['loop'\]"):
        Timeline.from_dict({"frames": 3, "frame_rate_hz": 2.0})
    with pytest.raises(ValueError, match="animation must be a map"):
        Timeline.from_dict([3, 2.0])


def test_the_smallest_animation_and_any_positive_rate_are_accepted():
    line = Timeline(2, 0.5)  # two frames two seconds apart
    assert line.duration_s == 2.0 and line.locate(1.0) == (0, 0.5, 0.5)
    assert Timeline(2, MAX_FRAME_RATE_HZ).frame_rate_hz == MAX_FRAME_RATE_HZ  # the bound is in


@pytest.mark.parametrize("frames, rate, speed, message", [
    (2.5, 1.0, 0.0, "an animation needs at least 2 frames, got 2.5"),
    (2, "24", 0.0, "the frame rate must be a number of frames per second in (0, 1e+06], got '24'"),
    (2, 1e300, 0.0, "the frame rate must be a number of frames per second in (0, 1e+06], got 1e+300"),
    (2, 1.0, "1", "max_surface_speed must be a finite number >= 0, got '1'"),
])
def test_numbers_of_the_wrong_type_are_refused_as_values(frames, rate, speed, message):
    with pytest.raises(ValueError) as info:
        Timeline(frames, rate, max_surface_speed=speed)
    assert str(info.value) == message


def test_a_clamped_end_under_a_second_is_held_at_the_last_frame():
    line = Timeline(3, 4.0)  # frames at 0, 0.25, 0.5 s
    assert line.locate(0.7) == (1, 1.0, 0.0)


def test_the_last_instant_before_the_end_stays_in_the_last_segment():
    """A time just below the duration whose position in frames rounds up to the last frame."""
    line = Timeline(4, 13.0)
    t = 0.23076923076923075  # the float below 3 / 13
    assert t < line.duration_s and t * 13.0 >= 3.0
    assert line.locate(t) == (2, 1.0, 13.0)


def test_from_dict_defaults_and_refusals():
    assert Timeline.from_dict({"frames": 3, "frame_rate_hz": 2, "loop": True}).max_surface_speed == 0.0
    with pytest.raises(ValueError) as info:
        Timeline.from_dict([3, 2, True])
    assert str(info.value) == "animation must be a map, got list"
