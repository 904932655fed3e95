"""The query core: colliders of every kind behind one query interface, their model files and
the repository that finds them by name (torch, numpy; no HTTP, no mesh files).

:class:`Collider` answers world-frame points with the rules of :mod:`collider_contract`; a kind
(:mod:`.kinds`) only evaluates its signed distance and gradient in its own frame.
"""

from .collider import Collider, ColliderInfo
from .modelfile import ModelFileError, load_collider, save_collider
from .repository import LoadedCollider, ModelRepository, served_models

__all__ = ["Collider", "ColliderInfo", "LoadedCollider", "ModelFileError", "ModelRepository", "load_collider",
           "save_collider", "served_models"]
