"""The specific-cutting-energy force model of a spherical grinding burr (model.md)."""

from .burr import DEFAULT_N_THETA, BurrGrid
from .cases import ORIENTATIONS, THESIS_ANGLES_DEG, CuttingCase, thesis_cases
from .cutting import CuttingModel, CuttingResult
from .params import THESIS_K, THESIS_US_N_MM2, CuttingParams
from .vibration import VibrationParams, vibration
from .workpiece import FlatWorkpiece, Workpiece

__all__ = [
    "DEFAULT_N_THETA",
    "ORIENTATIONS",
    "THESIS_ANGLES_DEG",
    "THESIS_K",
    "THESIS_US_N_MM2",
    "BurrGrid",
    "CuttingCase",
    "CuttingModel",
    "CuttingParams",
    "CuttingResult",
    "FlatWorkpiece",
    "VibrationParams",
    "Workpiece",
    "thesis_cases",
    "vibration",
]
