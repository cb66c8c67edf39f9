"""The tables a burr's tick reads, one typed tuple per kind of burr.

``tick.bone_tick`` and its shape hooks (``tick_hooks``, ``force_hooks``) are compiled once per
tuple type: ``SphereTick`` for the round abrasive burr, ``RevolvedTick`` for any other solid of
revolution. :class:`RevolvedTables` builds what a ``RevolvedTick`` holds beside the engine's
buffers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..model.revolved import RevolvedGrid
from ..model.shapes import Abrasive, Burr
from .carve_revolved import N_GEO, profile_table, shape_bounds


class SphereTick(NamedTuple):
    """The round abrasive burr's tables (``model.burr.BurrGrid``: element midpoints, corner
    and sub-element tables, steps in rad), its radius (mm), where it last carved (float64
    (3,), grid frame, NaN when unknown: the carve skips what that position swept) and its
    path (``history.BurrPath``'s ring, meta and candidates)."""

    cos_t: np.ndarray
    sin_t: np.ndarray
    cos_p: np.ndarray
    sin_p: np.ndarray
    d_theta: float
    d_phi: float
    cos_sub_t: np.ndarray
    sin_sub_t: np.ndarray
    cos_sub_p: np.ndarray
    sin_sub_p: np.ndarray
    cos_tv: np.ndarray
    sin_tv: np.ndarray
    cos_pv: np.ndarray
    sin_pv: np.ndarray
    radius: float
    previous: np.ndarray
    path_ring: np.ndarray
    path_meta: np.ndarray
    path_cand: np.ndarray


class RevolvedTick(NamedTuple):
    """Any other burr's tables: its ``RevolvedGrid`` (elem, ds, sub, ds_sub, cos_p, sin_p,
    d_phi, cos_sub_p, sin_sub_p), element corners (:func:`revolved_corners`),
    profile (``carve_revolved.profile_table``) and bounds (``carve_revolved.shape_bounds``),
    the cutter's normal and edge ratios and whether the materials' K replaces the normal one
    (``force_hooks``), and scratch: ``geo`` (N_GEO,) filled each tick,
    ``shaft_base`` (3,), ``rows`` the carve's per-row reach (``carve_revolved``)."""

    elem: np.ndarray
    ds: np.ndarray
    sub: np.ndarray
    ds_sub: np.ndarray
    cos_p: np.ndarray
    sin_p: np.ndarray
    d_phi: float
    cos_sub_p: np.ndarray
    sin_sub_p: np.ndarray
    corners: np.ndarray
    cos_pv: np.ndarray
    sin_pv: np.ndarray
    profile: np.ndarray
    bounds: np.ndarray
    geo: np.ndarray
    kn: float
    kg: float
    material_k: bool
    shaft_base: np.ndarray
    rows: np.ndarray



def revolved_corners(burr: Burr, grid: RevolvedGrid) -> tuple[np.ndarray, np.ndarray,
                                                              np.ndarray]:
    """The element corners of ``grid``: (ρ, z) at the n_s + 1 element boundaries along the
    profile, float64 (2, n_s + 1), mm, exact on the profile; cos and sin of the n_phi sector
    edges (k·dφ), float64 (n_phi,) each."""
    profile = burr.shape.profile()
    edges = np.concatenate(([0.0], np.cumsum(grid.ds)))
    starts = np.concatenate(([0.0], np.cumsum([seg.length_mm for seg in profile])))
    corners = np.empty((2, grid.n_s + 1))
    for n, s in enumerate(edges):
        i = min(int(np.searchsorted(starts, s, side="right")) - 1, len(profile) - 1)
        seg = profile[i]
        u = min(max((s - starts[i]) / seg.length_mm, 0.0), 1.0)
        rho, z = seg.at(np.array([u]))[:2]
        corners[0, n] = max(float(rho[0]), 0.0)
        corners[1, n] = float(z[0])
    for end in (0, grid.n_s):
        corners[0, end] = 0.0  # the tip and the top lie on the axis
    phi = np.arange(grid.n_phi) * grid.d_phi
    return (np.ascontiguousarray(corners), np.ascontiguousarray(np.cos(phi)),
            np.ascontiguousarray(np.sin(phi)))


@dataclass(frozen=True, eq=False)
class RevolvedTables:
    """What a tick of a burr other than the round abrasive one needs beside the engine's
    buffers: its grid (``RevolvedGrid``), element corners (:func:`revolved_corners`),
    profile (``carve_revolved.profile_table``) and its bounds (``shape_bounds``), the cutter's
    force ratios and scratch."""

    burr: Burr
    grid: RevolvedGrid
    corners: np.ndarray
    cos_pv: np.ndarray
    sin_pv: np.ndarray
    profile: np.ndarray
    bounds: np.ndarray
    normal_ratio: float
    edge_ratio: float
    material_k: bool
    vert: np.ndarray
    geo: np.ndarray
    shaft_base: np.ndarray

    @classmethod
    def build(cls, burr: Burr, k: float, n_elements: int, refine: int) -> RevolvedTables:
        grid = RevolvedGrid.build(burr, n_elements, refine)
        corners, cos_pv, sin_pv = revolved_corners(burr, grid)
        normal, edge = burr.cutter.force_ratios(k)
        return cls(burr, grid, corners, cos_pv, sin_pv, profile_table(grid.segments),
                   shape_bounds(burr), float(normal), float(edge),
                   isinstance(burr.cutter, Abrasive),
                   np.empty((grid.n_s + 1, grid.n_phi, 3)), np.zeros(N_GEO), np.zeros(3))
