"""What this burr has already cut: its path, kept as capsules, for exact availability.

The voxels keep how much of each voxel has been swept, not where inside it. Where a burr goes
back over its own groove (retracing, reversing, re-entering) its surface lies on the groove's
wall, inside the voxels the first pass half swept, and the voxels alone cannot tell that the
bone in front of a patch is gone: the side patches that face the feed kept reporting spindle
power with nothing removed, ~10 % of the first pass's. The path answers it exactly: the bone a
spherical burr swept between two carving positions is the capsule around the segment joining
them, and a point of the burr's surface is in cut bone iff it lies inside one of them.

The path is a ring of segments (``SEG_*`` columns) in the grid frame, plus the open segment
being extended (``meta``). Consecutive carving positions closer than ``JOIN_RADII`` burr radii
are joined (the carve's per-tick spheres leave scallops under R/800 between them); a position
is stored once the burr moved ``DECIMATE_VOXELS`` of a voxel from the last, and a stored
segment grows while the points it absorbs stay within ``COLLINEAR_VOXELS`` of it, so a straight
stroke is one segment however long. What the ring forgets (it is full) or never saw (carving
from before the engine existed: a resumed session, a recording) is an *unknown box*: where the
burr's reach meets it, the voxels' availability still applies, multiplied by the path's.

Kernels take and fill preallocated arrays; ``BurrPath`` owns them.
"""

from __future__ import annotations

import math

import numpy as np

from ..hot_kernel import hot_inline, hot_kernel
from ..model.kernels import box_fraction

# Columns of a segment: start a (3), direction u = b − a (3), radius r, |u|² (in the ring;
# a candidate row holds 1/|u|² there instead, 0 for a point: ``history_share`` multiplies).
SEG_AX = 0
SEG_UX = 3
SEG_R = 6
SEG_L2 = 7
SEG_COLS = 8

# Row 0 of the candidate array is a header (the candidates follow, one per row): how many,
# the tick's availability mode and the burr's centre. One array keeps the samplers' argument
# lists short (numba inlines at most 30 arguments).
CAND_COUNT = 0
CAND_MODE = 1
CAND_CENTRE = 2  # [2:5] the burr's centre c this tick, grid frame, mm
# A candidate row holds the segment (``SEG_*`` columns), then its front test
# (``_front_bounds``): d = c − e, e = a + u its axis's end point, and the two bounds.
CAND_D = SEG_COLS  # [8:11] d, mm
CAND_KAPPA = SEG_COLS + 3  # a sample at p is in front if (p − c)·d > this, mm²
CAND_MU = SEG_COLS + 4  # ... and (p − c)·u ≥ this, mm²
CAND_COLS = SEG_COLS + 5

# The meta vector: the open segment, the run and the ring's bookkeeping (grid frame, mm).
M_OPEN = 0  # 1 while a run is open
M_A = 1  # [1:4] start of the open segment
M_E = 4  # [4:7] its end: the last stored position
M_LAST = 7  # [7:10] the last carving position (the tail e → last is swept too)
M_R = 10  # the open run's burr radius
M_DEV = 11  # deviation the open segment has absorbed so far, mm
M_HEAD = 12  # next ring slot to write
M_COUNT = 13  # segments in the ring
M_CARVED_PREV = 14  # 1 if the previous tick carved (a run continues only through carving ticks)
M_UNKNOWN = 15  # [15:21] unknown box (lo xyz, hi xyz); lo > hi: empty
N_META = 21

#: Ring capacity, segments. A straight stroke is one segment; a wandering hand a few per mm.
PATH_SEGMENTS = 4096
#: Candidate capsules one tick tests its samples against, at most; beyond, the tick falls back
#: to the voxels' availability for what it left out.
MAX_CANDIDATES = 64
#: Carving positions further apart than this many burr radii are not joined by a capsule.
JOIN_RADII = 0.1
#: A position is stored when the burr moved this share of the smallest voxel side.
DECIMATE_VOXELS = 0.25
#: A stored segment absorbs positions while its accumulated deviation stays below this share
#: of the smallest voxel side.
COLLINEAR_VOXELS = 0.005
#: A sample this close to a capsule's surface counts as outside it (mm): the burr standing
#: where it last carved must not find its own surface cut.
ON_SURFACE_MM = 1e-7
#: Slack of the front test (``_front_bounds``): relative, a share of the squared distance it
#: bounds; and absolute, this many rounding steps of the grid's coordinates: a sample is placed
#: on the burr's sphere to within those, however far the grid extends.
FRONT_SLACK = 1e-9
FRONT_ULPS = 64.0

#: Availability modes for a tick (``history_mode``).
HISTORY_OFF = 0  # no path: the voxels' availability alone
HISTORY_EXACT = 1  # the path knows every cut within reach: it replaces the voxels'
HISTORY_PARTIAL = 2  # some cuts within reach are unknown: voxels' × path's


@hot_inline
def history_share(cand, px, py, pz, s1x, s1y, s1z, s2x, s2y, s2z):
    """Share of a surface patch at p (grid frame, mm) outside every candidate capsule in
    ``cand`` (``history_candidates``), in [0, 1]. The patch is the rectangle spanned by its
    half-sides s1, s2 (mm, tangent to the surface); the signed distance to the capsules' union
    is linearized across it, so a capsule wall crossing the patch gives its exact share
    (``box_fraction``) and a wall the patch lies along (the burr in its own groove) gives 0 or
    1, never a half. Where ``history_candidates`` set front tests (``patch`` ≥ 0), p must lie
    on the burr's sphere it was given and the patch reach at most ``patch``."""
    # Divisions and square roots share one unit, which ~400 calls a tick keep busy: the
    # candidates carry 1/|u|², the patch's reach is taken only once p is inside a capsule,
    # and the nearest wall's normal g is kept unnormalized (|g| = g_len), the share being
    # scale-free.
    n = int(cand[0, CAND_COUNT])
    # The burr's front (most of a tick's samples in bone), by the bounds the tick set: two
    # dot products a capsule, where the test below takes about thirty operations.
    if in_front(cand, n, px, py, pz):
        return 1.0
    # Then, without a square root or a division: is the patch clear of every capsule (beside
    # the path's walls, where the front test's bounds fall short)? Capsule i leaves the patch whole
    # iff (q − r + ON)·q > |q·s1| + |q·s2| (q the offset from its axis; the test the loop
    # below ends on, for its nearest capsule), i.e. a = q² − |q·s1| − |q·s2| > (r − ON)·q,
    # squared. Clear of all, the nearest is clear too and the share is 1, as the loop finds.
    clear = True
    for i in range(n, 0, -1):
        qx, qy, qz = _offset_from_axis(cand, i, px, py, pz)
        a = (qx * qx + qy * qy + qz * qz - abs(qx * s1x + qy * s1y + qz * s1z)
             - abs(qx * s2x + qy * s2y + qz * s2z))
        rr = cand[i, 6] - ON_SURFACE_MM
        if not (a > 0.0 and (rr <= 0.0 or a * a > rr * rr * (qx * qx + qy * qy + qz * qz))):
            clear = False
            break
    if clear:
        return 1.0
    patch = -1.0
    best = math.inf
    gx = 0.0
    gy = 0.0
    gz = 0.0
    g_len = 1.0
    # Newest first (``history_candidates`` appends the open run last): the capsule the burr
    # just left is the nearest to its surface, and with its distance as ``best`` the older
    # ones are mostly dismissed before their square root.
    for i in range(n, 0, -1):
        qx, qy, qz = _offset_from_axis(cand, i, px, py, pz)
        q2 = qx * qx + qy * qy + qz * qz
        r = cand[i, 6]
        reach = r + best
        if reach > 0.0 and q2 >= reach * reach:
            continue  # farther than the nearest wall so far
        q = math.sqrt(q2)
        d = q - r
        if d < best:
            best = d
            if q > 0.0:
                gx = qx
                gy = qy
                gz = qz
                g_len = q
            if best + ON_SURFACE_MM <= 0.0:
                if patch < 0.0:
                    patch = (math.sqrt(s1x * s1x + s1y * s1y + s1z * s1z)
                             + math.sqrt(s2x * s2x + s2y * s2y + s2z * s2z))
                if best + ON_SURFACE_MM <= -patch:
                    return 0.0  # the whole patch is inside this capsule
    if best == math.inf:
        return 1.0
    half_a = abs(gx * s1x + gy * s1y + gz * s1z)
    half_b = abs(gx * s2x + gy * s2y + gz * s2z)
    return box_fraction((best + ON_SURFACE_MM) * g_len, half_a, half_b)


@hot_inline
def _segment_offset(cx, cy, cz, ax, ay, az, ux, uy, uz, inv_l2):
    """Offset of point c from its nearest point on the segment a → a + u, mm, given
    1/|u|² (0 for a point: a segment shorter than ~1e-150 mm, whose 1/|u|² would overflow)."""
    wx = cx - ax
    wy = cy - ay
    wz = cz - az
    t = min(max((wx * ux + wy * uy + wz * uz) * inv_l2, 0.0), 1.0)
    return wx - t * ux, wy - t * uy, wz - t * uz


@hot_inline
def _inverse_length2(l2):
    """1/|u|² as ``_segment_offset`` and the candidate rows take it."""
    return 1.0 / l2 if l2 > 1e-300 else 0.0


@hot_inline
def _offset_from_axis(cand, i, px, py, pz):
    """``_segment_offset`` of point p from candidate i's axis segment, mm."""
    return _segment_offset(px, py, pz, cand[i, 0], cand[i, 1], cand[i, 2], cand[i, 3],
                           cand[i, 4], cand[i, 5], cand[i, 7])


@hot_inline
def _segment_gap(cx, cy, cz, ax, ay, az, ux, uy, uz, l2):
    """Distance from point c to the segment a → a + u, mm."""
    qx, qy, qz = _segment_offset(cx, cy, cz, ax, ay, az, ux, uy, uz, _inverse_length2(l2))
    return math.sqrt(qx * qx + qy * qy + qz * qz)


@hot_inline
def _add_candidate(cand, n, ax, ay, az, bx, by, bz, r, cx, cy, cz, reach):
    """Append segment a → b (radius r) to ``cand`` (as row n + 1) if it comes within
    ``reach`` + r of c. Returns the new count, or −1 when ``cand`` is full."""
    ux = bx - ax
    uy = by - ay
    uz = bz - az
    inv_l2 = _inverse_length2(ux * ux + uy * uy + uz * uz)
    qx, qy, qz = _segment_offset(cx, cy, cz, ax, ay, az, ux, uy, uz, inv_l2)
    if qx * qx + qy * qy + qz * qz >= (reach + r) ** 2:
        return n
    if n + 1 >= cand.shape[0]:
        return -1
    row = n + 1
    cand[row, 0] = ax
    cand[row, 1] = ay
    cand[row, 2] = az
    cand[row, 3] = ux
    cand[row, 4] = uy
    cand[row, 5] = uz
    cand[row, 6] = r
    cand[row, 7] = inv_l2
    return n + 1


@hot_kernel
def history_candidates(ring, meta, cx, cy, cz, reach, radius, patch, cand):
    """Collect the capsules that can hold a point within ``reach`` mm of c (the burr's centre
    and radius plus a stencil's reach) into ``cand``, float64 (MAX_CANDIDATES + 1, CAND_COLS),
    with its header: the count, the tick's availability mode (``HISTORY_EXACT`` if the path
    knows every cut within reach, else ``HISTORY_PARTIAL``) and c; and each capsule's front
    test for samples on the burr's sphere (``radius``, mm) whose patches reach at most
    ``patch`` mm (|s1| + |s2|; < 0: no front test, ``history_share`` then takes any point)."""
    n = 0
    overflow = False
    count = int(meta[M_COUNT])
    for i in range(count):
        a0 = ring[i, 0]
        a1 = ring[i, 1]
        a2 = ring[i, 2]
        r = ring[i, 6]
        # Cheap reject on the segment's bounding box before the exact distance.
        u0 = ring[i, 3]
        u1 = ring[i, 4]
        u2 = ring[i, 5]
        grow = reach + r
        if (cx < min(a0, a0 + u0) - grow or cx > max(a0, a0 + u0) + grow
                or cy < min(a1, a1 + u1) - grow or cy > max(a1, a1 + u1) + grow
                or cz < min(a2, a2 + u2) - grow or cz > max(a2, a2 + u2) + grow):
            continue
        m = _add_candidate(cand, n, a0, a1, a2, a0 + u0, a1 + u1, a2 + u2, r, cx, cy, cz,
                           reach)
        if m < 0:
            overflow = True
            break
        n = m
    if meta[M_OPEN] != 0.0 and not overflow:
        r = meta[M_R]
        for s in range(2):
            first = M_A if s == 0 else M_E
            last = M_E if s == 0 else M_LAST
            m = _add_candidate(cand, n, meta[first], meta[first + 1], meta[first + 2],
                               meta[last], meta[last + 1], meta[last + 2], r, cx, cy, cz,
                               reach)
            if m < 0:
                overflow = True
                break
            n = m
    lo = M_UNKNOWN
    hi = M_UNKNOWN + 3
    unknown = (meta[lo] <= meta[hi] and cx + reach > meta[lo] and cx - reach < meta[hi]
               and cy + reach > meta[lo + 1] and cy - reach < meta[hi + 1]
               and cz + reach > meta[lo + 2] and cz - reach < meta[hi + 2])
    cand[0, CAND_COUNT] = n
    cand[0, CAND_MODE] = HISTORY_PARTIAL if unknown or overflow else HISTORY_EXACT
    cand[0, CAND_CENTRE] = cx
    cand[0, CAND_CENTRE + 1] = cy
    cand[0, CAND_CENTRE + 2] = cz
    for i in range(1, n + 1):
        _front_bounds(cand, i, cx, cy, cz, radius, patch)


@hot_inline
def in_front(cand, n, px, py, pz):
    """True if a sample at p (grid frame, mm) is in front of each of the ``n`` candidates in
    ``cand`` by the bounds ``history_candidates`` set for the tick (``_front_bounds``): its
    patch is then clear of all of them, as ``history_share``'s first pass would find."""
    vx = px - cand[0, CAND_CENTRE]
    vy = py - cand[0, CAND_CENTRE + 1]
    vz = pz - cand[0, CAND_CENTRE + 2]
    for i in range(n, 0, -1):
        if not (vx * cand[i, CAND_D] + vy * cand[i, CAND_D + 1] + vz * cand[i, CAND_D + 2]
                > cand[i, CAND_KAPPA]
                and vx * cand[i, SEG_UX] + vy * cand[i, SEG_UX + 1] + vz * cand[i, SEG_UX + 2]
                >= cand[i, CAND_MU]):
            return False
    return True


@hot_inline
def _front_bounds(cand, i, cx, cy, cz, radius, patch):
    """Bounds of candidate i's front test, for samples p on the sphere of ``radius`` mm about
    c with patches (s1, s2 tangent to it) that reach at most ``patch`` mm: a sample with
    (p − c)·d > κ and (p − c)·u ≥ μ is clear of the capsule by ``history_share``'s first pass,
    which then needs not run for it.

    With e = a + u the axis's end point and d = c − e, (p − c)·u ≥ μ puts p beyond e (the
    offset's parameter ≥ 1 + FRONT_SLACK, so it is clamped to 1: q = p − e = (p − c) + d).
    Then |q|² = R² + 2(p − c)·d + |d|², and as s1, s2 ⊥ p − c, |q·s1| + |q·s2| ≤ |d|·patch.
    The first pass's a = q² − |q·s1| − |q·s2| exceeds (r − ON)·|q| (and 0) once |q| > Q*, the
    root of Q² − (r − ON)·Q − |d|·patch: κ puts |q|² above Q*² by FRONT_SLACK of it and by
    FRONT_ULPS rounding steps of the coordinates times (R + |d|), which p's own rounding (off
    the sphere by a few of those steps) and either test's cannot cross: for a 2 mm burr near
    100 mm, ~4·10⁻⁹ and ~3·10⁻¹² mm² against ~10⁻¹³. A point capsule (1/|u|² = 0: its offset
    is from a) has e = a and no condition on u. ``patch`` < 0: κ = ∞, no sample is in front.
    """
    ux = cand[i, SEG_UX]
    uy = cand[i, SEG_UX + 1]
    uz = cand[i, SEG_UX + 2]
    segment = cand[i, SEG_L2] > 0.0
    dx = cx - cand[i, SEG_AX] - (ux if segment else 0.0)
    dy = cy - cand[i, SEG_AX + 1] - (uy if segment else 0.0)
    dz = cz - cand[i, SEG_AX + 2] - (uz if segment else 0.0)
    d2 = dx * dx + dy * dy + dz * dz
    kappa = math.inf
    if patch >= 0.0:
        d_len = math.sqrt(d2)
        d_patch = d_len * patch
        rr = cand[i, SEG_R] - ON_SURFACE_MM
        q_star = (0.5 * (rr + math.sqrt(rr * rr + 4.0 * d_patch)) if rr > 0.0
                  else math.sqrt(d_patch))
        coords = max(max(abs(cx), abs(cy)), max(abs(cz), radius))
        rounding = FRONT_ULPS * 2.3e-16 * coords * (radius + d_len)
        kappa = 0.5 * (q_star * q_star * (1.0 + FRONT_SLACK) - radius * radius - d2) + rounding
    mu = -math.inf
    if segment:
        mu = FRONT_SLACK * (ux * ux + uy * uy + uz * uz) - (dx * ux + dy * uy + dz * uz)
    cand[i, CAND_D] = dx
    cand[i, CAND_D + 1] = dy
    cand[i, CAND_D + 2] = dz
    cand[i, CAND_KAPPA] = kappa
    cand[i, CAND_MU] = mu


@hot_kernel
def _commit(ring, meta, ax, ay, az, bx, by, bz, r):
    """Store segment a → b in the ring; the segment it overwrites joins the unknown box."""
    head = int(meta[M_HEAD])
    count = int(meta[M_COUNT])
    size = ring.shape[0]
    if count == size:
        lo = M_UNKNOWN
        hi = M_UNKNOWN + 3
        old_r = ring[head, 6]
        for q in range(3):
            a = ring[head, q]
            b = a + ring[head, 3 + q]
            meta[lo + q] = min(meta[lo + q], min(a, b) - old_r)
            meta[hi + q] = max(meta[hi + q], max(a, b) + old_r)
    ring[head, 0] = ax
    ring[head, 1] = ay
    ring[head, 2] = az
    ring[head, 3] = bx - ax
    ring[head, 4] = by - ay
    ring[head, 5] = bz - az
    ring[head, 6] = r
    ring[head, 7] = (bx - ax) ** 2 + (by - ay) ** 2 + (bz - az) ** 2
    meta[M_HEAD] = (head + 1) % size
    meta[M_COUNT] = min(count + 1, size)


@hot_kernel
def _close_run(ring, meta):
    """Store the open run (its segment and tail) and close it."""
    if meta[M_OPEN] == 0.0:
        return
    r = meta[M_R]
    _commit(ring, meta, meta[M_A], meta[M_A + 1], meta[M_A + 2], meta[M_E], meta[M_E + 1],
            meta[M_E + 2], r)
    tail2 = ((meta[M_LAST] - meta[M_E]) ** 2 + (meta[M_LAST + 1] - meta[M_E + 1]) ** 2
             + (meta[M_LAST + 2] - meta[M_E + 2]) ** 2)
    if tail2 > 0.0:
        _commit(ring, meta, meta[M_E], meta[M_E + 1], meta[M_E + 2], meta[M_LAST],
                meta[M_LAST + 1], meta[M_LAST + 2], r)
    meta[M_OPEN] = 0.0


@hot_kernel
def history_record(ring, meta, cx, cy, cz, radius, carved, voxel_mm):
    """After a tick: extend the path with the burr's centre c (grid frame, mm) if the tick
    carved, else note the break. ``voxel_mm``: the smallest voxel side."""
    if not carved:
        meta[M_CARVED_PREV] = 0.0
        return
    last_x = meta[M_LAST]
    last_y = meta[M_LAST + 1]
    last_z = meta[M_LAST + 2]
    step = math.sqrt((cx - last_x) ** 2 + (cy - last_y) ** 2 + (cz - last_z) ** 2)
    joined = (meta[M_OPEN] != 0.0 and meta[M_CARVED_PREV] != 0.0 and meta[M_R] == radius
              and step <= JOIN_RADII * radius)
    meta[M_CARVED_PREV] = 1.0
    if not joined:
        _close_run(ring, meta)
        for q in range(3):
            c = cx if q == 0 else (cy if q == 1 else cz)
            meta[M_A + q] = c
            meta[M_E + q] = c
            meta[M_LAST + q] = c
        meta[M_R] = radius
        meta[M_DEV] = 0.0
        meta[M_OPEN] = 1.0
        return
    meta[M_LAST] = cx
    meta[M_LAST + 1] = cy
    meta[M_LAST + 2] = cz
    ex = meta[M_E]
    ey = meta[M_E + 1]
    ez = meta[M_E + 2]
    if (cx - ex) ** 2 + (cy - ey) ** 2 + (cz - ez) ** 2 < (DECIMATE_VOXELS * voxel_mm) ** 2:
        return
    # Would the open segment a → e stretched to a → c still pass within tolerance of e?
    ax = meta[M_A]
    ay = meta[M_A + 1]
    az = meta[M_A + 2]
    ux = cx - ax
    uy = cy - ay
    uz = cz - az
    l2 = ux * ux + uy * uy + uz * uz
    dev = _segment_gap(ex, ey, ez, ax, ay, az, ux, uy, uz, l2)
    if meta[M_DEV] + dev <= COLLINEAR_VOXELS * voxel_mm:
        meta[M_DEV] += dev
    else:
        _commit(ring, meta, ax, ay, az, ex, ey, ez, meta[M_R])
        meta[M_A] = ex
        meta[M_A + 1] = ey
        meta[M_A + 2] = ez
        meta[M_DEV] = 0.0
    meta[M_E] = cx
    meta[M_E + 1] = cy
    meta[M_E + 2] = cz


class BurrPath:
    """The path one engine's burr has carved along (grid frame): the ring, the open run and
    the unknown box, plus the per-tick candidate buffer. Owned by ``BoneEngine``.

    Args:
        bounds_mm: (lo (3,), hi (3,)) of the grid, grid frame: the unknown box when the bone
            already holds cuts the path never saw.
        carved_before: the bone has swept voxels already.
    """

    def __init__(self, bounds_mm: tuple[np.ndarray, np.ndarray], carved_before: bool,
                 segments: int = PATH_SEGMENTS) -> None:
        self.ring = np.zeros((segments, SEG_COLS))
        self.meta = np.zeros(N_META)
        self.candidates = np.zeros((MAX_CANDIDATES + 1, CAND_COLS))
        self._bounds = (np.asarray(bounds_mm[0], dtype=np.float64),
                        np.asarray(bounds_mm[1], dtype=np.float64))
        self.clear(carved_before)

    def clear(self, carved_before: bool) -> None:
        """Forget the path. ``carved_before``: the bone holds cuts it cannot describe (the
        whole grid becomes the unknown box)."""
        self.meta[:] = 0.0
        lo, hi = self._bounds
        if carved_before:
            self.meta[M_UNKNOWN:M_UNKNOWN + 3] = lo
            self.meta[M_UNKNOWN + 3:M_UNKNOWN + 6] = hi
        else:
            self.meta[M_UNKNOWN:M_UNKNOWN + 3] = np.inf
            self.meta[M_UNKNOWN + 3:M_UNKNOWN + 6] = -np.inf

    def break_run(self) -> None:
        """The burr jumped (a teleport, a stream restart): the next carving position does not
        continue the last."""
        self.meta[M_CARVED_PREV] = 0.0

    @property
    def segments(self) -> int:
        """Segments stored in the ring (the open run not counted)."""
        return int(self.meta[M_COUNT])

    def state(self) -> dict:
        """The path as JSON-able data (a recording's snapshot: a replay must see the same
        availability). The unknown box is null when empty."""
        meta = self.meta.tolist()
        empty = self.meta[M_UNKNOWN] > self.meta[M_UNKNOWN + 3]
        box = None if empty else meta[M_UNKNOWN:M_UNKNOWN + 6]
        return {"meta": meta[:M_UNKNOWN], "unknown": box,
                "ring": self.ring[:self.segments].tolist()}

    def restore(self, state: dict) -> None:
        """Undo :meth:`state` (ValueError if it does not fit this path)."""
        meta = np.asarray(state["meta"], dtype=np.float64)
        ring = np.asarray(state["ring"], dtype=np.float64).reshape(-1, SEG_COLS)
        if meta.shape != (M_UNKNOWN,) or len(ring) > len(self.ring) \
                or int(meta[M_COUNT]) != len(ring) or not np.isfinite(ring).all():
            raise ValueError("the burr path's state does not fit this engine")
        self.clear(carved_before=state["unknown"] is not None)
        if state["unknown"] is not None:
            self.meta[M_UNKNOWN:M_UNKNOWN + 6] = np.asarray(state["unknown"], dtype=np.float64)
        self.meta[:M_UNKNOWN] = meta
        self.ring[:len(ring)] = ring
