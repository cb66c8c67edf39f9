"""Per-voxel numerics shared by carving and the voxel force: sphere coverage, the coverage
cache and the trilinear gathers the bone samplers read (``sampling``).

Positions are in the grid frame, mm, with voxel (i, j, k)'s centre at (i·hx, j·hy, k·hz).
"""

from __future__ import annotations

import math

import numpy as np

from ..hot_kernel import hot_inline, hot_kernel
from ..model.kernels import box_fraction


@hot_inline
def spacing_and_point(spacing, point):
    """(hx, hy, hz, px, py, pz): a voxel's sides (``spacing``, (3,) mm) and a point ((3,),
    grid frame, mm) as scalars, the way every kernel over the voxels starts."""
    return spacing[0], spacing[1], spacing[2], point[0], point[1], point[2]


@hot_kernel
def sphere_reach(radius, hx, hy, hz):
    """Squared radii (inner, outer) between which a voxel is partly covered by a sphere.

    A voxel's extent along any unit normal is at most half its diagonal, so centres closer
    than R − diag/2 are fully inside and those beyond R + diag/2 fully outside.
    """
    half_diag = 0.5 * math.sqrt(hx * hx + hy * hy + hz * hz)
    r_in = max(radius - half_diag, 0.0)
    r_out = radius + half_diag
    return r_in * r_in, r_out * r_out


@hot_inline
def plane_fraction(depth, a, b, c):
    """Share of a voxel whose centre lies ``depth`` mm inside a plane, given the voxel's three
    half-extents projected on the plane's normal: the trapezoid whose half-ranges are the
    largest projection and the sum of the other two — exact for planes aligned with an axis,
    symmetric about the plane always, so no volume is gained or lost on average. Only the
    ratios count: depth and half-extents may share any positive scale."""
    big = max(a, max(b, c))
    return box_fraction(depth, big, a + b + c - big)


@hot_kernel
def voxel_span(lo_mm, hi_mm, h, n):
    """First and last voxel index (of n, spacing h) whose centre lies in [lo_mm, hi_mm]."""
    return max(0, math.ceil(lo_mm / h)), min(n - 1, math.floor(hi_mm / h))


@hot_inline
def sphere_coverage(dx, dy, dz, radius, hx, hy, hz, r_in2, r_out2):
    """Fraction of a voxel inside a sphere, quantized to 0–255.

    (dx, dy, dz): voxel centre minus sphere centre, mm. Within a voxel the sphere is taken as
    its tangent plane (the error is O(h²/R)), whose share is ``plane_fraction``.
    """
    d2 = dx * dx + dy * dy + dz * dz
    if d2 >= r_out2:
        return 0
    if d2 <= r_in2:
        return 255
    d = math.sqrt(d2)
    # The plane's share is scale-free: depth and half-extents (h·|Δ|/2d) are all taken ×2d,
    # so no division waits on the square root (divisions and roots share one unit, and this
    # runs for every partly covered voxel).
    frac = plane_fraction(2.0 * d * (radius - d), hx * abs(dx), hy * abs(dy), hz * abs(dz))
    return int(frac * 255.0 + 0.5)


#: Coverage cache entries hold tick·256 + coverage: valid only for the tick that wrote them.
CACHE_SHIFT = 8


def coverage_cache_shape(radius, spacing):
    """Shape of a tick's coverage cache: the burr's voxel neighbourhood plus a stencil's reach."""
    half_diag = 0.5 * math.sqrt(sum(h * h for h in spacing))
    return tuple(2 * (math.ceil((radius + half_diag) / h) + 2) + 2 for h in spacing)


@hot_kernel
def cache_origin(cache, cx, cy, cz, hx, hy, hz):
    """Voxel index of the cache's (0, 0, 0) for a burr centred at (cx, cy, cz)."""
    return (math.floor(cx / hx) - (cache.shape[0] - 2) // 2,
            math.floor(cy / hy) - (cache.shape[1] - 2) // 2,
            math.floor(cz / hz) - (cache.shape[2] - 2) // 2)


@hot_inline
def cached_coverage(cache, o0, o1, o2, tick, i, j, k, dx, dy, dz, radius, hx, hy, hz, r_in2,
                    r_out2):
    """``sphere_coverage`` of voxel (i, j, k), computed at most once per tick: carving fills
    the cache, and every bone sample whose stencil shares the voxel reads it back."""
    a = i - o0
    b = j - o1
    c = k - o2
    if 0 <= a < cache.shape[0] and 0 <= b < cache.shape[1] and 0 <= c < cache.shape[2]:
        entry = cache[a, b, c]
        if (entry >> CACHE_SHIFT) == tick:
            return entry & 255
        cq = sphere_coverage(dx, dy, dz, radius, hx, hy, hz, r_in2, r_out2)
        cache[a, b, c] = (tick << CACHE_SHIFT) | cq
        return cq
    return sphere_coverage(dx, dy, dz, radius, hx, hy, hz, r_in2, r_out2)


@hot_inline
def stencils_inside(nx, ny, nz, hx, hy, hz, cx, cy, cz, reach):
    """True if every point within ``reach`` mm of (cx, cy, cz) (grid frame, mm) has its
    trilinear stencil inside a grid of (nx, ny, nz) voxels of (hx, hy, hz) mm: one voxel
    of margin, far more than the rounding of points placed on a sphere of that radius."""
    return (cx - reach - hx >= 0.0 and cx + reach + hx < (nx - 1) * hx
            and cy - reach - hy >= 0.0 and cy + reach + hy < (ny - 1) * hy
            and cz - reach - hz >= 0.0 and cz + reach + hz < (nz - 1) * hz)


@hot_inline
def gather_interior(density, swept, labels, us_tab, usk_tab, i0, j0, k0, tx, ty, tz):
    """Trilinear original density (×255), its Us and Us·K weighted sums and its gradient (per
    voxel step) for a stencil inside the grid, unrolled: the hot path of every sample."""
    # Unsigned indices (the caller checked the stencil lies inside the grid): numba then
    # omits the negative-index wraparound of each of the 24 loads.
    a0 = np.uint64(i0)
    b0 = np.uint64(j0)
    c0 = np.uint64(k0)
    a1 = np.uint64(i0 + 1)
    b1 = np.uint64(j0 + 1)
    c1 = np.uint64(k0 + 1)
    d000 = density[a0, b0, c0]
    d001 = density[a0, b0, c1]
    d010 = density[a0, b1, c0]
    d011 = density[a0, b1, c1]
    d100 = density[a1, b0, c0]
    d101 = density[a1, b0, c1]
    d110 = density[a1, b1, c0]
    d111 = density[a1, b1, c1]
    swept_any = (swept[a0, b0, c0] | swept[a0, b0, c1] | swept[a0, b1, c0] | swept[a0, b1, c1]
                 | swept[a1, b0, c0] | swept[a1, b0, c1] | swept[a1, b1, c0]
                 | swept[a1, b1, c1]) != 0
    if (d000 | d001 | d010 | d011 | d100 | d101 | d110 | d111) == 0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, swept_any
    ux = 1.0 - tx
    uy = 1.0 - ty
    uz = 1.0 - tz
    # Weight × density per corner.
    r000 = ux * uy * uz * float(d000)
    r001 = ux * uy * tz * float(d001)
    r010 = ux * ty * uz * float(d010)
    r011 = ux * ty * tz * float(d011)
    r100 = tx * uy * uz * float(d100)
    r101 = tx * uy * tz * float(d101)
    r110 = tx * ty * uz * float(d110)
    r111 = tx * ty * tz * float(d111)
    bone = r000 + r001 + r010 + r011 + r100 + r101 + r110 + r111
    l000 = labels[a0, b0, c0]
    if (l000 == labels[a0, b0, c1] and l000 == labels[a0, b1, c0]
            and l000 == labels[a0, b1, c1] and l000 == labels[a1, b0, c0]
            and l000 == labels[a1, b0, c1] and l000 == labels[a1, b1, c0]
            and l000 == labels[a1, b1, c1]):
        us = bone * us_tab[l000]
        usk = bone * usk_tab[l000]
    else:
        us = (r000 * us_tab[l000] + r001 * us_tab[labels[a0, b0, c1]]
              + r010 * us_tab[labels[a0, b1, c0]] + r011 * us_tab[labels[a0, b1, c1]]
              + r100 * us_tab[labels[a1, b0, c0]] + r101 * us_tab[labels[a1, b0, c1]]
              + r110 * us_tab[labels[a1, b1, c0]] + r111 * us_tab[labels[a1, b1, c1]])
        usk = (r000 * usk_tab[l000] + r001 * usk_tab[labels[a0, b0, c1]]
               + r010 * usk_tab[labels[a0, b1, c0]] + r011 * usk_tab[labels[a0, b1, c1]]
               + r100 * usk_tab[labels[a1, b0, c0]] + r101 * usk_tab[labels[a1, b0, c1]]
               + r110 * usk_tab[labels[a1, b1, c0]] + r111 * usk_tab[labels[a1, b1, c1]])
    f000 = float(d000)
    f001 = float(d001)
    f010 = float(d010)
    f011 = float(d011)
    f100 = float(d100)
    f101 = float(d101)
    f110 = float(d110)
    f111 = float(d111)
    gx = (uy * uz * (f100 - f000) + uy * tz * (f101 - f001) + ty * uz * (f110 - f010)
          + ty * tz * (f111 - f011))
    gy = (ux * uz * (f010 - f000) + ux * tz * (f011 - f001) + tx * uz * (f110 - f100)
          + tx * tz * (f111 - f101))
    gz = (ux * uy * (f001 - f000) + ux * ty * (f011 - f010) + tx * uy * (f101 - f100)
          + tx * ty * (f111 - f110))
    return bone, us, usk, gx, gy, gz, swept_any


@hot_kernel
def gather_edge(density, swept, labels, us_tab, usk_tab, i0, j0, k0, tx, ty, tz):
    """``gather_interior`` for a stencil that leaves the grid (outside voxels are empty)."""
    nx, ny, nz = density.shape
    bone = 0.0
    us = 0.0
    usk = 0.0
    gx = 0.0
    gy = 0.0
    gz = 0.0
    swept_any = False
    for di in range(2):
        i = i0 + di
        if i < 0 or i >= nx:
            continue
        wx = tx if di == 1 else 1.0 - tx
        sx = 1.0 if di == 1 else -1.0
        for dj in range(2):
            j = j0 + dj
            if j < 0 or j >= ny:
                continue
            wy = ty if dj == 1 else 1.0 - ty
            sy = 1.0 if dj == 1 else -1.0
            for dk in range(2):
                k = k0 + dk
                if k < 0 or k >= nz:
                    continue
                if swept[i, j, k] != 0:
                    swept_any = True
                d = density[i, j, k]
                if d == 0:
                    continue
                wz = tz if dk == 1 else 1.0 - tz
                sz = 1.0 if dk == 1 else -1.0
                rho = float(d)
                lab = labels[i, j, k]
                w = wx * wy * wz
                bone += w * rho
                us += w * rho * us_tab[lab]
                usk += w * rho * usk_tab[lab]
                gx += sx * wy * wz * rho
                gy += sy * wx * wz * rho
                gz += sz * wx * wy * rho
    return bone, us, usk, gx, gy, gz, swept_any
