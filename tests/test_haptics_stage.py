"""The haptic stage: limits, passivity, the implicit proxy and the coupled output of a real
session on a real voxel bone (no sockets: Dispatcher.handle)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.proto.codec import decode_server_message, encode_pose
from burrforce.proto.messages import (
    BAD_VALUE,
    OK,
    STATUS_CLAMPED,
    STATUS_CONTACT,
    STATUS_CUTTING,
    Pose,
)
from burrforce.server.bone import BoneEngine, workpiece_block
from burrforce.server.haptics import PROFILES, HapticsConfig, device_profile
from burrforce.server.haptics.coupling import coupled_finish, coupled_predict
from burrforce.server.haptics.layout import N_RESULT, R_CUT, R_FORCE, S_PROXY_V, new_state
from burrforce.server.haptics.limits import limit_force
from burrforce.server.haptics.passivity import control, observe
from burrforce.server.hotloop import Dispatcher, Session, SessionConfig
from burrforce.server.model.kernels import N_OUT, OUT_FORCE

ALPHA = math.radians(60.0)
#: Quaternion taking +z to the thesis's tool axis (−cos α, 0, sin α).
TILT = (0.0, math.sin((ALPHA - math.pi / 2) / 2), 0.0, math.cos((ALPHA - math.pi / 2) / 2))
vec = st.floats(-1e3, 1e3, allow_nan=False)


# -- limits and passivity ---------------------------------------------------------------------
@settings(max_examples=examples(300), deadline=None)
@given(st.tuples(vec, vec, vec), st.tuples(vec, vec, vec), st.floats(0.01, 100.0),
       st.floats(1e-4, 100.0))
def test_limits_hold_and_leave_what_is_within_them(force, previous, max_force, max_step):
    f = np.array(force)
    prev = np.array(previous)
    prev_mag = np.linalg.norm(prev)
    if prev_mag > max_force:  # the device renders at most max_force
        prev *= max_force / prev_mag
    limited = limit_force(f, prev, max_force, max_step)
    assert np.linalg.norm(f) <= max_force * (1 + 1e-12)
    assert np.linalg.norm(f - prev) <= max_step * (1 + 1e-9)
    if np.linalg.norm(force) <= max_force and np.linalg.norm(np.array(force) - prev) <= max_step:
        assert not limited and np.array_equal(f, force)


def test_the_passivity_controller_dissipates_what_an_active_environment_makes():
    """A 'negative damper' (F = +0.01·v, N·s/mm: it pushes along the motion) drives a mass
    on the device side. Uncontrolled it feeds the device energy every tick; with the
    observer and controller the net energy the loop gave the device stays ≤ one tick's
    worth."""
    dt = 1e-3
    for controlled in (False, True):
        x, v, e_obs, given_mJ, peak = 0.0, 10.0, 0.0, 0.0, 0.0
        prev_f = np.zeros(3)
        for _ in range(2000):
            f = np.array([0.01 * v, 0.0, 0.0])
            if controlled:
                e_obs = observe(e_obs, prev_f, np.array([v * dt, 0, 0]), 1e9)
                control(e_obs, f, np.array([v, 0.0, 0.0]), dt, 0.05)
            given_mJ += f[0] * v * dt
            peak = max(peak, given_mJ)
            v += f[0] / 0.1e-3 * dt  # 0.1 kg device, N·s²/mm
            x += v * dt
            prev_f = f
        if controlled:
            assert peak < 0.05  # mJ: the first tick's injection, then none
        else:
            assert peak > 10.0


# -- the implicit proxy -----------------------------------------------------------------------
def _stage(profile: str = "touch"):
    config = HapticsConfig.for_device(PROFILES[profile])
    return new_state(), config.params_vector(np.full(3, 0.1), 2000.0)


@settings(max_examples=examples(200), deadline=None)
@given(st.floats(0.0, 1e7), st.tuples(vec, vec, vec), st.tuples(vec, vec, vec),
       st.floats(1e-4, 0.05))
def test_the_proxy_is_stable_for_any_cutting_damping(beta, device_p, device_v, dt):
    """A cut of damping β (the force is exactly −β·v, as the kernels' Jacobian states) never
    speeds the proxy up: |v⁺| ≤ |v_free| for β from 0 to 10⁷ N·s/mm (the explicit step
    is stable only up to β·dt/m < 2)."""
    state, params = _stage()
    centre, feed = np.zeros(3), np.zeros(3)
    coupled_predict(state, params, np.zeros(3), np.zeros(3), dt, True, centre, feed)
    coupled_predict(state, params, np.array(device_p), np.array(device_v), dt, False, centre,
                    feed)
    free = state[16:19].copy()
    out = np.zeros(N_OUT)
    out[OUT_FORCE:OUT_FORCE + 3] = -beta * feed
    jac = (-beta * np.eye(3)).ravel()
    result = np.zeros(N_RESULT)
    coupled_finish(state, params, out, jac, np.zeros(8), True, 2.0, result, np.zeros(12))
    v = state[S_PROXY_V:S_PROXY_V + 3]
    assert np.all(np.isfinite(v)) and np.all(np.isfinite(result))
    assert np.linalg.norm(v) <= np.linalg.norm(free) * (1 + 1e-9) + 1e-12
    # The cut the proxy met opposes its motion.
    assert np.dot(result[R_CUT:R_CUT + 3], v) <= 1e-9
    assert np.linalg.norm(result[R_FORCE:R_FORCE + 3]) <= PROFILES["touch"].max_force_N + 1e-9


@pytest.mark.parametrize("limit", ["max_stiffness_N_mm", "max_damping_N_s_mm"])
def test_the_smallest_limits_the_api_accepts_tick_on_a_slow_stream(limit):
    """A device limit as small as the REST schema allows (> 0: 5e-324) on a stream 2 s between
    packets takes the coupling's stiffness to 0 (it scales with the rated period over the
    actual one); the tick must still give a finite answer, not a division by zero (an
    INTERNAL reply on every datagram: found by tests/test_api_schema.py)."""
    config = HapticsConfig.for_device(dataclasses.replace(PROFILES["touch"], **{limit: 5e-324}))
    state, params = new_state(), config.params_vector(np.full(3, 0.1), 2000.0)
    centre, feed = np.zeros(3), np.zeros(3)
    for place in (True, False):
        coupled_predict(state, params, np.zeros(3), np.zeros(3), 2.0, place, centre, feed)
    result = np.zeros(N_RESULT)
    coupled_finish(state, params, np.zeros(N_OUT), np.zeros(9), np.zeros(8), True, 2.0, result,
                   np.zeros(12))
    assert np.all(np.isfinite(result))


# -- a session's coupled output on a voxel bone -----------------------------------------------
class Rig:
    """A session on the thesis's workpiece (0.1 mm voxels, top surface z = 0), fed poses in
    the si_mm frame at 1 kHz of client time."""

    def __init__(self, haptics: HapticsConfig, **config) -> None:
        self.session = Session(1, BoneEngine(workpiece_block(0.1)),
                               SessionConfig(frame="si_mm", haptics=haptics, **config))
        self.session.hello()  # the stream handshake, done directly: nothing ticked
        self.session.commit()
        self.dispatcher = Dispatcher()
        self.dispatcher.add(self.session)
        self.seq = 0
        self.t_us = 0

    def send(self, position, rpm=60_000.0, on=True, dt_us=1000, flags=0):
        self.seq += 1
        self.t_us += dt_us
        pose = Pose(1, self.seq, self.t_us, tuple(position), TILT, rpm, on, None, flags,
                    self.session.stream)
        return decode_server_message(self.dispatcher.handle(encode_pose(pose),
                                                            10**12 + self.t_us * 1000))


def test_steady_coupled_cut_renders_the_cut_the_proxy_meets():
    """Fed at 3 mm/s with the device 0.5 mm deep, the proxy settles to the device's speed
    and the hand feels exactly the cut it meets (the proxy is in equilibrium): force ==
    resistive components resolved, within the device's limits."""
    rig = Rig(HapticsConfig.for_device(PROFILES["omega3"]))
    replies = [rig.send((2.0 + 0.003 * k, 0.0, 1.5)) for k in range(2000)]
    last = replies[-300:]
    assert all(r.error == OK and r.status & STATUS_CUTTING for r in last)
    proxy_v = np.array([r.proxy_velocity for r in last]).mean(axis=0)
    np.testing.assert_allclose(proxy_v, (3.0, 0.0, 0.0), atol=0.05)
    force = np.array([r.force for r in last]).mean(axis=0)
    feed, lateral, normal = np.array([r.resistive for r in last]).mean(axis=0)
    # Feed along +x, surface normal +z: feed, lateral (ŝ × f̂ = +y) and normal are the
    # force's x, y and z.
    assert force[0] == pytest.approx(feed, rel=0.02)
    assert force[1] == pytest.approx(lateral, rel=0.05, abs=0.005)
    assert force[2] == pytest.approx(normal, rel=0.02)
    assert feed < -0.05 and normal > 0.05
    assert max(np.linalg.norm(r.force) for r in replies) <= 12.0 + 1e-9
    assert last[-1].coupling_stiffness == pytest.approx(5.0)
    # The proxy rides above the device (the normal force pushes it out of the cut).
    assert last[-1].proxy_position[2] > 1.5


def test_a_burr_that_does_not_turn_is_a_rigid_obstacle():
    """Spindle off, the device pushed 2 mm into the bone: the proxy stays on the surface
    (within the contact skin and a voxel), the hand feels the coupling spring, nothing is
    carved."""
    rig = Rig(HapticsConfig.for_device(PROFILES["falcon"]))
    for k in range(300):  # descend from 1 mm above the surface to 2 mm into the bone
        z = 3.0 - min(k, 300) * 0.01
        r = rig.send((10.0, 0.0, z), on=False)
    for _ in range(200):
        r = rig.send((10.0, 0.0, 0.0), on=False)
    assert r.status & STATUS_CONTACT and r.removed_mm3 == 0.0 and r.bone_version == 0
    depth = 2.0 - r.proxy_position[2]
    assert -0.05 < depth < 0.02 + 0.1
    # k·(proxy − device) along z, Falcon 3 N/mm × ~2 mm, clamped to 8 N.
    assert r.force[2] == pytest.approx(min(3.0 * (r.proxy_position[2] - 0.0), 8.0), rel=0.05)


def test_slow_spindle_contacts_too_and_a_fast_one_cuts_through():
    rig = Rig(HapticsConfig.for_device(PROFILES["omega3"]))
    for k in range(400):
        r = rig.send((10.0, 0.0, 3.0 - k * 0.005), rpm=1000.0)  # below 5000 rpm: no cut
    assert r.proxy_position[2] > 1.85 and r.bone_version == 0
    for _ in range(3000):
        r = rig.send((10.0, 0.0, 1.0), rpm=60_000.0)
    assert r.bone_version > 0 and r.proxy_position[2] < 1.5  # plunged by cutting


def test_a_burr_started_inside_bone_is_pushed_out_gradually_and_within_limits():
    rig = Rig(HapticsConfig.for_device(PROFILES["touch"]))
    forces, zs = [], []
    for _ in range(300):
        r = rig.send((10.0, 0.0, 1.0), on=False)  # 1 mm deep, not cutting
        forces.append(np.linalg.norm(r.force))
        zs.append(r.proxy_position[2])
    assert max(forces) <= 3.3 + 1e-9
    assert zs[0] < 1.6 and zs[-1] > 1.9  # out over ticks, not in one jump
    assert np.all(np.diff(forces) <= 1000.0 * 1e-3 + 1e-9)  # slew: 1000 N/s × 1 ms


def test_nan_pose_gives_zero_force_and_the_force_comes_back_slew_limited():
    rig = Rig(HapticsConfig.for_device(device_profile("custom", base="touch",
                                                      max_slew_N_s=100.0)))
    for _ in range(100):
        r = rig.send((10.0, 0.0, 0.0), on=False)
    assert np.linalg.norm(r.force) > 0.5
    bad = rig.send((math.nan, 0.0, 0.0), on=False)
    assert bad.error == BAD_VALUE and bad.force == (0.0, 0.0, 0.0)
    # The device rendered zero for the error reply: the force ramps up again from zero,
    # 100 N/s over the 2 ms since the last good pose.
    after = rig.send((10.0, 0.0, 0.0), on=False)
    assert np.linalg.norm(after.force) == pytest.approx(0.2) and after.status & STATUS_CLAMPED


def test_slower_packets_get_a_softer_coupling():
    """Colgate: k·T/2 within the damping budget, and a sampled damper b·T/m < 2. At 20 ms per
    packet (r = 1 ms / 20 ms) the Falcon's budget is r·20 N·s/m: k = min(3·r, r·0.02/T)
    N/mm = 0.05 N/mm, b = half the budget."""
    rig = Rig(HapticsConfig.for_device(PROFILES["falcon"]))
    for _ in range(60):
        r = rig.send((10.0, 0.0, 5.0), dt_us=20_000)
    assert r.coupling_stiffness == pytest.approx(0.05, rel=0.01)
    assert r.coupling_damping == pytest.approx(0.010 / 20.0, rel=0.01)
    for _ in range(200):  # the interval is smoothed (gain 0.1 per packet)
        r = rig.send((10.0, 0.0, 5.0), dt_us=1000)
    assert r.coupling_stiffness == pytest.approx(3.0, rel=0.01)  # rated again


def test_a_pause_in_the_stream_does_not_soften_the_coupling():
    """A gap (here 300 ms: a client pausing) is not a packet interval: the coupling stays at
    the rated stiffness for the packets after it."""
    rig = Rig(HapticsConfig.for_device(PROFILES["falcon"]))
    for _ in range(50):
        rig.send((10.0, 0.0, 5.0))
    r = rig.send((10.0, 0.0, 5.0), dt_us=300_000)
    assert r.coupling_stiffness == pytest.approx(3.0)
    r = rig.send((10.0, 0.0, 5.0))
    assert r.coupling_stiffness == pytest.approx(3.0)


def test_a_teleport_moves_the_proxy_without_cutting_a_trench():
    rig = Rig(HapticsConfig.for_device(PROFILES["generic"]))
    for _ in range(50):
        rig.send((-10.0, 0.0, 1.5))  # outside the block
    r = rig.send((13.0, 0.0, 1.5))  # 23 mm in one tick: 23 m/s
    assert r.proxy_position[0] == pytest.approx(13.0)
    assert rig.session.counters["teleports"] == 1
    removed = rig.session.engine.removed_mm3_by_material()
    # At most the burr's own cap at the landing point, not a 23 mm trench.
    assert sum(removed.values()) < 2.0


def test_raw_output_on_a_device_is_clamped_and_marked():
    rig = Rig(HapticsConfig.for_device(device_profile("custom", max_force_N=0.2), "raw"))
    replies = [rig.send((2.0 + 0.003 * k, 0.0, 1.5)) for k in range(600)]
    assert max(np.linalg.norm(r.force) for r in replies) <= 0.2 + 1e-9
    assert replies[-1].status & STATUS_CLAMPED
    assert replies[-1].coupling_stiffness == 0.0  # raw: render the force


def test_profiles_reject_nonsense():
    with pytest.raises(ValueError, match="max_force_N"):
        device_profile("custom", max_force_N=-1.0)
    with pytest.raises(ValueError, match="unknown device profile"):
        device_profile("phantom")
    with pytest.raises(ValueError, match="unknown device profile field"):
        device_profile("custom", stiffness=3.0)
    with pytest.raises(ValueError, match="output"):
        HapticsConfig(output="smooth")
    assert HapticsConfig(output="coupled").profile == PROFILES["generic"]
