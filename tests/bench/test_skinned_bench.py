"""``collider bench CHARACTER`` on the public RiggedSimple glTF character, as a user runs it: the
exact skinned kind and an articulated network of the repository (a few training steps) measured
at random clip times and at random poses (joints turned, asked by joint transforms), apart,
against the exact skin at each pose; timed at a clip time and at a random pose, embedded and
served. The exact kind's errors are nil in both pose sets, which fails if a pose were asked
otherwise than it was drawn. Structure and accuracy are asserted, never timings."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from collider_cli.bench.timing import SKINNED_MODES

from .test_bench import collider_here

SAMPLE = Path(__file__).parents[1] / "data" / "gltf" / "RiggedSimple.gltf"


@pytest.mark.slow
def test_bench_of_a_character_measures_both_kinds_at_clip_times_and_random_poses(tmp_path, trained_character):
    # The network: a copy of the shared 20-step `collider train SAMPLE` (tests/conftest.py).
    assert trained_character["code"] == 0, trained_character["err"]
    (tmp_path / "models").mkdir()
    shutil.copy(trained_character["models"] / "cylinder-neural.safetensors", tmp_path / "models")
    code, out, err = collider_here("bench", SAMPLE, "--fit-size", 1.0, "--quick", "--sizes", "500",
                                   "--accuracy-points", 300, "--times", 2, "--poses", 3, "--repeats", 3,
                                   "--cell-seconds", 0.1, "--threads", 1, "--models", tmp_path / "models",
                                   "--output", tmp_path / "out", "--cache", tmp_path / "cache", "--quiet")
    assert code == 0, err
    report = json.loads((tmp_path / "out" / "bench.json").read_text())
    rows = {r["name"]: r for r in report["colliders"]}
    assert list(rows) == ["skinned", "neural-cylinder-neural"] and report["skipped"] == []
    for row in rows.values():
        accuracy = row["accuracy"]
        assert [p["perturbed"] for p in accuracy["clip_times"]["poses"]] == [False] * 2
        assert [p["perturbed"] for p in accuracy["random_poses"]["poses"]] == [True] * 3
        for part in ("clip_times", "random_poses"):
            assert accuracy[part]["band_1mm"]["points"] == 300 and accuracy[part]["band_10mm"]["points"] == 300
        assert accuracy["band_1mm"] == accuracy["random_poses"]["band_1mm"]  # what the tables rank by
        cells = {(t["path"], t["mode"], t["points"]) for t in row["timings"]}
        assert cells == {(p, m, 500) for p in ("embedded", "served") for m in SKINNED_MODES}
    # The same poses for both candidates; the exact kind is the truth itself at every one of them.
    assert rows["skinned"]["accuracy"]["random_poses"]["poses"] == \
        rows["neural-cylinder-neural"]["accuracy"]["random_poses"]["poses"]
    for part in ("clip_times", "random_poses"):
        for band in ("band_1mm", "band_10mm"):
            assert rows["skinned"]["accuracy"][part][band]["distance_max_mm"] < 1e-4  # float32 answers
        neural = rows["neural-cylinder-neural"]["accuracy"][part]["band_1mm"]["distance_max_mm"]
        assert np.isfinite(neural) and neural > 1e-3  # 20 steps: not exact
    timed = report["skinned"]["timed_at"]
    assert not timed["clip_times"]["perturbed"] and timed["random_poses"]["perturbed"]
    markdown = (tmp_path / "out" / "bench.md").read_text()
    assert "Skinned: 2 joints, clips animation 0. Errors at 2 random clip times" in markdown
    assert "Errors against the exact skin (its union) at 3 random poses" in markdown
    assert "| collider | clip times | random poses |" in markdown
    assert "Reference time: distance+normal+contact+velocity, random pose on 500 points" in markdown
    assert "| neural-skinned cylinder-neural | " in out


@pytest.mark.parametrize("extra, message", [
    (["--poses", "0"], "--poses must be a positive number of random poses, got 0"),
    (["--kinds", "voxel"], "--kinds with a character must name some of ['skinned', 'neural-skinned'], got ['voxel']"),
    (["--train-minutes", "1"], "--train-minutes: not for a skinned character; its bench measures the exact"),
    (["--kinds", "neural-skinned"], "nothing to measure: neural-skinned: no articulated network of this character"),
])
def test_bench_of_a_character_refuses_what_it_cannot_do_in_one_line(extra, message, tmp_path):
    code, _, err = collider_here("bench", SAMPLE, *extra, "--models", tmp_path, "--output", tmp_path,
                                 "--cache", tmp_path, "--quiet")
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and message in lines[0], err


def test_poses_need_a_character(tmp_path):
    code, _, err = collider_here("bench", Path(__file__).parents[2] / "examples/meshes/spot.obj",
                                 "--poses", 3, "--output", tmp_path, "--cache", tmp_path)
    assert code == 2 and "--poses is for a skinned character (glTF with a skin, USD)" in err
