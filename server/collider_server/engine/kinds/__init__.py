"""The collider kinds, by the name stored in model files."""

from .kdtree import KDTreeCollider
from .mesh import MeshCollider
from .neural import NeuralCollider
from .voxel import VoxelCollider

KINDS = {cls.kind: cls for cls in (NeuralCollider, VoxelCollider, MeshCollider, KDTreeCollider)}

__all__ = ["KINDS", "KDTreeCollider", "MeshCollider", "NeuralCollider", "VoxelCollider"]
