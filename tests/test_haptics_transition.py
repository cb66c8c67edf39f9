"""The coupled output from rigid contact to cutting (``haptics.transition``), a burr started
inside bone, and a proxy placed inside bone by a teleport."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.proto.codec import decode_server_message, encode_pose
from burrforce.proto.messages import Pose
from burrforce.server.bench import stability as bench
from burrforce.server.bone import BoneEngine, workpiece_block
from burrforce.server.haptics import PROFILES, HapticsConfig
from burrforce.server.haptics.coupling import coupled_finish, coupled_predict
from burrforce.server.haptics.layout import N_RESULT, P_SHAFT_RADIUS, R_FORCE, new_state
from burrforce.server.haptics.transition import cut_weight
from burrforce.server.hotloop import Dispatcher, Session, SessionConfig
from burrforce.server.model.params import CuttingParams

MIN_RPM = CuttingParams().min_cutting_rpm
BAND_RPM = MIN_RPM * CuttingParams().cutting_band
AXIS = np.array([-math.cos(math.radians(60.0)), 0.0, math.sin(math.radians(60.0))])
#: Quaternion taking +z to that axis.
TILT = (0.0, math.sin(math.radians(-15.0)), 0.0, math.cos(math.radians(-15.0)))


class Rig:
    """A coupled session on the thesis's workpiece (0.1 mm voxels, the top face at z = 0),
    fed poses at 1 kHz of client time (as in test_haptics_stage)."""

    def __init__(self, haptics: HapticsConfig) -> None:
        self.session = Session(1, BoneEngine(workpiece_block(0.1)),
                               SessionConfig(frame="si_mm", haptics=haptics))
        self.session.hello()
        self.session.commit()
        self.dispatcher = Dispatcher()
        self.dispatcher.add(self.session)
        self.seq = 0

    def send(self, position, rpm=0.0, on=False):
        self.seq += 1
        t_us = 1000 * self.seq
        pose = Pose(1, self.seq, t_us, tuple(position), TILT, rpm, on, None, 0,
                    self.session.stream)
        return decode_server_message(self.dispatcher.handle(encode_pose(pose),
                                                            10**12 + t_us * 1000))


@settings(max_examples=examples(300), deadline=None)
@given(st.floats(0.0, 2e5), st.floats(0.0, 2e5))
def test_the_weight_is_a_monotone_smooth_step(r1, r2):
    lo, hi = sorted((r1, r2))
    s_lo, s_hi = cut_weight(lo, MIN_RPM, BAND_RPM), cut_weight(hi, MIN_RPM, BAND_RPM)
    assert 0.0 <= s_lo <= s_hi <= 1.0
    # Lipschitz: the smooth step's slope is at most 1.5 per band.
    assert s_hi - s_lo <= 1.5 * (hi - lo) / BAND_RPM + 1e-12
    assert cut_weight(MIN_RPM - 1e-9, MIN_RPM, BAND_RPM) == 0.0
    assert cut_weight(MIN_RPM + BAND_RPM, MIN_RPM, BAND_RPM) == 1.0


def _coupled_force(engine, rpm, state0, params):
    """One coupled tick from ``state0``: the device 0.6 mm into the block's top face, moving
    along +x at 10 mm/s; the proxy at rest in steady contact (within the contact skin).
    Returns (force N, proxy velocity mm/s)."""
    state = state0.copy()
    origin = engine.grid.origin_mm
    device = np.array([10.0, 0.0, 1.4]) - origin
    centre, feed = np.zeros(3), np.zeros(3)
    coupled_predict(state, params, device, np.array([10.0, 0.0, 0.0]), 1e-3, False, centre,
                    feed)
    engine.step_raw(centre, AXIS, feed, rpm, carve=False)
    result = np.zeros(N_RESULT)
    coupled_finish(state, params, engine.out, engine.jacobian, engine.shaft_out,
                   cut_weight(rpm, MIN_RPM, BAND_RPM), 2.0, result, np.zeros(12))
    return result[R_FORCE:R_FORCE + 3].copy(), state[3:6].copy()


def test_the_force_and_the_proxy_step_are_continuous_across_the_band():
    """A fine sweep of spindle speed through the band: the force the hand feels and the
    proxy's velocity change by small steps only (a step rpm moves s by ≤ 1.5·step/band), from
    the rigid answer below the minimum cutting speed to the cut above the band. (Before, both
    stepped at the minimum speed from the rigid answer to the whole cut.)"""
    engine = BoneEngine(workpiece_block(0.1))
    config = HapticsConfig.for_device(PROFILES["omega3"])
    params = config.params_vector(engine.grid.spacing_mm, 2000.0)
    params[P_SHAFT_RADIUS] = engine.shaft.radius_mm
    state0 = new_state()
    origin = engine.grid.origin_mm
    centre, feed = np.zeros(3), np.zeros(3)
    coupled_predict(state0, params, np.array([10.0, 0.0, 1.99]) - origin, np.zeros(3), 1e-3,
                    True, centre, feed)
    step_rpm = 10.0
    rpms = np.arange(MIN_RPM - 100.0, MIN_RPM + BAND_RPM + 100.0, step_rpm)
    forces, speeds = zip(*(_coupled_force(engine, r, state0, params) for r in rpms),
                         strict=True)
    forces, speeds = np.array(forces), np.array(speeds)
    # From the rigid answer (below the band) to the cut (above it).
    jump_f = np.linalg.norm(forces[-1] - forces[0])
    jump_v = np.linalg.norm(speeds[-1] - speeds[0])
    assert jump_f > 0.01 and jump_v > 0.1  # the cut and the rigid contact differ
    step_f = np.max(np.linalg.norm(np.diff(forces, axis=0), axis=1))
    step_v = np.max(np.linalg.norm(np.diff(speeds, axis=0), axis=1))
    # A step moves s by at most 1.5·step/band; the cut itself changes as 1/ω (< 0.3 % a step).
    bound = 1.5 * step_rpm / BAND_RPM
    assert step_f <= bound * jump_f + 3e-3 * np.max(np.linalg.norm(forces, axis=1))
    assert step_v <= bound * jump_v + 3e-3 * np.max(np.linalg.norm(speeds, axis=1))
    # Rigid below the minimum speed (no inward motion), the cut above the band (inward).
    below, above = speeds[rpms < MIN_RPM], speeds[rpms >= MIN_RPM + BAND_RPM]
    assert np.all(below[:, 2] >= -1e-9) and np.all(above[:, 2] < -0.01)


def test_a_burr_started_inside_bone_settles_at_any_spindle_speed():
    """The stability harness's ``inside`` event (the burr's centre 3 mm deep, the shaft in bone
    too) at rest, in the transition band and cutting: no energy generated, no buzz."""
    short = bench.BASE.with_(duration_s=0.6, event="inside")
    cases = [short.with_(case="inside", value=rpm, rpm=rpm)
             for rpm in (0.0, MIN_RPM + 0.5 * BAND_RPM, 60_000.0)]
    rows = bench.run(["generic", "falcon"], cases, modes=("coupled",))
    assert len(rows) == 6
    for r in rows:
        assert r["nonfinite"] == 0 and r["limit_violations"] == 0, r
        assert r["energy_generated_J"] <= bench.ENERGY_TOL_J, r
        assert not r["oscillation"], r


def test_a_proxy_teleported_inside_bone_stays_quiet_and_one_half_in_comes_out():
    """A jump of 23 mm in one tick places the proxy on the device. Wholly inside bone it has
    no way out: it stays with the device and the hand feels nothing (before, the engine's
    direction was noise and the proxy was pushed through the block). Half in, it is pushed out
    over a few ticks and settles on the surface without bouncing."""
    for z, inside in ((-3.0, True), (1.0, False)):  # the burr's centre; the top face z = 0
        rig = Rig(HapticsConfig.for_device(PROFILES["generic"]))
        for _ in range(50):
            rig.send((-10.0, 0.0, z))
        replies = [rig.send((13.0, 0.0, z)) for _ in range(300)]
        assert rig.session.counters["teleports"] == 1
        forces = np.array([r.force for r in replies])
        proxy_z = np.array([r.proxy_position[2] for r in replies])
        if inside:
            assert np.max(np.linalg.norm(forces, axis=1)) < 0.05
            assert np.ptp(proxy_z) < 0.05
        else:
            assert proxy_z[-1] > 1.95  # resting on the surface (its centre R above it)
            fz = forces[:, 2]
            assert fz[-1] > 0.5 and abs(fz[-1] - fz[-250]) < 0.01  # settled, pulling up
            # Out over several ticks, monotonically: no rebound into the bone.
            assert proxy_z[1] < 1.7 and np.all(np.diff(proxy_z) >= -1e-6)


def test_a_teleport_settles_without_generating_energy():
    """The harness's ``teleport`` (the hand's target 30 mm up at 0.6 s and back at 0.8 s, the
    device slamming back into the groove at ~0.8 m/s): no energy generated, and over the
    last quarter of the run the force is quiet again. (The impact itself, the force at the
    clamp for ~25 ms, is what the harness's oscillation verdict over the second half sees.)"""
    sc = bench.BASE.with_(case="teleport", event="teleport")
    for r in bench.run(["generic", "touch"], [sc], modes=("coupled",)):
        assert r["nonfinite"] == 0 and r["limit_violations"] == 0, r
        assert r["energy_generated_J"] <= bench.ENERGY_TOL_J, r
        max_force = PROFILES[r["profile"]].max_force_N
        assert r["oscillation_tail_N"] <= bench.OSC_FRACTION * max_force, r
