"""The mesh check of bake, train, bench and info: watertight or not, holes, pieces, edges of more
than two faces, faces wound against their neighbours, faces that cross (units: the mesh's)."""

from __future__ import annotations

import numpy as np
import pytest

from collider_server.engine.meshes import Mesh
from collider_server.making.mesh_check import MeshCheck, check_mesh


def box(centre=(0.0, 0.0, 0.0), size=1.0) -> Mesh:
    import trimesh

    m = trimesh.creation.box(extents=(size, size, size))
    return Mesh(np.asarray(m.vertices) + centre, np.asarray(m.faces, dtype=np.int64), "box")


def join(*meshes: Mesh) -> Mesh:
    vertices, faces, offset = [], [], 0
    for m in meshes:
        vertices.append(m.vertices)
        faces.append(m.faces + offset)
        offset += len(m.vertices)
    return Mesh(np.concatenate(vertices), np.concatenate(faces), "joined")


def test_a_closed_box_is_watertight_and_its_sign_exact():
    check = check_mesh(box())
    assert (check.faces, check.boundary_edges, check.holes, check.pieces, check.intersecting_pairs) == (12, 0, 0, 1, 0)
    assert check.watertight
    assert check.lines() == ["mesh: 12 faces, watertight, 1 piece, no self-intersections",
                             "  sign: inside and outside are well defined; the winding-number sign is exact"]


def test_split_vertices_along_seams_are_not_holes():
    """An OBJ writes a vertex per face corner along texture seams: merged by position first."""
    b = box()
    corners = b.vertices[b.faces].reshape(-1, 3)
    check = check_mesh(Mesh(corners, np.arange(len(corners)).reshape(-1, 3), "split"))
    assert check.watertight and check.vertices == 8 and check.pieces == 1


def test_a_missing_face_is_one_hole_and_the_sign_near_it_a_guess():
    b = box()
    check = check_mesh(Mesh(b.vertices, b.faces[2:], "open"))  # one side's two triangles gone
    assert (check.boundary_edges, check.holes, check.watertight) == (4, 1, False)
    assert check.summary().startswith("10 faces, not watertight (1 hole, 4 boundary edges), 1 piece")
    assert "sign near the holes is a guess" in check.lines()[1]


def test_pieces_faces_wound_against_their_neighbours_and_faces_that_cross():
    apart = check_mesh(join(box(), box((3.0, 0.0, 0.0))))
    assert apart.pieces == 2 and apart.watertight and apart.intersecting_pairs == 0
    assert "2 pieces: the inside is the union" in "\n".join(apart.lines())
    crossing = check_mesh(join(box(), box((0.5, 0.3, 0.2))))
    assert crossing.pieces == 2 and crossing.intersecting_pairs > 0
    assert "distance, normal and contact refer to the boundary of the union" in "\n".join(crossing.lines())
    b = box()
    faces = b.faces.copy()
    faces[0] = faces[0, ::-1]  # one triangle inside out
    flipped = check_mesh(Mesh(b.vertices, faces, "flipped"))
    assert flipped.flipped_edges == 3 and not flipped.watertight and flipped.boundary_edges == 0
    assert "wound against their neighbours" in "\n".join(flipped.lines())


def test_the_check_round_trips_through_a_dict_and_is_skipped_above_its_face_limit():
    check = check_mesh(box())
    assert MeshCheck.from_dict(check.to_dict()) == check and check.to_dict()["watertight"] is True
    skipped = check_mesh(box(), max_faces_intersections=5)
    assert skipped.intersecting_pairs is None and "self-intersections not checked (more than 5 faces)" in skipped.summary()


@pytest.mark.parametrize("name, summary", [
    ("stanford-bunny.obj", "69,451 faces, not watertight (5 holes, 223 boundary edges), 1 piece, no self-intersections"),
    ("dragon.obj", "100,000 faces, watertight, 1 piece, 25 pairs of faces that cross each other"),
    ("spot.obj", "5,856 faces, watertight, 1 piece, no self-intersections"),
])
def test_the_shared_meshes(load_shared_mesh, name, summary):
    assert check_mesh(load_shared_mesh(name)).summary() == summary


def test_an_animation_is_checked_for_crossing_faces_in_every_frame():
    """Two boxes apart at rest that pass through each other in frame 2 of 4: the rest pose alone
    says nothing crosses; the animation's check names the frame (a bending arm may fold into
    itself so)."""
    from collider_contract.animation import Timeline
    from collider_server.engine.animated_meshes import AnimatedMesh
    from collider_server.making.mesh_check import check_animation

    rest = join(box(), box((3.0, 0.0, 0.0)))
    frames = np.stack([rest.vertices] * 4)
    moving = np.arange(8, 16)
    for k, x in enumerate((3.0, 2.0, 0.5, 2.0)):
        frames[k, moving] = box((x, 0.3, 0.2)).vertices
    animation = AnimatedMesh(frames, rest.faces, Timeline(4, 4.0))
    check = check_animation(animation)
    assert check.pieces == 2 and check.watertight and check.intersecting_pairs > 0
    assert check.intersections_note == "the most in frame 2; every frame checked"
    assert f"{check.intersecting_pairs} pairs of faces that cross each other (the most in frame 2" in check.summary()
    still = check_animation(AnimatedMesh(np.stack([rest.vertices] * 3), rest.faces, Timeline(3, 4.0)))
    assert still.intersecting_pairs == 0 and still.summary().endswith("no self-intersections (every frame checked)")
