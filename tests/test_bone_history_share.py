"""The path's share of a surface patch (``history.history_share``) against the geometry it
stands for: the share of a small patch outside a union of capsules, found by sampling the
patch densely. Its answer of exactly 1 where the patch lies wholly outside every capsule comes
from a test without square roots (the burr's front, most samples in bone); everywhere else
from the nearest capsule's wall, linearized across the patch."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from burrforce.server.bone.history import (
    CAND_COUNT,
    CAND_MODE,
    HISTORY_EXACT,
    SEG_COLS,
    history_share,
)

R_MM = 2.0
#: Half-sides of the patch, mm: a 1152-element burr's sub-element on R = 2 mm is ~0.07 mm.
HALF_MM = 0.03
GRID = 41


def candidates(capsules: list[tuple[np.ndarray, np.ndarray, float]]) -> np.ndarray:
    """The candidate array ``history_candidates`` fills: header, then a → a + u, r, 1/|u|²."""
    cand = np.zeros((len(capsules) + 1, SEG_COLS))
    cand[0, CAND_COUNT] = len(capsules)
    cand[0, CAND_MODE] = HISTORY_EXACT
    for n, (a, u, r) in enumerate(capsules, start=1):
        l2 = float(u @ u)
        cand[n, :3] = a
        cand[n, 3:6] = u
        cand[n, 6] = r
        cand[n, 7] = 1.0 / l2 if l2 > 1e-300 else 0.0
    return cand


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


@st.composite
def patch_near_capsules(draw):
    """A burr surface patch at p (half-sides s1, s2 tangent to the burr's sphere) and one to
    three capsules of the burr's radius, their ends within a few patch sizes of the burr's
    surface, as a groove's path is."""
    centre = np.zeros(3)
    n = np.array([draw(st.floats(-1, 1)) for _ in range(3)])
    if np.linalg.norm(n) < 0.1:
        n = np.array([0.0, 0.0, 1.0])
    normal = unit(n)
    p = centre + R_MM * normal
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = unit(np.cross(normal, helper))
    t2 = np.cross(normal, t1)
    s1 = HALF_MM * t1
    s2 = draw(st.floats(0.2, 1.0)) * HALF_MM * t2
    capsules = []
    for _ in range(draw(st.integers(1, 3))):
        # The burr's earlier positions: its centre moved back by up to a quarter radius.
        back = np.array([draw(st.floats(-0.5, 0.5)) for _ in range(3)])
        end = centre + back
        length = draw(st.floats(0.0, 1.0))
        direction = np.array([draw(st.floats(-1, 1)) for _ in range(3)])
        u = length * unit(direction) if np.linalg.norm(direction) > 0.1 else np.zeros(3)
        capsules.append((end - u, u, R_MM))
    return p, s1, s2, capsules


@settings(max_examples=300, deadline=None)
@given(patch_near_capsules())
def test_the_share_is_the_patch_outside_the_path(case):
    p, s1, s2, capsules = case
    share = history_share(candidates(capsules), *p, *s1, *s2)
    assert 0.0 <= share <= 1.0
    u, v = np.meshgrid(np.linspace(-1, 1, GRID), np.linspace(-1, 1, GRID))
    points = p + u.reshape(-1, 1) * s1 + v.reshape(-1, 1) * s2
    gaps = gap_mm(points, capsules)
    # The walls curve over the patch by ~|s|²/2r (a few 1e-4 mm): a sliver of that width is
    # all the linearization can misplace, plus the sampling's step.
    bend = (HALF_MM * 2) ** 2 / R_MM
    walls = [c for c in capsules if gap_mm(points, [c]).min() <= bend]
    if len(walls) <= 1:  # where two walls cross the patch, only the nearer is linearized
        outside = float(np.mean(gaps > 0.0))
        sliver = np.mean(np.abs(gaps) < bend)
        assert abs(share - outside) <= sliver + 2.5 / GRID
    if gaps.min() > bend:
        assert share == 1.0  # wholly outside: exactly 1, as the burr's front must read
    if gaps.max() < -bend:
        assert share == 0.0


def test_a_burr_standing_where_it_last_carved_finds_its_surface_uncut():
    """The patch lies on the capsule's wall (the burr at its last position): outside."""
    normal = unit([0.3, -0.2, 0.9])
    p = R_MM * normal
    helper = unit(np.cross(normal, [1.0, 0.0, 0.0]))
    s1 = HALF_MM * helper
    s2 = HALF_MM * np.cross(normal, helper)
    stroke = (np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), R_MM)
    assert history_share(candidates([stroke]), *p, *s1, *s2) == 1.0
    # Moved back into its own groove by 10 µm: the patch is now inside the stroke's capsule.
    inside = p - 0.01 * normal
    assert history_share(candidates([stroke]), *inside, *s1, *s2) == 0.0


def test_no_capsule_leaves_the_whole_patch():
    s = HALF_MM * np.eye(3)
    assert history_share(candidates([]), 0.0, 0.0, R_MM, *s[0], *s[1]) == 1.0
