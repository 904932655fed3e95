"""Collision response a simulator calls after its own integration step (numpy only).

All arrays are world frame, metres (velocities in m/s). ``mask`` arrays select the colliding
points (``collides`` from a query, or ``distance < eps``).

- the physics (:mod:`.physics`): :func:`project_to_contacts`, :func:`respond_velocities`,
  :func:`collider_velocity`;
- where each collider is and when (:mod:`.placement`): :class:`ColliderPlacement`,
  :func:`animation_time`, :func:`world_box`;
- :class:`CollisionHook` (here, with its state) puts them together with the SDK: positions and velocities in, responded
  positions and velocities out. It asks each collider at its animation time with its pose's
  velocity, and uses the surface ``velocity`` the service answers. It is what an adapter for
  another simulator calls.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from collider_contract import ModelInfo, SceneCollider, Timeline, transform_points

from .physics import collider_velocity, project_to_contacts, respond_velocities, unit_rows
from .placement import ColliderPlacement, animation_time, world_box

__all__ = [
    "ColliderPlacement",
    "CollisionHook",
    "HookStats",
    "TunnellingError",
    "animation_time",
    "collider_velocity",
    "project_to_contacts",
    "respond_velocities",
    "world_box",
]


class TunnellingError(ValueError):
    """A step too long for the collision offset: a point could have passed through a thin
    feature between two queries (speed x dt >= eps relative to the collider)."""


@dataclass
class HookStats:
    """What the hook did over its calls (times in seconds)."""

    calls: int = 0
    points_total: int = 0
    points_sent: int = 0
    queries: int = 0
    colliding_last: int = 0
    colliding_max: int = 0
    deepest_penetration_m: float = 0.0  # most negative signed distance seen (<= 0): the worst penetration
    # points answered deeper than they could have gone since the last call (the collider's
    # error), once a call: not responded, they went on as if unanswered (CollisionHook.apply)
    false_contacts: int = 0
    query_s: float = 0.0
    response_s: float = 0.0
    fields: list[str] = field(default_factory=list)


class CollisionHook:
    """Collide points with one or more colliders through the SDK; numpy in, numpy out.

    client : a :class:`collider_client.Client` (remote or embedded)
    colliders : :class:`ColliderPlacement` list
    eps : collision offset, metres (points closer than eps to a surface are pushed out to eps)
    friction : Coulomb coefficient; ``None`` = no velocity response: colliding points take the
        velocity of the collider's surface (inelastic and sticky), which needs no normals
    restitution : 0..1, used with friction
    cull : send only the points inside a collider's inflated box (True); False sends every point
        (for benchmarks that show what culling saves)
    only_colliding : ask for ``contact``, ``normal`` and ``velocity`` of the colliding points
        only (the service then does the gradient work for those alone; the response never uses
        the others'). False asks for them at every point sent (for benchmarks that show the
        saving)
    check_step : raise :class:`TunnellingError` when a point near a collider moves ``eps`` or
        more relative to it in one step (the limit below which nothing tunnels; see
        :meth:`substeps`)

    A contact answered deeper than the point could have gone into the surface since the last call
    (``eps`` plus its approach to the surface along the answer's normal, within its own travel
    plus the surface's, :meth:`apply`) is a **false contact**: a signed distance changes no
    faster than that, so the answer is the collider's error (a learned field wrong off the skin),
    and its normal is not to be believed either. It is not a contact: the point goes on as if
    unanswered (pushed along false normals, bounded or not, or kept where it was, the cloth's
    springs stretched and threw it). Counted in ``stats.false_contacts``.

    Call :meth:`apply` after each integration step (or substep). Only points inside a collider's
    inflated world box are sent, and only the fields the response needs are asked for: the
    surface ``velocity`` when a collider moves or is animated. Each collider is asked at its
    animation time (:func:`animation_time`; a skinned model in its placement's clip) with its
    pose's velocity (the backward difference of
    its pose over the step); the service answers the velocity of the surface at each contact,
    its frame's motion plus its own deformation, and the response is relative to it.
    """

    def __init__(self, client, colliders: Sequence[ColliderPlacement], eps: float = 1e-3,
                 friction: float | None = None, restitution: float = 0.0,
                 infos: dict[str, ModelInfo] | None = None, cull: bool = True,
                 only_colliding: bool = True, check_step: bool = True):
        if not eps > 0:
            raise ValueError(f"eps must be > 0, got {eps}")
        if not colliders:
            raise ValueError("CollisionHook needs at least one collider")
        self.client = client
        self.colliders = list(colliders)
        self.eps = float(eps)
        self.friction = friction
        self.restitution = float(restitution)
        self.cull = cull
        self.check_step = check_step
        self.only_colliding = bool(only_colliding)
        if infos is None:
            infos = {m.name: m for m in client.list_models()}
        missing = sorted({c.model for c in self.colliders} - set(infos))
        if missing:
            raise ValueError(f"unknown model(s) {missing}; available: {sorted(infos)}")
        self.infos = infos
        #: Per collider, its model's timeline (None: static), a skinned model's clip's
        #: (:meth:`ModelInfo.clip_timeline`: the clip's duration, the model's loop, the clip's
        #: max_surface_speed), and that clip's name (None for any other model).
        self.timelines: list[Timeline | None] = []
        self.clips: list[str | None] = []
        for placement in self.colliders:
            timeline: Timeline | None
            info = infos[placement.model]
            if info.skinned:
                try:
                    timeline = info.clip_timeline(placement.clip)
                except ValueError as error:
                    raise ValueError(f"ColliderPlacement({placement.model!r}): {error}") from None
                self.clips.append(placement.clip or info.skeleton["clips"][0]["name"])
            elif placement.clip is not None:
                raise ValueError(f"ColliderPlacement({placement.model!r}): clip applies to "
                                 f"skinned models; this one is {info.kind}")
            else:
                timeline = info.timeline
                self.clips.append(None)
            self.timelines.append(timeline)
        for placement, timeline in zip(self.colliders, self.timelines, strict=True):
            if timeline is None and (placement.time_offset_s or placement.loop is not None):
                raise ValueError(f"ColliderPlacement({placement.model!r}): time_offset_s and "
                                 "loop apply to animated models; this one is static")
        #: Whether a collider moves or deforms: its surface's velocity is asked for, and a point
        #: caught part-way through a step is checked again at the step's later checks.
        self.moving = any(not c.static or line is not None
                          for c, line in zip(self.colliders, self.timelines, strict=True))
        moving = self.moving
        # distance gives the penetration; contact moves them out; collides (one byte a point)
        # decides who collides, exactly as the service decided whose contact and normal to
        # compute; velocity (a moving or animated collider) is what a contact moves with; normal
        # only when velocities are corrected along it.
        self.fields = (["distance", "contact", "collides"] + (["velocity"] if moving else [])
                       + (["normal"] if friction is not None else []))
        self.stats = HookStats(fields=list(self.fields))
        #: The point count of the last call: the same count continues those points, which all
        #: ended it outside (at eps or beyond by the collider's answers), and so bounds their
        #: pushes.
        self._last_count: int | None = None

    #: Most collision substeps of one step (see :meth:`substeps`); beyond, TunnellingError.
    max_substeps = 64

    def collider_moves(self, poses: list, t: float, dt: float) -> list[float]:
        """Per collider, the largest displacement (m) of any point of its surface over the step
        from ``t - dt`` to ``t``: its domain box's corners under the two poses (a rigid motion
        moves a box's points at most as far as its corners), plus, animated, its fastest
        surface point's own travel (``max_surface_speed``, an animation's or a skinned model's
        clip's, times the pose's scale and ``dt``); 0 for static colliders."""
        moves = []
        for placement, pose, timeline in zip(self.colliders, poses, self.timelines, strict=True):
            move = 0.0
            if not placement.static:
                corners = self.infos[placement.model].domain_corners()
                moved = transform_points(pose, corners) - transform_points(placement.pose(t - dt), corners)
                move = float(np.linalg.norm(moved, axis=1).max())
            if timeline is not None:
                scale = float(np.cbrt(abs(np.linalg.det(pose[:3, :3]))))
                move += timeline.max_surface_speed * scale * dt
            moves.append(move)
        return moves

    def substeps(self, velocities: np.ndarray, index: np.ndarray, moves: list[float], t: float,
                 dt: float) -> int:
        """How many collision checks the step needs along the points' paths so that nothing
        tunnels: ``floor(relative displacement / eps) + 1``.

        Why eps: a point at least eps outside (where every point is after a step: colliding
        ones are moved to eps) that moves less than eps relative to the surface cannot reach the
        far side of anything, however thin, without first landing within eps, where it is
        caught. The relative displacement is bounded by the point's own plus the collider's
        (:meth:`collider_moves`: its frame's motion and its surface's deformation).
        Raises :class:`TunnellingError` beyond :attr:`max_substeps`."""
        speed = np.linalg.norm(np.asarray(velocities, dtype=np.float64)[index], axis=1)
        own = float(speed.max(initial=0.0)) * dt
        box = max(moves, default=0.0)
        if not np.isfinite(own + box):
            raise TunnellingError(f"at t = {t:.6g} s a point near a collider has a non-finite velocity")
        count = int(np.floor((own + box) / self.eps)) + 1
        if count > self.max_substeps:
            raise TunnellingError(
                f"at t = {t:.6g} s a point near a collider moved {1e3 * (own + box):.3g} mm "
                f"relative to it in one step ({1e3 * own:.3g} mm itself at {own / dt:.3g} m/s, "
                f"{1e3 * box:.3g} mm the collider's surface): more than {self.max_substeps} x "
                f"eps = {1e3 * self.eps:.3g} mm, it could pass through a thin feature unseen. "
                "Keep speed x dt below eps: lower dt or raise eps")
        return count

    def apply(self, positions: np.ndarray, velocities: np.ndarray, t: float, dt: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Respond to contacts at time ``t`` (seconds: the poses and animation times at ``t``;
        ``dt`` for the colliders' velocities).

        positions : (n, 3) float, metres, world frame, after the step; velocities : (n, 3) float,
            m/s, the step's (positions moved by about velocities * dt during it)
        Returns ``(positions, velocities, mask)`` with new arrays for the first two and ``mask``
        (n,) bool of the points that were in contact.

        When the call continues the last one (the same point count: every point ended it outside),
        a contact is pushed out no further than the point could have gone in: ``eps`` plus how
        far it came towards the surface along the answer's normal, relative to the surface's
        velocity there, since its velocity was set; and, all the step's checks together, no
        further than its reach, ``eps`` + ``|velocity| dt`` + the colliders' largest surface move
        over the step (:meth:`collider_moves`). A contact deeper than that is a false contact, not
        a contact: the point goes on as if unanswered, and ``stats.false_contacts`` counts it,
        once a call. (A true contact is never that deep; a point answered falsely where it truly
        touches goes in by at most its approach, under eps a check, until a check answers it
        right.) The first call pushes every point fully out.

        A step in which a point moves ``eps`` or more relative to a collider's surface is
        checked at :meth:`substeps` times along the paths (``check_step``), each at its own
        time; a point caught part-way is responded there and moves on with its responded
        velocity, so it cannot pass through a feature thinner than its step. When a collider
        moves or deforms, a caught point is checked again at the later times (a surface that
        keeps pushing keeps it outside), so a surface moving faster than eps per step does not
        leave it inside either.
        """
        started = time.perf_counter()
        positions = np.asarray(positions)
        n = len(positions)
        poses = [c.pose(t) for c in self.colliders]
        surface_moves = self.collider_moves(poses, t, dt)
        moves = surface_moves if self.check_step else [0.0] * len(poses)
        sweep = np.asarray(velocities, dtype=np.float64) * dt if self.check_step else None
        index = np.flatnonzero(self._near(positions, poses, self.eps + 1e-9, sweep, moves))
        reach = None
        if self._last_count == n:
            reach = (self.eps + max(surface_moves, default=0.0)
                     + np.linalg.norm(np.asarray(velocities, dtype=np.float64), axis=1) * dt)
        self._last_count = n
        self.stats.calls += 1
        self.stats.points_total += n
        mask = np.zeros(n, dtype=bool)
        self.stats.colliding_last = 0
        if not len(index):
            self.stats.response_s += time.perf_counter() - started
            return positions, velocities, mask
        count = self.substeps(velocities, index, moves, t, dt) if self.check_step else 1
        positions = np.array(positions, copy=True)
        velocities = np.array(velocities, dtype=np.float64, copy=True)
        since = np.zeros(n)  # seconds into the step at which each point's velocity was last set
        false = np.zeros(n, dtype=bool)  # points answered a false contact at some check of the step
        query_s = 0.0
        for j in range(1, count + 1):
            back = 1.0 - j / count  # fraction of the step after this check
            t_j = t - back * dt
            poses_j = poses if j == count else [c.pose(t_j) for c in self.colliders]
            # Where each point is at t_j on its path (positions hold where it ends the step).
            points = positions[index] - back * velocities[index] * dt
            hit, q = self._respond(points, index, positions, velocities, since, false, poses_j, t_j, dt,
                                   (1.0 - back) * dt, back * dt, reach)
            query_s += q
            mask[index[hit]] = True  # _respond wrote their positions and velocities
            if not self.moving:  # a still surface cannot catch up with a responded point
                index = index[~hit]
                if not len(index):
                    break
        self.stats.colliding_last = int(mask.sum())
        self.stats.false_contacts += int(false.sum())
        self.stats.colliding_max = max(self.stats.colliding_max, self.stats.colliding_last)
        self.stats.response_s += (time.perf_counter() - started) - query_s
        return positions, velocities, mask

    def _near(self, positions, poses, margin: float, sweep, moves: list[float]) -> np.ndarray:
        """(n,) bool: points inside some collider's world box grown by ``margin`` plus the
        collider's own move over the step (``moves``, m; all points when culling is off); with
        ``sweep`` (n, 3) displacements (None: none), points whose path from ``positions - sweep``
        to ``positions`` may meet such a box."""
        n = len(positions)
        if not self.cull:
            return np.ones(n, dtype=bool)
        near = np.zeros(n, dtype=bool)
        for k, (placement, pose) in enumerate(zip(self.colliders, poses, strict=True)):
            grow = margin + moves[k]
            lo, hi = world_box(self.infos[placement.model], pose, grow)
            if sweep is None:
                near |= np.all((positions >= lo) & (positions <= hi), axis=1)
            else:  # the path's own box overlaps the collider's box
                start = positions - sweep
                near |= np.all((np.maximum(positions, start) >= lo)
                               & (np.minimum(positions, start) <= hi), axis=1)
        return near

    def _query(self, points, poses, t: float, dt: float):
        """The SDK call at ``t``: each collider at its animation time (a skinned one in its clip)
        with its pose's velocity.
        Returns ``(result, which collider per point or None, held per collider)``."""
        times = [animation_time(c, line, t) for c, line in zip(self.colliders, self.timelines, strict=True)]
        rates = [c.pose_velocity(t, dt) for c in self.colliders]
        if len(self.colliders) == 1:
            placement = self.colliders[0]
            result = self.client.query(
                placement.model, points, fields=self.fields, pose=poses[0], eps=self.eps,
                only_colliding=self.only_colliding, time=times[0][0], pose_velocity=rates[0],
                clip=self.clips[0])
            return result, None, [times[0][1]]
        result = self.client.scene_query(
            [SceneCollider(c.model, p, at, rate, clip) for c, p, (at, _), rate, clip in
             zip(self.colliders, poses, times, rates, self.clips, strict=True)],
            points, fields=self.fields, eps=self.eps, only_colliding=self.only_colliding)
        return result, np.asarray(result.collider), [held for _, held in times]

    def _respond(self, points, index, positions, velocities, since, false, poses, t: float, dt: float,
                 travelled_s: float, remaining_s: float, reach: np.ndarray | None):
        """Query ``points`` (the rows ``index`` at time ``t``, ``travelled_s`` into the step and
        ``remaining_s`` before its end), and for those within eps write the contact, moved on
        with the responded velocity for ``remaining_s``, and that velocity into ``positions`` /
        ``velocities`` (in place; ``since`` records when). A false contact (further than eps plus
        the point's approach along the answer's normal, or than ``reach`` (n,) metres, the
        step's budget left; None: the first call, no bound) is left out of ``hit`` and marked in
        ``false`` (n,) bool; what a push uses is taken from ``reach``, in place.
        Returns ``(hit (len(index),) bool, seconds spent in the query)``."""
        q0 = time.perf_counter()
        result, which, held = self._query(points, poses, t, dt)
        spent = time.perf_counter() - q0
        self.stats.query_s += spent
        self.stats.queries += 1
        self.stats.points_sent += len(index)
        hit = np.array(result.collides, dtype=bool)  # a copy: false contacts are taken out
        local_index = np.flatnonzero(hit)
        if not len(local_index):
            return hit, spent
        deepest = float(np.min(result.distance[local_index]))
        self.stats.deepest_penetration_m = min(self.stats.deepest_penetration_m, deepest)
        contact = np.asarray(result.contact, dtype=np.float64)[local_index]
        rows = index[local_index]
        # The surface's velocity at the contacts (world frame, m/s): the service's answer.
        if result.velocity is not None:
            v_col = np.asarray(result.velocity, dtype=np.float64)[local_index]
        else:
            v_col = np.zeros((len(local_index), 3))
        for k, placement in enumerate(self.colliders):
            if held[k]:  # an end frame held here (a scene's clamp on a looping model): frame only
                sel = slice(None) if which is None else (which[local_index] == k)
                v_col[sel] = 0.0 if placement.static else collider_velocity(
                    placement.pose(t - dt), poses[k], contact[sel], dt)
        v_before = velocities[rows]
        elapsed = travelled_s - since[rows]  # seconds on its path since its velocity was set
        if reach is not None:
            push = contact - points[local_index]
            length = np.linalg.norm(push, axis=1)
            limit = reach[rows]
            # How far the point came towards the surface along the answer's normal since its
            # velocity was set (outside then), relative to the surface there: with eps, the
            # deepest a true contact can be (to first order in the step, which the checks keep
            # below eps).
            inward = -np.einsum("ij,ij->i", v_before - v_col, push) / np.maximum(length, 1e-300)
            wrong = length > np.minimum(limit, self.eps + np.maximum(inward, 0.0) * elapsed)
            # The step's later checks (a moving collider's) push from what is left: a contact held
            # through them would otherwise be pushed by the reach at every check.
            reach[rows] = limit - np.where(wrong, 0.0, length)
            if wrong.any():
                # Deeper than the point could have gone: a false contact, the collider's error, its
                # normal and velocity as wrong as its distance. Not a contact: the point goes on
                # as if unanswered. Pushed along the false normal, bounded, it stretched the
                # springs and threw the cloth; kept where it was, it was glued there while the
                # springs stretched, and thrown when let go.
                false[rows[wrong]] = True
                hit[local_index[wrong]] = False
                keep = ~wrong
                local_index, rows, contact, v_col, v_before, elapsed = (
                    local_index[keep], rows[keep], contact[keep], v_col[keep], v_before[keep], elapsed[keep])
                if not len(local_index):
                    return hit, spent
        if self.friction is None:
            v_after = v_col
        else:
            normal = np.asarray(result.normal)[local_index]
            v_after = respond_velocities(v_before, normal, np.ones(len(local_index), bool),
                                         self.friction, self.restitution, v_col)
        velocities[rows] = v_after
        # The step already moved the point along the surface with its old velocity since that
        # was set; the response changed the velocity, so take the tangential part of the
        # change back from that stretch too: a contact that sticks does not creep (it slid
        # g sin(theta) dt^2 per step on a slope). The normal part is the projection's job.
        normal = unit_rows(contact - points[local_index])
        change = (v_after - v_before) * elapsed[:, None]
        change -= np.einsum("ij,ij->i", change, normal)[:, None] * normal
        positions[rows] = contact + change + v_after * remaining_s
        since[rows] = travelled_s
        return hit, spent
