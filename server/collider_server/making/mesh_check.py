"""What a mesh is, as far as the sign of its distance is concerned: watertight or not, holes,
pieces, edges shared by more than two faces, faces wound against their neighbours, and faces
that cross each other.

Every collider takes its inside/outside from the exact SDF's sign, the fast generalised winding
number (:class:`~collider_server.engine.meshes.ExactSDF`): exact for a closed, consistently wound
surface, a smooth guess near holes. Where the surface crosses itself or buries a piece, the exact
SDF measures distances to the boundary of the region whose winding number exceeds 1/2
(:mod:`collider_server.engine.union`). ``collider bake``, ``train``, ``bench``
and ``info`` say what the mesh is and what that means for the sign (:meth:`MeshCheck.lines`),
and the closing lines of the first three give the sign errors they measured.

Topology is read on the vertices merged by position (OBJ files split vertices along texture
seams; those are not holes). Self-intersections: the project's own finder
(:func:`collider_server.engine.intersections.self_intersections`, the one the union uses): pairs
of faces whose interiors meet along a segment or, coplanar, over an area; not faces that only
touch at a point or share an edge or a vertex. Units: those of the mesh.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from ..engine.intersections import self_intersections
from ..engine.meshes import Mesh

#: Above this many faces the self-intersection test is skipped (its candidate pairs take about
#: 1 KB per face); the others always run.
MAX_FACES_INTERSECTIONS = 2_000_000


@dataclass(frozen=True)
class MeshCheck:
    """faces : triangles of the file; vertices : after merging equal positions; boundary_edges :
    edges of one face only; holes : loops those edges form; non_manifold_edges : edges of more
    than two faces; flipped_edges : edges whose two faces are wound the same way along them
    (one is inside out); pieces : connected parts; intersecting_pairs : pairs of faces that
    cross (None: not checked, see ``intersections_note``)."""

    faces: int
    vertices: int
    boundary_edges: int
    holes: int
    non_manifold_edges: int
    flipped_edges: int
    pieces: int
    intersecting_pairs: int | None
    intersections_note: str = ""

    @property
    def watertight(self) -> bool:
        """Every edge shared by exactly two faces wound against each other."""
        return self.boundary_edges == 0 and self.non_manifold_edges == 0 and self.flipped_edges == 0

    def to_dict(self) -> dict:
        return {**asdict(self), "watertight": self.watertight}

    @classmethod
    def from_dict(cls, data: dict) -> MeshCheck:
        """The check :meth:`to_dict` wrote (stored in a model's ``source`` or a bench report)."""
        return cls(**{k: data[k] for k in cls.__dataclass_fields__ if k in data})

    def summary(self) -> str:
        """One line: ``mesh: 69,451 faces, not watertight (5 holes, 223 boundary edges), 1 piece,
        no self-intersections``."""
        parts = [f"{self.faces:,} faces"]
        if self.watertight:
            parts.append("watertight")
        else:
            why = []
            if self.boundary_edges:
                why.append(f"{self.holes} hole{'s' * (self.holes != 1)}, {self.boundary_edges} boundary edges")
            if self.non_manifold_edges:
                why.append(f"{self.non_manifold_edges} edges of more than two faces")
            if self.flipped_edges:
                why.append(f"{self.flipped_edges} edges between faces wound against each other")
            parts.append(f"not watertight ({'; '.join(why)})")
        parts.append(f"{self.pieces} piece{'s' * (self.pieces != 1)}")
        if self.intersecting_pairs is None:
            parts.append(f"self-intersections not checked ({self.intersections_note})")
        elif self.intersecting_pairs:
            parts.append(f"{self.intersecting_pairs} pairs of faces that cross each other")
        else:
            parts.append("no self-intersections")
        if self.intersecting_pairs is not None and self.intersections_note:  # an animation's frames
            parts[-1] += f" ({self.intersections_note})"
        return ", ".join(parts)

    def lines(self) -> list[str]:
        """The summary, then what it means for the sign, one line per finding."""
        out = [f"mesh: {self.summary()}"]
        if self.watertight and self.pieces == 1 and not self.intersecting_pairs:
            out.append("  sign: inside and outside are well defined; the winding-number sign is exact")
            return out
        if self.boundary_edges:
            out.append("  sign near the holes is a guess: the winding number closes each hole smoothly, so "
                       "points within about a hole's size of it may get either sign, and every collider "
                       "made from this mesh carries that guess (sign errors gather there)")
        if self.non_manifold_edges:
            out.append("  edges of more than two faces: the surface branches there; the winding number "
                       "adds the branches, so the inside next to them may count twice or not at all")
        if self.flipped_edges:
            out.append("  faces wound against their neighbours turn their part of the surface inside out "
                       "for the winding number: expect wrong signs near them (fix the winding in the file)")
        if self.pieces > 1:
            out.append(f"  {self.pieces} pieces: the inside is the union of the pieces (winding numbers add); "
                       "a piece buried inside another is inside and no part of the surface distances are "
                       "measured to (one wound the other way is a cavity)")
        if self.intersecting_pairs:
            out.append("  where the surface passes through itself, points inside both parts have a winding "
                       "number near 2: they are inside, and distance, normal and contact refer to the boundary "
                       "of the union (the parts of faces buried in the body are left out), so contacts land "
                       "outside")
        return out


def check_mesh(mesh: Mesh, max_faces_intersections: int = MAX_FACES_INTERSECTIONS) -> MeshCheck:
    """The :class:`MeshCheck` of ``mesh`` (vertices merged by position first)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    unique, faces, _ = merged(mesh.vertices, mesh.faces)
    n = len(unique)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    low, high = directed.min(axis=1), directed.max(axis=1)
    codes, key, counts = np.unique(low * n + high, return_inverse=True, return_counts=True)
    edges = np.stack([codes // n, codes % n], axis=1)
    boundary = edges[counts == 1]
    # Along an interior edge its two faces run opposite ways (a->b and b->a) when wound alike.
    forward_count = np.bincount(key.reshape(-1), weights=directed[:, 0] < directed[:, 1], minlength=len(edges))
    flipped = int(((counts == 2) & (forward_count != 1)).sum())
    holes = 0
    if len(boundary):
        graph = coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n))
        labels = connected_components(graph, directed=False)[1]
        holes = len(np.unique(labels[np.unique(boundary)]))
    pieces = 0
    if len(faces):
        graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
        labels = connected_components(graph, directed=False)[1]
        pieces = len(np.unique(labels[np.unique(faces)]))
    pairs, note = crossing_pairs(unique, faces, max_faces_intersections)
    return MeshCheck(faces=len(mesh.faces), vertices=int(n), boundary_edges=len(boundary),
                     holes=int(holes), non_manifold_edges=int((counts > 2).sum()), flipped_edges=flipped,
                     pieces=int(pieces), intersecting_pairs=pairs, intersections_note=note)


def merged(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vertices merged by position, the faces on them (those that collapse dropped), and
    each merged vertex's first index in ``vertices``."""
    unique, first, inverse = np.unique(np.asarray(vertices, dtype=np.float64), axis=0,
                                       return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[np.asarray(faces, dtype=np.int64)]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return unique, faces[keep], first


#: Frames of an animation whose self-intersections :func:`check_animation` counts at most (about
#: 0.25 s each for the bunny's 69k faces): beyond, this many evenly spaced.
MAX_FRAMES_INTERSECTIONS = 100


def check_animation(animation, max_faces_intersections: int = MAX_FACES_INTERSECTIONS) -> MeshCheck:
    """The :class:`MeshCheck` of an animated mesh: the topology of its first frame (every frame
    shares its faces) and the self-intersections of its frames (a bending mesh may cross itself
    where the rest pose does not): the most crossing pairs of any frame checked, named in
    ``intersections_note``."""
    first = check_mesh(animation.frame(0), max_faces_intersections)
    frames = animation.timeline.frames
    if first.intersecting_pairs is None:
        return first
    _, faces, index = merged(animation.frame(0).vertices, animation.frame(0).faces)
    checked = np.unique(np.linspace(0, frames - 1, min(frames, MAX_FRAMES_INTERSECTIONS)).round().astype(int))
    worst, at = first.intersecting_pairs, 0
    for k in checked[1:]:
        pairs, note = crossing_pairs(animation.frame(int(k)).vertices[index], faces, max_faces_intersections)
        if pairs is None:
            return replace(first, intersecting_pairs=None, intersections_note=f"frame {k}: {note}")
        if pairs > worst:
            worst, at = pairs, int(k)
    where = "every frame checked" if len(checked) == frames else f"{len(checked)} of {frames} frames checked"
    note = f"the most in frame {at}; {where}" if worst else where
    return replace(first, intersecting_pairs=worst, intersections_note=note)


def crossing_pairs(vertices: np.ndarray, faces: np.ndarray, max_faces: int) -> tuple[int | None, str]:
    """How many pairs of faces cross (:func:`~collider_server.engine.intersections.self_intersections`),
    or None and why not."""
    if len(faces) > max_faces:
        return None, f"more than {max_faces:,} faces"
    return len(self_intersections(vertices, faces)), ""
