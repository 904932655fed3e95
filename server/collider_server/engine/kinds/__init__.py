"""The collider kinds, by the name stored in model files; :func:`kind_class` picks the class of
a model (an animated one's when its info has an ``animation``)."""

from .animated_mesh import AnimatedMeshCollider
from .animated_neural import AnimatedNeuralCollider
from .animated_voxel import AnimatedVoxelCollider
from .kdtree import KDTreeCollider
from .mesh import MeshCollider
from .neural import NeuralCollider
from .neural_skinned import ArticulatedNeuralCollider
from .skinned import SkinnedCollider
from .voxel import VoxelCollider

KINDS = {cls.kind: cls for cls in (NeuralCollider, VoxelCollider, MeshCollider, KDTreeCollider,
                                   SkinnedCollider, ArticulatedNeuralCollider)}
#: The kinds that can be animated, and the class of an animated model of each.
ANIMATED_KINDS = {cls.kind: cls for cls in (AnimatedMeshCollider, AnimatedVoxelCollider, AnimatedNeuralCollider)}


def kind_class(info):
    """The class that loads a model of ``info`` (a ColliderInfo); ValueError for an unknown kind
    or one that cannot be animated."""
    if info.kind not in KINDS:
        raise ValueError(f"unknown collider kind {info.kind!r}; known kinds are {sorted(KINDS)}")
    if not info.animation:
        return KINDS[info.kind]
    if info.kind not in ANIMATED_KINDS:
        raise ValueError(f"a {info.kind} collider cannot be animated; animated kinds are "
                         f"{sorted(ANIMATED_KINDS)}")
    return ANIMATED_KINDS[info.kind]


__all__ = [
    "ANIMATED_KINDS",
    "KINDS",
    "AnimatedMeshCollider",
    "AnimatedNeuralCollider",
    "AnimatedVoxelCollider",
    "ArticulatedNeuralCollider",
    "KDTreeCollider",
    "MeshCollider",
    "NeuralCollider",
    "SkinnedCollider",
    "VoxelCollider",
    "kind_class",
]
