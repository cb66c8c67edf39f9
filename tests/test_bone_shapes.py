"""Burr shapes on the voxel bone: steady grooves against the flat model (``RevolvedModel``),
the energy balance, carving's volume, the round fluted burr against the sphere's own kernel,
and tool changes mid-stream."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import settings as hsettings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.server.bench.accuracy import oblique_rotation
from burrforce.server.bench.groove import GROOVE_BLOCK_HI_MM, GROOVE_BLOCK_LO_MM, groove_block
from burrforce.server.bone import BoneEngine, ShaftParams, workpiece_block
from burrforce.server.bone.grid import BoneGrid
from burrforce.server.model import (
    Abrasive,
    Barrel,
    Burr,
    CuttingParams,
    Cylinder,
    Fluted,
    RevolvedModel,
    Sphere,
)
from burrforce.server.model.cases import CuttingCase
from burrforce.server.model.kernels import OUT_FORCE, OUT_POWER
from burrforce.server.model.shapes import profile_points

FLAT = Burr(Cylinder(1.0, 4.0))
ROUND = Burr(Cylinder(1.5, 5.0, "round"))
BARREL = Burr(Barrel(1.5, 1.0, 4.0))
FLUTED = Burr(Cylinder(1.0, 4.0), Fluted(6, 30.0, 5.0))

#: One pose per shape (orientation, tilt). Poses where an end disc's centre lies on the bone's
#: surface are avoided: there the flat model's force changes by ~12 % per 25 µm of depth (the
#: cancelled weight ds·dφ/ω does not vanish at the axis), which 0.1 mm voxels cannot resolve
#: (at parallel 60° on a fresh block: flat cylinder −2.4 %, barrel −2.4 %, the fluted
#: cylinder −10.5 %).
SHAPE_CASES = [
    (FLAT, CuttingCase("parallel", 30.0)),
    (ROUND, CuttingCase("parallel", 60.0)),
    (BARREL, CuttingCase("diagonal", 45.0)),
    (FLUTED, CuttingCase("diagonal", 45.0)),
]
IDS = ["cylinder-flat", "cylinder-round", "barrel", "fluted-cylinder"]


def reference_centre(burr: Burr, case: CuttingCase) -> np.ndarray:
    """The reference centre that puts the burr's deepest point the case's depth into the flat
    workpiece (bone in z < 0)."""
    points = profile_points(burr.shape.profile(), 512)
    a = case.axis / np.linalg.norm(case.axis)
    lowest = np.min(points[:, 1] * a[2] - points[:, 0] * math.sqrt(max(1.0 - a[2] ** 2, 0.0)))
    return np.array([0.0, 0.0, -case.depth_mm - lowest])


def groove(engine: BoneEngine, burr: Burr, case: CuttingCase, start_xy: np.ndarray,
           length_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Plough a straight groove with ``burr`` from ``start_xy``; per-tick force (world, N)
    and spindle power (W)."""
    engine.set_burr(burr)
    grid = engine.grid
    start = np.array([start_xy[0], start_xy[1], 0.0]) + reference_centre(burr, case)
    n = round(length_mm / (case.feed_mm_s * 1e-3))
    axis_g = grid.to_grid_vector(case.axis / np.linalg.norm(case.axis))
    feed_g = grid.to_grid_vector(case.feed_velocity_mm_s)
    force = np.empty((n, 3))
    power = np.empty(n)
    for i in range(n):
        engine.step_raw(grid.to_grid_point(start + case.feed_velocity_mm_s * (i * 1e-3)),
                        axis_g, feed_g, case.rpm)
        force[i] = grid.to_world_vector(engine.out[OUT_FORCE:OUT_FORCE + 3])
        power[i] = engine.out[OUT_POWER] * 1e-3
    return force, power


def new_engine(grid: BoneGrid) -> BoneEngine:
    engine = BoneEngine(grid, shaft=ShaftParams(length_mm=0.0))
    engine.warm_up()
    return engine


@pytest.mark.parametrize("oblique", [False, True], ids=["aligned", "oblique"])
@pytest.mark.parametrize(("burr", "case"), SHAPE_CASES, ids=IDS)
def test_steady_groove_matches_the_flat_model(burr, case, oblique):
    grid = groove_block(0.1, oblique_rotation() if oblique else None)
    mid = 0.5 * (np.asarray(GROOVE_BLOCK_LO_MM) + np.asarray(GROOVE_BLOCK_HI_MM))
    warmup_mm, measure_mm = 0.3, 0.9
    start = mid[:2] - 0.5 * (warmup_mm + measure_mm) * case.feed_direction[:2]
    force, _ = groove(new_engine(grid), burr, case, start, warmup_mm + measure_mm)
    steady = force[round(warmup_mm / (case.feed_mm_s * 1e-3)):]
    mag = np.linalg.norm(steady, axis=1)
    flat = RevolvedModel(burr).evaluate(reference_centre(burr, case), case.axis,
                                        case.feed_velocity_mm_s, case.rpm)
    assert mag.mean() == pytest.approx(flat.force_magnitude_N, rel=0.02)
    assert mag.std() / mag.mean() <= 0.02
    mean = steady.mean(axis=0)
    assert np.dot(mean, flat.force_N) / (np.linalg.norm(mean) * flat.force_magnitude_N) > 0.998


@pytest.mark.parametrize(("burr", "case"), [SHAPE_CASES[0], SHAPE_CASES[2], SHAPE_CASES[3]],
                         ids=[IDS[0], IDS[2], IDS[3]])
def test_energy_balance_entering_from_outside(burr, case):
    """∫ P dt = Σ Us × removed volume over a whole groove entered through a side face.
    Measured: −1.02 % (flat cylinder), −0.53 % (barrel), −1.16 % (fluted)."""
    length = 11.0
    start = np.array([6.0, 6.0]) - length * case.feed_direction[:2]  # clear of the block
    engine = new_engine(groove_block(0.1))
    _, power = groove(engine, burr, case, start, length)
    assert engine.removal_energy_J() > 0.01
    assert power.sum() * 1e-3 == pytest.approx(engine.removal_energy_J(), rel=0.015)


def deep_block() -> BoneGrid:
    return workpiece_block(0.1, lo_mm=(0.0, 0.0, -6.0), hi_mm=(6.0, 6.0, 0.0), margin_mm=0.5,
                           offset_voxels=(0.31, 0.17, 0.43))


_DEEP = {}


@hsettings(max_examples=examples(12))
@given(shape=st.sampled_from(["flat", "round", "barrel"]),
       polar=st.floats(0.0, math.pi), azimuth=st.floats(0.0, 2.0 * math.pi),
       shift=st.tuples(*[st.floats(-0.5, 0.5)] * 3))
def test_carving_removes_the_solid_volume(shape, polar, azimuth, shift):
    """One carving tick deep inside bone removes the solid's volume (partial volume)."""
    burr, volume = {
        "flat": (Burr(Cylinder(0.8, 2.0)), math.pi * 0.8 ** 2 * 2.0),
        "round": (Burr(Cylinder(0.8, 2.0, "round")),
                  math.pi * 0.8 ** 2 * 1.2 + 2.0 / 3.0 * math.pi * 0.8 ** 3),
        "barrel": (Burr(Barrel(1.0, 0.6, 2.0)), None),
    }[shape]
    if volume is None:  # the barrel: the profile's solid of revolution, numerically
        pts = profile_points(burr.shape.profile(), 4096)
        rho, z = pts[:, 0], pts[:, 1]
        volume = float(np.sum(np.pi * 0.25 * (rho[1:] + rho[:-1]) ** 2 * np.diff(z)))
    if "grid" not in _DEEP:
        _DEEP["grid"] = deep_block()
        _DEEP["swept"] = _DEEP["grid"].swept.copy()
        _DEEP["state"] = (_DEEP["grid"].brick_bone.copy(), _DEEP["grid"].brick_full.copy())
    grid = _DEEP["grid"]
    grid.swept[...] = _DEEP["swept"]
    grid.brick_bone[...] = _DEEP["state"][0]
    grid.brick_full[...] = _DEEP["state"][1]
    engine = BoneEngine(grid, shaft=ShaftParams(length_mm=0.0))
    engine.set_burr(burr)
    axis = (math.sin(polar) * math.cos(azimuth), math.sin(polar) * math.sin(azimuth),
            math.cos(polar))
    centre = np.array([3.0, 3.0, -3.0]) + np.asarray(shift)
    result = engine.step(centre, axis, (0.0, 0.0, 0.0), 60000.0)
    assert result.removed_mm3 == pytest.approx(volume, rel=0.01)
    again = engine.step(centre, axis, (0.0, 0.0, 0.0), 60000.0)
    assert again.removed_mm3 == 0.0  # nothing left to take where it stands


def test_round_fluted_burr_without_helix_or_rake_is_the_sphere():
    """A sphere whose cutter gives exactly the abrasive ratios runs the revolved kernels; its
    force on a fresh block matches the sphere's own kernel."""
    params = CuttingParams()
    cutter = Fluted(6, 0.0, 0.0, math.degrees(math.atan(params.k)))
    case = CuttingCase("diagonal", 60.0)
    centre = case.centre_mm + np.array([6.0, 6.0, 0.0])
    grid = groove_block(0.1)
    sphere = BoneEngine(grid, shaft=ShaftParams(length_mm=0.0))
    expected = sphere.step(centre, case.axis, case.feed_velocity_mm_s, case.rpm, carve=False)
    revolved = BoneEngine(grid, shaft=ShaftParams(length_mm=0.0))
    revolved.set_burr(Burr(Sphere(2.0), cutter))
    got = revolved.step(centre, case.axis, case.feed_velocity_mm_s, case.rpm, carve=False)
    assert got.cut.force_magnitude_N == pytest.approx(expected.cut.force_magnitude_N, rel=0.01)
    assert np.dot(got.cut.force_N, expected.cut.force_N) > 0.999 * (
        got.cut.force_magnitude_N * expected.cut.force_magnitude_N)
    assert np.allclose(got.cut.surface_normal, expected.cut.surface_normal, atol=1e-3)


def test_burr_shape_and_set_burr():
    engine = BoneEngine(groove_block(0.2), shaft=ShaftParams(radius_mm=0.5))
    assert engine.burr_shape == Burr(Sphere(2.0), Abrasive())
    assert engine.contact_radius_mm == 2.0
    engine.set_burr(FLAT)
    assert engine.burr_shape == FLAT and engine.params.radius_mm == 1.0
    # Contact areas compare with the sphere of the same surface (the coupled output's "wholly
    # in bone" share): R1 L4 flat ends, 2π·1·4 + 2·π·1² = 10π mm².
    assert engine.contact_radius_mm == pytest.approx((10.0 * np.pi / (4.0 * np.pi)) ** 0.5,
                                                     rel=1e-3)
    engine.set_burr(Burr(Sphere(1.5)))
    assert engine.burr_shape == Burr(Sphere(1.5)) and engine.params.radius_mm == 1.5
    assert engine.params.burr is None  # the round abrasive burr: the sphere's own tick
    with pytest.raises(ValueError, match="shaft radius"):
        engine.set_burr(Burr(Cylinder(0.4, 3.0)))
    with pytest.raises(ValueError, match="coarser than the burr"):
        engine.set_burr(Burr(Cylinder(0.1, 3.0)))
    assert engine.burr_shape == Burr(Sphere(1.5))  # a refused burr changes nothing
    with pytest.raises(TypeError):
        engine.set_burr(Sphere(1.0))  # type: ignore[arg-type]


def test_tool_change_mid_stream_matches_fresh_engines():
    """Sphere → cylinder → sphere on one engine, each on fresh bone: each groove's steady
    force is the one a fresh engine with that burr gives."""
    sphere, cylinder = Burr(Sphere(2.0)), FLAT
    case = CuttingCase("parallel", 30.0)
    legs = [(sphere, 2.5), (cylinder, 6.0), (sphere, 9.5)]
    length, skip = 1.2, 100
    engine = new_engine(groove_block(0.1))
    for burr, y in legs:
        changed, _ = groove(engine, burr, case, np.array([4.0, y]), length)
        fresh, _ = groove(new_engine(groove_block(0.1)), burr, case, np.array([4.0, y]), length)
        a = np.linalg.norm(changed[skip:], axis=1).mean()
        b = np.linalg.norm(fresh[skip:], axis=1).mean()
        assert a == pytest.approx(b, rel=0.01), burr


def test_shaft_starts_at_the_top_of_the_shape():
    """A cylinder standing clear of a wall whose shaft leans into it: the shaft (from the top
    disc) is pushed away, the burr does not cut; the torque is about the reference centre."""
    grid = workpiece_block(0.1, lo_mm=(5.0, 0.0, 0.0), hi_mm=(12.0, 12.0, 12.0),
                           margin_mm=0.0, offset_voxels=(0.31, 0.17, 0.43))
    axis = np.array([0.5, 0.0, math.sqrt(0.75)])
    engine = BoneEngine(grid, shaft=ShaftParams(radius_mm=0.5, length_mm=10.0))
    engine.set_burr(Burr(Cylinder(1.0, 2.0)))
    result = engine.step((2.5, 6.0, 1.0), axis, (0.0, 0.0, 0.0), 60000.0)
    assert not result.cut.contact and result.shaft_contact
    f = result.shaft_force_N
    assert f[0] < 0 and abs(np.dot(f, axis)) < 1e-9 * np.linalg.norm(f)
    # The push acts beyond the top (z = 1 mm along the axis): its moment about the reference
    # centre is that of a force applied there or farther.
    lever = np.cross(f, result.shaft_torque_Nmm) / np.dot(f, f)  # the line of action's foot
    assert np.dot(lever, axis) > 1.0


def test_below_cutting_speed_a_shape_touches_without_force_or_carving():
    grid = groove_block(0.2)
    swept = grid.swept.copy()
    engine = BoneEngine(grid, shaft=ShaftParams(length_mm=0.0))
    engine.set_burr(BARREL)
    result = engine.step((6.0, 6.0, 1.5), (0.3, 0.0, 1.0), (3.0, 0.0, 0.0), 1000.0)
    assert result.cut.contact and not result.cut.cutting
    assert not result.cut.force_N.any() and result.removed_mm3 == 0.0
    assert np.array_equal(grid.swept, swept)


def test_force_switches_on_continuously_at_first_touch():
    """Lowering a tilted flat cylinder onto the top face: its rim enters first, and the force
    grows without a step larger than a quarter of where it ends."""
    grid = groove_block(0.1)
    engine = BoneEngine(grid, shaft=ShaftParams(length_mm=0.0))
    engine.set_burr(FLAT)
    axis = np.array([-0.5, 0.0, math.sqrt(0.75)])
    touch_z = reference_centre(FLAT, CuttingCase("parallel", 60.0))[2] + 0.5
    forces = []
    for gap_um in range(120, -60, -5):
        result = engine.step((6.0, 6.0, touch_z + gap_um * 1e-3), axis, (0.0, 0.0, -3.0),
                             60000.0, carve=False)
        forces.append(result.cut.force_magnitude_N)
    steps = np.diff(forces)
    assert forces[0] == 0.0 and forces[-1] > 0.0
    assert np.abs(steps).max() <= 0.25 * forces[-1]


# -- the carve's reach: the solid's ball -------------------------------------------------------

def _barrel_or_none(eq: float, share: float, stretch: float) -> Barrel | None:
    end = eq * share
    try:  # the arc bulges at most a half-circle: eq − end ≤ length/2
        return Barrel(eq, end, 2.0 * (eq - end) * (1.0 + 3.0 * stretch) + 1e-3)
    except ValueError:
        return None


PROFILES = st.one_of(
    st.builds(Sphere, st.floats(0.3, 4.0)),
    st.builds(lambda r, extra, end: Cylinder(r, r + extra, end), st.floats(0.3, 3.0),
              st.floats(0.05, 6.0), st.sampled_from(["flat", "round"])),
    st.builds(_barrel_or_none, st.floats(0.3, 3.0), st.floats(0.0, 0.95),
              st.floats(0.0, 1.0)).filter(lambda b: b is not None),
)


@given(shape=PROFILES)
@hsettings(max_examples=examples(60), deadline=None)
def test_the_ball_reaches_the_farthest_point_of_the_solid(shape):
    """``bounding_radius_mm`` bounds every point of the profile (the carve skips voxels beyond
    it) and is reached (it is the farthest point, not a loose box)."""
    from burrforce.server.bone.carve_revolved import bounding_radius_mm

    points = profile_points(shape.profile(), per_arc=4096)
    farthest = float(np.hypot(points[:, 0], points[:, 1]).max())
    r_ball = bounding_radius_mm(Burr(shape))
    assert farthest <= r_ball * (1.0 + 1e-12)
    assert r_ball <= farthest + 1e-6  # the chords' error at 4096 per arc is below this


@given(shape=PROFILES, direction=st.tuples(*[st.floats(-1.0, 1.0)] * 3),
       beyond=st.floats(0.0, 0.5), voxel_mm=st.sampled_from([0.05, 0.1, 0.2]))
@hsettings(max_examples=examples(80), deadline=None)
def test_a_voxel_beyond_the_ball_is_not_covered(shape, direction, beyond, voxel_mm):
    """The premise of the carve's cut to the ball: a voxel whose centre lies half a diagonal
    beyond the solid's farthest point gets no coverage from the full computation either
    (the ball's own reject switched off)."""
    from burrforce.server.bone.carve_revolved import (
        GEO_R_BALL,
        N_GEO,
        fill_geometry,
        profile_table,
        revolved_coverage,
        shape_bounds,
    )
    from burrforce.server.model.revolved import RevolvedGrid

    d = np.asarray(direction)
    if np.linalg.norm(d) < 1e-3:
        return
    burr = Burr(shape)
    bounds = shape_bounds(burr)
    spacing = np.full(3, voxel_mm)
    geo = np.zeros(N_GEO)
    axis = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
    fill_geometry(geo, axis, bounds, spacing)
    half_diag = 0.5 * math.sqrt(3.0) * voxel_mm
    p = d / np.linalg.norm(d) * (bounds[3] + half_diag * (1.0 + beyond))
    table = profile_table(RevolvedGrid.build(burr, 256, 2).segments)
    geo[GEO_R_BALL] = 1e9
    assert revolved_coverage(p[0], p[1], p[2], table, geo, voxel_mm, voxel_mm, voxel_mm) == 0


@pytest.mark.parametrize(("burr", "examined"), [
    (Burr(Sphere(2.0), Fluted(6)), 0.25), (FLAT, 1.0), (ROUND, 1.0), (BARREL, 0.8),
    (FLUTED, 1.0)], ids=["round-fluted", "cylinder-flat", "cylinder-round", "barrel",
                         "fluted-cylinder"])
def test_cutting_rows_to_the_ball_changes_no_bit(burr, examined):
    """The same groove with the carve's ball and its per-row cache and without them (the
    ball's radius made huge, the cache one entry): every
    force, torque, contact and removal of every tick and every swept voxel are identical,
    while fewer voxels are examined (at most the share ``examined``; measured: 0.14 for the
    round burr, whose ball is its solid, 0.72 for the barrel, now that air reached is marked
    once and skipped; 0.21 and 0.79 when air was covered every tick)."""
    case = CuttingCase("parallel", 60.0)
    runs = []
    for limited in (True, False):
        engine = new_engine(groove_block(0.1, oblique_rotation()))
        engine.set_burr(burr)
        if not limited:
            engine._revolved.bounds[3] = 1e9
            # and each row's reach computed for every brick it crosses, not once a tick
            engine._rows = np.zeros((1, 1, 3), dtype=np.int64)
        grid = engine.grid
        start = np.array([4.0, 6.0, 0.0]) + reference_centre(burr, case)
        axis_g = grid.to_grid_vector(case.axis / np.linalg.norm(case.axis))
        feed_g = grid.to_grid_vector(case.feed_velocity_mm_s)
        rows, visited = [], 0.0
        for i in range(150):
            engine.step_raw(grid.to_grid_point(start + case.feed_velocity_mm_s * (i * 1e-3)),
                            axis_g, feed_g, case.rpm, carve=i % 40 != 7)
            rows.append(np.concatenate([engine.out, engine.shaft_out, engine.touch[[0, 2, 3]],
                                        [engine.removed_this_tick_mm3()]]))
            visited += engine.touch[1]
        runs.append((np.array(rows), grid.swept.copy(), visited))
    (a, swept_a, visited_a), (b, swept_b, visited_b) = runs
    assert np.array_equal(a.view(np.uint64), b.view(np.uint64))
    assert np.array_equal(swept_a, swept_b)
    assert a[:, 0:3].any()  # it cut
    assert visited_a <= examined * visited_b
