"""One tick of the bone stage for any burr, fused: carve, cutting force, shaft contact — one
numba call.

numba keys the cached ``bone_tick`` on this file only, not on the kernels it calls; the
``burrforce`` command and the tests keep the cache in a directory per digest of the kernel
modules and what they import (``compile_cache``), so an edit to carve.py or voxels.py never
runs a stale tick.
"""

from __future__ import annotations

from ..hot_kernel import hot_inline, hot_kernel
from ..model.kernels import N_ACC, N_OUT
from .carve import TOUCH_NEAR_BONE
from .force import cut_voxels
from .tick_hooks import carve_stage, clear, path_candidates, shaft_stage, tick_end


@hot_kernel
def bone_tick(burr, density, swept, labels, us_tab, usk_tab, forbidden, brick_bone, brick_full,
              brick_version, brick_forbidden, spacing, shaft_radius, shaft_length,
              shaft_stiffness, removed, removed_total, touch, touched, vert, acc, out,
              shaft_out, cache, centre, axis, v_feed, omega, cutting, carve, version_next, tick):
    """Carve (if ``carve`` and ``cutting``), then the cutting force, then the shaft, then
    what the burr keeps for the next tick (``tick_hooks.tick_end``: the round burr's path
    and last carving position).

    ``burr``: the tables of the burr cutting now, ``tick_tables.SphereTick`` or
    ``tick_tables.RevolvedTick``; the stages that depend on its shape are chosen by that type
    when this compiles (``tick_hooks``). The arguments that change every tick come last
    (from ``centre``): the engine binds the others once (``hot_kernel.DirectCall``). All
    vectors are in the grid frame; ``centre`` is the burr's (reference) centre and ``axis``
    the unit tool axis. A burr with no bone brick within reach skips the force stage
    entirely: far from bone a tick costs a few brick lookups. See ``carve.carve_sphere``,
    ``force.cut_voxels`` and ``shaft.shaft_contact`` for the arguments; ``vert`` is the force's
    corner scratch for this burr's grid; ``removed`` receives this tick's removal per label
    and is added to ``removed_total`` (both float64 (256,), units of 255² voxel volumes).

    Returns:
        True if bone was removed (the caller then bumps the bone version).
    """
    carved = carve and cutting
    clear(removed, removed.shape[0])
    removed_any = carve_stage(burr, density, swept, labels, forbidden, brick_bone, brick_full,
                              brick_version, brick_forbidden, spacing, centre, axis, carved,
                              version_next, removed, touch, touched, cache, tick)
    if removed_any:
        add_to(removed_total, removed)
    near_bone = touch[TOUCH_NEAR_BONE] != 0.0
    if near_bone:
        path_candidates(burr, centre, spacing)
        cut_voxels(burr, centre, axis, v_feed, omega, cutting, density, swept, labels, us_tab,
                   usk_tab, brick_bone, spacing, vert, acc, out, cache, tick)
    else:
        clear(out, N_OUT)
        clear(acc, N_ACC)
    shaft_stage(burr, density, swept, brick_bone, spacing, centre, axis, shaft_radius,
                shaft_length, shaft_stiffness, shaft_out)
    tick_end(burr, centre, spacing, carved, near_bone)
    return removed_any


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
