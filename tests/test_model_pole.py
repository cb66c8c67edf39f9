"""Plunges into the flat workpiece (issue 21, item 2): the cut cap around the depth extremum.

A plunge feeds the burr straight into the surface (v_f = −v·ŝ) with the tool at an angle α to
it (axis (−cos α, 0, sin α): at 90° the cap sits on the spin pole). Every element of the cap
then cuts, so the removal rate is exactly v × the cap's projected disc, π·(2Rh − h²).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.server.model import CuttingModel, CuttingParams
from burrforce.server.model.kernels import ACC_JACOBIAN
from burrforce.server.model.reference import plunge_removal_mm3_s, reference_flat

R_MM = 2.0
RPM = 60000.0
FEED_MM_S = 1.0
ANGLES_DEG = (0.0, 10.0, 30.0, 45.0, 60.0, 90.0)
MODEL = CuttingModel(CuttingParams(radius_mm=R_MM))


def _axis(angle_deg: float) -> np.ndarray:
    alpha = math.radians(angle_deg)
    return np.array([-math.cos(alpha), 0.0, math.sin(alpha)])


def _plunge(model: CuttingModel, angle_deg: float, depth_mm: float):
    return model.evaluate(np.array([0.0, 0.0, R_MM - depth_mm]), _axis(angle_deg),
                          np.array([0.0, 0.0, -FEED_MM_S]), RPM)


@pytest.mark.parametrize("angle", ANGLES_DEG)
@pytest.mark.parametrize("depth", [1e-2, 3e-2, 0.1, 0.2, 0.3, 1.0])
def test_removal_is_the_analytic_cap_from_ten_microns(angle, depth):
    removed = _plunge(MODEL, angle, depth).removed_mm3_s
    assert removed == pytest.approx(plunge_removal_mm3_s(R_MM, depth, FEED_MM_S), rel=0.02)


@pytest.mark.parametrize("angle", ANGLES_DEG)
@pytest.mark.parametrize("depth", [1e-6, 1e-3])
def test_shallower_caps_are_integrated_exactly_too(angle, depth):
    # Was ×144 (90°) and ×4 (other angles) at 1 nm, +48 % at 1 µm.
    removed = _plunge(MODEL, angle, depth).removed_mm3_s
    assert removed == pytest.approx(plunge_removal_mm3_s(R_MM, depth, FEED_MM_S), rel=1e-3)


@pytest.mark.parametrize("angle", [10.0, 60.0, 90.0])
@pytest.mark.parametrize("depth", [1e-3, 0.05, 0.2])
def test_shallow_plunge_force_matches_the_reference(angle, depth):
    r = _plunge(MODEL, angle, depth)
    centre = np.array([0.0, 0.0, R_MM - depth])
    ref = reference_flat(MODEL.params, centre, _axis(angle), np.array([0.0, 0.0, -FEED_MM_S]),
                         RPM)
    assert np.linalg.norm(r.force_N - ref.force_N) <= 0.01 * np.linalg.norm(ref.force_N)
    assert np.linalg.norm(r.torque_Nmm - ref.torque_Nmm) <= 0.01 * np.linalg.norm(
        ref.torque_Nmm)


def test_exact_cap_keeps_the_identities_of_the_grid():
    # F = J·v_f, P = Us × removal, and the spindle delivers P = −T·Ω, in the exact regime.
    model = CuttingModel(CuttingParams(radius_mm=R_MM))
    feed = np.array([1.5, -0.4, -0.8])
    axis = np.array([-0.3, 0.2, 0.93])
    r = model.evaluate(np.array([0.0, 0.0, R_MM - 0.05]), axis, feed, RPM)
    jac = model._scratch[ACC_JACOBIAN:].reshape(3, 3)
    np.testing.assert_allclose(jac @ feed, r.force_N, rtol=1e-10, atol=1e-14)
    p = model.params
    assert r.power_W == pytest.approx(p.us_n_mm2 * r.removed_mm3_s * 1e-3, rel=1e-12)
    omega = model.omega_rad_s(RPM) * axis / np.linalg.norm(axis)
    assert -float(r.torque_Nmm @ omega) * 1e-3 == pytest.approx(r.power_W, rel=1e-12)
    assert 1 <= r.cutting_elements <= model.grid.n_elements


@pytest.mark.parametrize("n_theta", [16, 24, 32])
@pytest.mark.parametrize("angle", [*ANGLES_DEG, 75.0, 89.0])
def test_force_and_removal_grow_on_a_fine_depth_sweep(n_theta, angle):
    model = CuttingModel(CuttingParams(radius_mm=R_MM), n_theta=n_theta)
    depths = np.geomspace(1e-3, 3.5, 200)
    normal = np.array([_plunge(model, angle, h).normal_N for h in depths])
    removed = np.array([_plunge(model, angle, h).removed_mm3_s for h in depths])
    assert np.all(np.diff(removed) >= -1e-12 * removed[1:])
    assert np.all(np.diff(normal) >= -1e-6 * normal[1:])


@settings(max_examples=examples(300), deadline=None)
@given(angle=st.floats(0.0, 90.0), depth=st.floats(1e-3, 3.5), step=st.floats(1e-9, 0.3))
def test_deeper_never_cuts_less(angle, depth, step):
    shallow = _plunge(MODEL, angle, depth)
    deep = _plunge(MODEL, angle, depth + step)
    assert deep.removed_mm3_s >= shallow.removed_mm3_s * (1.0 - 1e-12)
    # The normal force is a sum of parts of both signs (the tangential parts lean along the
    # tilted surface): exactly monotone in the continuum, to ~1e-7 on the grid near h = R.
    assert deep.normal_N >= shallow.normal_N - 1e-6 * abs(deep.normal_N)
