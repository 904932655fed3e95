"""Adapters that make other simulators' cloth collide with our colliders.

An adapter is small: read the simulator's particle positions and velocities as numpy (world frame,
metres, m/s), call :meth:`collider_client.CollisionHook.apply`, write the answer back, between the
simulator's substeps. :mod:`.newton` is the first (NVIDIA Newton; its ``articulation_pose`` also
reads a skinned collider's joint transforms from Newton's rigid bodies); ``docs/client.md`` shows
how to write one for another simulator.
"""
