"""One tick of the bone stage, fused: carve, cutting force, shaft contact — one numba call.

numba keys the cached ``bone_tick`` on this file only, not on the kernels it calls; the
``burrforce`` command and the tests keep the cache in a directory per digest of the server's
sources (``compile_cache``), so an edit to carve.py or voxels.py never runs a stale tick.
"""

from __future__ import annotations

from ..hot_kernel import hot_inline, hot_kernel
from ..model.kernels import N_ACC, N_OUT
from .carve import TOUCH_NEAR_BONE, carve_sphere
from .force import cut_voxels, patch_half_sides
from .history import history_candidates, history_record
from .shaft import N_SHAFT, shaft_contact


@hot_kernel
def bone_tick(cos_t, sin_t, cos_p, sin_p, d_theta, d_phi, cos_sub_t, sin_sub_t, cos_sub_p,
              sin_sub_p, cos_tv, sin_tv, cos_pv, sin_pv, radius, density, swept, labels, us_tab,
              usk_tab, forbidden, brick_bone, brick_full, brick_version, brick_forbidden,
              spacing, previous, shaft_radius, shaft_length, shaft_stiffness, removed,
              removed_total, touch, touched, vert, acc, out, shaft_out, cache, path_ring,
              path_meta, path_cand, centre, axis, v_feed, omega, cutting, carve, version_next,
              tick):
    """Carve (if ``carve`` and ``cutting``), then the cutting force, then the shaft, then
    extend the burr's path (``history``: ``path_ring``, ``path_meta``, and ``path_cand`` for
    this tick's nearby capsules) with this tick's position if it carved, and keep that
    position in ``previous`` for the next tick's carve.

    The arguments that change every tick come last (from ``centre``): the engine binds the
    others once (``hot_kernel.DirectCall``). All vectors are in the grid frame; ``axis`` is
    the unit tool axis. A burr with no bone brick within reach skips the force stage entirely:
    far from bone a tick costs a few brick lookups. See ``carve_sphere``, ``cut_voxels`` and
    ``shaft_contact`` for the arguments; ``removed`` receives this tick's removal per label
    and is added to ``removed_total`` (both float64 (256,), units of 255² voxel volumes).

    Returns:
        True if bone was removed (the caller then bumps the bone version).
    """
    carved = carve and cutting
    clear(removed, removed.shape[0])
    removed_any = carve_sphere(density, swept, labels, forbidden, brick_bone, brick_full,
                               brick_version, brick_forbidden, spacing, centre, previous,
                               radius, carved, version_next, removed, touch, touched, cache,
                               tick)
    if removed_any:
        add_to(removed_total, removed)
    if touch[TOUCH_NEAR_BONE] != 0.0:
        # The path's capsules that can hold a sample: the burr's surface plus a stencil.
        h_max = max(spacing[0], max(spacing[1], spacing[2]))
        half_t, half_p = patch_half_sides(radius, d_theta, d_phi, cos_sub_t.shape[0])
        history_candidates(path_ring, path_meta, centre[0], centre[1], centre[2],
                           radius + 2.0 * h_max, radius, half_t + half_p, path_cand)
        cut_voxels(cos_t, sin_t, cos_p, sin_p, d_theta, d_phi, cos_sub_t, sin_sub_t, cos_sub_p,
                   sin_sub_p, (cos_tv, sin_tv, cos_pv, sin_pv), radius, centre, axis, v_feed,
                   omega, cutting, density, swept, labels, us_tab, usk_tab,
                   brick_bone, spacing, vert, acc, out, cache, tick, path_cand)
    else:
        clear(out, N_OUT)
        clear(acc, N_ACC)
    if shaft_length > 0.0:
        shaft_contact(density, swept, brick_bone, spacing, centre, axis, radius,
                      shaft_radius, shaft_length, shaft_stiffness, shaft_out)
    else:
        clear(shaft_out, N_SHAFT)
    # Only near bone: a hand wandering in air would fill the ring and push real cuts out.
    history_record(path_ring, path_meta, centre[0], centre[1], centre[2], radius,
                   carved and touch[TOUCH_NEAR_BONE] != 0.0,
                   min(spacing[0], min(spacing[1], spacing[2])))
    if carved:
        for n in range(3):
            previous[n] = centre[n]
    return removed_any


@hot_inline
def clear(values, n_values):
    """Zero the first ``n_values`` of a float64 vector (outputs nothing wrote this tick)."""
    for n in range(n_values):
        values[n] = 0.0


@hot_inline
def add_to(total, part):
    """total += part, float64 (n,) each (this tick's removal into the running total)."""
    for n in range(part.shape[0]):
        total[n] += part[n]


@hot_kernel
def removed_mm3(removed, spacing):
    """Total of a tick's removal per label (float64 (n ≤ 256,), units of 255² voxel volumes, as
    ``bone_tick`` fills it), in mm³ for voxels of ``spacing`` (3,) mm. Summed in numpy's
    order (``pairwise_sum``), so the totals are those of the numpy sum it replaces to the
    last bit: a recording's replay compares them bit for bit (``record.replay``)."""
    return pairwise_sum(removed, 0, removed.shape[0]) * (
        spacing[0] * spacing[1] * spacing[2] / (255.0 * 255.0))


@hot_kernel
def pairwise_sum(values, lo, n):
    """Σ values[lo:lo + n], n ≤ 256, as numpy adds a float64 array: blocks of at most 128, the
    first split at a multiple of 8 below the half, each block on ``_block_sum``. (Written out
    rather than recursive: numba's cache does not keep recursive kernels reliably.)"""
    if n <= 128:
        return _block_sum(values, lo, n)
    half = n // 2
    half -= half % 8
    rest = n - half
    if rest <= 128:
        right = _block_sum(values, lo + half, rest)
    else:
        quarter = rest // 2
        quarter -= quarter % 8
        right = (_block_sum(values, lo + half, quarter)
                 + _block_sum(values, lo + half + quarter, rest - quarter))
    return _block_sum(values, lo, half) + right


@hot_inline
def _block_sum(values, lo, n):
    """numpy's sum of a block of n ≤ 128 float64: below 8 one by one; else on eight
    interleaved partial sums, combined as ((0+1)+(2+3))+((4+5)+(6+7)), then the rest."""
    if n < 8:
        total = 0.0
        for i in range(lo, lo + n):
            total += values[i]
        return total
    r0 = values[lo]
    r1 = values[lo + 1]
    r2 = values[lo + 2]
    r3 = values[lo + 3]
    r4 = values[lo + 4]
    r5 = values[lo + 5]
    r6 = values[lo + 6]
    r7 = values[lo + 7]
    end = lo + n - n % 8
    for i in range(lo + 8, end, 8):
        r0 += values[i]
        r1 += values[i + 1]
        r2 += values[i + 2]
        r3 += values[i + 3]
        r4 += values[i + 4]
        r5 += values[i + 5]
        r6 += values[i + 6]
        r7 += values[i + 7]
    total = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    for i in range(end, lo + n):
        total += values[i]
    return total
