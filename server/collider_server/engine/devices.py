"""Which torch device a collider runs on: CUDA when present, else the CPU; the exact kinds on
the CPU whatever is asked."""

from __future__ import annotations

#: The kinds that run on the device they are given (torch); the exact ``mesh`` and the
#: ``kdtree`` kinds run on the CPU whatever it is (libigl, SciPy).
DEVICE_KINDS = ("voxel", "neural", "neural-skinned")


def device_of(kind: str, device: str) -> str:
    """Where a collider of ``kind`` asked to run on ``device`` (a resolved name) runs."""
    return device if kind in DEVICE_KINDS else "cpu"


def default_device() -> str:
    """"cuda" when a CUDA GPU is usable, else "cpu"."""
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def resolve_device(device: str | None) -> str:
    """Validate a device name ("cpu", "cuda", "cuda:1"); ``None`` or "auto" picks the default."""
    import torch

    if device in (None, "auto"):
        return default_device()
    try:
        parsed = torch.device(device)
    except RuntimeError:
        raise ValueError(f"unknown device {device!r}; use 'cpu', 'cuda' or 'auto'") from None
    if parsed.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} asked for but no CUDA GPU is available")
    return str(parsed)
