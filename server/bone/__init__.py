"""The bone as voxels: grid and bricks, materials, phantoms, carving, voxel-driven forces."""

from .engine import BoneEngine, BoneTickResult, ForbiddenContact, ShaftParams
from .grid import BoneGrid
from .materials import CORTICAL, CORTICAL_LABEL, Material, MaterialTable
from .phantoms import workpiece_block
from .workpiece import VoxelWorkpiece

__all__ = [
    "CORTICAL",
    "CORTICAL_LABEL",
    "BoneEngine",
    "BoneGrid",
    "BoneTickResult",
    "ForbiddenContact",
    "Material",
    "MaterialTable",
    "ShaftParams",
    "VoxelWorkpiece",
    "workpiece_block",
]
