"""CuttingModel is the one entry point: it computes the burr it is given (docs/model.md, "Using
it from Python"). A shaped or fluted burr on the flat workpiece is RevolvedModel's result,
exactly; on a workpiece that takes only the round abrasive burr it refuses, naming the class
that does."""

from __future__ import annotations

import numpy as np
import pytest

from burrforce.server.bench.shapes import BURRS, centre_at_depth
from burrforce.server.model import (
    Burr,
    CuttingModel,
    CuttingParams,
    Cylinder,
    FlatWorkpiece,
    Fluted,
    RevolvedModel,
    Sphere,
    Workpiece,
)


def _poses(burr, nine_cases):
    return [(centre_at_depth(burr.shape, c.axis, c.depth_mm), c.axis, c.feed_velocity_mm_s,
             c.rpm) for c in nine_cases]


def _same(a, b) -> None:
    np.testing.assert_array_equal(a.force_N, b.force_N)
    np.testing.assert_array_equal(a.torque_Nmm, b.torque_Nmm)
    assert (a.power_W, a.removed_mm3_s, a.feed_N, a.lateral_N, a.normal_N) == (
        b.power_W, b.removed_mm3_s, b.feed_N, b.lateral_N, b.normal_N)


@pytest.mark.parametrize("name", sorted(set(BURRS) - {"sphere"}))
@pytest.mark.parametrize("spin", ["forward", "reverse"])
def test_a_shaped_burr_is_the_revolved_model(name, spin, nine_cases):
    burr = BURRS[name]
    params = CuttingParams(burr=burr, spin=spin, k=1.1)
    workpiece = FlatWorkpiece((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    model = CuttingModel(params, workpiece)
    revolved = RevolvedModel(burr, params, workpiece)
    for pose in _poses(burr, nine_cases):
        got = model.evaluate(*pose)
        assert got.cutting
        _same(got, revolved.evaluate(*pose))


def test_the_issue_pose_cuts_the_cylinder_not_the_sphere():
    # Issue 45: here the cylinder cuts 1.36 N; the sphere of its largest radius, which
    # CuttingModel used to compute, does not reach the bone at all.
    cylinder = Burr(Cylinder(1.0, 4.0, "flat"))
    pose = ((0.0, 0.0, 1.5), (-0.5, 0.0, 0.866), (3.0, 0.0, 0.0), 60000.0)
    got = CuttingModel(CuttingParams(burr=cylinder), FlatWorkpiece()).evaluate(*pose)
    want = RevolvedModel(cylinder, CuttingParams()).evaluate(*pose)
    assert got.force_magnitude_N == pytest.approx(1.36, abs=0.01)
    _same(got, want)
    sphere = CuttingModel(CuttingParams(radius_mm=1.0)).evaluate(*pose)
    assert sphere.force_magnitude_N == 0.0


def test_resolution_and_later_params_carry_over(nine_cases):
    burr = BURRS["barrel"]
    case = nine_cases[4]
    pose = _poses(burr, [case])[0]
    model = CuttingModel(n_theta=12)  # a round burr first: 12 × 24 = 288 elements
    model.params = CuttingParams(burr=burr, us_n_mm2=400.0)
    _same(model.evaluate(*pose),
          RevolvedModel(burr, CuttingParams(us_n_mm2=400.0), n_elements=288).evaluate(*pose))
    model.set_resolution(32)
    model.params = model.params.with_(k=0.7)  # the normal ratio of an abrasive burr is K
    _same(model.evaluate(*pose),
          RevolvedModel(burr, model.params, n_elements=2048).evaluate(*pose))
    # Back to the round abrasive burr: the sphere grid again.
    model.params = CuttingParams()
    round_burr = CuttingModel(n_theta=32).evaluate(case.centre_mm, case.axis,
                                                  case.feed_velocity_mm_s, case.rpm)
    _same(model.evaluate(case.centre_mm, case.axis, case.feed_velocity_mm_s, case.rpm),
          round_burr)


def test_a_round_fluted_burr_is_not_the_abrasive_sphere(nine_cases):
    fluted = Burr(Sphere(2.0), Fluted(6, 20.0, 5.0, 30.0))
    c = nine_cases[0]
    pose = (c.centre_mm, c.axis, c.feed_velocity_mm_s, c.rpm)
    got = CuttingModel(CuttingParams(burr=fluted)).evaluate(*pose)
    _same(got, RevolvedModel(fluted, CuttingParams()).evaluate(*pose))
    abrasive = CuttingModel().evaluate(*pose)
    assert not np.allclose(got.force_N, abrasive.force_N, rtol=1e-3)


class _RoundOnly(Workpiece):
    """A workpiece with its own kernel for the sphere grid (as the voxel bone's)."""

    def cut(self, grid, radius_mm, centre_mm, axis, feed_mm_s, omega_rad_s, us_n_mm2, k,
            cutting, scratch, out):
        raise AssertionError("a shaped burr must not reach the sphere kernel")


def test_a_shaped_burr_on_another_workpiece_is_refused_by_name():
    params = CuttingParams(burr=Burr(Cylinder(1.0, 4.0)))
    with pytest.raises(ValueError, match=r"abrasive cylinder burr on a FlatWorkpiece only.*"
                                         r"RevolvedModel.*BoneEngine"):
        CuttingModel(params, _RoundOnly())
    model = CuttingModel(CuttingParams(), _RoundOnly())  # the round abrasive burr is fine
    model.params = params
    with pytest.raises(ValueError, match="_RoundOnly takes the round abrasive burr"):
        model.evaluate((0.0, 0.0, 1.0), (0.0, 0.0, 1.0), (3.0, 0.0, 0.0), 60000.0)
