"""A model repository: a folder where every ``NAME.safetensors`` collider is found by NAME."""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

from collider_contract import ModelInfo

from .collider import Collider, ColliderInfo
from .modelfile import SUFFIX, load_collider, read_info

NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def is_valid_name(name: str) -> bool:
    """1-64 letters, digits, '_', '-', '.', starting with a letter or digit, not ending in the
    model file suffix (so names are safe file and URL parts)."""
    return isinstance(name, str) and bool(NAME_PATTERN.match(name)) and not name.endswith(SUFFIX)


def check_name(name: str) -> str:
    """``name`` if :func:`is_valid_name`, else ValueError saying what a name may hold."""
    if not is_valid_name(name):
        raise ValueError(
            f"invalid model name {name!r}: use 1-64 letters, digits, '_', '-' or '.', "
            "starting with a letter or digit"
        )
    return name


SHIPPED_MODELS_DATA = "share/neural-collider/models"  # where pyproject's data-files put them
#: The source checkout's root: where an editable install's files are when run from elsewhere.
CHECKOUT = Path(__file__).resolve().parents[3]


def installed_models_dir() -> Path | None:
    """The shipped models' folder of a (non-editable) ``pip install``, wherever pip's scheme put
    it (``<venv>/share/...``, ``~/.local/share/...``), found through the distribution's file
    list; ``None`` when the package is not installed that way."""
    from importlib import metadata

    try:
        files = metadata.distribution("neural-collider").files or []
    except metadata.PackageNotFoundError:
        return None
    for file in files:
        if file.as_posix().endswith(f"{SHIPPED_MODELS_DATA}/{file.name}") and file.name.endswith(SUFFIX):
            return Path(file.locate()).resolve().parent
    return None


def default_models_dir() -> Path:
    """``$COLLIDER_MODELS`` if set, else ``./models`` if it exists, else the source checkout's
    ``models/`` (editable install), else the shipped models of an installed package."""
    if os.environ.get("COLLIDER_MODELS"):
        return Path(os.environ["COLLIDER_MODELS"])
    local = Path("models")
    if local.is_dir():
        return local
    checkout = CHECKOUT / "models"
    if checkout.is_dir():
        return checkout
    return installed_models_dir() or checkout


def check_writable_folder(folder: Path, what: str) -> Path:
    """Create ``folder`` (and its parents) if missing, then write and delete a probe file in it:
    permission bits alone do not tell (root ignores them; a read-only mount does not)."""
    import tempfile

    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder, prefix=".write-probe."):
            pass
    except FileExistsError:
        raise PermissionError(f"{what} {folder} is a file, not a folder") from None
    except OSError as exc:
        raise PermissionError(f"{what} {folder} is not writable ({exc.strerror or exc})") from None
    return folder


def model_info(name: str, info: ColliderInfo, size_bytes: int, device: str) -> ModelInfo:
    """What the service's ``GET /v1/models`` and the SDK's ``list_models`` say of a model:
    ``name`` (the file's, whatever name it was made under), its collider info, the file's size
    in bytes and the device it runs on."""
    return ModelInfo(name=name, kind=info.kind, units=info.units, meters_per_unit=info.meters_per_unit,
                     domain_min=np.asarray(info.domain_min, dtype=np.float64),
                     domain_max=np.asarray(info.domain_max, dtype=np.float64), bytes=size_bytes,
                     approximate=info.approximate, accuracy=info.accuracy, source=info.source,
                     settings=info.settings, device=device, animation=info.animation,
                     skeleton=info.skeleton)


class LoadedCollider(NamedTuple):
    """A repository's model, loaded: its collider and what ``GET /v1/models`` and the SDK's
    ``list_models`` say of it (:func:`model_info`)."""

    collider: Collider
    info: ModelInfo


def served_models(loaded: Mapping[str, LoadedCollider]) -> list[ModelInfo]:
    """The models a service or an embedded client serves, as both list them: every loaded
    model (a repository's file that failed to load is not served), sorted by name. ``loaded``'s
    values need only an ``info``."""
    return [loaded[name].info for name in sorted(loaded)]


class ModelRepository:
    """Colliders stored as ``root/NAME.safetensors``."""

    def __init__(self, root: str | Path | None = None):
        self.root = Path(root) if root is not None else default_models_dir()

    def names(self) -> list[str]:
        """Sorted names of the model files in the folder (empty if the folder is absent).

        Files whose stem is not a valid model name (hidden files, spaces, ...) are not models:
        callers pass every name to :meth:`path`, which would refuse them."""
        if not self.root.is_dir():
            return []
        stems = (p.name[: -len(SUFFIX)] for p in self.root.glob(f"*{SUFFIX}") if p.is_file())
        return sorted(stem for stem in stems if is_valid_name(stem))

    def path(self, name: str) -> Path:
        return self.root / f"{check_name(name)}{SUFFIX}"

    def model_file(self, name: str) -> Path:
        """The file of the repository's model ``name``, a name only, never a path (what the
        service and the SDK's embedded backend serve): ValueError for an invalid name,
        FileNotFoundError when the repository holds no such model."""
        path = self.path(name)
        if not path.is_file():
            raise FileNotFoundError(f"no model file {path.name} in {self.root}")
        return path

    def load_model(self, name: str, device: str | None = None) -> LoadedCollider:
        """The repository's model ``name`` (a name only: :meth:`model_file`) loaded on ``device``
        (None: CUDA if present), with its :func:`model_info`. Raises ValueError,
        FileNotFoundError or ModelFileError."""
        path = self.model_file(name)
        size_bytes = path.stat().st_size  # read first: a file replaced meanwhile fails here
        collider = load_collider(path, device)
        return LoadedCollider(collider, model_info(name, collider.info, size_bytes, collider.device))

    def resolve(self, name_or_path: str) -> Path:
        """A model name in this repository, or a path to a model file (one that ends in
        ``.safetensors`` or has a directory part), for the ``collider`` commands, which take
        either. A bare name is always a repository name, even when a file of that name happens
        to exist in the working directory. The service and the SDK take names only
        (:meth:`load_model`)."""
        if name_or_path.endswith(SUFFIX) or Path(name_or_path).name != name_or_path:
            return Path(name_or_path)
        path = self.path(name_or_path)
        if not path.is_file():
            known = ", ".join(self.names()) or "none"
            raise FileNotFoundError(f"no model named {name_or_path!r} in {self.root} (models: {known})")
        return path

    def check_writable(self) -> Path:
        """Create the folder if missing and prove a file can be written in it; raise
        PermissionError naming the folder otherwise (before hours of training, not after)."""
        return check_writable_folder(self.root, "model repository")

    def info(self, name: str) -> ColliderInfo:
        return read_info(self.resolve(name))

    def load(self, name: str, device: str | None = None) -> Collider:
        return load_collider(self.resolve(name), device)
