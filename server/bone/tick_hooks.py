"""The stages of the bone tick that depend on the burr's shape, chosen by its tables' type.

``tick.bone_tick`` is one kernel for every burr; its first argument holds the tables of the
burr cutting now, as a typed tuple (``tick_tables``): ``SphereTick`` for the round abrasive
burr (its grid on the sphere, radius, path and last carving position), ``RevolvedTick`` for
any other solid of revolution (``revolved.RevolvedGrid``'s tables, profile, force ratios and
scratch). The force stage is one kernel with hooks of its own (``force``, ``force_hooks``). Each
stage below is a shape hook (``hot_kernel.hot_hook``): numba picks its body by that type and
inlines it into the tick, so a tick compiled for one shape holds that shape's stages only —
the round burr's path and half-space skip compile to nothing for the others.
"""

from __future__ import annotations

from ..hot_kernel import hot_hook, hot_inline
from .carve import carve_voxels
from .carve_hooks import RevolvedCarve, SphereCarve
from .carve_revolved import GEO_Z_TOP, fill_geometry
from .cutters import is_shape, no_shape
from .force_hooks import patch_half_sides
from .history import history_candidates, history_record
from .shaft import N_SHAFT, SHAFT_TORQUE, shaft_contact
from .tick_tables import RevolvedTick, SphereTick


@hot_inline
def clear(values, n_values):
    """Zero the first ``n_values`` of a float64 vector (outputs nothing wrote this tick)."""
    for n in range(n_values):
        values[n] = 0.0


def carve_stage(burr, density, swept, labels, forbidden, brick_bone, brick_full, brick_version,
                brick_forbidden, spacing, centre, axis, carve, version_next, removed, touch,
                touched, cache, tick):
    """Sweep what the burr covers (``carve.carve_voxels``); returns True if bone was
    removed."""


@hot_hook(carve_stage)
def _carve_stage(burr, density, swept, labels, forbidden, brick_bone, brick_full, brick_version,
                 brick_forbidden, spacing, centre, axis, carve, version_next, removed, touch,
                 touched, cache, tick):
    if is_shape(burr, SphereTick):
        def sphere(burr, density, swept, labels, forbidden, brick_bone, brick_full,
                   brick_version, brick_forbidden, spacing, centre, axis, carve, version_next,
                   removed, touch, touched, cache, tick):
            return carve_voxels(SphereCarve(burr.radius, burr.previous), density, swept,
                                labels, forbidden, brick_bone, brick_full, brick_version,
                                brick_forbidden, spacing, centre, carve, version_next, removed,
                                touch, touched, cache, tick)
        return sphere
    if is_shape(burr, RevolvedTick):
        def revolved(burr, density, swept, labels, forbidden, brick_bone, brick_full,
                     brick_version, brick_forbidden, spacing, centre, axis, carve, version_next,
                     removed, touch, touched, cache, tick):
            fill_geometry(burr.geo, axis, burr.bounds, spacing)
            return carve_voxels(RevolvedCarve(burr.profile, burr.geo, burr.rows), density,
                                swept, labels, forbidden, brick_bone, brick_full, brick_version,
                                brick_forbidden, spacing, centre, carve, version_next, removed,
                                touch, touched, cache, tick)
        return revolved
    return no_shape(burr)


def path_candidates(burr, centre, spacing):
    """Before the force: the round burr gathers the capsules of its path that can hold a
    sample this tick (``history.history_candidates``: the burr's surface plus a stencil).
    Nothing for the others."""


@hot_hook(path_candidates)
def _path_candidates(burr, centre, spacing):
    if is_shape(burr, SphereTick):
        def sphere(burr, centre, spacing):
            h_max = max(spacing[0], max(spacing[1], spacing[2]))
            radius = burr.radius
            half_t, half_p = patch_half_sides(radius, burr.d_theta, burr.d_phi,
                                              burr.cos_sub_t.shape[0])
            history_candidates(burr.path_ring, burr.path_meta, centre[0], centre[1],
                               centre[2], radius + 2.0 * h_max, radius, half_t + half_p,
                               burr.path_cand)
        return sphere
    if is_shape(burr, RevolvedTick):
        return lambda burr, centre, spacing: None
    return no_shape(burr)


def shaft_stage(burr, density, swept, brick_bone, spacing, centre, axis, shaft_radius,
                shaft_length, shaft_stiffness, shaft_out):
    """The shaft's contact into ``shaft_out`` (``shaft.shaft_contact``; zeros when
    ``shaft_length`` is 0), its torque about the burr's (reference) centre."""


@hot_hook(shaft_stage)
def _shaft_stage(burr, density, swept, brick_bone, spacing, centre, axis, shaft_radius,
                 shaft_length, shaft_stiffness, shaft_out):
    if is_shape(burr, SphereTick):
        def sphere(burr, density, swept, brick_bone, spacing, centre, axis, shaft_radius,
                   shaft_length, shaft_stiffness, shaft_out):
            if shaft_length > 0.0:
                shaft_contact(density, swept, brick_bone, spacing, centre, axis, burr.radius,
                              shaft_radius, shaft_length, shaft_stiffness, shaft_out)
            else:
                clear(shaft_out, N_SHAFT)
        return sphere
    if is_shape(burr, RevolvedTick):
        def revolved(burr, density, swept, brick_bone, spacing, centre, axis, shaft_radius,
                     shaft_length, shaft_stiffness, shaft_out):
            clear(shaft_out, N_SHAFT)
            if shaft_length > 0.0:
                top = burr.geo[GEO_Z_TOP]
                base = burr.shaft_base
                for n in range(3):
                    base[n] = centre[n] + top * axis[n]
                # Nothing of the shaft lies inside the burr past its top: no sphere to exclude.
                shaft_contact(density, swept, brick_bone, spacing, base, axis, 0.0,
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
        return revolved
    return no_shape(burr)


def tick_end(burr, centre, spacing, carved, near_bone):
    """What the burr keeps of this tick for the next: the round burr extends its path with
    this position if it carved near bone (a hand wandering in air would fill the ring and
    push real cuts out) and keeps it as the last carving position. Nothing for the others."""


@hot_hook(tick_end)
def _tick_end(burr, centre, spacing, carved, near_bone):
    if is_shape(burr, SphereTick):
        def sphere(burr, centre, spacing, carved, near_bone):
            history_record(burr.path_ring, burr.path_meta, centre[0], centre[1], centre[2],
                           burr.radius, carved and near_bone,
                           min(spacing[0], min(spacing[1], spacing[2])))
            if carved:
                previous = burr.previous
                for n in range(3):
                    previous[n] = centre[n]
        return sphere
    if is_shape(burr, RevolvedTick):
        return lambda burr, centre, spacing, carved, near_bone: None
    return no_shape(burr)
