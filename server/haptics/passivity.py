"""Passivity observer and controller (Hannaford & Ryu, IEEE TRO 2002), at the device port.

The observer integrates the energy that flowed from the device into the server: over each
packet interval the force sent last tick acted while the device moved by Δx, so the server
took in −F·Δx. Negative means the loop (discretization, delay, velocity estimation, the
model) generated energy. The controller then adds a damper just strong enough to dissipate the
deficit over the coming interval, bounded by what the device can render.

The observed energy is capped: a long cut stores joules of dissipated energy, and an uncapped
observer would let the loop spend that reserve on an oscillation before acting. The cap is the
energy the coupling spring can hold at the device's maximum force, F_max²/(2k): what the
spring may legitimately give back.

Units: N, mm, s; energy N·mm (= mJ).
"""

from __future__ import annotations

from ..hot_kernel import hot_kernel


@hot_kernel
def observe(energy_mJ, previous_force, dx_mm, cap_mJ):
    """The observer after one interval: ``previous_force`` (float64 (3,), N) acted over the
    device's displacement ``dx_mm`` (float64 (3,)). Returns the new energy, at most
    ``cap_mJ``."""
    e = energy_mJ - (previous_force[0] * dx_mm[0] + previous_force[1] * dx_mm[1]
                     + previous_force[2] * dx_mm[2])
    return min(e, cap_mJ)


@hot_kernel
def control(energy_mJ, force, velocity_mm_s, dt_s, max_damping_N_s_mm):
    """Add to ``force`` (float64 (3,), N, in place) the damping −α·v that keeps the observed
    energy from going negative over the next interval if the device keeps ``velocity_mm_s``.

    Returns:
        α, N·s/mm (0 when no correction was needed), at most ``max_damping_N_s_mm``.
    """
    vx = velocity_mm_s[0]
    vy = velocity_mm_s[1]
    vz = velocity_mm_s[2]
    v2 = vx * vx + vy * vy + vz * vz
    if v2 <= 0.0 or dt_s <= 0.0:
        return 0.0
    # Energy left after the next interval if the force is sent as is.
    e_next = energy_mJ - (force[0] * vx + force[1] * vy + force[2] * vz) * dt_s
    if e_next >= 0.0:
        return 0.0
    alpha = min(-e_next / (v2 * dt_s), max_damping_N_s_mm)
    force[0] -= alpha * vx
    force[1] -= alpha * vy
    force[2] -= alpha * vz
    return alpha
