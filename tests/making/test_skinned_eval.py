"""``evaluate_skinned_collider``: a skinned model measured at random clip times and at random poses
off its clips (:func:`collider_server.engine.skinning.random_poses`), against the exact skin at each
pose. The exact kind of the generated arm, asked by clip and time or by joint transforms, is the
truth itself: its errors are nil in both sets, which fails if a pose were asked otherwise than it
was drawn. Metres, seconds."""

from __future__ import annotations

import numpy as np

from collider_server.engine.skinning import PERTURB_DEG
from collider_server.making.evaluation import evaluate_skinned_collider, format_report
from collider_server.making.skinned import skinned_arm, skinned_collider


def test_the_exact_arm_is_its_own_truth_at_clip_times_and_at_random_poses():
    skin = skinned_arm()
    collider = skinned_collider(skin, "arm")
    report = evaluate_skinned_collider(collider, skin, points=1200, times=3, poses=4, seed=5, show_progress=False)
    clip_times, poses = report["clip_times"], report["random_poses"]
    assert [p["perturbed"] for p in clip_times["poses"]] == [False] * 3
    assert [p["perturbed"] for p in poses["poses"]] == [True] * 4
    assert {p["clip"] for p in clip_times["poses"] + poses["poses"]} <= {"wave", "reach"}
    assert report["perturb_deg"] == PERTURB_DEG
    for part in (clip_times, poses):
        assert part["points_per_pose"] == 1200 // len(part["poses"])
        for name in ("band_1mm", "band_10mm", "box"):
            assert part[name]["points"] == 1200
            assert part[name]["distance_max_mm"] < 1e-4  # float32 answers: 0.1 um
            assert part[name]["sign_errors_percent"] == 0.0
    # The contact lands on the offset surface of the union at that pose (eps = 1 mm).
    assert poses["band_1mm"]["contact_p99_mm"] < 1e-4
    text = format_report("arm", "skinned", report)
    assert "3 random clip times" in text and "4 random poses" in text
    assert f"up to {PERTURB_DEG:g} deg per joint" in text
    assert text.count("+-1mm") == 2


def test_a_still_arm_is_measured_as_wrong_at_the_poses_it_does_not_follow():
    """The same measure of a model that answers every query at its rest pose finds large errors
    in both sets: the truth moves with each drawn pose."""
    skin = skinned_arm()
    collider = skinned_collider(skin, "arm")
    report = evaluate_skinned_collider(collider, skin, points=600, times=2, poses=2, seed=9, show_progress=False)
    still = evaluate_skinned_collider(_RestOnly(collider), skin, points=600, times=2, poses=2, seed=9,
                                      show_progress=False)
    assert report["random_poses"]["band_1mm"]["distance_max_mm"] < 1e-4
    assert still["random_poses"]["band_1mm"]["distance_max_mm"] > 1.0
    assert still["clip_times"]["band_1mm"]["distance_max_mm"] > 1.0


class _RestOnly:
    """A collider that answers every query at the rest pose (the pose it is given ignored)."""

    def __init__(self, collider):
        self._collider = collider
        self.info, self.domain_min, self.domain_max = collider.info, collider.domain_min, collider.domain_max
        self.device = collider.device

    def query(self, points, fields, eps=None, time=None, **_pose):
        rest = self._collider.skin.skeleton.rest_world()
        return self._collider.query(points, fields, eps=eps, joint_transforms=rest)


def test_the_random_poses_are_the_seeds(tmp_path):
    skin = skinned_arm()
    collider = skinned_collider(skin, "arm")
    one = evaluate_skinned_collider(collider, skin, points=300, times=2, poses=2, seed=3, show_progress=False)
    two = evaluate_skinned_collider(collider, skin, points=300, times=2, poses=2, seed=3, show_progress=False)
    assert one["random_poses"]["poses"] == two["random_poses"]["poses"]
    assert one["clip_times"]["poses"] == two["clip_times"]["poses"]
    assert np.isfinite(one["query_seconds_per_million"])
