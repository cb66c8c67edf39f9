"""The path's share of a surface patch (``history.history_share``) against the geometry it
stands for: the share of a small patch outside a union of capsules, found by sampling the
patch densely. Its answer of exactly 1 where the patch lies wholly outside every capsule comes
from a test without square roots, or before it from the tick's front test (two dot products a
capsule, bounds set once a tick), which must agree with it exactly; everywhere else from the
nearest capsule's wall, linearized across the patch."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.server.bone.history import (
    CAND_CENTRE,
    CAND_COLS,
    CAND_COUNT,
    CAND_MODE,
    CAND_MU,
    HISTORY_EXACT,
    _front_bounds,
    history_share,
    in_front,
)

R_MM = 2.0
#: Half-sides of the patch, mm: a 1152-element burr's sub-element on R = 2 mm is ~0.07 mm.
HALF_MM = 0.03
GRID = 41


def candidates(capsules: list[tuple[np.ndarray, np.ndarray, float]],
               front_patch_mm: float = -1.0) -> np.ndarray:
    """The candidate array ``history_candidates`` fills: header, then a → a + u, r, 1/|u|²,
    and the front test's bounds for a burr of radius R_MM centred at 0 whose patches reach
    at most ``front_patch_mm`` (< 0: no front test)."""
    cand = np.zeros((len(capsules) + 1, CAND_COLS))
    cand[0, CAND_COUNT] = len(capsules)
    cand[0, CAND_MODE] = HISTORY_EXACT
    cand[0, CAND_CENTRE:CAND_CENTRE + 3] = 0.0
    for n, (a, u, r) in enumerate(capsules, start=1):
        l2 = float(u @ u)
        cand[n, :3] = a
        cand[n, 3:6] = u
        cand[n, 6] = r
        cand[n, 7] = 1.0 / l2 if l2 > 1e-300 else 0.0
        _front_bounds(cand, n, 0.0, 0.0, 0.0, R_MM, front_patch_mm)
    return cand


def shares(p, s1, s2, capsules) -> float:
    """The share without the front test, once checked to be the same, to the last bit, with
    it (bounds for this patch's reach)."""
    plain = history_share(candidates(capsules), *p, *s1, *s2)
    reach = float(np.linalg.norm(s1) + np.linalg.norm(s2))
    assert history_share(candidates(capsules, reach), *p, *s1, *s2) == plain
    return plain


def gap_mm(points: np.ndarray, capsules) -> np.ndarray:
    """Signed distance of each point (n, 3) to the union of the capsules, mm."""
    best = np.full(len(points), np.inf)
    for a, u, r in capsules:
        l2 = float(u @ u)
        t = np.clip((points - a) @ u / l2, 0.0, 1.0) if l2 > 0 else np.zeros(len(points))
        best = np.minimum(best, np.linalg.norm(points - a - t[:, None] * u, axis=1) - r)
    return best


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def patch_at(normal: np.ndarray, s2_scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The patch of the burr's sphere (centre 0, radius R) at ``normal``: its centre and its
    half-sides, tangent to the sphere."""
    p = R_MM * normal
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = unit(np.cross(normal, helper))
    return p, HALF_MM * t1, s2_scale * HALF_MM * np.cross(normal, t1)


def vectors(draw) -> np.ndarray:
    v = np.array([draw(st.floats(-1, 1)) for _ in range(3)])
    return unit(v) if np.linalg.norm(v) > 0.1 else np.array([0.0, 0.0, 1.0])


def sampled(p, s1, s2) -> np.ndarray:
    """The patch sampled on a GRID × GRID lattice, (GRID², 3)."""
    u, v = np.meshgrid(np.linspace(-1, 1, GRID), np.linspace(-1, 1, GRID))
    return p + u.reshape(-1, 1) * s1 + v.reshape(-1, 1) * s2


#: The walls curve over the patch by ~|s|²/r (a few 1e-4 mm): a sliver of that width is all
#: the share's linearization can misplace.
BEND_MM = (HALF_MM * 2) ** 2 / R_MM


@st.composite
def patch_across_one_wall(draw):
    """A patch of the burr's surface and one capsule of the burr's radius (a stroke of its
    path, or a point) whose wall passes within two patch sizes of the patch's centre, at any
    angle to it: most examples have the wall crossing the patch."""
    p, s1, s2 = patch_at(vectors(draw), draw(st.floats(0.2, 1.0)))
    u = draw(st.floats(0.0, 1.0)) * vectors(draw)
    # The capsule's axis passes R + offset from p, square to ``toward``: its wall lies
    # ``offset`` from p (outside for offset > 0).
    toward = vectors(draw)
    u = u - (u @ toward) * toward
    offset = draw(st.floats(-3 * HALF_MM, 3 * HALF_MM))
    nearest = p + (R_MM + offset) * toward
    return p, s1, s2, [(nearest - draw(st.floats(0.0, 1.0)) * u, u, R_MM)]


@settings(max_examples=examples(300), deadline=None)
@given(patch_across_one_wall())
def test_the_share_is_the_patch_outside_a_capsule(case):
    """Against one capsule the share is the patch's part outside it, up to the sliver its
    curvature bends and the lattice's step; exactly 1 wholly outside and 0 wholly inside."""
    p, s1, s2, capsules = case
    share = shares(p, s1, s2, capsules)
    gaps = gap_mm(sampled(p, s1, s2), capsules)
    outside = float(np.mean(gaps > 0.0))
    sliver = float(np.mean(np.abs(gaps) < BEND_MM))
    assert abs(share - outside) <= sliver + 2.5 / GRID
    if gaps.min() > BEND_MM:
        assert share == 1.0
    if gaps.max() < -BEND_MM:
        assert share == 0.0


@st.composite
def patch_near_a_path(draw):
    """A patch of the burr's surface and one to three capsules of the burr's radius: its
    earlier positions, the centre moved back by up to 0.9 mm, strokes up to 1 mm long."""
    p, s1, s2 = patch_at(vectors(draw), draw(st.floats(0.2, 1.0)))
    capsules = []
    for _ in range(draw(st.integers(1, 3))):
        end = np.array([draw(st.floats(-0.5, 0.5)) for _ in range(3)])
        u = draw(st.floats(0.0, 1.0)) * vectors(draw)
        capsules.append((end - u, u, R_MM))
    return p, s1, s2, capsules


@settings(max_examples=examples(300), deadline=None)
@given(patch_near_a_path())
def test_a_patch_clear_of_the_whole_path_reads_exactly_one(case):
    """The burr's front, outside every capsule of its path, reads exactly 1 (the share's first
    pass, without square roots); anywhere else the share stays in [0, 1]."""
    p, s1, s2, capsules = case
    share = shares(p, s1, s2, capsules)
    assert 0.0 <= share <= 1.0
    if gap_mm(sampled(p, s1, s2), capsules).min() > BEND_MM:
        assert share == 1.0


def test_a_burr_standing_where_it_last_carved_finds_its_surface_uncut():
    """The patch lies on the capsule's wall (the burr at its last position): outside."""
    normal = unit([0.3, -0.2, 0.9])
    p = R_MM * normal
    helper = unit(np.cross(normal, [1.0, 0.0, 0.0]))
    s1 = HALF_MM * helper
    s2 = HALF_MM * np.cross(normal, helper)
    stroke = (np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), R_MM)
    assert shares(p, s1, s2, [stroke]) == 1.0
    # Moved back into its own groove by 10 µm: the patch is now inside the stroke's capsule.
    inside = p - 0.01 * normal
    assert history_share(candidates([stroke]), *inside, *s1, *s2) == 0.0


def test_no_capsule_leaves_the_whole_patch():
    s = HALF_MM * np.eye(3)
    assert history_share(candidates([]), 0.0, 0.0, R_MM, *s[0], *s[1]) == 1.0


@st.composite
def burr_just_ahead_of_its_path(draw):
    """The tick's case: a patch of the burr's surface and its path's last capsules, a run and
    the tail to where it last carved, which lies 0.1 µm to 50 µm behind its centre; the run
    bends away from the tail by up to ~12°, or is a point."""
    p, s1, s2 = patch_at(vectors(draw), draw(st.floats(0.2, 1.0)))
    back = -vectors(draw)
    last = 10.0 ** draw(st.floats(-4.0, np.log10(0.05))) * back
    tail_mm = draw(st.floats(0.0, 0.05))
    joint = last + tail_mm * back
    bend = unit(back + draw(st.floats(0.0, 0.2)) * vectors(draw))
    run_mm = draw(st.sampled_from([0.0, 0.3, 3.0]))
    capsules = [(joint + run_mm * bend, -run_mm * bend, R_MM), (joint, last - joint, R_MM)]
    return p, s1, s2, capsules


@settings(max_examples=examples(500), deadline=None)
@given(burr_just_ahead_of_its_path())
def test_the_front_test_agrees_with_the_first_pass_next_to_the_path(case):
    """Next to the capsules' walls, where the front test's bounds are tight (the centre a few
    µm ahead of where it last carved), a patch it passes is one the first pass clears: the
    share is the same with the front test as without, to the last bit."""
    p, s1, s2, capsules = case
    assert 0.0 <= shares(p, s1, s2, capsules) <= 1.0


def test_the_front_test_passes_the_burrs_front_and_nothing_behind():
    """A burr 3 µm ahead of where it last carved, at the end of a straight 3 mm stroke: the
    front test passes most of the surface that faces the feed (it is what makes the share
    cheap there), none of the surface behind, and every answer is the first pass's."""
    feed = unit([1.0, 0.2, -0.1])
    last = -0.003 * feed
    joint = -0.02 * feed
    capsules = [(joint - 3.0 * feed, 3.0 * feed, R_MM), (joint, last - joint, R_MM)]
    golden = np.pi * (3.0 - np.sqrt(5.0))
    k = np.arange(4000)
    z = 1.0 - 2.0 * (k + 0.5) / len(k)
    normals = np.column_stack([np.sqrt(1 - z * z) * np.cos(golden * k),
                               np.sqrt(1 - z * z) * np.sin(golden * k), z])
    ahead = []
    for normal in normals:
        p, s1, s2 = patch_at(normal, 1.0)
        shares(p, s1, s2, capsules)
        cand = candidates(capsules, float(np.linalg.norm(s1) + np.linalg.norm(s2)))
        ahead.append(in_front(cand, len(capsules), *p))
    ahead = np.array(ahead)
    facing = normals @ feed
    assert ahead[facing > 0.1].mean() > 0.95
    assert not ahead[facing < 0.0].any()


def test_a_sample_beside_a_capsule_is_not_in_front_of_its_end():
    """A run passing beneath the burr and ending beside it: a sample on the burr's flank is
    in front of the run's end by d alone, yet inside the run's capsule (share 0). The test on
    u (the sample beyond the end) is what keeps the front test from passing it."""
    run = (np.array([-3.0, 0.0, -1.0]), np.array([2.99, 0.0, 0.0]), R_MM)
    p, s1, s2 = patch_at(unit([-0.9, 0.0, 0.2]), 1.0)
    assert shares(p, s1, s2, [run]) == 0.0
    cand = candidates([run], float(np.linalg.norm(s1) + np.linalg.norm(s2)))
    assert not in_front(cand, 1, *p)
    cand[1, CAND_MU] = -np.inf
    assert in_front(cand, 1, *p)
