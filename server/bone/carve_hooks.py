"""What the one carve (``carve.carve_voxels``) asks of a burr's shape, per shape.

A burr reaches the carve as a typed tuple: ``SphereCarve`` for the round abrasive burr (its
radius and where it last carved), ``RevolvedCarve`` for any other solid of revolution (its
profile, this tick's geometry and the per-row reach table of ``carve_revolved``). Each hook is
a ``hot_kernel.hot_hook``: numba picks its body by that type and inlines it into the carve.

The sphere's hooks skip what its last carving position already swept: the half-space of
points no farther from there than from the centre (a voxel there cannot gain coverage; a
burr at rest carves nothing), its bricks, slabs and rows at once, and rows wholly inside that
position's inner sphere. The argument needs a solid whose coverage falls with the distance to
one centre, so the other shapes examine every voxel within reach (swept-through ones cost a
byte read) and cut their rows to the solid's ball instead.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..hot_kernel import hot_hook, hot_kernel
from .carve_revolved import (
    BALL_SLACK_VOXELS,
    GEO_HALF_DIAG,
    GEO_R_BALL,
    GEO_RHO_MAX,
    GEO_Z_TIP,
    GEO_Z_TOP,
    axis_gap,
    cached_revolved_coverage,
    cached_row_reach,
)
from .cutters import is_shape, no_shape
from .voxels import cached_coverage, sphere_reach, voxel_span

#: ``brick_reach``'s verdicts: beyond the force's reach; near bone but not covered (or, for
#: the sphere, wholly swept by its last position); to be carved.
BRICK_FAR = 0
BRICK_NEAR = 1
BRICK_CARVE = 2


class SphereCarve(NamedTuple):
    """The round abrasive burr as the carve sees it: radius (mm) and where it last carved
    (float64 (3,), grid frame, NaN when unknown)."""

    radius: float
    previous: np.ndarray


class RevolvedCarve(NamedTuple):
    """Any other burr as the carve sees it: its profile (``carve_revolved.profile_table``),
    this tick's geometry (``carve_revolved.fill_geometry``) and the rows' reach table (int64
    (n0, n1, 3): ``carve_revolved.cached_row_reach``)."""

    profile: np.ndarray
    geo: np.ndarray
    rows: np.ndarray


class SphereFrame(NamedTuple):
    """The sphere's constants for one carve: 1/hz (1/mm); the squared radii between which a
    voxel is partly covered (``voxels.sphere_reach``) and the force's reach, squared (mm²);
    the half-space of points no farther from the last carving position than from the centre
    (``has_prev``; q = centre − previous, mm; q0 = q·their midpoint, mm²; 1/(q_z·hz), or 0
    where that underflows); that position (mm) and its inner radius², shrunk against rounding
    (mm²); the grid's voxels along k."""

    inv_hz: float
    r_in2: float
    r_out2: float
    near2: float
    has_prev: bool
    qx: float
    qy: float
    qz: float
    q0: float
    inv_qzh: float
    px: float
    py: float
    pz: float
    r_in2_prev: float
    nz: int


class RevolvedFrame(NamedTuple):
    """Any other shape's constants for one carve: the cylinder about its axis that holds it,
    widened by half a voxel's diagonal (mm), the force's reach beyond that axis (mm), and the
    solid's ball, squared, to which its rows are cut (mm²)."""

    r_out: float
    near: float
    ball2: float


class BrickState(NamedTuple):
    """What the sphere's slab and row hooks need of a brick: whether its last position's
    half-space may skip voxels there (never in a brick holding a forbidden label), whether the
    brick lies wholly inside the sphere's inner radius, and its squared gap from the centre
    along k (mm²). Unused (False, False, 0) for other shapes."""

    skip_old: bool
    inside: bool
    ez2: float


#: A brick the slab and row hooks will not read.
_NO_BRICK = BrickState(False, False, 0.0)


@hot_kernel
def interval_gap(c, lo, hi):
    """Distance from c to the interval [lo, hi] along one axis."""
    if c < lo:
        return lo - c
    if c > hi:
        return c - hi
    return 0.0


def carve_frame(cutter, shape, hx, hy, hz, cx, cy, cz, carve):
    """The voxels (i_lo, i_hi, j_lo, j_hi, k_lo, k_hi) the carve walks — those within the
    force's reach: bone a stencil beyond the burr's coverage switches the force stage on, so
    it starts continuously — and the tick's constants the other hooks read (``frame``)."""


@hot_hook(carve_frame)
def _carve_frame(cutter, shape, hx, hy, hz, cx, cy, cz, carve):
    if is_shape(cutter, SphereCarve):
        def sphere(cutter, shape, hx, hy, hz, cx, cy, cz, carve):
            nx, ny, nz = shape
            previous = cutter.previous
            r_in2, r_out2 = sphere_reach(cutter.radius, hx, hy, hz)
            r_out = math.sqrt(r_out2)
            near = r_out + max(hx, max(hy, hz))
            i_lo, i_hi = voxel_span(cx - near, cx + near, hx, nx)
            j_lo, j_hi = voxel_span(cy - near, cy + near, hy, ny)
            k_lo, k_hi = voxel_span(cz - near, cz + near, hz, nz)
            # Half-space of points closer to ``previous`` than to the centre: (x − mid)·Δ ≤ 0.
            has_prev = carve and previous[0] == previous[0]
            qx = cx - previous[0] if has_prev else 0.0
            qy = cy - previous[1] if has_prev else 0.0
            qz = cz - previous[2] if has_prev else 0.0
            q0 = 0.5 * (qx * (cx + previous[0]) + qy * (cy + previous[1])
                        + qz * (cz + previous[2])) if has_prev else 0.0
            # The half-space along a row is q_row + qzh·k > 0, cut at k = −q_row / qzh. Where
            # qzh is too small for a finite reciprocal (a subnormal qz underflowed it to 0: a
            # division by zero in the tick) the row is not cut at all: skipping is only a
            # saving, and keeping voxels that cannot gain costs their visit, nothing else.
            qzh = qz * hz
            inv_qzh = 1.0 / qzh if abs(qzh) > 1e-300 else 0.0
            # Every voxel inside ``previous``'s inner sphere was swept through (255) by that
            # carve, directly or, where its half-space skipped the voxel, by an earlier one no
            # farther from it. Shrunk by far more than the rounding of either test, so a voxel
            # on the boundary is read as before.
            px = previous[0] if has_prev else 0.0
            py = previous[1] if has_prev else 0.0
            pz = previous[2] if has_prev else 0.0
            frame = SphereFrame(1.0 / hz, r_in2, r_out2, near * near, has_prev, qx, qy, qz, q0,
                                inv_qzh, px, py, pz, r_in2 * (1.0 - 1e-9), nz)
            return i_lo, i_hi, j_lo, j_hi, k_lo, k_hi, frame
        return sphere
    if is_shape(cutter, RevolvedCarve):
        def revolved(cutter, shape, hx, hy, hz, cx, cy, cz, carve):
            nx, ny, nz = shape
            geo = cutter.geo
            ax = geo[6]
            ay = geo[7]
            az = geo[8]
            half_diag = geo[GEO_HALF_DIAG]
            r_out = geo[GEO_RHO_MAX] + half_diag
            near = r_out + max(hx, max(hy, hz))
            z_tip = geo[GEO_Z_TIP]
            z_top = geo[GEO_Z_TOP]
            # The voxels of the capsule about the axis segment, radius ``near``: it holds the
            # solid.
            i_lo, i_hi = voxel_span(min(cx + z_tip * ax, cx + z_top * ax) - near,
                                    max(cx + z_tip * ax, cx + z_top * ax) + near, hx, nx)
            j_lo, j_hi = voxel_span(min(cy + z_tip * ay, cy + z_top * ay) - near,
                                    max(cy + z_tip * ay, cy + z_top * ay) + near, hy, ny)
            k_lo, k_hi = voxel_span(min(cz + z_tip * az, cz + z_top * az) - near,
                                    max(cz + z_tip * az, cz + z_top * az) + near, hz, nz)
            # Rows are cut to the solid's ball too (``revolved_coverage``'s first reject): for
            # a round burr the cylinder about its axis holds half as much again as the ball.
            ball = geo[GEO_R_BALL] + half_diag + BALL_SLACK_VOXELS * min(hx, min(hy, hz))
            return i_lo, i_hi, j_lo, j_hi, k_lo, k_hi, RevolvedFrame(r_out, near, ball * ball)
        return revolved
    return no_shape(cutter)


def brick_side(cutter, c, lo, hi):
    """(gap, far): the distance from c to a brick's extent [lo, hi] along one axis and to
    its far end, mm (the sphere's brick tests); zeros for shapes that do not use them."""


@hot_hook(brick_side)
def _brick_side(cutter, c, lo, hi):
    if is_shape(cutter, SphereCarve):
        return lambda cutter, c, lo, hi: (interval_gap(c, lo, hi), max(abs(c - lo), abs(c - hi)))
    if is_shape(cutter, RevolvedCarve):
        return lambda cutter, c, lo, hi: (0.0, 0.0)
    return no_shape(cutter)


def brick_reach(cutter, frame, ex, ey, fx, fy, a0, a1, b0, b1, c0, c1, hx, hy, hz, cx, cy, cz,
                forbidden_here):
    """(verdict, brick): whether the brick's part (a0..a1, b0..b1, c0..c1) holding bone is
    beyond the force's reach (``BRICK_FAR``), within it but not to be carved (``BRICK_NEAR``)
    or to be carved (``BRICK_CARVE``), and what the slab and row hooks need of it.
    ``forbidden_here``: the brick holds a forbidden label (its contact is always checked)."""


@hot_hook(brick_reach)
def _brick_reach(cutter, frame, ex, ey, fx, fy, a0, a1, b0, b1, c0, c1, hx, hy, hz, cx, cy, cz,
                 forbidden_here):
    if is_shape(cutter, SphereCarve):
        def sphere(cutter, frame, ex, ey, fx, fy, a0, a1, b0, b1, c0, c1, hx, hy, hz, cx, cy,
                   cz, forbidden_here):
            qx = frame.qx
            qy = frame.qy
            qz = frame.qz
            ez = interval_gap(cz, c0 * hz, c1 * hz)
            ez2 = ez * ez
            gap2 = ex * ex + ey * ey + ez2
            if gap2 >= frame.near2:
                return BRICK_FAR, _NO_BRICK
            if gap2 >= frame.r_out2:
                return BRICK_NEAR, _NO_BRICK
            skip_old = frame.has_prev and forbidden_here == 0
            if skip_old and (max(qx * a0 * hx, qx * a1 * hx) + max(qy * b0 * hy, qy * b1 * hy)
                             + max(qz * c0 * hz, qz * c1 * hz)) <= frame.q0:
                return BRICK_NEAR, _NO_BRICK
            fz = max(abs(cz - c0 * hz), abs(cz - c1 * hz))
            inside = fx * fx + fy * fy + fz * fz <= frame.r_in2
            return BRICK_CARVE, BrickState(skip_old, inside, ez2)
        return sphere
    if is_shape(cutter, RevolvedCarve):
        def revolved(cutter, frame, ex, ey, fx, fy, a0, a1, b0, b1, c0, c1, hx, hy, hz, cx, cy,
                     cz, forbidden_here):
            # The brick's part in range, as its bounding sphere.
            mx = 0.5 * (a0 + a1) * hx
            my = 0.5 * (b0 + b1) * hy
            mz = 0.5 * (c0 + c1) * hz
            brick_half = 0.5 * math.sqrt(((a1 - a0) * hx) ** 2 + ((b1 - b0) * hy) ** 2
                                         + ((c1 - c0) * hz) ** 2)
            gap = axis_gap(mx, my, mz, cx, cy, cz, cutter.geo) - brick_half
            if gap >= frame.near:
                return BRICK_FAR, _NO_BRICK
            if gap >= frame.r_out:
                return BRICK_NEAR, _NO_BRICK
            return BRICK_CARVE, _NO_BRICK
        return revolved
    return no_shape(cutter)


def slab_reach(cutter, frame, brick, i, b0, b1, c0, c1, ey, hx, hy, hz, cx):
    """(keep, dx): whether slab i of the brick may hold covered voxels, and its offset from
    the centre along x, mm."""


@hot_hook(slab_reach)
def _slab_reach(cutter, frame, brick, i, b0, b1, c0, c1, ey, hx, hy, hz, cx):
    if is_shape(cutter, SphereCarve):
        def sphere(cutter, frame, brick, i, b0, b1, c0, c1, ey, hx, hy, hz, cx):
            qx = frame.qx
            qy = frame.qy
            qz = frame.qz
            # A slab of rows wholly closer to ``previous`` is skipped at once, not row by row
            # (the brick test already drops most of them).
            if brick.skip_old and (qx * i * hx + max(qy * b0 * hy, qy * b1 * hy)
                                   + max(qz * c0 * hz, qz * c1 * hz)) <= frame.q0:
                return False, 0.0
            dx = i * hx - cx
            if dx * dx + ey * ey + brick.ez2 >= frame.r_out2:
                return False, dx  # the slab's rows all pass beside the burr in this brick
            return True, dx
        return sphere
    if is_shape(cutter, RevolvedCarve):
        return lambda cutter, frame, brick, i, b0, b1, c0, c1, ey, hx, hy, hz, cx: (
            True, i * hx - cx)
    return no_shape(cutter)


def row_span(cutter, frame, brick, i, j, dx, dy, c0, c1, k_lo, k_hi, o0, o1, tick, hx, hy, hz,
             cz):
    """(first, last): the voxels k of row (i, j) in the brick (c0..c1) that may gain
    coverage; empty when first > last."""


@hot_hook(row_span)
def _row_span(cutter, frame, brick, i, j, dx, dy, c0, c1, k_lo, k_hi, o0, o1, tick, hx, hy, hz,
              cz):
    if is_shape(cutter, SphereCarve):
        def sphere(cutter, frame, brick, i, j, dx, dy, c0, c1, k_lo, k_hi, o0, o1, tick, hx,
                   hy, hz, cz):
            qz = frame.qz
            inv_qzh = frame.inv_qzh
            skip_old = brick.skip_old
            k_from = c0
            k_to = c1
            if skip_old:
                # Keep only k with q_row + qz·k·hz > 0 (closer to the centre), before the
                # row's square root: rows wholly behind cost nothing.
                q_row = frame.qx * i * hx + frame.qy * j * hy - frame.q0
                # Where the half-space crosses the row, clamped to the grid: a step almost
                # level in z puts it far away, beyond what converts to an int.
                k_cut = min(max(-q_row * inv_qzh, -1.0), float(frame.nz))
                if inv_qzh > 0.0:
                    k_from = max(k_from, math.floor(k_cut) + 1)
                elif inv_qzh < 0.0:
                    k_to = min(k_to, math.ceil(k_cut) - 1)
                elif qz == 0.0 and q_row <= 0.0:
                    return 1, 0
                if k_from > k_to:
                    return 1, 0
            rest = frame.r_out2 - dx * dx - dy * dy
            if rest <= brick.ez2:
                # The row's chord of the burr ends short of this brick's part of the row
                # (most rows near the burr's rim, in a cut's bone bricks).
                return 1, 0
            reach_z = math.sqrt(rest)
            k_first = max(k_from, math.ceil((cz - reach_z) * frame.inv_hz))
            k_last = min(k_to, math.floor((cz + reach_z) * frame.inv_hz))
            if skip_old:
                # Both ends inside ``previous``'s inner sphere: so is the whole row (convex),
                # which that carve swept through. Its run of 255 is skipped unread.
                rest_in = (frame.r_in2_prev - (i * hx - frame.px) ** 2
                           - (j * hy - frame.py) ** 2)
                if ((k_first * hz - frame.pz) ** 2 < rest_in
                        and (k_last * hz - frame.pz) ** 2 < rest_in):
                    return 1, 0
            return k_first, k_last
        return sphere
    if is_shape(cutter, RevolvedCarve):
        def revolved(cutter, frame, brick, i, j, dx, dy, c0, c1, k_lo, k_hi, o0, o1, tick, hx,
                     hy, hz, cz):
            k_first, k_last = cached_row_reach(cutter.rows, o0, o1, tick, i, j, dx, dy, cz, hz,
                                               cutter.geo, frame.r_out, frame.ball2, k_lo, k_hi)
            return max(k_first, c0), min(k_last, c1)
        return revolved
    return no_shape(cutter)


def voxel_coverage(cutter, frame, brick, cache, o0, o1, o2, tick, i, j, k, dx, dy, dz, hx, hy,
                   hz):
    """The share (0–255) of voxel (i, j, k) the burr covers, (dx, dy, dz) from its centre
    (mm), through the tick's coverage cache; 255 for a brick wholly inside the sphere."""


@hot_hook(voxel_coverage)
def _voxel_coverage(cutter, frame, brick, cache, o0, o1, o2, tick, i, j, k, dx, dy, dz, hx, hy,
                    hz):
    if is_shape(cutter, SphereCarve):
        def sphere(cutter, frame, brick, cache, o0, o1, o2, tick, i, j, k, dx, dy, dz, hx, hy,
                   hz):
            return 255 if brick.inside else cached_coverage(
                cache, o0, o1, o2, tick, i, j, k, dx, dy, dz, cutter.radius, hx, hy, hz,
                frame.r_in2, frame.r_out2)
        return sphere
    if is_shape(cutter, RevolvedCarve):
        def revolved(cutter, frame, brick, cache, o0, o1, o2, tick, i, j, k, dx, dy, dz, hx, hy,
                     hz):
            return cached_revolved_coverage(cache, o0, o1, o2, tick, i, j, k, dx, dy, dz,
                                            cutter.profile, cutter.geo, hx, hy, hz)
        return revolved
    return no_shape(cutter)
