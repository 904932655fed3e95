"""Checkpoints of a training run (safetensors: weights, Adam state, progress; no pickle), and
what a checkpoint belongs to: a run resumes one only for the same mesh, settings and
architecture."""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ...engine.animated_meshes import AnimatedMesh
from ...engine.meshes import Mesh
from .config import TrainConfig


def save_checkpoint(path: Path, network, optimizer, state: dict) -> None:
    import torch

    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in network.state_dict().items()}
    for index, param_state in optimizer.state_dict()["state"].items():
        for key, value in param_state.items():
            value = value if torch.is_tensor(value) else torch.tensor(value)  # Adam's step count
            tensors[f"adam.{index}.{key}"] = value.detach().cpu().contiguous()
    save_tensors_atomically(tensors, path, metadata={"state": json.dumps(state)})


def save_tensors_atomically(tensors: dict, path: Path, metadata: dict | None = None) -> None:
    """Write a safetensors file so that a run killed mid-write leaves the previous file intact
    (a resumed run reads it back)."""
    from safetensors.torch import save_file

    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=metadata)
    os.replace(tmp, path)


def read_checkpoint_state(path: Path) -> dict:
    """The progress state saved in a checkpoint's metadata (ValueError naming the file)."""
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as fh:
            state = json.loads((fh.metadata() or {})["state"])
    except Exception as exc:  # noqa: BLE001 -- safetensors' own error type, JSON errors, a missing "state"
        raise ValueError(f"{path}: not a readable training checkpoint ({type(exc).__name__}: "
                         f"{exc}); delete it to start over") from None
    if not isinstance(state, dict):
        raise ValueError(f"{path}: not a readable training checkpoint (state is not an object)")
    return state


def load_checkpoint(path: Path, network, optimizer) -> dict:
    """Restore ``network`` and ``optimizer`` from ``path``; returns the saved progress state.

    Raises ValueError naming the file when it is unreadable or was written for another
    architecture (a stale checkpoint of an earlier run under the same name)."""
    from safetensors.torch import load_file

    state = read_checkpoint_state(path)
    try:
        tensors = load_file(str(path))
    except Exception as exc:  # noqa: BLE001 -- safetensors' own error type
        raise ValueError(f"{path}: not a readable training checkpoint ({type(exc).__name__}: "
                         f"{exc}); delete it to start over") from None
    weights = {k[6:]: v for k, v in tensors.items() if k.startswith("model.")}
    expected = {k: tuple(v.shape) for k, v in network.state_dict().items()}
    found = {k: tuple(v.shape) for k, v in weights.items()}
    if found != expected:
        differ = sorted(set(found) ^ set(expected)) or [
            k for k in sorted(expected) if found[k] != expected[k]]
        key = differ[0]
        raise ValueError(f"{path}: checkpoint of another network architecture ({key}: checkpoint "
                         f"{found.get(key, 'absent')}, this run {expected.get(key, 'absent')}); "
                         "delete it or pass another --checkpoint")
    network.load_state_dict(weights)
    opt_state = optimizer.state_dict()
    restored: dict = {}
    for key, value in tensors.items():
        if key.startswith("adam."):
            _, index, name = key.split(".", 2)
            restored.setdefault(int(index), {})[name] = value
    opt_state["state"] = restored
    optimizer.load_state_dict(opt_state)
    return state


#: Settings a resumed run may change: they say how long and how often, not what is learnt.
RESUMABLE_SETTINGS = frozenset({"steps", "max_minutes", "threads", "validate_every"})


def run_identity(mesh: Mesh | AnimatedMesh, config: TrainConfig, meters_per_unit: float) -> dict:
    """What a checkpoint must match to be resumed: the placed mesh's content (sha256 of its
    vertices and faces, so a rescaled or rotated file differs; an animation's: of every frame's
    vertices, and its timeline), the settings that shape the training, and the architecture."""
    import hashlib

    animated = isinstance(mesh, AnimatedMesh)
    digest = hashlib.sha256()
    for array in (np.ascontiguousarray(mesh.frames if animated else mesh.vertices, dtype=np.float64),
                  np.ascontiguousarray(mesh.faces, dtype=np.int64)):
        digest.update(array.tobytes())
    settings = {k: v for k, v in asdict(config).items() if k not in RESUMABLE_SETTINGS}
    identity = {"mesh": mesh.name, "mesh_sha256": digest.hexdigest(), "meters_per_unit": meters_per_unit,
                "settings": settings, "architecture": asdict(config.resolved_architecture())}
    if animated:
        identity["animation"] = mesh.timeline.to_dict()
    return identity


def identity_differences(saved: dict | None, current: dict) -> list[str]:
    """Human-readable differences between a checkpoint's identity and this run's (empty: same)."""
    if not saved:
        return ["it records no mesh, settings or architecture (written by an older version)"]
    differs = []
    what = "animation" if "animation" in current else "mesh"
    if (saved.get("mesh_sha256"), saved.get("meters_per_unit")) != (current["mesh_sha256"], current["meters_per_unit"]):
        differs.append(f"{what} differs (checkpoint: {saved.get('mesh')} sha256 {str(saved.get('mesh_sha256'))[:12]}, "
                       f"this run: {current['mesh']} sha256 {current['mesh_sha256'][:12]})")
    if saved.get("animation") != current.get("animation"):
        differs.append(f"timeline differs (checkpoint: {saved.get('animation')}, this run: {current.get('animation')})")
    for group in ("settings", "architecture"):
        old, new = saved.get(group, {}), current[group]
        keys = sorted(k for k in set(old) | set(new) if json.dumps(old.get(k)) != json.dumps(new.get(k)))
        if keys:
            differs.append(f"{group} differ: " + ", ".join(f"{k} {old.get(k)!r} -> {new.get(k)!r}" for k in keys))
    return differs


def check_resumable(path: Path, saved: dict | None, current: dict) -> None:
    """Raise ValueError naming what differs when the checkpoint at ``path`` is another run's."""
    differs = identity_differences(saved, current)
    if differs:
        raise ValueError(f"{path}: checkpoint of another run, not resumed: {'; '.join(differs)}; "
                         "delete it or pass another --checkpoint")
