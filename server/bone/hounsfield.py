"""CT → bone: Hounsfield units to partial-volume density and material.

A CT voxel is bone when its HU falls in one of a mapping's bands; the band names its material.
The defaults are the usual bone presets: trabecular 148–661 HU, cortical 662–1988 HU; air, fat,
water and soft tissue (below 148 HU) are not bone. Voxels denser than the top band (petrous
bone and enamel can pass 2000 HU) count as the top band's material unless the mapping sets
``above_top = false`` (to drop metal). HU between two bands that do not touch is not bone.

Thresholding a partial-volume scan puts the surface on the threshold's iso-level and makes it
a staircase at the scan's resolution. ``partial_volume_hu`` > 0 replaces the hard step at the
lowest threshold t by a ramp: occupancy = clip(0.5 + (HU − t)/w, 0, 1), the linear mixing of
bone and background a CT voxel straddling the surface records when w is the bone–background
contrast.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

#: The usual CT bone presets, HU (inclusive ranges).
TRABECULAR_HU = (148.0, 661.0)
CORTICAL_HU = (662.0, 1988.0)
#: Any HU a file could hold: int16 and beyond, with room for float rescales.
MAX_ABS_HU = 1e6


@dataclass(frozen=True)
class HUBand:
    """Voxels with ``min_hu <= HU <= max_hu`` (or up to the next band) are ``material``."""

    material: str
    min_hu: float
    max_hu: float

    def __post_init__(self) -> None:
        for name in ("min_hu", "max_hu"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not math.isfinite(value) or abs(value) > MAX_ABS_HU:
                raise ValueError(f"HU band {self.material!r}: {name} must be a finite number "
                                 f"within ±{MAX_ABS_HU:g}, got {value!r}")
        if not self.min_hu <= self.max_hu:
            raise ValueError(f"HU band {self.material!r}: min_hu {self.min_hu} exceeds "
                             f"max_hu {self.max_hu}")


@dataclass(frozen=True)
class CTMapping:
    """HU bands (sorted, not overlapping) and what to do above and at the bone threshold.

    Attributes:
        bands: the bone bands, lowest first.
        above_top: ``True``: HU above the top band is the top band's material; ``False``: it is
            not bone (metal).
        partial_volume_hu: width w of the occupancy ramp at the lowest threshold, HU; 0 for a
            hard threshold.
    """

    bands: tuple[HUBand, ...] = (HUBand("trabecular", *TRABECULAR_HU),
                                 HUBand("cortical", *CORTICAL_HU))
    above_top: bool = True
    partial_volume_hu: float = 0.0

    def __post_init__(self) -> None:
        if not self.bands:
            raise ValueError("a CT mapping needs at least one HU band")
        for lower, upper in zip(self.bands, self.bands[1:], strict=False):
            if upper.min_hu <= lower.max_hu:
                raise ValueError(f"HU bands {lower.material!r} ({lower.min_hu:g}–"
                                 f"{lower.max_hu:g}) and {upper.material!r} ({upper.min_hu:g}–"
                                 f"{upper.max_hu:g}) overlap or are out of order")
        w = self.partial_volume_hu
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not 0.0 <= w <= 1e4:
            raise ValueError(f"partial_volume_hu must be a number in [0, 10000], got {w!r}")

    @property
    def threshold_hu(self) -> float:
        """The lowest HU that is bone (the 50 % level when there is a ramp)."""
        return self.bands[0].min_hu


class CTClassifier:
    """Density and labels of HU values under ``mapping``, a block at a time.

    Args:
        mapping: the bands.
        band_labels: (n_bands,) uint8: the material label of each band.
    """

    def __init__(self, mapping: CTMapping, band_labels: np.ndarray) -> None:
        self.lo = np.array([b.min_hu for b in mapping.bands], dtype=np.float64)
        hi = np.array([b.max_hu for b in mapping.bands], dtype=np.float64)
        # Bands whose integer ranges touch (661 | 662) meet at the next band's start, so
        # 661.5 in a float scan is not lost between them; a wider gap is a gap. The top band
        # ends at max_hu unless above_top.
        upper = np.append(self.lo[1:], np.inf)
        for b in range(len(hi) - 1):
            if self.lo[b + 1] - hi[b] > 1.0:
                upper[b] = np.nextafter(hi[b], np.inf)
        if not mapping.above_top:
            upper[-1] = np.nextafter(hi[-1], np.inf)
        self.upper = upper
        self.band_labels = np.asarray(band_labels, dtype=np.uint8)
        self.ramp_hu = float(mapping.partial_volume_hu)

    def __call__(self, hu: np.ndarray, density: np.ndarray, labels: np.ndarray) -> None:
        """Write the density and labels of ``hu`` (3-D, any real dtype) into the uint8
        arrays of its shape."""
        _classify(hu, self.lo, self.upper, self.band_labels, self.ramp_hu, density, labels)


@njit(cache=True, nogil=True)
def _classify(hu, lo, upper, band_labels, ramp_hu, density, labels):
    nb = lo.shape[0]
    t = lo[0]
    half = 0.5 * ramp_hu
    nx, ny, nz = hu.shape
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                v = float(hu[i, j, k])
                d = 0
                lab = 0
                if v >= t - half and v < upper[nb - 1]:
                    b = 0
                    while b + 1 < nb and v >= lo[b + 1]:
                        b += 1
                    lab = band_labels[b]
                    if v >= upper[b]:  # in a gap between bands: not bone
                        lab = 0
                    elif ramp_hu > 0.0 and v < t + half:
                        frac = 0.5 + (v - t) / ramp_hu
                        d = int(255.0 * frac + 0.5)
                        if d <= 0:
                            d = 0
                            lab = 0
                    else:
                        d = 255
                density[i, j, k] = d
                labels[i, j, k] = lab
