"""Engine frames and units: round trips, known axis mappings, handedness, torque, quaternions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from burrforce.proto.frames import FRAMES, Transform, frame, quat_matrix, quat_rotate

NAMES = list(FRAMES)
IDENTITY_Q = (0.0, 0.0, 0.0, 1.0)
LEFT_HANDED = {"unity", "unreal"}


# -- helpers ------------------------------------------------------------------------------------
def _norm(v) -> float:
    return math.hypot(*v)  # no underflow for tiny components


def assert_close(got, expected, scale: float = 1.0, rel: float = 1e-9) -> None:
    """``got`` equals ``expected`` within ``rel`` × (scale + the vectors' size), and never
    closer than the smallest normal double: the relative bound underflows to 0 for vectors
    of subnormal size (CI drew a torque of 5e-324 against 0)."""
    got = np.asarray(got, dtype=np.float64)
    expected = np.asarray(expected, dtype=np.float64)
    assert got.shape == expected.shape
    tol = rel * (scale + float(np.max(np.abs(expected), initial=0.0))
                 + float(np.max(np.abs(got), initial=0.0))) + np.finfo(np.float64).tiny
    assert float(np.max(np.abs(got - expected), initial=0.0)) <= tol, (got, expected)


def _normalize(q):
    n = _norm(q)
    return tuple(x / n for x in q)


component = st.floats(-1.0, 1.0, allow_nan=False)
raw_quats = st.tuples(component, component, component, component).filter(
    lambda q: _norm(q) > 0.1)
unit_quats = raw_quats.map(_normalize)
coordinate = st.floats(-100.0, 100.0, allow_nan=False)
vectors = st.tuples(coordinate, coordinate, coordinate)
origins = st.tuples(*[st.floats(-1000.0, 1000.0, allow_nan=False)] * 3)


@st.composite
def transforms_with_args(draw):
    """(A Transform of a random frame, placement and target, (placement position and
    orientation, target rotation and origin))."""
    f = FRAMES[draw(st.sampled_from(NAMES))]
    placement_position = draw(vectors)
    placement_orientation = draw(unit_quats)
    target_rotation = Rotation.from_quat(draw(unit_quats)).as_matrix()
    target_origin = np.array(draw(origins))
    tr = Transform(f, placement_position, placement_orientation, target_rotation, target_origin)
    return tr, (placement_position, placement_orientation, target_rotation, target_origin)


def transforms():
    return transforms_with_args().map(lambda t: t[0])


def _size(tr: Transform) -> float:
    """Length scale of a transform's offsets, mm."""
    return float(np.max(np.abs(tr.offset_mm)))


# -- round trips --------------------------------------------------------------------------------
@given(tr=transforms(), p=vectors)
def test_point_round_trip(tr, p):
    assert_close(tr.point_out(tr.point_in(p)), p, scale=1.0 + _size(tr) / tr.scale)


@given(tr=transforms(), v=vectors)
def test_vector_round_trip(tr, v):
    assert_close(tr.vector_out(tr.vector_in(v)), v)


@given(tr=transforms(), d=vectors)
def test_direction_round_trip(tr, d):
    assert_close(tr.direction_out(tr.direction_in(d)), d)


@given(tr=transforms(), a=vectors, b=vectors)
def test_transform_is_a_scaled_isometry(tr, a, b):
    """Distances scale by mm_per_unit; points differ by vectors; directions keep their length."""
    pa, pb = np.array(tr.point_in(a)), np.array(tr.point_in(b))
    diff = np.array(a) - np.array(b)
    assert_close(pa - pb, tr.vector_in(tuple(diff)), scale=_size(tr) + 1.0)
    assert_close([_norm(pa - pb)], [tr.scale * _norm(diff)], scale=_size(tr) + 1.0)
    assert_close([_norm(tr.direction_in(a))], [_norm(a)])
    assert_close(np.array(tr.vector_in(a)), tr.scale * np.array(tr.direction_in(a)))
    assert tr.det == (1.0 if tr.frame.right_handed else -1.0)
    assert_close(tr.matrix @ tr.matrix.T, np.eye(3))


@given(tr_args=transforms_with_args())
def test_placement_and_target_mean_what_the_docstring_says(tr_args):
    """The placement position (engine units) is the server origin; the placement orientation
    rotates the server axes in the engine's world; the target origin and rotation are the
    target frame's origin and axes in the server frame."""
    tr, (position, orientation, g, o) = tr_args
    m = np.array(tr.frame.to_server, dtype=np.float64)
    assert_close(tr.point_in(position), -g.T @ o, scale=_size(tr))
    for i in range(3):
        server_axis_in_engine = quat_rotate(orientation, tuple(m.T[:, i]))
        assert_close(tr.direction_in(server_axis_in_engine), g.T[:, i])


@given(name=st.sampled_from(NAMES), p0=vectors, q=unit_quats, x=vectors, f=vectors)
def test_conversions_follow_the_spec_formulas(name, p0, q, x, f):
    """SPEC.md 6.3 with the server frame as target: x_s = s·M·Pᵀ·(x_e − p0), v_s = s·M·Pᵀ·v_e,
    F_e = P·Mᵀ·F_s, τ_e = det(M)·P·Mᵀ·τ_s / s, x_e = p0 + P·Mᵀ·x_s / s (P from scipy)."""
    fr = FRAMES[name]
    tr = Transform(fr, p0, q)
    m = np.array(fr.to_server, dtype=np.float64)
    p = Rotation.from_quat(q).as_matrix()
    s = fr.mm_per_unit
    det = np.linalg.det(m)
    x_e, v_e = np.array(x), np.array(f)
    size = s * (_norm(x) + _norm(p0))
    assert_close(tr.point_in(x), s * m @ p.T @ (x_e - np.array(p0)), scale=size)
    assert_close(tr.vector_in(f), s * m @ p.T @ v_e, scale=s * _norm(f))
    assert_close(tr.direction_in(f), m @ p.T @ v_e)
    assert_close(tr.direction_out(f), p @ m.T @ v_e)
    assert_close(tr.vector_out(f), p @ m.T @ v_e / s)
    assert_close(tr.torque_out(f), det * p @ m.T @ v_e / s)
    assert_close(tr.point_out(x), np.array(p0) + p @ m.T @ x_e / s, scale=_norm(p0) + 1.0)


# -- known mappings (identity placement) --------------------------------------------------------
KNOWN_POINTS = [
    # frame, engine point, server point (mm)
    ("unity", (0.0, 1.0, 0.0), (0.0, 0.0, 1000.0)),  # up
    ("unity", (0.0, 0.0, 1.0), (1000.0, 0.0, 0.0)),  # forward
    ("unity", (1.0, 0.0, 0.0), (0.0, -1000.0, 0.0)),  # right
    ("unreal", (0.0, 0.0, 100.0), (0.0, 0.0, 1000.0)),  # up, cm
    ("unreal", (1.0, 0.0, 0.0), (10.0, 0.0, 0.0)),  # forward
    ("unreal", (0.0, 1.0, 0.0), (0.0, -10.0, 0.0)),  # right
    ("godot", (0.0, 0.0, -1.0), (1000.0, 0.0, 0.0)),  # forward
    ("godot", (0.0, 1.0, 0.0), (0.0, 0.0, 1000.0)),  # up
    ("godot", (1.0, 0.0, 0.0), (0.0, -1000.0, 0.0)),  # right
    ("ros", (1.0, 2.0, 3.0), (1000.0, 2000.0, 3000.0)),
    ("ros", (-0.5, 0.25, -4.0), (-500.0, 250.0, -4000.0)),
    ("si_mm", (1.0, 2.0, 3.0), (1.0, 2.0, 3.0)),
    ("si_mm", (-7.5, 0.0, 12.0), (-7.5, 0.0, 12.0)),
]


@pytest.mark.parametrize(("name", "engine", "server"), KNOWN_POINTS)
def test_known_mappings(name, engine, server):
    tr = Transform(frame(name))
    scale = FRAMES[name].mm_per_unit
    assert_close(tr.point_in(engine), server, rel=1e-12)
    assert_close(tr.vector_in(engine), server, rel=1e-12)
    assert_close(tr.direction_in(engine), tuple(x / scale for x in server), rel=1e-12)
    assert_close(tr.point_out(server), engine, rel=1e-12)
    assert_close(tr.direction_out(tuple(x / scale for x in server)), engine, rel=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_units(name):
    f = FRAMES[name]
    assert f.name == name
    assert {"mm": 1.0, "cm": 10.0, "m": 1000.0}[f.length_unit] == f.mm_per_unit
    m = np.array(f.to_server, dtype=np.float64)
    # a signed permutation: one ±1 per row and column
    assert sorted(np.abs(m).sum(axis=0)) == [1, 1, 1] and sorted(np.abs(m).sum(axis=1)) == [1, 1, 1]
    assert set(np.unique(m)) <= {-1.0, 0.0, 1.0}


@pytest.mark.parametrize("name", NAMES)
def test_handedness(name):
    assert FRAMES[name].right_handed is (name not in LEFT_HANDED)
    assert Transform(FRAMES[name]).det == (-1.0 if name in LEFT_HANDED else 1.0)


def test_left_handed_frames_are_unity_and_unreal():
    assert {n for n, f in FRAMES.items() if not f.right_handed} == LEFT_HANDED


@pytest.mark.parametrize("name", NAMES)
def test_tool_pointing_up_maps_to_server_up(name):
    f = FRAMES[name]
    axis = quat_rotate(IDENTITY_Q, f.tool_axis)
    assert_close(Transform(f).direction_in(axis), (0.0, 0.0, 1.0), rel=1e-12)


# -- torque -------------------------------------------------------------------------------------
@given(tr=transforms(), r=vectors, force=vectors)
def test_torque_is_a_pseudovector(tr, r, force):
    """An engine's own r × F (engine units, N) equals torque_out of the server's r × F (mm, N).
    For the left-handed engines this needs the det(M) = −1 factor."""
    r_server = np.array(tr.vector_in(r))
    f_server = np.array(tr.direction_in(force))
    engine_torque = np.cross(r, force)
    got = tr.torque_out(tuple(np.cross(r_server, f_server)))
    assert_close(got, engine_torque, scale=_norm(r) * _norm(force))


@pytest.mark.parametrize("name", NAMES)
def test_torque_sign_in_left_handed_frames(name):
    """Without the det factor a left-handed engine would get the torque reversed."""
    tr = Transform(FRAMES[name])
    r, force = (0.25, -0.5, 1.0), (3.0, 1.0, -2.0)
    server = tuple(np.cross(tr.vector_in(r), tr.direction_in(force)))
    naive = np.array(tr.direction_out(server)) / tr.scale
    assert_close(tr.torque_out(server), np.cross(r, force), rel=1e-12)
    sign = 1.0 if name not in LEFT_HANDED else -1.0
    assert_close(naive, sign * np.cross(r, force), rel=1e-12)


# -- quaternions --------------------------------------------------------------------------------
@given(q=raw_quats, v=vectors)
def test_quat_rotate_agrees_with_scipy(q, v):
    expected = Rotation.from_quat(q).apply(v)
    assert_close(quat_rotate(q, v), expected)
    assert_close(quat_matrix(q), Rotation.from_quat(q).as_matrix())


@given(q=unit_quats, v=vectors, k=st.floats(0.01, 100.0))
def test_quat_rotate_normalizes(q, v, k):
    scaled = tuple(k * x for x in q)
    assert_close(quat_rotate(scaled, v), quat_rotate(q, v))
    assert_close([_norm(quat_rotate(scaled, v))], [_norm(v)])
    negated = tuple(-x for x in q)  # q and −q are the same rotation
    assert_close(quat_rotate(negated, v), quat_rotate(q, v))


def test_quat_rotate_known_rotations():
    h = math.sqrt(0.5)
    assert_close(quat_rotate((0.0, 0.0, h, h), (1.0, 0.0, 0.0)), (0.0, 1.0, 0.0), rel=1e-15)
    assert_close(quat_rotate((h, 0.0, 0.0, h), (0.0, 1.0, 0.0)), (0.0, 0.0, 1.0), rel=1e-15)
    assert_close(quat_rotate((0.0, 2.0, 0.0, 0.0), (1.0, 0.0, 0.0)), (-1.0, 0.0, 0.0),
                 rel=1e-15)
    assert quat_rotate(IDENTITY_Q, (1.5, -2.0, 3.0)) == (1.5, -2.0, 3.0)


# -- lookup -------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", ["nope", "", "Unity", None, ["unity"]])
def test_unknown_frame(bad):
    with pytest.raises(ValueError) as info:
        frame(bad)
    for name in NAMES:
        assert name in str(info.value)


@pytest.mark.parametrize("name", NAMES)
def test_frame_lookup(name):
    assert frame(name) is FRAMES[name]
