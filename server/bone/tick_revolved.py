"""One tick of the bone stage for a burr of any shape, fused: carve, cutting force, shaft.

The counterpart of ``tick.bone_tick`` for ``shapes.Burr`` values other than the abrasive
sphere; numba keys this cache on this file only (see tick.py on ``compile_cache``).
"""

from __future__ import annotations

from ..hot_kernel import hot_kernel
from ..model.kernels import N_ACC, N_OUT
from .carve import TOUCH_NEAR_BONE
from .carve_revolved import GEO_Z_TOP, carve_revolved, fill_geometry
from .force_revolved import cut_voxels_revolved
from .shaft import N_SHAFT, SHAFT_TORQUE, shaft_contact
from .tick import add_to, clear


@hot_kernel
def bone_tick_revolved(elem, ds, sub, ds_sub, cos_p, sin_p, d_phi, cos_sub_p, sin_sub_p,
                       corners, cos_pv, sin_pv, profile, bounds, geo, centre, axis, v_feed,
                       omega, cutting, carve, kn, kg, material_k, density, swept, labels,
                       us_tab, usk_tab, forbidden, brick_bone, brick_full, brick_version,
                       brick_forbidden, spacing, version_next, shaft_radius, shaft_length,
                       shaft_stiffness, shaft_base, removed, removed_total, touch, touched,
                       vert, acc, out, shaft_out, cache, rows, tick):
    """Carve (if ``carve`` and ``cutting``), then the cutting force, then the shaft.

    All vectors are in the grid frame; ``centre`` is the burr's reference centre and ``axis``
    the unit tool axis. ``profile``: (n_seg, 9) ``carve_revolved.profile_table``;
    ``bounds``: (ρ_max, z_tip, z_top, r_ball) of the shape (``carve_revolved.shape_bounds``);
    ``geo``: (N_GEO,) scratch filled here;
    ``shaft_base``: (3,) scratch, the centre of the top disc where the shaft starts (its
    torque is reported about the reference centre); ``rows``: the carve's per-row scratch.
    The rest as ``carve_revolved``,
    ``force_revolved.cut_voxels_revolved`` and ``tick.bone_tick``.

    Returns:
        True if bone was removed (the caller then bumps the bone version).
    """
    fill_geometry(geo, axis, bounds, spacing)
    carved = carve and cutting
    clear(removed, removed.shape[0])
    removed_any = carve_revolved(density, swept, labels, forbidden, brick_bone, brick_full,
                                 brick_version, brick_forbidden, spacing, centre, profile,
                                 geo, carved, version_next, removed, touch, touched, cache,
                                 rows, tick)
    if removed_any:
        add_to(removed_total, removed)
    if touch[TOUCH_NEAR_BONE] != 0.0:
        cut_voxels_revolved(elem, ds, sub, ds_sub, cos_p, sin_p, d_phi, cos_sub_p, sin_sub_p,
                            (corners, cos_pv, sin_pv), profile, geo, centre, v_feed, omega,
                            cutting, (kn, kg, material_k), density, swept, labels, us_tab,
                            usk_tab, brick_bone, spacing, vert, acc, out, cache, tick)
    else:
        clear(out, N_OUT)
        clear(acc, N_ACC)
    clear(shaft_out, N_SHAFT)
    if shaft_length > 0.0:
        top = geo[GEO_Z_TOP]
        for n in range(3):
            shaft_base[n] = centre[n] + top * axis[n]
        # Nothing of the shaft lies inside the burr past its top: no sphere to exclude.
        shaft_contact(density, swept, brick_bone, spacing, shaft_base, axis, 0.0,
                      shaft_radius, shaft_length, shaft_stiffness, shaft_out)
        # Moment about the reference centre: T_c = T_top + (top·a) × F.
        fx = shaft_out[0]
        fy = shaft_out[1]
        fz = shaft_out[2]
        ox = top * axis[0]
        oy = top * axis[1]
        oz = top * axis[2]
        shaft_out[SHAFT_TORQUE] += oy * fz - oz * fy
        shaft_out[SHAFT_TORQUE + 1] += oz * fx - ox * fz
        shaft_out[SHAFT_TORQUE + 2] += ox * fy - oy * fx
    return removed_any
