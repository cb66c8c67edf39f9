"""The specific-cutting-energy force model of a burr, round, cylindrical or barrel-shaped,
abrasive or fluted (model.md)."""

from .burr import DEFAULT_N_THETA, BurrGrid
from .cases import ORIENTATIONS, THESIS_ANGLES_DEG, CuttingCase, thesis_cases
from .cutting import CuttingModel, CuttingResult
from .params import THESIS_K, THESIS_US_N_MM2, CuttingParams
from .revolved import DEFAULT_ELEMENTS, RevolvedGrid, RevolvedModel
from .shapes import Abrasive, Barrel, Burr, BurrShape, Cutter, Cylinder, Fluted, Sphere
from .vibration import VibrationParams, flute_harmonic, vibration
from .workpiece import FlatWorkpiece, Workpiece

__all__ = [
    "DEFAULT_ELEMENTS",
    "DEFAULT_N_THETA",
    "ORIENTATIONS",
    "THESIS_ANGLES_DEG",
    "THESIS_K",
    "THESIS_US_N_MM2",
    "Abrasive",
    "Barrel",
    "Burr",
    "BurrGrid",
    "BurrShape",
    "Cutter",
    "CuttingCase",
    "CuttingModel",
    "CuttingParams",
    "CuttingResult",
    "Cylinder",
    "FlatWorkpiece",
    "Fluted",
    "RevolvedGrid",
    "RevolvedModel",
    "Sphere",
    "VibrationParams",
    "Workpiece",
    "flute_harmonic",
    "thesis_cases",
    "vibration",
]
