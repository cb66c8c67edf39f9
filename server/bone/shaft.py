"""Contact of the burr's shaft with bone: a volumetric penalty, reported apart from cutting.

The shaft is a cylinder of radius r_s from the burr centre along the tool axis (toward the
handle) for a given length; the part inside the burr sphere belongs to the burr. Bone the shaft
overlaps pushes it out radially: each voxel's overlapping bone volume V pushes with
stiffness·V along the direction from the voxel to the axis. The shaft does not cut.
"""

from __future__ import annotations

import math

from ..hot_kernel import hot_kernel
from .bricks import BRICK, BRICK_SHIFT
from .voxels import plane_fraction, spacing_and_point, voxel_span

# Layout of the float64 shaft vector (length N_SHAFT), grid frame until rotated to the world.
SHAFT_FORCE = 0  # [0:3] force on the shaft, N
SHAFT_TORQUE = 3  # [3:6] its moment about the burr centre, N·mm
SHAFT_VOLUME = 6  # bone volume inside the shaft, mm³
SHAFT_DEPTH = 7  # deepest penetration of a voxel centre into the shaft, mm
N_SHAFT = 8


@hot_kernel
def shaft_contact(density, swept, brick_bone, spacing, centre, axis, burr_radius, shaft_radius,
                  length, stiffness, out):
    """Penalty contact of the shaft with bone (one call per tick).

    Args:
        density, swept: uint8 voxels.  brick_bone: int32 brick counts.  spacing: (3,) mm.
        centre: (3,) burr centre, grid frame, mm.  axis: (3,) unit tool axis, grid frame.
        burr_radius, shaft_radius, length: mm.  stiffness: N per mm³ of overlapping bone.
        out: float64 (N_SHAFT,), overwritten.
    """
    for n in range(N_SHAFT):
        out[n] = 0.0
    if length <= 0.0 or shaft_radius <= 0.0:
        return
    hx, hy, hz, cx, cy, cz = spacing_and_point(spacing, centre)
    ax = axis[0]
    ay = axis[1]
    az = axis[2]
    nx, ny, nz = density.shape
    half_diag = 0.5 * math.sqrt(hx * hx + hy * hy + hz * hz)
    reach = shaft_radius + half_diag
    reach2 = reach * reach
    burr2 = burr_radius * burr_radius
    voxel_mm3 = hx * hy * hz / (255.0 * 255.0)
    lo = (min(cx, cx + length * ax) - reach, min(cy, cy + length * ay) - reach,
          min(cz, cz + length * az) - reach)
    hi = (max(cx, cx + length * ax) + reach, max(cy, cy + length * ay) + reach,
          max(cz, cz + length * az) + reach)
    i_lo, i_hi = voxel_span(lo[0], hi[0], hx, nx)
    j_lo, j_hi = voxel_span(lo[1], hi[1], hy, ny)
    k_lo, k_hi = voxel_span(lo[2], hi[2], hz, nz)
    brick_half = 0.5 * BRICK * math.sqrt(hx * hx + hy * hy + hz * hz)
    for bi in range(i_lo >> BRICK_SHIFT, (i_hi >> BRICK_SHIFT) + 1):
        a0 = max(bi * BRICK, i_lo)
        a1 = min(bi * BRICK + BRICK - 1, i_hi)
        for bj in range(j_lo >> BRICK_SHIFT, (j_hi >> BRICK_SHIFT) + 1):
            b0 = max(bj * BRICK, j_lo)
            b1 = min(bj * BRICK + BRICK - 1, j_hi)
            for bk in range(k_lo >> BRICK_SHIFT, (k_hi >> BRICK_SHIFT) + 1):
                if brick_bone[bi, bj, bk] == 0:
                    continue
                c0 = max(bk * BRICK, k_lo)
                c1 = min(bk * BRICK + BRICK - 1, k_hi)
                # Skip bricks whose bounding sphere misses the shaft's segment.
                mx = 0.5 * (a0 + a1) * hx - cx
                my = 0.5 * (b0 + b1) * hy - cy
                mz = 0.5 * (c0 + c1) * hz - cz
                t = min(max(mx * ax + my * ay + mz * az, 0.0), length)
                rx = mx - t * ax
                ry = my - t * ay
                rz = mz - t * az
                if math.sqrt(rx * rx + ry * ry + rz * rz) > reach + brick_half:
                    continue
                for i in range(a0, a1 + 1):
                    dx = i * hx - cx
                    for j in range(b0, b1 + 1):
                        dy = j * hy - cy
                        for k in range(c0, c1 + 1):
                            d = density[i, j, k]
                            if d == 0:
                                continue
                            s = swept[i, j, k]
                            if s == 255:
                                continue
                            dz = k * hz - cz
                            t = dx * ax + dy * ay + dz * az
                            if t < 0.0 or t > length:
                                continue
                            if dx * dx + dy * dy + dz * dz < burr2:
                                continue
                            rx = dx - t * ax
                            ry = dy - t * ay
                            rz = dz - t * az
                            r2 = rx * rx + ry * ry + rz * rz
                            if r2 >= reach2 or r2 == 0.0:
                                continue
                            r = math.sqrt(r2)
                            cov = plane_fraction(shaft_radius - r, 0.5 * hx * abs(rx) / r,
                                                 0.5 * hy * abs(ry) / r, 0.5 * hz * abs(rz) / r)
                            if cov <= 0.0:
                                continue
                            vol = cov * float(d) * float(255 - s) * voxel_mm3
                            push = stiffness * vol / r  # along −(rx, ry, rz)/r
                            fx = -push * rx
                            fy = -push * ry
                            fz = -push * rz
                            out[0] += fx
                            out[1] += fy
                            out[2] += fz
                            out[3] += dy * fz - dz * fy
                            out[4] += dz * fx - dx * fz
                            out[5] += dx * fy - dy * fx
                            out[6] += vol
                            out[7] = max(out[7], shaft_radius - r)
