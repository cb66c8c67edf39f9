"""The bone as voxels: grid and bricks, materials, loaders, phantoms, carving, voxel-driven
forces."""

from .bone import Bone
from .engine import BoneEngine, BoneTickResult, ForbiddenContact, ShaftParams
from .grid import BoneGrid
from .loaders import BoneFileError, LoadOptions, load_bone, save_bone
from .material_map import MaterialMap
from .materials import CORTICAL, CORTICAL_LABEL, NERVE, TRABECULAR, Material, MaterialTable
from .phantoms import PHANTOMS, layered_block, phantom, temporal_bone, workpiece_block
from .workpiece import VoxelWorkpiece

__all__ = [
    "CORTICAL",
    "CORTICAL_LABEL",
    "NERVE",
    "PHANTOMS",
    "TRABECULAR",
    "Bone",
    "BoneEngine",
    "BoneFileError",
    "BoneGrid",
    "BoneTickResult",
    "ForbiddenContact",
    "LoadOptions",
    "Material",
    "MaterialMap",
    "MaterialTable",
    "ShaftParams",
    "VoxelWorkpiece",
    "layered_block",
    "load_bone",
    "phantom",
    "save_bone",
    "temporal_bone",
    "workpiece_block",
]
