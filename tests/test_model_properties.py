"""Property-based tests: random poses, velocities and spindle speeds."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.server.model import CuttingModel, CuttingParams, FlatWorkpiece
from burrforce.server.model.kernels import box_fraction
from burrforce.server.model.kernels_flat import positive_mean

MODEL = CuttingModel(CuttingParams(min_cutting_rpm=1000.0), n_theta=16)
finite = st.floats(-50.0, 50.0, allow_nan=False, allow_infinity=False)
vec = st.tuples(finite, finite, finite).map(np.array)
unit = vec.filter(lambda v: np.linalg.norm(v) > 1e-3).map(lambda v: v / np.linalg.norm(v))
rpm = st.floats(-100_000.0, 100_000.0, allow_nan=False)
feed = st.tuples(*[st.floats(-500.0, 500.0, allow_nan=False)] * 3).map(np.array)


@settings(max_examples=examples(300), deadline=None)
@given(centre=vec, axis=unit, v=feed, speed=rpm, normal=unit)
def test_always_finite_and_physically_signed(centre, axis, v, speed, normal):
    model = CuttingModel(MODEL.params, FlatWorkpiece((0.0, 0.0, 0.0), normal), n_theta=16)
    r = model.evaluate(centre, axis, v, speed)
    for value in (*r.force_N, *r.torque_Nmm, r.power_W, r.removed_mm3_s, r.mean_speed_m_s,
                  r.feed_N, r.lateral_N, r.normal_N):
        assert math.isfinite(value)
    assert r.power_W >= 0.0 and r.removed_mm3_s >= 0.0
    assert 0 <= r.cutting_elements <= model.grid.n_elements
    equator_m_s = abs(speed) * 2 * math.pi / 60.0 * model.params.radius_mm * 1e-3
    assert r.mean_speed_m_s <= equator_m_s + 1e-12
    if r.cutting:
        # Each element's force is at most Us·R·dθ·dφ/ω·|v|·(1 + K); Σ dθ·dφ = 2π².
        omega = abs(speed) * 2.0 * math.pi / 60.0
        p = model.params
        bound = p.us_n_mm2 * p.radius_mm / omega * np.linalg.norm(v) * (1 + p.k) * 2 * math.pi**2
        assert np.linalg.norm(r.force_N) <= bound
        assert math.isclose(r.power_W, p.us_n_mm2 * r.removed_mm3_s * 1e-3, rel_tol=1e-9,
                            abs_tol=1e-15)


@settings(max_examples=examples(200), deadline=None)
@given(xy=st.tuples(finite, finite), height=st.floats(2.0, 100.0), axis=unit, v=feed, speed=rpm)
def test_zero_when_the_burr_is_clear_of_the_bone(xy, height, axis, v, speed):
    r = MODEL.evaluate(np.array([xy[0], xy[1], height]), axis, v, speed)
    assert not r.contact and not r.cutting
    assert np.all(r.force_N == 0.0) and np.all(r.torque_Nmm == 0.0) and r.power_W == 0.0


@settings(max_examples=examples(200), deadline=None)
@given(centre=vec, axis=unit, v=feed, speed=st.floats(-999.0, 999.0, allow_nan=False))
def test_zero_below_the_minimum_cutting_speed(centre, axis, v, speed):
    r = MODEL.evaluate(centre, axis, v, speed)
    assert not r.cutting and np.all(r.force_N == 0.0) and r.removed_mm3_s == 0.0


@settings(max_examples=examples(200), deadline=None)
@given(centre=vec, axis=unit, speed=rpm)
def test_zero_without_feed(centre, axis, speed):
    r = MODEL.evaluate(centre, axis, np.zeros(3), speed)
    assert not r.cutting and np.all(r.force_N == 0.0)


@settings(max_examples=examples(150), deadline=None)
@given(depth=st.floats(0.05, 3.9), axis=unit, v=feed.filter(lambda v: np.linalg.norm(v) > 1e-6),
       speed=st.floats(5000.0, 100_000.0), scale=st.floats(0.01, 100.0))
def test_linear_in_us_at_random_poses(depth, axis, v, speed, scale):
    centre = np.array([0.0, 0.0, 2.0 - depth])
    a = CuttingModel(CuttingParams(us_n_mm2=100.0), n_theta=12).evaluate(centre, axis, v, speed)
    b = CuttingModel(CuttingParams(us_n_mm2=100.0 * scale), n_theta=12).evaluate(
        centre, axis, v, speed)
    np.testing.assert_allclose(b.force_N, scale * a.force_N, rtol=1e-9,
                               atol=1e-12 * np.linalg.norm(b.force_N))


@given(g0=st.floats(-10, 10), a=st.floats(0, 5), b=st.floats(0, 5))
@example(g0=0.0, a=5e-324, b=5e-324)  # subnormal sides: 1/A would overflow
@example(g0=5e-324, a=1e-323, b=5e-324)
@example(g0=-2e-310, a=3e-310, b=1e-310)
def test_box_fraction_is_a_cdf(g0, a, b):
    f = box_fraction(g0, a, b)
    assert 0.0 <= f <= 1.0
    assert math.isclose(f + box_fraction(-g0, a, b), 1.0, abs_tol=1e-12) or g0 == 0.0 == a + b
    assert box_fraction(g0 + 0.1, a, b) >= f - 1e-15
    assert box_fraction(g0, b, a) == f


@given(g0=st.floats(-2.0, 2.0), a=st.floats(0.01, 1.0), b=st.floats(0.01, 1.0))
@settings(max_examples=examples(60), deadline=None)
def test_box_fraction_is_the_exact_area_fraction(g0, a, b):
    # Midpoint sampling of the rectangle on a fine grid converges to the exact area.
    n = 400
    u = (np.arange(n) + 0.5) / n * 2 * a - a
    w = (np.arange(n) + 0.5) / n * 2 * b - b
    sampled = float(np.mean(g0 + u[:, None] + w[None, :] > 0.0))
    assert abs(box_fraction(g0, a, b) - sampled) < 6.0 / n


@given(x=st.floats(-3.0, 3.0), a=st.floats(0.01, 1.0), b=st.floats(0.0, 1.0))
@example(x=0.0, a=5e-324, b=5e-324)  # subnormal sides: A·B would underflow
@example(x=1e-194, a=3e-193, b=2e-193)
@settings(max_examples=examples(60), deadline=None)
def test_positive_mean_is_the_mean_of_the_positive_part(x, a, b):
    # The facing share of an element the facing edge crosses (kernels_flat.positive_mean):
    # the integral of box_fraction, E[max(x + u + v, 0)], never below max(x, 0) or above it
    # by more than (A + B)/2.
    g = positive_mean(x, a, b)
    assert max(x, 0.0) <= g <= max(x, 0.0) + 0.5 * (a + b) + 1e-300
    if a < 0.01:
        return
    n = 400
    u = (np.arange(n) + 0.5) / n * 2 * a - a
    w = (np.arange(n) + 0.5) / n * 2 * b - b
    sampled = float(np.mean(np.maximum(x + u[:, None] + w[None, :], 0.0)))
    assert abs(g - sampled) < 1e-4
    assert positive_mean(x, b, a) == g
