"""Brick deltas: the bone that changed since bone version N, for a game engine's own copy.

Format reference ("burrforce-bricks", format_version 1)
=======================================================

A game engine keeps its own copy of the bone's *remaining density* — uint8, one byte per
voxel, 0 (empty) to 255 (all bone), array shape (nx, ny, nz) — to draw it (e.g. by marching
cubes at 127.5) and keeps it current by asking for the 8³-voxel bricks changed since the bone
version its copy is at. The bone version is a counter the server bumps on every tick that
removed bone; each brick remembers the version that last changed it.

Getting started
---------------
Ask without ``since_version`` (``brick_delta(grid, None)``): a *full* answer, every brick
that holds bone, on a copy set to 0. Or fetch the whole remaining volume
(``write_volume(grid, f, "npy" | "nrrd")``; a NRRD file carries ``burrforce_bone_version:=N``
and ``burrforce_bone_generation:=G``, and an HTTP layer should report the version it read
*before* writing) and continue from that version, or start from the bone's original density
at version 0: an untouched brick's remaining density equals its original density, so the
original file plus ``brick_delta(grid, 0)`` reproduces the current bone.

Generations: when the bone is replaced, start over
--------------------------------------------------
Bone versions restart at 0 whenever a session's bone is replaced (a new load, a reset, a
restore of a snapshot), so a version alone does not say which bone a copy is of. The server
numbers each bone it loads with a *generation* (``server/api/generation.py``: never repeated
while its data directory lives) and sends it in every message (``generation``). A client
keeps (generation, version) and asks with both (``generation=G&since=N`` over REST). When G
is not the bone's generation any more the server ignores N and answers in full (``full``
true): the client sets its whole copy to 0, reallocated to ``grid_shape`` if that changed
(another bone may have another grid), applies the bricks, and from then on keeps the
message's ``generation``. A client that does not send its generation gets what it did before
generations existed (and a 422 when N is newer than the bone, its only hint of a new bone).

The message
-----------
One msgpack map (``burrforce.proto.bricks.encode_delta``) with string keys; numbers are
msgpack ints, float64 and booleans, byte strings are msgpack ``bin``. Readers ignore keys
they do not know (``generation`` and ``full`` came later, within format version 1):

=================  ============  ==========================================================
key                type          meaning
=================  ============  ==========================================================
``format``         str           ``"burrforce-bricks"``
``format_version`` int           1
``generation``     int or nil    the bone's generation (nil: the server does not know it)
``full``           bool          the client's copy is not of this bone, or it asked without
                                 ``since_version``: set the copy to 0 (of ``grid_shape``)
                                 before applying; every brick with bone follows (paged)
``bone_version``   int           the bone's version when the delta was made
``since_version``  int or nil    the version asked for (nil: not given)
``next_since``     int or nil    the version the client's copy is at once this delta is
                                 applied: ask for ``since_version = next_since`` next time.
                                 nil together with ``reload``.
``complete``       bool          every changed brick is in this message (then
                                 ``next_since == bone_version``)
``reload``         bool          too many bricks changed in a single tick to page them:
                                 fetch the whole volume again (``count`` is 0)
``changed``        int           bricks changed since ``since_version`` in all
``brick``          int           brick edge, voxels (8)
``grid_shape``     [int×3]       nx, ny, nz: voxels along the grid's axes i, j, k
``spacing_mm``     [float×3]     voxel size along i, j, k, mm
``origin_mm``      [float×3]     world position of voxel (0, 0, 0)'s centre, mm
``direction``      [float×9]     3×3 rotation, row-major; its columns are the grid's i, j, k
                                 axes in the world (LPS for loaded scans): voxel (i, j, k)'s
                                 centre is ``origin + D @ (i·sx, j·sy, k·sz)``
``count``          int           bricks in this message, c (≤ max_bricks)
``bricks``         bin (12·c)    brick indices (a, b, c) as int32 little-endian, c rows of
                                 3, sorted by the version that last changed each brick,
                                 then in C order of (a, b, c)
``remaining``      bin (512·c)   per brick, in the same order, its 8×8×8 remaining
                                 densities (uint8) in C order: index ``x·64 + y·8 + z`` is
                                 voxel (8a + x, 8b + y, 8c + z); voxels past the grid's edge
                                 (partial bricks at the far faces) are 0
=================  ============  ==========================================================

Applying it
-----------
For each brick ``n`` with index (a, b, c): copy ``remaining[512n:512n+512]`` viewed as
8×8×8 into ``volume[8a:8a+8, 8b:8b+8, 8c:8c+8]``, clipped to the grid (:func:`apply_delta`
does exactly that). Bricks hold absolute values, not differences, so applying a brick twice,
or a brick older than the copy's version, is harmless. Labels never change while carving and
are not sent; neither is the swept fraction.

Paging (why no brick can be skipped)
------------------------------------
At most ``max_bricks`` bricks are sent. When more changed, the bricks are ordered by the
version that last changed them and cut only *between* versions: every brick changed in
(since, next_since] is in the message, none of the later ones is, and ``complete`` is false.
After applying it the client's copy is right for every brick whose last change is at or
before ``next_since``; it asks again with ``since_version = next_since`` (at once, since more
is waiting) and gets every brick changed after that, including any changed again meanwhile.
One version is never split across messages, so if a single tick changed more than
``max_bricks`` bricks (a burr far larger than usual, or a tiny ``max_bricks``) no safe cut
exists: the reply has ``reload`` true, no bricks, and the client fetches the whole volume.
A full answer pages the same way (its bricks by the version that last changed them, the
never-carved ones at version 0 first; the pages after the first are ordinary deltas of the
new generation), so a bone with more than ``max_bricks`` never-carved bricks holding bone
gets ``reload``: fetch the whole volume (its generation and version come with it).

Concurrency
-----------
The delta reads ``grid.version`` first, then only bricks stamped at or before it. A tick
running meanwhile stamps the bricks it changes with a later version, so a brick read in the
middle of a change is sent again next time: the copy converges. For a copy that matches one
exact version, take the bone's lock (or pause ticks) while making the delta.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ...proto.bricks import BRICK_VOXELS, FORMAT, FORMAT_VERSION
from .bricks import BRICK
from .export import remaining_of
from .grid import BoneGrid

#: The largest ``max_bricks`` accepted: 65 536 bricks are a 32 MB message.
MAX_BRICKS_LIMIT = 1 << 16
assert BRICK ** 3 == BRICK_VOXELS, "the wire format's brick is the grid's brick"


def brick_delta(grid: BoneGrid, since_version: int | None, max_bricks: int = 4096,
                generation: int | None = None,
                client_generation: int | None = None) -> dict[str, Any]:
    """The bricks whose bone changed after ``since_version``, as a plain dict; every brick
    with bone (``full``) when the client has no copy of this bone.

    Parameters
    ----------
    grid : BoneGrid
        The bone (read, never written).
    since_version : int or None
        The bone version the client's copy is at, 0..``grid.version``; None: the client has
        no copy (a full answer).
    max_bricks : int
        The most bricks to send (1..65 536; 512 bytes of densities each). When more
        changed, the delta holds the oldest changes and ``complete`` is False (see the
        module's "Paging").
    generation : int or None
        The bone's generation (the server's; None: unknown), sent back in the message.
    client_generation : int or None
        The generation the client's copy is of (None: the client did not say, and
        ``since_version`` is trusted to be of this bone). When it is not ``generation`` the
        copy is of another bone: a full answer, whatever ``since_version`` is.

    Returns
    -------
    dict
        The fields of the module's format table. ``bricks`` (12·count bytes, int32 LE) and
        ``remaining`` (512·count bytes, uint8) are ``bytes``; everything else is a Python
        int, float, bool, str, None or list, ready for ``proto.bricks.encode_delta`` or JSON.

    Raises
    ------
    ValueError
        ``since_version`` not None or an integer in 0..``grid.version`` (newer is accepted
        when the answer is full anyway), or ``max_bricks`` not in 1..65 536.
    """
    bone_version = int(grid.version)  # before the stamps: see "Concurrency"
    full = since_version is None or (client_generation is not None
                                     and client_generation != generation)
    since = None if since_version is None else _since(since_version)
    if not full and since > bone_version:
        raise ValueError(f"since_version {since} is newer than the bone (version "
                         f"{bone_version}): the bone was reloaded or reset, or the version "
                         "belongs to another bone; pass the generation your copy is of, or "
                         "ask without since_version for every brick")
    if isinstance(max_bricks, bool) or not isinstance(max_bricks, (int, np.integer)) \
            or not 1 <= int(max_bricks) <= MAX_BRICKS_LIMIT:
        raise ValueError(f"max_bricks must be an integer in 1..{MAX_BRICKS_LIMIT}, got "
                         f"{max_bricks!r}")
    max_bricks = int(max_bricks)
    versions = grid.brick_version.copy()  # one snapshot: a tick may stamp bricks meanwhile
    if full:
        # Bricks that never held bone are 0 in the client's cleared copy already.
        changed = bricks_with_bone(grid.density) & (versions <= bone_version)
    else:
        changed = (versions > since) & (versions <= bone_version)
    index = np.argwhere(changed)  # C order
    order = np.argsort(versions[changed], kind="stable")  # by version, then C order
    index = index[order]
    stamped = versions[changed][order]
    total = len(index)
    complete = total <= max_bricks
    reload = False
    next_since: int | None = bone_version
    if not complete:
        first_left_out = stamped[max_bricks]
        keep = int(np.searchsorted(stamped, first_left_out, side="left"))
        if keep == 0:  # the oldest version alone is too many: no safe cut
            reload, next_since = True, None
        else:
            next_since = int(first_left_out) - 1
        index = index[:keep]
    index = index.astype(np.int32)
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "generation": None if generation is None else int(generation),
        "full": full,
        "bone_version": bone_version,
        "since_version": since,
        "next_since": next_since,
        "complete": complete,
        "reload": reload,
        "changed": total,
        "brick": BRICK,
        "grid_shape": [int(n) for n in grid.shape],
        "spacing_mm": [float(x) for x in grid.spacing_mm],
        "origin_mm": [float(x) for x in grid.origin_mm],
        "direction": [float(x) for x in grid.direction.reshape(-1)],
        "count": len(index),
        "bricks": index.astype("<i4").tobytes(),
        "remaining": brick_remaining(grid, index).tobytes(),
    }


def _since(since_version: object) -> int:
    if isinstance(since_version, bool) or not isinstance(since_version, (int, np.integer)):
        raise ValueError(f"since_version must be an integer bone version, got "
                         f"{since_version!r}")
    if since_version < 0:
        raise ValueError(f"since_version must be ≥ 0 (bone versions start at 0), got "
                         f"{since_version}")
    return int(since_version)


def bricks_with_bone(density: np.ndarray) -> np.ndarray:
    """bool, brick shape: the bricks with any voxel of original density > 0 (only those can
    hold bone, since carving only removes it)."""
    m = density
    for axis, n in enumerate(density.shape):
        m = np.maximum.reduceat(m, np.arange(0, n, BRICK), axis=axis)
    return m > 0


def _brick_voxels(shape: tuple[int, int, int], index: np.ndarray):
    """Per brick and axis, its 8 voxel indices clipped into the grid, and which are inside:
    three (c, 8) int64 arrays and three (c, 8) bool arrays."""
    offsets = np.arange(BRICK)
    axes, inside = [], []
    for a in range(3):
        voxel = index[:, a].astype(np.int64)[:, None] * BRICK + offsets
        inside.append(voxel < shape[a])
        axes.append(np.minimum(voxel, shape[a] - 1))
    return axes, inside


def brick_remaining(grid: BoneGrid, index: np.ndarray) -> np.ndarray:
    """The remaining density of bricks ``index`` ((c, 3) ints): uint8 (c, 8, 8, 8), 0 past
    the grid's edge."""
    index = np.asarray(index).reshape(-1, 3)
    (i, j, k), (in_i, in_j, in_k) = _brick_voxels(grid.shape, index)
    at = (i[:, :, None, None], j[:, None, :, None], k[:, None, None, :])
    out = remaining_of(grid.density[at], grid.swept[at])
    out[~(in_i[:, :, None, None] & in_j[:, None, :, None] & in_k[:, None, None, :])] = 0
    return out


def apply_delta(volume: np.ndarray, d: dict[str, Any]) -> int | None:
    """Write a decoded delta's bricks into a client's copy of the remaining density.

    Parameters
    ----------
    volume : np.ndarray
        uint8 (nx, ny, nz) remaining density, C-contiguous, updated in place (set to 0
        first when ``d["full"]``; reallocate it to ``grid_shape`` before if that changed).
    d : dict
        From ``proto.bricks.decode_delta`` (or :func:`brick_delta`: byte fields are accepted too).

    Returns
    -------
    int or None
        The version the copy is at now (``d["next_since"]``); None when ``d["reload"]``:
        the whole volume must be fetched again.

    Raises
    ------
    ValueError
        ``volume`` is not a C-contiguous uint8 array of the delta's ``grid_shape``, or a brick
        lies outside it.
    """
    shape = tuple(int(n) for n in d["grid_shape"])
    if not isinstance(volume, np.ndarray) or volume.dtype != np.uint8 \
            or volume.shape != shape or not volume.flags.c_contiguous:
        raise ValueError(f"volume must be a C-contiguous uint8 array of shape {shape}")
    bricks, remaining = d["bricks"], d["remaining"]
    if isinstance(bricks, bytes):
        bricks = np.frombuffer(bricks, dtype="<i4").reshape(-1, 3)
    if isinstance(remaining, bytes):
        remaining = np.frombuffer(remaining, dtype=np.uint8)
    remaining = np.asarray(remaining).reshape(-1, BRICK, BRICK, BRICK)
    if len(bricks) != len(remaining):
        raise ValueError("bricks and remaining disagree in count")
    if d.get("full"):
        volume[...] = 0  # a copy of another bone, or none: nothing of it may survive
    if len(bricks):
        limit = -(-np.asarray(shape) // BRICK)
        if (bricks < 0).any() or (bricks >= limit).any():
            raise ValueError(f"a brick index lies outside the brick grid {limit.tolist()}")
        (i, j, k), (in_i, in_j, in_k) = _brick_voxels(shape, bricks)
        inside = in_i[:, :, None, None] & in_j[:, None, :, None] & in_k[:, None, None, :]
        flat = (i[:, :, None, None] * shape[1] + j[:, None, :, None]) * shape[2] \
            + k[:, None, None, :]
        volume.reshape(-1)[flat[inside]] = remaining[inside]
    return None if d.get("reload") else int(d["next_since"])
