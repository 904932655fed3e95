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
