"""One tick of the bone stage, fused: carve, cutting force, shaft contact — one numba call.

numba keys the cached ``bone_tick`` on this file only, not on the kernels it calls; the
``burrforce`` command and the tests keep the cache in a directory per digest of the server's
sources (``compile_cache``), so an edit to carve.py or voxels.py never runs a stale tick.
"""

from __future__ import annotations

from numba import njit

from ..model.kernels import N_ACC, N_OUT
from .carve import TOUCH_NEAR_BONE, carve_sphere
from .force import cut_voxels
from .shaft import N_SHAFT, shaft_contact


@njit(cache=True, nogil=True)
def bone_tick(cos_t, sin_t, cos_p, sin_p, d_theta, d_phi, cos_sub_t, sin_sub_t, cos_sub_p,
              sin_sub_p, cos_tv, sin_tv, cos_pv, sin_pv, radius, centre, axis, v_feed, omega,
              cutting, carve, density, swept, labels, us_tab, usk_tab, forbidden, brick_bone,
              brick_full, brick_version, brick_forbidden, spacing, previous, version_next,
              shaft_radius, shaft_length, shaft_stiffness, removed, removed_total, touch,
              touched, vert, acc, out, shaft_out, cache, tick):
    """Carve (if ``carve`` and ``cutting``), then the cutting force, then the shaft.

    All vectors are in the grid frame; ``axis`` is the unit tool axis. A burr with no bone
    brick within reach skips the force stage entirely: far from bone a tick costs a few brick
    lookups. See ``carve_sphere``,
    ``cut_voxels`` and ``shaft_contact`` for the arguments; ``removed`` receives this tick's
    removal per label and is added to ``removed_total`` (both float64 (256,), units of 255²
    voxel volumes).

    Returns:
        True if bone was removed (the caller then bumps the bone version).
    """
    carved = carve and cutting
    for n in range(removed.shape[0]):
        removed[n] = 0.0
    removed_any = carve_sphere(density, swept, labels, forbidden, brick_bone, brick_full,
                               brick_version, brick_forbidden, spacing, centre, previous,
                               radius, carved, version_next, removed, touch, touched, cache,
                               tick)
    if removed_any:
        for n in range(removed.shape[0]):
            removed_total[n] += removed[n]
    if touch[TOUCH_NEAR_BONE] != 0.0:
        cut_voxels(cos_t, sin_t, cos_p, sin_p, d_theta, d_phi, cos_sub_t, sin_sub_t, cos_sub_p,
                   sin_sub_p, cos_tv, sin_tv, cos_pv, sin_pv, radius, centre, axis, v_feed,
                   omega, cutting, density, swept, labels, us_tab, usk_tab,
                   brick_bone, spacing, vert, acc, out, cache, tick)
    else:
        for n in range(N_OUT):
            out[n] = 0.0
        for n in range(N_ACC):
            acc[n] = 0.0
    if shaft_length > 0.0:
        shaft_contact(density, swept, brick_bone, spacing, centre, axis, radius,
                      shaft_radius, shaft_length, shaft_stiffness, shaft_out)
    else:
        for n in range(N_SHAFT):
            shaft_out[n] = 0.0
    return removed_any
