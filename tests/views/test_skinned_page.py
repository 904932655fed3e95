"""``collider view`` of a skinned model, in process: the clip dropdown and the time slider pose
the character; the page's mesh and bones are the engine's skinning at that pose
(collider_cli.views.skinned). RiggedSimple (tests/data/gltf), placed --fit-size 1.7."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from .page_driver import node

pytest.importorskip("viser", reason="the [view] extra (viser) is not installed")

SAMPLE = Path(__file__).parents[1] / "data" / "gltf" / "RiggedSimple.gltf"


@pytest.fixture(scope="module")
def collider():
    from collider_server.making.characters import skinned_from_file
    from collider_server.making.placement import MeshPlacement

    made, _, _ = skinned_from_file(SAMPLE, "cylinder", MeshPlacement(fit_size=1.7), loop=False)
    return made


@pytest.fixture
def page(collider):
    from collider_cli.views.skinned import serve_skinned_view

    page = serve_skinned_view(collider, host="127.0.0.1", port=0)
    yield page
    page.server.stop()


def test_the_time_slider_poses_the_character(page, collider):
    from collider_server.engine.skinning import pose_at, skin_vertices

    skin = collider.skin
    assert page.clip.value == "animation 0" and page.time.max == pytest.approx(2.083333, abs=1e-5)
    for t in (0.0, 1.5):
        page.time.value = t
        shown = node(page.server, "/skin").vertices
        expected = skin_vertices(skin, pose_at(skin, None, t, "clamp")[0])
        np.testing.assert_allclose(shown, expected, atol=1e-6)
        assert page.label.content.startswith(f"**animation 0** at **t = {t:g} s** of 2.08333 s (clamps)")
    bones = node(page.server, "/skeleton").points
    tip = pose_at(skin, None, 1.5, "clamp")[0][1, :3, 3]
    np.testing.assert_allclose(bones[0, 1], tip, atol=1e-6)  # joint 1's segment ends at it
    assert np.abs(node(page.server, "/skin").vertices - skin.vertices).max() > 0.05  # it bends


def test_a_skin_with_no_clips_is_shown_at_its_rest_pose(collider):
    """A skin without clips (glTF allows it): no clip dropdown and no time slider; the page draws
    the skin at its rest pose and says so."""
    from dataclasses import replace

    from collider_cli.views.skinned import serve_skinned_view
    from collider_server.engine.kinds.skinned import SkinnedCollider
    from collider_server.engine.skinning import skin_vertices

    clipless = SkinnedCollider(collider.info, replace(collider.skin, clips=()))
    page = serve_skinned_view(clipless, host="127.0.0.1", port=0)
    try:
        assert page.clip is None and page.time is None
        rest = skin_vertices(collider.skin, collider.skin.skeleton.rest_world())
        np.testing.assert_allclose(node(page.server, "/skin").vertices, rest, atol=1e-6)
        assert page.label.content.startswith("**rest pose**: ") and page.label.content.endswith("no clips")
    finally:
        page.server.stop()
