"""Materials: what each voxel label is made of, and how it cuts.

A voxel's label (uint8) indexes a :class:`MaterialTable`. Each material has its own specific
cutting energy ``Us`` and normal/tangential ratio ``K`` (model.md), and a ``forbidden`` flag for
critical structures (nerve, vessel, dura): touching one is recorded as an event, because
training simulators grade on it. Label 0 is always empty space.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace

import numpy as np

from ..model.params import THESIS_K, THESIS_US_N_MM2
from .hounsfield import CORTICAL_HU, TRABECULAR_HU

N_LABELS = 256
EMPTY_LABEL = 0
#: The thesis's calibrated material (Us = 805.1 N/mm², K = 1.3) is label 1 in the default table.
CORTICAL_LABEL = 1
MAX_NAME_LENGTH = 64


@dataclass(frozen=True)
class Material:
    """One material.

    Attributes:
        name: unique, 1–64 printable characters.
        us_n_mm2: specific cutting energy Us, N/mm² (N·mm of work per mm³ removed), ≥ 0.
        k: normal/tangential force ratio K, ≥ 0.
        forbidden: a critical structure: touching it is recorded as an event.
    """

    name: str
    us_n_mm2: float
    k: float
    forbidden: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not 1 <= len(self.name) <= MAX_NAME_LENGTH \
                or not self.name.isprintable():
            raise ValueError(
                f"material name must be 1..{MAX_NAME_LENGTH} printable characters, "
                f"got {self.name!r}")
        # The same bounds as CuttingParams: far beyond any bone, far below overflow.
        for field, value, upper in (("us_n_mm2", self.us_n_mm2, 1e7), ("k", self.k, 100.0)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not math.isfinite(value) or not 0.0 <= value <= upper:
                raise ValueError(f"material {self.name!r}: {field} must be a number in "
                                 f"[0, {upper:g}], got {value!r}")
        if not isinstance(self.forbidden, bool):
            raise ValueError(f"material {self.name!r}: forbidden must be true or false")


#: The thesis's synthetic cortical bone (chapter III calibration).
CORTICAL = Material("cortical", THESIS_US_N_MM2, THESIS_K)


def _trabecular_us() -> float:
    """NOT MEASURED: the thesis calibrated cortical bone only. Us is scaled from cortical by
    the ratio of the two HU presets' mid-points (CT number is roughly proportional to
    apparent mineral density): 404.5 / 1325 × 805.1 ≈ 245.8 N/mm². Calibrate it on your
    own recordings (``burrforce calibrate``) before trusting trabecular forces."""
    mid = sum(TRABECULAR_HU) / 2.0 / (sum(CORTICAL_HU) / 2.0)
    return round(THESIS_US_N_MM2 * mid, 1)


#: Cancellous bone; Us is an assumption (see :func:`_trabecular_us`), K the cortical one.
TRABECULAR = Material("trabecular", _trabecular_us(), THESIS_K)
#: A nerve (a critical structure): soft tissue, which a burr cuts with no resistance worth
#: rendering next to bone; touching it is what matters, so it is forbidden.
NERVE = Material("nerve", 0.0, 0.0, forbidden=True)
#: Built-in materials by name: a materials file can name them without repeating Us and K.
BUILTIN_MATERIALS = {m.name: m for m in (CORTICAL, TRABECULAR, NERVE)}


class MaterialTable:
    """Materials by label (1..255; 0 is empty space and cannot be assigned).

    Keeps flat float64 tables (``us``, ``usk`` = Us·K) and a uint8 ``forbidden`` table of shape
    (256,) for the kernels, rebuilt on every change. A voxel whose label has no material still
    holds its density (it is carved and reported as ``label N``) but cuts with Us = K = 0.
    """

    def __init__(self, materials: dict[int, Material] | None = None) -> None:
        self._by_label: dict[int, Material] = {}
        self.us = np.zeros(N_LABELS, dtype=np.float64)
        self.usk = np.zeros(N_LABELS, dtype=np.float64)
        self.forbidden = np.zeros(N_LABELS, dtype=np.uint8)
        #: Bumped by every change, so users of the tables can tell they changed.
        self.revision = 0
        #: Bumped only when some label's ``forbidden`` flag changes.
        self.forbidden_revision = 0
        for label, material in (materials or {CORTICAL_LABEL: CORTICAL}).items():
            self.set(label, material)

    def set(self, label: int, material: Material) -> None:
        """Assign ``material`` to ``label``; names must stay unique."""
        label = _check_label(label)
        if not isinstance(material, Material):
            raise TypeError(f"expected a Material, got {type(material).__name__}")
        for other_label, other in self._by_label.items():
            if other.name == material.name and other_label != label:
                raise ValueError(f"material name {material.name!r} is already label "
                                 f"{other_label}")
        self._by_label[label] = material
        self._refresh(label)

    def update(self, label: int, **changes: object) -> Material:
        """Change some fields of the material at ``label`` (e.g. ``us_n_mm2=900.0``)."""
        material = replace(self[label], **changes)
        self.set(label, material)
        return material

    def remove(self, label: int) -> None:
        label = _check_label(label)
        if label not in self._by_label:
            raise KeyError(f"no material at label {label}")
        del self._by_label[label]
        self._refresh(label)

    def __getitem__(self, label: int) -> Material:
        label = _check_label(label)
        try:
            return self._by_label[label]
        except KeyError:
            raise KeyError(f"no material at label {label}") from None

    def __contains__(self, label: object) -> bool:
        return label in self._by_label

    def __iter__(self) -> Iterator[tuple[int, Material]]:
        return iter(sorted(self._by_label.items()))

    def __len__(self) -> int:
        return len(self._by_label)

    def label_of(self, name: str) -> int:
        for label, material in self._by_label.items():
            if material.name == name:
                return label
        raise KeyError(f"no material named {name!r}")

    def name_of(self, label: int) -> str:
        material = self._by_label.get(int(label))
        return material.name if material is not None else f"label {int(label)}"

    def copy(self) -> MaterialTable:
        return MaterialTable(dict(self._by_label))

    def labels(self) -> Iterable[int]:
        return sorted(self._by_label)

    def _refresh(self, label: int) -> None:
        self.revision += 1
        was_forbidden = self.forbidden[label]
        material = self._by_label.get(label)
        if material is None:
            self.us[label] = self.usk[label] = 0.0
            self.forbidden[label] = 0
        else:
            self.us[label] = material.us_n_mm2
            self.usk[label] = material.us_n_mm2 * material.k
            self.forbidden[label] = 1 if material.forbidden else 0
        if self.forbidden[label] != was_forbidden:
            self.forbidden_revision += 1

    def __repr__(self) -> str:
        return f"MaterialTable({dict(self)!r})"


def _check_label(label: object) -> int:
    if isinstance(label, bool) or not isinstance(label, (int, np.integer)):
        raise TypeError(f"a label must be an integer, got {type(label).__name__}")
    if not 1 <= int(label) <= N_LABELS - 1:
        raise ValueError(f"a material label must be in 1..{N_LABELS - 1} (0 is empty space), "
                         f"got {label}")
    return int(label)
