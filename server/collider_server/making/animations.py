"""Animations the project generates (nothing downloaded), to test animated colliders and to ship
with scenes; each has an exact reference.

- :func:`bending_arm`: a capsule "arm" along +x whose forearm bends up at the elbow by linear
  blend skinning; reference: the interpolated mesh, evaluated by libigl at that time;
- :func:`twisting_bunny`: the Stanford bunny (Z-up), its holes closed, under a smooth
  time-varying twist about the vertical axis and a volume-keeping squash; reference: the
  interpolated mesh by libigl;
- :func:`pulsing_sphere`: an icosphere whose centre moves and whose radius pulses; reference:
  :class:`SphereReference`, analytic (the interpolated mesh is the polyhedron inscribed in the
  sphere of interpolated centre and radius, and its surface velocity is known in closed form);
- :func:`bending_spot`: the spot cow bending its rear half sideways while it moves, once (issue
  34's recorded motion that the project's methods were not designed for); reference: the
  interpolated mesh by libigl.

Every animation but the bending spot loops without a jump (its last frame is its first); the
bending spot clamps (it holds its end frames). All are in metres, their own frame, z up.
:data:`GENERATED` names them for ``collider animate``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from collider_contract import Timeline

from ..engine.animated_meshes import AnimatedMesh, max_surface_speed
from ..engine.meshes import Mesh
from .placement import Y_UP_TO_Z_UP


def _animation(frames: np.ndarray, faces: np.ndarray, fps: float, name: str, loop: bool = True) -> AnimatedMesh:
    timeline = Timeline(len(frames), float(fps), loop, max_surface_speed(frames, fps))
    return AnimatedMesh(frames, faces, timeline, name)


def _phase(frames: int) -> np.ndarray:
    """(frames,) the phase ``2 pi k / (frames - 1)`` of each frame: one period, ending where it
    starts."""
    return 2.0 * np.pi * np.arange(frames) / (frames - 1)


# -- the bending arm ---------------------------------------------------------------------------

def capsule(length: float, radius: float, rings: int = 64, segments: int = 32,
            cap_rings: int = 8) -> Mesh:
    """A closed capsule along +x: a cylinder from x = 0 to ``length`` of ``radius`` (metres)
    with ``rings`` + 1 rings of ``segments`` vertices, capped by hemispheres of ``cap_rings``
    rings; triangles wound outward."""
    profile = [(-radius * math.cos(a), radius * math.sin(a))
               for a in np.linspace(0.0, math.pi / 2, cap_rings + 1)[1:]]
    profile += [(x, radius) for x in np.linspace(0.0, length, rings + 1)[1:]]
    profile += [(length + radius * math.sin(a), radius * math.cos(a))
                for a in np.linspace(0.0, math.pi / 2, cap_rings + 1)[1:-1]]
    angles = 2.0 * np.pi * np.arange(segments) / segments
    ring_points = [np.stack([np.full(segments, x), r * np.cos(angles), r * np.sin(angles)], axis=1)
                   for x, r in profile]
    vertices = np.concatenate([[[-radius, 0.0, 0.0]], *ring_points, [[length + radius, 0.0, 0.0]]])
    faces = []
    last = len(vertices) - 1
    j = np.arange(segments)
    jn = (j + 1) % segments
    faces.append(np.stack([np.zeros(segments, int), 1 + jn, 1 + j], axis=1))  # the -x pole
    for ring in range(len(profile) - 1):
        a, b = 1 + ring * segments, 1 + (ring + 1) * segments
        faces.append(np.stack([a + j, a + jn, b + jn], axis=1))
        faces.append(np.stack([a + j, b + jn, b + j], axis=1))
    a = 1 + (len(profile) - 1) * segments
    faces.append(np.stack([a + j, a + jn, np.full(segments, last)], axis=1))  # the +x pole
    return Mesh(vertices, np.concatenate(faces).astype(np.int64), "capsule")


def bending_arm(frames: int = 25, fps: float = 24.0, length: float = 0.5, radius: float = 0.04,
                elbow: float = 0.25, blend: float = 0.05, bend_deg: float = 60.0) -> AnimatedMesh:
    """A capsule arm along +x (shoulder at x = 0, hand at ``length``, metres) whose forearm
    bends up (towards +z) about the elbow at x = ``elbow`` by up to ``bend_deg``, and back, over
    ``frames`` frames: angle ``bend_deg (1 - cos phase) / 2``. Linear blend skinning: a vertex
    moves by ``w`` times the forearm's rotation, ``w`` a smoothstep of x over ``elbow +-
    blend``."""
    rest = capsule(length, radius)
    x = rest.vertices[:, 0]
    s = np.clip((x - (elbow - blend)) / (2.0 * blend), 0.0, 1.0)
    weight = (s * s * (3.0 - 2.0 * s))[:, None]
    pivot = np.array([elbow, 0.0, 0.0])
    out = np.empty((frames, len(x), 3))
    for k, phase in enumerate(_phase(frames)):
        angle = math.radians(bend_deg) * 0.5 * (1.0 - math.cos(phase))
        c, s_ = math.cos(angle), math.sin(angle)
        rotation = np.array([[c, 0.0, -s_], [0.0, 1.0, 0.0], [s_, 0.0, c]])  # +x towards +z
        moved = (rest.vertices - pivot) @ rotation.T + pivot
        out[k] = (1.0 - weight) * rest.vertices + weight * moved
    return _animation(out, rest.faces, fps, "arm")


# -- the twisting bunny ------------------------------------------------------------------------

def closed(mesh: Mesh) -> Mesh:
    """``mesh`` with every hole closed by a fan of triangles around the centroid of its boundary
    loop (found on the vertices merged by position; the new vertices appended, the new faces
    wound as their neighbours). The scanned bunny's base is open: a cloth that wraps under it
    meets, near the holes, points whose inside or outside is a guess (winding number near 0.5),
    and an exact collider there may push a vertex from a wrong "inside" tens of millimetres out
    in one step."""
    import igl

    from .mesh_check import merged

    _, faces, first = merged(mesh.vertices, mesh.faces)
    directed = {(int(a), int(b)) for a, b in np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])}
    vertices, new_faces = [np.asarray(mesh.vertices, dtype=np.float64)], [np.asarray(mesh.faces, dtype=np.int64)]
    count = len(mesh.vertices)
    for loop in igl.boundary_loop_all(faces):
        loop = np.asarray(loop, dtype=np.int64)
        if (int(loop[0]), int(loop[1])) in directed:  # the faces run along the loop: fill against it
            loop = loop[::-1]
        ring = first[loop]
        vertices.append(vertices[0][ring].mean(axis=0, keepdims=True))
        new_faces.append(np.stack([ring, np.roll(ring, -1), np.full(len(ring), count)], axis=1))
        count += 1
    return Mesh(np.concatenate(vertices), np.concatenate(new_faces), mesh.name, mesh.sha256)


def twisting_bunny(bunny: Mesh, frames: int = 25, fps: float = 12.0, twist_deg: float = 45.0,
                   squash: float = 0.1) -> AnimatedMesh:
    """``bunny`` (a Y-up mesh in metres, such as examples/meshes/stanford-bunny.obj, every
    vertex in file order, then one per hole) with its holes :func:`closed`, turned Z-up,
    centred over the origin with its base at z = 0, then twisted about the z axis by
    ``twist_deg sin(phase) * height fraction`` and squashed along z by
    ``1 - squash sin^2(phase / 2)`` (x and y widened to keep the volume), over ``frames``
    frames."""
    bunny = closed(bunny)
    v = bunny.vertices @ Y_UP_TO_Z_UP[:3, :3].T
    used = v[np.unique(bunny.faces)]
    lo, hi = used.min(axis=0), used.max(axis=0)
    v = v - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    height = hi[2] - lo[2]
    out = np.empty((frames, len(v), 3))
    for k, phase in enumerate(_phase(frames)):
        angle = math.radians(twist_deg) * math.sin(phase) * (v[:, 2] / height)
        c, s = np.cos(angle), np.sin(angle)
        z_scale = 1.0 - squash * math.sin(phase / 2) ** 2
        widen = 1.0 / math.sqrt(z_scale)
        out[k, :, 0] = (c * v[:, 0] - s * v[:, 1]) * widen
        out[k, :, 1] = (s * v[:, 0] + c * v[:, 1]) * widen
        out[k, :, 2] = v[:, 2] * z_scale
    return _animation(out, bunny.faces, fps, "twisting-bunny")


# -- the bending spot --------------------------------------------------------------------------

def _smoothstep(s):
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def bending_spot(spot: Mesh, frames: int = 25, fps: float = 12.0, bend_deg: float = 30.0, shift: float = 0.05,
                 pivot: float = 0.2, blend: float = 0.3) -> AnimatedMesh:
    """``spot`` (the cow of examples/meshes/spot.obj: metres, Y up, 1.72 m from its head at -z to
    its tail at +z) bending its rear half sideways while it moves, over ``frames`` frames, once
    (clamped): in the file's frame every vertex turned about the vertical axis through (0, y,
    ``pivot``) by ``bend_deg s(t) w(z)`` (``w`` a smoothstep of z over ``pivot +- blend``: the
    head still, the rear turned by the whole angle; the tail swings 0.44 m) and moved ``shift s(t)``
    along x, ``s`` a smoothstep of the time (starting and stopping at rest); then turned Z-up
    (Y_UP_TO_Z_UP) and lifted so that its feet stand at z = 0."""
    v = np.asarray(spot.vertices, np.float64)
    weight = _smoothstep((v[:, 2] - (pivot - blend)) / (2.0 * blend))
    to_z_up = Y_UP_TO_Z_UP[:3, :3]
    lift = -(v[np.unique(spot.faces)] @ to_z_up.T)[:, 2].min()
    out = np.empty((frames, len(v), 3))
    for k in range(frames):
        progress = float(_smoothstep(k / (frames - 1)))
        angle = math.radians(bend_deg) * progress * weight
        c, s = np.cos(angle), np.sin(angle)
        z = v[:, 2] - pivot
        bent = np.stack([c * v[:, 0] + s * z + shift * progress, v[:, 1], -s * v[:, 0] + c * z + pivot], axis=1)
        out[k] = bent @ to_z_up.T + np.array([0.0, 0.0, lift])
    return _animation(out, spot.faces, fps, "spot-bend", loop=False)


# -- the pulsing sphere ------------------------------------------------------------------------

@dataclass(frozen=True)
class SphereReference:
    """The analytic reference of :func:`pulsing_sphere`: per frame its centre (F, 3) and radius
    (F,), metres, interpolated linearly in time as the vertices are (a vertex is ``c + r u`` with
    ``u`` a unit vector, so the interpolated mesh is the icosphere of the interpolated ``c`` and
    ``r``)."""

    centres: np.ndarray
    radii: np.ndarray
    timeline: Timeline

    def at(self, t: float) -> tuple[np.ndarray, float, np.ndarray, float]:
        """``(centre, radius, dcentre/dt, dradius/dt)`` at ``t`` seconds."""
        k, u, rate = self.timeline.locate(t)
        c0, c1, r0, r1 = self.centres[k], self.centres[k + 1], self.radii[k], self.radii[k + 1]
        return c0 + u * (c1 - c0), float(r0 + u * (r1 - r0)), (c1 - c0) * rate, float((r1 - r0) * rate)

    def signed_distance(self, points: np.ndarray, t: float) -> np.ndarray:
        """(n,) signed distance to the sphere at ``t``: within the tessellation gap of the mesh's
        (:func:`pulsing_sphere`'s ``gap``) and equal on its vertices."""
        centre, radius, _, _ = self.at(t)
        return np.linalg.norm(points - centre, axis=1) - radius

    def surface_velocity(self, surface_points: np.ndarray, t: float) -> np.ndarray:
        """(n, 3) m/s: the interpolated mesh's velocity at points on it: ``c' + r' (q - c) / r``
        (exact: a point of a triangle is ``c + r sum w_i u_i`` with fixed weights)."""
        centre, radius, dc, dr = self.at(t)
        return dc + dr * (surface_points - centre) / radius


def pulsing_sphere(frames: int = 13, fps: float = 12.0, radius: float = 0.1, pulse: float = 0.2,
                   travel: float = 0.1, subdivisions: int = 3) -> tuple[AnimatedMesh, SphereReference]:
    """An icosphere of radius ``radius (1 + pulse sin phase)`` whose centre moves along x by
    ``travel sin phase`` (metres), over ``frames`` frames; and its analytic reference."""
    import trimesh

    unit = np.asarray(trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0).vertices)
    faces = np.asarray(trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0).faces)
    phase = _phase(frames)
    radii = radius * (1.0 + pulse * np.sin(phase))
    centres = np.stack([travel * np.sin(phase), np.zeros(frames), np.zeros(frames)], axis=1)
    out = centres[:, None, :] + radii[:, None, None] * unit[None]
    animation = _animation(out, faces.astype(np.int64), fps, "pulsing-sphere")
    return animation, SphereReference(centres, radii, animation.timeline)


#: ``collider animate NAME``: what each generated animation is.
GENERATED = {
    "arm": "a capsule arm (0.5 m, radius 4 cm) bending 60 degrees at the elbow and back, "
           "25 frames at 24 fps, looping",
    "twisting-bunny": "the Stanford bunny, its holes closed, twisting 45 degrees and squashing "
                      "10 %, 25 frames at 12 fps, looping",
    "pulsing-sphere": "a sphere of radius 0.1 m pulsing 20 % while moving 0.1 m along x, "
                      "13 frames at 12 fps, looping",
    "spot-bend": "the spot cow (1.72 m long) bending its rear half 30 degrees sideways while moving 5 cm, "
                 "25 frames at 12 fps over 2 s, once (clamped)",
    "walker": "a generated human figure (1.73 m, 20 joints, 7,920 faces) walking in place, 31 "
              "frames at 30 fps, looping; also walker.glb, the skinned character (Y up, as glTF "
              "is) with its clips walk (1 s) and wave (2 s)",
}
