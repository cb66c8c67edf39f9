"""The device side of SPEC 7.5: re-rendering the coupling model at the servo rate, with the
watchdog, the delay limit, the device's limits and the passivity controller."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from burrforce.server.devices.mapping import WorkspaceMap, bone_top_centre
from burrforce.server.devices.render import C_PASSIVITY, C_TRIPS, CouplingRenderer
from burrforce.server.devices.sim import SimMechanism
from burrforce.server.haptics.profiles import PROFILES, DeviceProfile
from burrforce.server.haptics.velocity import DeviceVelocity

ZERO = np.zeros(3)
# Wide limits: what the renderer computes, unclamped.
WIDE = DeviceProfile("wide", max_force_N=1e6, max_stiffness_N_mm=1e6, max_damping_N_s_mm=1e6,
                     max_slew_N_s=1e12)


def _renderer(profile=WIDE, **kw) -> CouplingRenderer:
    return CouplingRenderer(profile, passivity=kw.pop("passivity", False), **kw)


def test_no_model_renders_zero_and_trips_once():
    r = _renderer()
    for t in (0.001, 0.002, 0.003):
        assert not r.render(np.array([1.0, 2.0, 3.0]), ZERO, t).any()
    assert r.counters[C_TRIPS] == 1
    assert not r.live


def test_the_spring_follows_the_hand_between_replies():
    r = _renderer()
    r.accept(0.0, 0.0, np.array([0.0, 0.0, 0.0]), ZERO, 2.0, 0.0, ZERO)
    # Between replies the hand moves: the force is the spring at the new position.
    for x in (0.1, 0.2, 0.5):
        f = r.render(np.array([x, 0.0, 0.0]), ZERO, 0.001 + x / 100)
        assert f == pytest.approx([-2.0 * x, 0.0, 0.0])


def test_the_proxy_is_extrapolated_by_its_velocity_from_the_pose_sample():
    r = _renderer()
    # The reply answers a pose sampled at 1.000 s and arrives at 1.000 s (no delay), proxy
    # moving at 10 mm/s: 4 ms later it is expected 0.04 mm further.
    r.accept(1.0, 1.0, np.array([1.0, 0.0, 0.0]), np.array([10.0, 0.0, 0.0]), 3.0, 0.01, ZERO)
    f = r.render(np.array([1.0, 0.0, 0.0]), np.array([10.0, 0.0, 0.0]), 1.004)
    assert f[0] == pytest.approx(3.0 * 0.04)
    f = r.render(np.array([1.0, 0.0, 0.0]), np.array([10.0, 0.0, 0.0]), 1.029)
    assert f[0] == pytest.approx(3.0 * 0.29)


def test_extrapolation_stops_at_50_ms():
    r = _renderer(stale_s=0.05)
    # Sampled at 1.00 s, arrived 40 ms later; rendered at 1.07 s: 70 ms old, extrapolated 50.
    r.accept(1.0, 1.04, np.array([1.0, 0.0, 0.0]), np.array([10.0, 0.0, 0.0]), 3.0, 0.0, ZERO)
    f = r.render(np.array([1.0, 0.0, 0.0]), ZERO, 1.07)
    assert f[0] == pytest.approx(3.0 * 10.0 * 0.05)


def test_a_non_finite_reading_does_not_poison_the_renderer():
    r = _renderer(passivity=True)
    r.accept(0.0, 0.0, np.array([1.0, 0.0, 0.0]), ZERO, 1.0, 0.0, ZERO)
    r.render(ZERO, ZERO, 0.001)
    r.render(np.array([math.nan, 0.0, 0.0]), ZERO, 0.002)
    f = r.render(ZERO, ZERO, 0.003)
    assert np.isfinite(f).all() and f[0] == pytest.approx(1.0)


def test_watchdog_zeroes_the_force_when_the_model_is_stale_and_recovers():
    r = _renderer(stale_s=0.03)
    r.accept(0.0, 0.0, np.array([1.0, 0.0, 0.0]), ZERO, 1.0, 0.0, ZERO)
    assert r.render(ZERO, ZERO, 0.0299)[0] == pytest.approx(1.0)
    assert not r.render(ZERO, ZERO, 0.0301).any()
    assert r.counters[C_TRIPS] == 1 and not r.live
    # Still zero, no second trip, until a new reply.
    assert not r.render(ZERO, ZERO, 0.2).any()
    assert r.counters[C_TRIPS] == 1
    r.accept(0.2, 0.2, np.array([1.0, 0.0, 0.0]), ZERO, 1.0, 0.0, ZERO)
    assert r.render(ZERO, ZERO, 0.201)[0] == pytest.approx(1.0) and r.live


def test_an_error_reply_drops_the_model_at_once():
    r = _renderer()
    r.accept(0.0, 0.0, np.array([1.0, 0.0, 0.0]), ZERO, 1.0, 0.0, ZERO)
    r.drop()
    assert not r.render(ZERO, ZERO, 0.001).any()


def test_a_non_finite_model_is_never_rendered():
    r = _renderer()
    r.accept(0.0, 0.0, np.array([math.nan, 0.0, 0.0]), ZERO, 1.0, 0.0, ZERO)
    assert not r.render(ZERO, ZERO, 0.001).any() and not r.live


def test_raw_replies_are_held_as_their_force():
    r = _renderer()
    r.accept(0.0, 0.0, ZERO, ZERO, 0.0, 0.0, np.array([0.5, -0.25, 1.0]))
    assert r.render(np.array([3.0, 3.0, 3.0]), ZERO, 0.01) == pytest.approx([0.5, -0.25, 1.0])


def test_stiffness_is_limited_by_the_round_trip_and_the_workspace_scale():
    falcon = PROFILES["falcon"]
    r = CouplingRenderer(falcon, passivity=False)
    # 20 ms from the pose's sample to the reply: k·delay ≤ the device's damping budget.
    r.accept(0.0, 0.02, np.array([0.1, 0.0, 0.0]), ZERO, falcon.max_stiffness_N_mm, 0.0, ZERO)
    f = r.render(ZERO, ZERO, 0.021)
    assert f[0] == pytest.approx(falcon.max_damping_N_s_mm / 0.02 * 0.1)
    # Scale 4: the hand feels k × 4, so k is held to max / 4.
    r = CouplingRenderer(falcon, scale=4.0, passivity=False)
    r.accept(0.0, 0.0, np.array([0.1, 0.0, 0.0]), ZERO, falcon.max_stiffness_N_mm, 0.0, ZERO)
    f = r.render(ZERO, ZERO, 0.001)
    assert f[0] == pytest.approx(falcon.max_stiffness_N_mm / 4.0 * 0.1)


@given(st.floats(-100.0, 100.0), st.floats(-100.0, 100.0), st.floats(-100.0, 100.0),
       st.floats(0.0, 1000.0))
def test_the_force_stays_within_the_devices_limits(px, py, pz, k):
    touch = PROFILES["touch"]
    r = CouplingRenderer(touch, passivity=False)
    r.accept(0.0, 0.0, np.array([px, py, pz]), ZERO, k, 0.0, np.array([px, py, pz]))
    previous = np.zeros(3)
    for i in range(1, 6):
        f = r.render(ZERO, ZERO, i * 1e-3).copy()
        assert np.linalg.norm(f) <= touch.max_force_N * (1 + 1e-12)
        assert np.linalg.norm(f - previous) <= touch.max_slew_N_s * 1e-3 * (1 + 1e-9) + 1e-12
        previous = f


def _push(profile: DeviceProfile, passivity: bool) -> tuple[float, int]:
    """An active environment: every reply puts the proxy 0.5 mm ahead of the device along
    its motion, so the spring keeps pushing the hand on. Returns (the largest running work
    the rendered force did on the device, mJ; controller ticks)."""
    r = CouplingRenderer(profile, passivity=passivity)
    mech = SimMechanism(profile, (0.0, 0.0, 0.0), hand_k_N_mm=0.0, hand_b_N_s_mm=0.0)
    mech.v[0] = 20.0
    velocity = DeviceVelocity(profile.resolution_mm)
    t = 0.0
    worst = 0.0
    force = np.zeros(3)
    for _ in range(1000):
        reading = np.array(mech.reading())
        v = velocity.update(reading, t)
        ahead = reading + np.array([0.5, 0.0, 0.0])
        r.accept(t, t, ahead, np.array(mech.v), profile.max_stiffness_N_mm, 0.0, ZERO)
        force = r.render(reading, v, t).copy()
        mech.advance(force, 1e-3, lambda _t: ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), t)
        worst = max(worst, mech.work_mJ)
        t += 1e-3
    return worst, int(r.counters[C_PASSIVITY])


def test_the_passivity_controller_bounds_what_an_active_model_puts_in():
    falcon = PROFILES["falcon"]
    unbounded, _ = _push(falcon, passivity=False)
    bounded, ticks = _push(falcon, passivity=True)
    assert unbounded > 100.0  # the push runs away without the controller
    assert ticks > 0
    # The reserve a coupling spring may give back (F²/2k) plus one tick's leak.
    reserve = falcon.max_force_N ** 2 / (2.0 * falcon.max_stiffness_N_mm)
    assert bounded <= reserve + 1.0


def test_the_renderer_refuses_a_watchdog_over_50_ms():
    with pytest.raises(ValueError, match="50 ms"):
        CouplingRenderer(WIDE, stale_s=0.06)


def test_workspace_map_round_trip_and_validation():
    m = WorkspaceMap((10.0, 0.0, -5.0), (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)),
                     2.0)
    # A quarter turn about z: device x → server y, doubled, then placed.
    assert m.point(np.array([1.0, 0.0, 0.0])) == pytest.approx([10.0, 2.0, -5.0])
    assert m.vector(np.array([0.0, 1.0, 0.0])) == pytest.approx([-2.0, 0.0, 0.0])
    assert m.force_to_device(np.array([0.0, 3.0, 0.0])) == pytest.approx([3.0, 0.0, 0.0])
    for bad in ({"scale": 0.0}, {"scale": math.inf}, {"placement_mm": (0, 0, math.nan)},
                {"rotation": (0.0, 0.0, 0.0, 0.1)}):
        with pytest.raises(ValueError):
            WorkspaceMap(**bad)


def test_the_default_placement_is_the_top_centre_of_the_bone():
    info = {"origin_mm": [0.0, -8.0, -11.0], "shape": [290, 160, 140],
            "spacing_mm": [0.1, 0.1, 0.1], "direction": np.eye(3).tolist()}
    assert bone_top_centre(info) == pytest.approx((14.5, 0.0, 3.0))
    assert bone_top_centre(None) == (0.0, 0.0, 0.0)
