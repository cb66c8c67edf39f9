"""What the shared voxel kernels ask of a burr's shape, answered per shape at compile time.

A burr reaches the kernels as a small typed tuple (``typing.NamedTuple``): ``SphereReach`` for
the round abrasive burr (a sphere with its path), ``RevolvedReach`` for any other solid of
revolution (its profile table and this tick's geometry). The shared kernels call the hooks
below with it; each hook is a ``numba.extending.overload`` whose body numba picks by the
tuple's type and inlines where it is called (``hot_hook``), so a kernel compiled for one shape
holds that shape's code only: a hook that means nothing for a shape compiles to nothing.

The hooks keep each shape's own arithmetic where the two differed by rounding (a product by a
reciprocal against a division): every output stays what it was to the last bit.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import types

from ..hot_kernel import hot_hook
from .carve_revolved import cached_revolved_coverage
from .history import CAND_COUNT, CAND_MODE, HISTORY_EXACT, history_share
from .voxels import cached_coverage


class SphereReach(NamedTuple):
    """The round abrasive burr as the samplers see it: radius R (mm), the squared radii
    between which a voxel is partly covered (``voxels.sphere_reach``, mm²) and the path's
    candidates near it this tick (``history.history_candidates``, with their header)."""

    radius: float
    r_in2: float
    r_out2: float
    cand: np.ndarray


class RevolvedReach(NamedTuple):
    """Any other burr as the samplers see it: its profile (``carve_revolved.profile_table``)
    and this tick's geometry (``carve_revolved.fill_geometry``). It keeps no path."""

    profile: np.ndarray
    geo: np.ndarray


def is_shape(cutter, cls) -> bool:
    """True if the numba type ``cutter`` is that of the NamedTuple class ``cls`` (a hook's
    typing function picks its body with this)."""
    return isinstance(cutter, types.BaseNamedTuple) and cutter.instance_class is cls


def no_shape(cutter):
    """A hook's answer to a type it has no body for."""
    raise TypeError(f"no burr shape of type {cutter}")


def grid_ratio(cutter, a, b):
    """a / b as the shape's kernels always took it: a times b's reciprocal for the sphere
    (LLVM hoists the reciprocal of a loop-invariant b), a plain division otherwise."""


@hot_hook(grid_ratio)
def _grid_ratio(cutter, a, b):
    if is_shape(cutter, SphereReach):
        return lambda cutter, a, b: a * (1.0 / b)
    if is_shape(cutter, RevolvedReach):
        return lambda cutter, a, b: a / b
    return no_shape(cutter)


def own_coverage(cutter, cache, o0, o1, o2, tick, i, j, k, dx, dy, dz, hx, hy, hz):
    """The share (0–255) of voxel (i, j, k) the burr covers, (dx, dy, dz) from its (reference)
    centre, mm, through the tick's coverage cache (``voxels.cached_coverage``). The sphere
    answers 255 for a voxel inside its inner sphere without touching the cache."""


@hot_hook(own_coverage)
def _own_coverage(cutter, cache, o0, o1, o2, tick, i, j, k, dx, dy, dz, hx, hy, hz):
    if is_shape(cutter, SphereReach):
        def sphere(cutter, cache, o0, o1, o2, tick, i, j, k, dx, dy, dz, hx, hy, hz):
            if dx * dx + dy * dy + dz * dz <= cutter.r_in2:
                return 255
            return cached_coverage(cache, o0, o1, o2, tick, i, j, k, dx, dy, dz, cutter.radius,
                                   hx, hy, hz, cutter.r_in2, cutter.r_out2)
        return sphere
    if is_shape(cutter, RevolvedReach):
        def revolved(cutter, cache, o0, o1, o2, tick, i, j, k, dx, dy, dz, hx, hy, hz):
            return cached_revolved_coverage(cache, o0, o1, o2, tick, i, j, k, dx, dy, dz,
                                            cutter.profile, cutter.geo, hx, hy, hz)
        return revolved
    return no_shape(cutter)


def path_replaces_voxels(cutter):
    """True if the burr's path knows every cut within reach this tick (``HISTORY_EXACT``):
    then its share replaces the voxels' availability. Never for a burr without a path."""


@hot_hook(path_replaces_voxels)
def _path_replaces_voxels(cutter):
    if is_shape(cutter, SphereReach):
        return lambda cutter: cutter.cand[0, CAND_MODE] == HISTORY_EXACT
    if is_shape(cutter, RevolvedReach):
        return lambda cutter: False
    return no_shape(cutter)


def path_scale(cutter, scale, px, py, pz, s1, s2):
    """``scale`` times the share of the patch at p (half-sides s1, s2: 3-tuples, mm) that the
    burr's path has not cut (``history.history_share``); ``scale`` itself for a burr without
    a path, or where no capsule is near."""


@hot_hook(path_scale)
def _path_scale(cutter, scale, px, py, pz, s1, s2):
    if is_shape(cutter, SphereReach):
        def sphere(cutter, scale, px, py, pz, s1, s2):
            cand = cutter.cand
            if cand[0, CAND_COUNT] > 0.0 and scale > 0.0:
                return scale * history_share(cand, px, py, pz, s1[0], s1[1], s1[2], s2[0],
                                             s2[1], s2[2])
            return scale
        return sphere
    if is_shape(cutter, RevolvedReach):
        return lambda cutter, scale, px, py, pz, s1, s2: scale
    return no_shape(cutter)
