"""The bone a burr's surface meets at a point: one sampler for every burr shape.

What differs between shapes (the burr's own coverage of a voxel, its path) comes from the
shape hooks of ``cutters``, chosen by the type of the ``cutter`` tuple at compile time.
Positions are in the grid frame, mm, with voxel (i, j, k)'s centre at (i·hx, j·hy, k·hz).
"""

from __future__ import annotations

import math

import numpy as np

from ..hot_kernel import hot_inline
from .bricks import BRICK_MASK, BRICK_SHIFT
from .cutters import grid_ratio, own_coverage, path_replaces_voxels, path_scale
from .voxels import gather_edge, gather_interior


@hot_inline
def sample_bone(cutter, density, swept, labels, us_tab, usk_tab, brick_bone, px, py, pz, hx,
                hy, hz, cx, cy, cz, cache, o0, o1, o2, tick, s1, s2, interior):
    """The bone the burr meets at point p (grid frame, mm), trilinear in the voxel centres.

    Returns (fraction, us_fraction, usk_fraction, gx, gy, gz):
        fraction: the original density at p (0–1) times its availability — the share of the
            bone around p outside the burr that no *other* burr position has swept. What the
            burr at (cx, cy, cz) (its reference centre) covers counts as available whether or
            not this tick carved it: it is what the model's elements are cutting (or, below
            the cutting speed, touching). Where the stencil holds swept voxels, a burr with a
            path (``cutters.SphereReach``) lets the path decide: its capsules near the burr
            either replace the voxels' availability (``HISTORY_EXACT``) or multiply it; the
            patch at p is the rectangle spanned by its half-sides s1, s2 (mm, tangent to the
            burr; 3-tuples, unused for a burr without a path).
        us_fraction, usk_fraction: fraction weighted by each voxel's Us, Us·K (N/mm²).
        gx, gy, gz: gradient of the original density, 1/mm (points into the bone).

    ``cutter``: the burr (``cutters.SphereReach`` or ``cutters.RevolvedReach``). Voxels
    outside the grid are empty and unswept. ``interior``: the caller knows p's stencil lies
    inside the grid (``voxels.stencils_inside``), so it is not checked. ``cache``, (o0, o1,
    o2), ``tick``: the tick's coverage cache (``voxels.cached_coverage``).
    """
    nx, ny, nz = density.shape
    # Reciprocals of loop-invariant spacings: LLVM hoists them out of the caller's loops.
    fx = grid_ratio(cutter, px, hx)
    fy = grid_ratio(cutter, py, hy)
    fz = grid_ratio(cutter, pz, hz)
    i0f = math.floor(fx)
    j0f = math.floor(fy)
    k0f = math.floor(fz)
    if not interior and (i0f < -1.0 or j0f < -1.0 or k0f < -1.0 or i0f >= nx or j0f >= ny
                         or k0f >= nz):
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    i0 = int(i0f)
    j0 = int(j0f)
    k0 = int(k0f)
    inside = interior or (i0 >= 0 and j0 >= 0 and k0 >= 0 and i0 + 1 < nx and j0 + 1 < ny
                          and k0 + 1 < nz)
    # A stencil inside one brick that holds no bone reads nothing else.
    if (inside and (i0 & BRICK_MASK) != BRICK_MASK and (j0 & BRICK_MASK) != BRICK_MASK
            and (k0 & BRICK_MASK) != BRICK_MASK
            and brick_bone[np.uint64(i0 >> BRICK_SHIFT), np.uint64(j0 >> BRICK_SHIFT),
                           np.uint64(k0 >> BRICK_SHIFT)] == 0):
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    tx = fx - i0f
    ty = fy - j0f
    tz = fz - k0f
    if inside:
        bone, us, usk, gx, gy, gz, swept_any = gather_interior(
            density, swept, labels, us_tab, usk_tab, i0, j0, k0, tx, ty, tz)
    else:
        bone, us, usk, gx, gy, gz, swept_any = gather_edge(
            density, swept, labels, us_tab, usk_tab, i0, j0, k0, tx, ty, tz)
    if bone == 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    scale = 1.0 / 255.0
    if swept_any:
        if not path_replaces_voxels(cutter):
            scale *= availability(cutter, swept, i0, j0, k0, tx, ty, tz, hx, hy, hz, cx, cy,
                                  cz, density, cache, o0, o1, o2, tick)
        scale = path_scale(cutter, scale, px, py, pz, s1, s2)
    return (bone * scale, us * scale, usk * scale, grid_ratio(cutter, gx, 255.0 * hx),
            grid_ratio(cutter, gy, 255.0 * hy), grid_ratio(cutter, gz, 255.0 * hz))


@hot_inline
def availability(cutter, swept, i0, j0, k0, tx, ty, tz, hx, hy, hz, cx, cy, cz, density, cache,
                 o0, o1, o2, tick):
    """Share of the stencil's bone outside the burr that no other burr position has swept
    (see ``sample_bone``), in [0, 1]. Weighted by the original density, so air — which carving
    does not track everywhere — has no say. A voxel the burr wholly covers
    (``cutters.own_coverage``) says nothing about what lies outside it."""
    nx, ny, nz = swept.shape
    a_num = 0.0
    a_den = 0.0
    for di in range(2):
        i = i0 + di
        wx = tx if di == 1 else 1.0 - tx
        in_x = 0 <= i < nx
        dx = i * hx - cx
        for dj in range(2):
            j = j0 + dj
            wy = ty if dj == 1 else 1.0 - ty
            in_xy = in_x and 0 <= j < ny
            dy = j * hy - cy
            for dk in range(2):
                k = k0 + dk
                w = wx * wy * (tz if dk == 1 else 1.0 - tz)
                if not (in_xy and 0 <= k < nz):
                    continue
                d = density[i, j, k]
                if d == 0:
                    continue
                w *= float(d)
                c = swept[i, j, k]
                if c == 0:
                    a_num += w
                    a_den += w
                    continue
                cq = own_coverage(cutter, cache, o0, o1, o2, tick, i, j, k, dx, dy, k * hz - cz,
                                  hx, hy, hz)
                if cq == 255:
                    continue  # wholly inside the burr: says nothing about what lies outside
                a_den += w
                if c <= cq:
                    a_num += w
                else:
                    a_num += w * float(255 - c) / float(255 - cq)
    if a_den <= 0.0:
        return 0.0
    return a_num / a_den
