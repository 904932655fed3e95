"""NVIDIA Newton adapter: our collision response applied to a Newton model's particles.

Newton (``pip install 'neural-collider[newton]'``, built on NVIDIA Warp, CPU or CUDA) steps its
cloth as usual; call :meth:`NewtonCollider.apply` on the state after each substep::

    adapter = NewtonCollider(model, CollisionHook(client, [ColliderPlacement("bunny", pose)]))
    for substep in range(n):
        state_0.clear_forces()
        solver.step(state_0, state_1, control, None, dt)
        state_0, state_1 = state_1, state_0
        t += dt
        adapter.apply(state_0, t, dt)        # at Newton's time: numpy round trip

The hook asks for contacts and normals of the colliding particles only (``only_colliding``, its
default): the service skips the gradient work for the others.

A skinned collider (a character) follows Newton's articulation: :func:`articulation_pose` reads
the joints' world transforms and their time derivatives from Newton's rigid bodies (``body_q``,
``body_qd``), for ``Client.query(..., joint_transforms=, joint_velocities=)``::

    transforms, rates = articulation_pose(model, state_0, bodies=[0, 1, 2])
    result = client.query("character", points, fields=["contact", "velocity"],
                          joint_transforms=transforms, joint_velocities=rates)
Particles with zero mass (Newton's fixed/kinematic particles) are never moved. Newton's frame is
taken as the world frame of the poses (metres, z up by default).
"""

from __future__ import annotations

import numpy as np

from ..response import CollisionHook


class NewtonCollider:
    """Applies ``hook`` (a :class:`collider_client.CollisionHook`) to ``model``'s particles.

    model : a finalized ``newton.Model`` with particles (e.g. from ``ModelBuilder.add_cloth_grid``)
    """

    def __init__(self, model, hook: CollisionHook):
        if getattr(model, "particle_count", 0) == 0:
            raise ValueError("the Newton model has no particles to collide")
        self.model = model
        self.hook = hook
        mass = model.particle_mass.numpy()
        self.free = mass > 0.0  # zero mass = fixed by the simulator (pins): leave them alone

    def apply(self, state, t: float, dt: float) -> int:
        """Respond to contacts on ``state`` (a ``newton.State``) in place at time ``t`` (s):
        Newton's simulation time, at which the hook poses its colliders and asks animated ones
        (plus each placement's ``time_offset_s``); ``dt`` the substep just taken.

        Returns the number of particles that were in contact.
        """
        q = state.particle_q.numpy()   # (n, 3) float32, metres, world frame
        qd = state.particle_qd.numpy()  # (n, 3) float32, m/s
        positions, velocities, mask = self.hook.apply(q, qd, t, dt)
        mask &= self.free
        if not mask.any():
            return 0
        q[mask] = positions[mask]
        qd[mask] = velocities[mask]
        state.particle_q.assign(q.astype(np.float32, copy=False))
        state.particle_qd.assign(qd.astype(np.float32, copy=False))
        return int(mask.sum())


def _skew(w: np.ndarray) -> np.ndarray:
    """(n, 3, 3): the cross-product matrices of rows ``w`` (n, 3)."""
    out = np.zeros((len(w), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    return out


def articulation_pose(model, state, bodies, collider_pose=None, offsets=None):
    """A skinned collider's pose from Newton's rigid bodies: ``(joint_transforms, joint_velocities)``,
    both (J, 4, 4) float64, collider frame (the form of ``Client.query``'s skeleton pose).

    model : the finalized ``newton.Model`` (its ``body_com``: each body's centre of mass, body frame)
    state : a ``newton.State``: ``body_q`` (position, quaternion x y z w; metres, world frame) and
        ``body_qd`` (linear velocity of the centre of mass in m/s, then angular velocity in
        rad/s, world frame: Newton's twist convention)
    bodies : (J,) int, the Newton body that moves each of the collider's joints, in the order of
        its ``ModelInfo.skeleton["joints"]``
    collider_pose : (4, 4) the collider frame in Newton's world frame (default the identity); a
        moving one is the query's ``pose`` and ``pose_velocity``, not this
    offsets : (J, 4, 4) each joint's frame in its body's frame (default: the body's frame)

    A joint's transform is ``inv(collider_pose) @ W_body @ offset``; with the body rotating at
    omega and its centre of mass c (world ``R c`` from the origin) moving at v, ``dW/dt`` has
    rotation part ``[omega]x R`` and translation rate ``v - omega x (R c)``.
    """
    bodies = np.asarray(bodies, dtype=np.int64).reshape(-1)
    q = np.asarray(state.body_q.numpy(), dtype=np.float64)[bodies]    # (J, 7)
    qd = np.asarray(state.body_qd.numpy(), dtype=np.float64)[bodies]  # (J, 6)
    com = np.asarray(model.body_com.numpy(), dtype=np.float64)[bodies]  # (J, 3)
    x, y, z, w = q[:, 3], q[:, 4], q[:, 5], q[:, 6]
    norm = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    rotation = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1),
    ], axis=1)
    world = np.tile(np.eye(4), (len(bodies), 1, 1))
    world[:, :3, :3] = rotation
    world[:, :3, 3] = q[:, :3]
    linear, angular = qd[:, :3], qd[:, 3:]
    rate = np.zeros_like(world)
    rate[:, :3, :3] = _skew(angular) @ rotation
    rate[:, :3, 3] = linear - np.cross(angular, np.einsum("jab,jb->ja", rotation, com))
    if offsets is not None:
        offsets = np.asarray(offsets, dtype=np.float64)
        world, rate = world @ offsets, rate @ offsets
    if collider_pose is not None:
        to_collider = np.linalg.inv(np.asarray(collider_pose, dtype=np.float64))
        world, rate = to_collider @ world, to_collider @ rate
    return world, rate
