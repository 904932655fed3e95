"""One self-describing file per collider: safetensors for the arrays, JSON metadata beside them.

Layout (safetensors header metadata, all strings):
- ``format``: ``"neural-collider/1"``;
- ``collider``: JSON of :class:`ColliderInfo` (kind, units, domain box, source mesh and sha256,
  settings, recorded accuracy);
- ``content_sha256``: sha256 over the info JSON and every tensor (name, dtype, shape, bytes),
  so a tampered or mixed-up file is refused.

Loading never executes code from the file (safetensors holds raw arrays only; no pickle).
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from .collider import Collider, ColliderInfo

FORMAT = "neural-collider/1"
SUFFIX = ".safetensors"


class ModelFileError(ValueError):
    """A model file that cannot be used; the message names the file and the problem."""

    def __init__(self, path, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = str(path)
        self.problem = problem


def content_hash(info_json: str, tensors: dict[str, np.ndarray]) -> str:
    digest = hashlib.sha256(info_json.encode())
    for name in sorted(tensors):
        array = np.ascontiguousarray(tensors[name]).reshape(np.shape(tensors[name]))
        digest.update(f"{name}|{array.dtype.str}|{array.shape}|".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def save_collider(collider: Collider, path: str | Path) -> Path:
    """Write ``collider`` to ``path`` atomically (a reader never sees half a file)."""
    from safetensors.numpy import save_file

    path = Path(path)
    if path.suffix != SUFFIX:
        path = path.with_name(path.name + SUFFIX)
    # np.ascontiguousarray turns a 0-d array (the neural kind's radius) into shape (1,): keep
    # every array's own shape so the file loads back into the same module.
    tensors = {k: np.ascontiguousarray(v).reshape(np.shape(v)) for k, v in collider.tensors().items()}
    info_json = json.dumps(collider.info.to_dict(), sort_keys=True)
    metadata = {
        "format": FORMAT,
        "collider": info_json,
        "content_sha256": content_hash(info_json, tensors),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        save_file(tensors, tmp, metadata=metadata)
        # mkstemp creates the file private (0600); a model file is meant to be shared (a server
        # or container running as another user reads it), so give it the usual 0644.
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def _read_header(path: Path) -> tuple[dict, ColliderInfo]:
    from safetensors import safe_open

    if path.is_dir():
        raise ModelFileError(path, "is a directory, not a model file")
    if not path.is_file():
        raise ModelFileError(path, "no such model file")
    try:
        with safe_open(str(path), framework="numpy") as fh:
            metadata = fh.metadata() or {}
    except Exception as exc:  # noqa: BLE001 -- safetensors raises its own error type for damaged headers
        raise ModelFileError(path, f"not a readable safetensors file ({exc})") from None
    if metadata.get("format") != FORMAT:
        raise ModelFileError(path, f"not a collider model (format {metadata.get('format')!r}, expected {FORMAT!r})")
    try:
        info = ColliderInfo.from_dict(json.loads(metadata["collider"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelFileError(path, f"collider metadata is malformed ({exc})") from None
    return metadata, info


def read_info(path: str | Path) -> ColliderInfo:
    """The :class:`ColliderInfo` of a model file, read from its header without loading arrays."""
    return _read_header(Path(path))[1]


def load_collider(path: str | Path, device: str | None = None) -> Collider:
    """Load a collider from ``path`` onto ``device`` ("cpu", "cuda", or None for the default).

    Raises :class:`ModelFileError` when the file is missing, truncated, not a collider model,
    tampered with (content hash mismatch) or holds arrays that do not fit its kind.
    """
    from safetensors.numpy import load_file

    from .devices import resolve_device
    from .kinds import kind_class

    path = Path(path)
    # A bad device is the caller's mistake, not the file's: say so before reading the file.
    device = resolve_device(device) if device is not None else None
    metadata, info = _read_header(path)
    try:
        cls = kind_class(info)
    except ValueError as exc:
        raise ModelFileError(path, str(exc)) from None
    try:
        tensors = load_file(str(path))
    except Exception as exc:  # noqa: BLE001 -- safetensors raises its own error type
        raise ModelFileError(path, f"arrays are unreadable, the file may be truncated ({exc})") from None
    if content_hash(metadata["collider"], tensors) != metadata.get("content_sha256"):
        raise ModelFileError(path, "content hash mismatch: the file was modified or damaged")
    try:
        return cls.from_tensors(info, tensors, device)
    except ValueError as exc:
        raise ModelFileError(path, str(exc)) from None
