"""Where ``collider train`` puts what it makes and what it says after: the checkpoint beside the
model folder (or in ``--runs``), the mesh check before the run, the sign errors and a pasteable
``next:`` line after it (with the model folder and the placement the model was made with)."""

from __future__ import annotations

import trimesh

from collider_cli import main


def test_train_keeps_its_checkpoint_beside_the_model_folder_or_in_runs(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    trimesh.creation.icosphere(subdivisions=3, radius=0.05).export(tmp_path / "ball.obj")
    place = tmp_path / "work" / "colliders"
    argv = ["train", "ball.obj", "--name", "ball", "--preset", "fast", "--samples", "2000", "--steps", "20",
            "--batch-size", "256", "--quiet", "--models", str(place), "--units", "mm", "--scale", "1000"]
    assert main(argv) == 0
    out = capsys.readouterr().out.splitlines()
    assert (tmp_path / "work" / "runs" / "ball.ckpt.safetensors").is_file()  # beside the model folder
    assert not (tmp_path / "runs").exists()  # not in the working folder
    assert out[0] == "mesh: 1,280 faces, watertight, 1 piece, no self-intersections"
    assert out[-2].startswith("sign errors: ")
    assert out[-1] == f"next: collider eval ball --mesh ball.obj --models {place} --scale 1000.0 --units mm"
    assert main(argv[:-6] + ["--models", str(place), "--runs", "elsewhere", "--name", "ball2"]) == 0
    assert (tmp_path / "elsewhere" / "ball2.ckpt.safetensors").is_file()
