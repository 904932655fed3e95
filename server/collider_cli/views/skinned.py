"""``collider view NAME`` of a skinned model: the character posed in the browser.

A **clip** dropdown and a **time** slider (seconds, 0 to the clip's duration; beyond the ends the
model's loop or clamp rule is the engine's) pose the skeleton; the page shows the skinned mesh at
that pose (the exact surface the model answers against: no grid, no error to colour), the bones
(each joint to its parent) and the domain box. A model without clips shows its rest pose.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from collider_server.engine.skinning import Skin, pose_at, skin_vertices

from .collider import BOX_COLOR, PLAIN_COLOR, box_segments
from .page import look_at_box, start_server

BONE_COLOR = (200, 60, 40)
#: Time slider steps per second.
STEPS_PER_SECOND = 60


@dataclass
class SkinnedPage:
    """The view of one skinned collider: its started viser server and its controls (viser GUI
    handles; a test sets their values as a browser would)."""

    server: object
    clip: object | None  # dropdown: the clip shown (None without clips)
    time: object | None  # slider, seconds
    label: object  # markdown: the pose shown


def posed(skin: Skin, clip: str | None, t: float, loop: bool) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3), bones (B, 2, 3))`` of ``skin`` in ``clip`` at ``t`` seconds (no
    clip: the rest pose), collider frame: the skinned mesh and each joint's segment to its
    parent's position."""
    if clip is None:
        transforms = skin.skeleton.rest_world()
    else:
        transforms, _ = pose_at(skin, clip, t, "loop" if loop else "clamp")
    positions = transforms[:, :3, 3]
    children = np.flatnonzero(skin.skeleton.parents >= 0)
    bones = np.stack([positions[skin.skeleton.parents[children]], positions[children]], axis=1)
    return skin_vertices(skin, transforms), bones


def pose_text(skin: Skin, clip: str | None, t: float, loop: bool) -> str:
    if clip is None:
        return f"**rest pose**: {skin.skeleton.joint_count} joints, no clips"
    duration = skin.clip(clip).duration_s
    return (f"**{clip}** at **t = {t:.4g} s** of {duration:g} s ({'loops' if loop else 'clamps'}); "
            f"{skin.skeleton.joint_count} joints")


def serve_skinned_view(collider, *, host: str, port: int, up: str = "+z") -> SkinnedPage:
    """Build the view of the skinned ``collider`` and return its page, its server started; the
    caller serves until Ctrl-C."""
    info, skin = collider.info, collider.skin
    loop = bool(info.skeleton.get("loop"))
    server = start_server(host, port, label=f"collider {info.name} (skinned)")
    server.scene.set_up_direction(up)
    lo, hi = np.asarray(info.domain_min), np.asarray(info.domain_max)
    look_at_box(server, lo, hi, up)
    scene, gui = server.scene, server.gui
    scene.add_line_segments("/domain", box_segments(lo, hi), BOX_COLOR, thickness=1.5,
                            thickness_units="screen")
    gui.add_markdown(f"**{info.name}**: skinned collider, {info.units}, collider frame")
    names = skin.clip_names
    clip = gui.add_dropdown("clip", names, names[0]) if names else None
    time = (gui.add_slider("time (s)", 0.0, max(skin.clip(names[0]).duration_s, 1.0 / STEPS_PER_SECOND),
                           1.0 / STEPS_PER_SECOND, 0.0, hint="seconds in the clip")
            if names else None)
    label = gui.add_markdown("")
    lock = threading.Lock()

    def draw(_=None) -> None:
        with lock:
            name = clip.value if clip is not None else None
            t = float(time.value) if time is not None else 0.0
            vertices, bones = posed(skin, name, t, loop)
            scene.add_mesh_simple("/skin", vertices.astype(np.float32), skin.faces.astype(np.uint32),
                                  color=PLAIN_COLOR)
            if len(bones):
                scene.add_line_segments("/skeleton", bones.astype(np.float32), BONE_COLOR,
                                        thickness=3.0, thickness_units="screen")
            label.content = pose_text(skin, name, t, loop)

    def clip_changed(_=None) -> None:
        time.max = max(skin.clip(clip.value).duration_s, 1.0 / STEPS_PER_SECOND)
        if time.value > time.max:
            time.value = time.max  # draws
        else:
            draw()

    if clip is not None:
        clip.on_update(clip_changed)
        time.on_update(draw)
    draw()
    return SkinnedPage(server, clip, time, label)
