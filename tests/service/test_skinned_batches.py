"""The service's batch step with a skinned model: jobs at different skeleton poses in one batch
each get the answer of their own pose (one evaluation per pose), equal to the engine's."""

from __future__ import annotations

import numpy as np


def test_a_batch_answers_each_skeleton_pose_on_its_own():
    from collider_contract import ModelQuery
    from collider_server.engine.skinning import pose_at
    from collider_server.making.skinned import skinned_arm, skinned_collider
    from collider_server.service.batching import BatchPart
    from collider_server.service.query_jobs import QueryJob, answer_batch

    skin = skinned_arm()
    collider = skinned_collider(skin, "arm")
    calls = []
    query_local = collider.query_local

    def recording(local, want_gradient, below=None, time=None, skeleton=None):
        calls.append(len(local))
        return query_local(local, want_gradient, below, time, skeleton)

    collider.query_local = recording
    rng = np.random.default_rng(5)
    points = [rng.uniform(collider.domain_min, collider.domain_max, (n, 3)) for n in (50, 60, 70, 80)]
    fields = ("distance", "normal", "velocity")
    bent, bent_rates = pose_at(skin, "reach", 1.1)
    jobs = [QueryJob(ModelQuery.build(points[0], fields, time=0.2, clip="wave")),
            QueryJob(ModelQuery.build(points[1], fields, joint_transforms=bent,
                                      joint_velocities=bent_rates)),
            QueryJob(ModelQuery.build(points[2], fields, time=0.2, clip="reach")),
            QueryJob(ModelQuery.build(points[3], fields, time=0.2, clip="wave"))]
    answers = answer_batch(collider, "arm", [BatchPart(j, 0, len(j.query.points)) for j in jobs])
    assert sorted(calls) == [60, 70, 130]  # one evaluation per pose: the two "wave" jobs joined
    engine = skinned_collider(skin, "arm")
    for job, answer in zip(jobs, answers):
        q, s = job.query, job.query.skeleton
        want = engine.query(q.points, fields, time=q.time, clip=s.clip,
                            joint_transforms=s.joint_transforms,
                            joint_velocities=s.joint_velocities).fields()
        for name in fields:
            np.testing.assert_array_equal(answer[name], want[name], err_msg=name)
