"""The carved bone as mesh chunks (proto/MESH.md): the union of the chunks is the full
export's surface in every frame and winding, seams agree, updates after a cut converge to a
fresh copy, the binary format round-trips and rejects damage, and the REST and WebSocket
endpoints serve it from a real uvicorn."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples
from test_bone_export import carve_groove, engine_for, small_block
from test_rest_client import live_server

from burrforce.client.mesh import ChunkedMesh, sync_rest, watch
from burrforce.client.rest import BurrRest, RestError
from burrforce.client.udp import BurrClient
from burrforce.proto import frames
from burrforce.proto.mesh_chunks import (
    CHUNK_HEAD,
    FLAG_CW,
    FLAG_FULL,
    FLAG_SESSION_FRAME,
    GENERATION,
    HEADER,
    MeshMessage,
    decode,
    encode,
)
from burrforce.server.api.mesh_pages import MAX_BYTES_MIN, MeshRequest, mesh_page
from burrforce.server.bench.accuracy import oblique_rotation
from burrforce.server.bone.chunks import chunk_cells, chunks_of_bricks, mesh_chunk
from burrforce.server.bone.mesh import surface_mesh


def _union(m: ChunkedMesh) -> tuple[np.ndarray, np.ndarray]:
    positions, _, _, triangles = m.arrays()
    return positions.astype(np.float64), triangles


def _server_frame(positions: np.ndarray, triangles: np.ndarray, req: MeshRequest):
    """Delivered chunks → server frame, mm, counter-clockwise outward."""
    if req.session_frame:
        tf = frames.Transform(frames.frame(req.frame_name), req.placement_position,
                              req.placement_orientation)
        positions = np.array([tf.point_in(tuple(p)) for p in positions])
        reflected = not frames.frame(req.frame_name).right_handed
    else:
        reflected = False
    if req.cw != reflected:
        triangles = triangles[:, ::-1]
    return positions, triangles


def _weld(positions: np.ndarray, triangles: np.ndarray, tol: float = 1e-4):
    key = np.round(positions / tol).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return inverse.reshape(-1)[triangles], inverse.reshape(-1), first


def _closed(faces: np.ndarray) -> bool:
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    directed = np.unique(edges, axis=0)
    return len(directed) == len(edges) and bool(
        (np.unique(edges[:, ::-1], axis=0) == directed).all())


def _volume(positions: np.ndarray, triangles: np.ndarray) -> float:
    v = positions - positions.mean(axis=0)
    a, b, c = v[triangles[:, 0]], v[triangles[:, 1]], v[triangles[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _copy(grid, req: MeshRequest, since=None, max_bytes=64 << 20) -> ChunkedMesh:
    m = ChunkedMesh()
    m.have = since
    cursor = 0
    while True:
        page = decode(encode(mesh_page(grid, req, since, cursor, max_bytes)))
        m.apply(page)
        if not page.more:
            return m
        cursor = page.next_cursor


@pytest.fixture(scope="module")
def carved():
    grid = small_block(voxel_mm=0.2)
    grid.labels[:, :, grid.shape[2] // 2:] = 2  # two materials, to see them per vertex
    carve_groove(grid, (1.0, 2.5, 0.8), (6.0, 2.5, 0.8))
    return grid


@pytest.mark.parametrize("frame", ["si_mm", "unity", "unreal", "godot"])
@pytest.mark.parametrize("cw", [False, True])
def test_union_is_the_full_surface_in_every_frame_and_winding(carved, frame, cw):
    req = MeshRequest(1, 1, True, cw, frame, (0.01, -0.02, 0.03), (0.0, 0.0, 0.0, 1.0))
    m = _copy(carved, req)
    full = surface_mesh(carved)
    positions, triangles = _server_frame(*_union(m), req)
    assert len(triangles) == full.n_faces
    welded, _, _ = _weld(positions, triangles)
    assert _closed(welded), "the chunks' union is not closed and consistently wound"
    assert _volume(positions, triangles) == pytest.approx(full.volume_mm3(), rel=1e-6)
    assert len(m.chunks) > 8


def test_seams_agree_in_position_normal_and_material(carved):
    req = MeshRequest(1, 1, False)
    m = _copy(carved, req)
    positions, normals, materials, triangles = m.arrays()
    _, inverse, first = _weld(positions.astype(np.float64), triangles)
    # Every copy of a welded vertex (one per chunk it lies on) has the first copy's values.
    assert len(first) < len(positions), "no vertex lies on a seam"
    assert np.abs(normals - normals[first][inverse]).max() < 1e-5
    assert (materials == materials[first][inverse]).all()
    assert set(np.unique(materials).tolist()) == {1, 2}


def test_normals_point_out_of_the_bone(carved):
    m = _copy(carved, MeshRequest(1, 2, False))
    positions, normals, _, triangles = m.arrays()
    p = positions.astype(np.float64)
    a, b, c = (p[triangles[:, k]] for k in range(3))
    face = np.cross(b - a, c - a)
    face /= np.linalg.norm(face, axis=1, keepdims=True)
    agree = np.einsum("ij,ij->i", face, normals[triangles[:, 0]].astype(np.float64))
    assert np.median(agree) > 0.95 and (agree > 0.0).mean() > 0.99
    assert np.abs(np.linalg.norm(normals, axis=1) - 1.0).max() < 1e-5


def test_oblique_grid_keeps_the_union_closed():
    grid = small_block(oblique_rotation(), voxel_mm=0.25)
    req = MeshRequest(1, 2, False)
    positions, triangles = _server_frame(*_union(_copy(grid, req)), req)
    welded, _, _ = _weld(positions, triangles)
    assert _closed(welded)
    assert _volume(positions, triangles) == pytest.approx(surface_mesh(grid).volume_mm3(),
                                                          rel=1e-6)


def test_updates_after_cuts_converge_to_a_fresh_copy():
    grid = small_block(voxel_mm=0.2)
    req = MeshRequest(1, 1, True, True, "unity")
    m = _copy(grid, req)
    assert m.have == 0 and m.replaced == 0
    engine = engine_for(grid)
    for y in (1.5, 2.5, 3.5):
        before = grid.version
        carve_groove(grid, (1.0, y, 0.8), (3.0 + y, y, 0.8), engine=engine)
        assert grid.version > before
        page = mesh_page(grid, req, m.have)
        assert not page.flags & FLAG_FULL and page.since == before
        # Only what changed (a chunk with no surface is 20 bytes: "remove it if you have it").
        assert 0 < sum(not c.empty for c in page.chunks) < len(m.chunks)
        m.apply(decode(encode(page)))
        assert m.have == grid.version
    fresh = _copy(grid, req)
    assert m.replaced > 0
    assert m.chunks.keys() == fresh.chunks.keys()
    for k, c in fresh.chunks.items():
        assert np.array_equal(m.chunks[k].positions, c.positions)
        assert np.array_equal(m.chunks[k].triangles, c.triangles)


def test_a_chunk_cut_away_is_sent_empty_and_removed():
    grid = small_block(voxel_mm=0.25)
    req = MeshRequest(1, 1, False)
    m = _copy(grid, req)
    count = len(m.chunks)
    # Cut everything away (as carving does: swept = 255, stamped with a new version).
    grid.swept[:] = 255
    grid.version += 1
    grid.brick_version[grid.brick_bone > 0] = grid.version
    grid.recount()
    page = mesh_page(grid, req, m.have)
    assert len(page.chunks) >= count and all(c.empty for c in page.chunks)
    m.apply(page)
    assert not m.chunks and m.have == grid.version


def test_paging_covers_every_chunk_once(carved):
    req = MeshRequest(1, 1, False)
    whole = mesh_page(carved, req, None, 0, 64 << 20)
    cursor, seen, pages = 0, [], 0
    while True:
        page = mesh_page(carved, req, None, cursor, MAX_BYTES_MIN)
        assert bool(page.flags & FLAG_FULL) == (cursor == 0)
        seen += [c.index for c in page.chunks]
        pages += 1
        if not page.more:
            break
        cursor = page.next_cursor
    assert pages > 1
    assert seen == [c.index for c in whole.chunks]


def test_since_newer_than_the_bone_gets_everything(carved):
    page = mesh_page(carved, MeshRequest(1, 1, False), carved.version + 5)
    assert page.flags & FLAG_FULL and page.since == 0


def test_dirty_chunks_of_a_brick():
    cells = chunk_cells(1)  # 8: brick b touches chunks b and b + 1
    got = chunks_of_bricks(np.array([[0, 0, 0]]), cells, (3, 3, 3))
    assert got.tolist() == [[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    top = chunks_of_bricks(np.array([[2, 2, 2]]), cells, (3, 3, 3))
    assert top.tolist() == [[2, 2, 2]]  # clipped to the chunk grid
    with pytest.raises(ValueError, match="chunk_bricks"):
        chunk_cells(9)


def test_chunk_without_surface_is_empty(carved):
    deep = mesh_chunk(carved, (50, 50, 50), 8)
    assert deep.triangles.shape == (0, 3)


def test_header_and_flags(carved):
    req = MeshRequest(7, 2, True, True, "godot")
    b = encode(mesh_page(carved, req, None))
    magic, version, flags, session, cells, bone_version, since, _, count = \
        HEADER.unpack_from(b)
    assert (magic, version, session, cells, bone_version) == (b"BFMC", 1, 7, 16,
                                                               carved.version)
    assert flags == FLAG_FULL | FLAG_CW | FLAG_SESSION_FRAME and since == 0 and count > 0


def test_version_2_carries_the_generation_after_version_1s_header(carved):
    req = MeshRequest(7, 2, False)
    v1 = encode(mesh_page(carved, req, None))
    v2 = encode(mesh_page(carved, req, None, generation=(1 << 63) + 5))
    assert HEADER.unpack_from(v1)[1] == 1 and HEADER.unpack_from(v2)[1] == 2
    assert len(v2) == len(v1) + 8
    assert v2[:4] + v2[6:40] == v1[:4] + v1[6:40] and v2[48:] == v1[40:]
    assert GENERATION.unpack_from(v2, 40) == ((1 << 63) + 5,)
    back = decode(v2)
    assert back.generation == (1 << 63) + 5 and back.format_version == 2
    assert decode(v1).generation is None
    assert [c.index for c in back.chunks] == [c.index for c in decode(v1).chunks]


def test_a_copy_of_another_generation_starts_over():
    old = small_block(voxel_mm=0.25)
    carve_groove(old, (1.0, 1.5, 0.8), (6.0, 1.5, 0.8))
    req = MeshRequest(1, 1, False)
    m = ChunkedMesh()
    m.apply(decode(encode(mesh_page(old, req, None, 0, 64 << 20, generation=3))))
    assert (m.have, m.generation) == (old.version, 3)
    new = small_block(voxel_mm=0.25)  # the bone replaced: versions restart at 0
    carve_groove(new, (1.0, 3.5, 0.8), (6.0, 3.5, 0.8), n=20)
    assert new.version > m.have
    # A server answers a copy of generation 3 in full (routes_mesh turns it into since=None).
    page = decode(encode(mesh_page(new, req, None, 0, 64 << 20, generation=4)))
    assert page.full
    m.apply(page)
    fresh = _copy(new, req)
    assert (m.have, m.generation) == (new.version, 4)
    assert m.chunks.keys() == fresh.chunks.keys()
    # Changes of another bone without FULL (a bone replaced under a version 1 style request)
    # leave a copy that cannot be trusted: the next update asks for everything.
    stale = ChunkedMesh()
    stale.apply(decode(encode(mesh_page(old, req, None, 0, 64 << 20, generation=3))))
    stale.apply(decode(encode(mesh_page(new, req, stale.have, 0, 64 << 20, generation=4))))
    assert stale.have is None and stale.generation is None
    # Pages of one update from two bones: the same.
    split = ChunkedMesh()
    first = mesh_page(new, req, None, 0, MAX_BYTES_MIN, generation=4)
    assert first.more
    split.apply(decode(encode(first)))
    split.apply(decode(encode(mesh_page(new, req, None, first.next_cursor, 64 << 20,
                                        generation=5))))
    assert split.have is None and split.generation is None


@settings(max_examples=examples(60), deadline=None)
@given(cut=st.integers(0, 10_000), flip=st.integers(0, 10_000), value=st.integers(0, 255))
def test_decode_rejects_damage_and_never_crashes(carved, cut, flip, value):
    data = encode(mesh_page(carved, MeshRequest(1, 1, False), None, 0, MAX_BYTES_MIN,
                            generation=cut))
    truncated = data[:cut % len(data)]
    with pytest.raises(ValueError):
        decode(truncated)
    damaged = bytearray(data)
    damaged[flip % len(data)] = value
    try:
        decode(bytes(damaged))
    except ValueError:
        pass


def test_decode_checks_indices_and_counts():
    m = MeshMessage(1, 8, 0, 0, 0)
    with pytest.raises(ValueError, match="magic"):
        decode(b"XXXX" + bytes(36))
    with pytest.raises(ValueError, match="format_version"):
        decode(HEADER.pack(b"BFMC", 3, 0, 1, 8, 0, 0, 0, 0))
    with pytest.raises(ValueError, match="version 2 mesh-chunk message is at least 48"):
        decode(HEADER.pack(b"BFMC", 2, 0, 1, 8, 0, 0, 0, 0) + bytes(7))
    with pytest.raises(ValueError, match="after the last chunk"):
        decode(encode(m) + b"\0")
    bad = HEADER.pack(b"BFMC", 1, 0, 1, 8, 0, 0, 0, 1) + CHUNK_HEAD.pack(0, 0, 0, 1, 1) \
        + bytes(25) + bytes(3) + np.array([0, 0, 1], "<u4").tobytes()
    with pytest.raises(ValueError, match="past its 1 vertices"):
        decode(bad)
    lonely = HEADER.pack(b"BFMC", 1, 0, 1, 8, 0, 0, 0, 1) + CHUNK_HEAD.pack(0, 0, 0, 1, 0) \
        + bytes(25) + bytes(3)
    with pytest.raises(ValueError, match="no triangles"):
        decode(lonely)
    huge = HEADER.pack(b"BFMC", 1, 0, 1, 8, 0, 0, 0, 1) + CHUNK_HEAD.pack(0, 0, 0, 1 << 30, 0)
    with pytest.raises(ValueError, match="more than the bytes left"):
        decode(huge)


# -- a real uvicorn ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """A live server (uvicorn, hot loop) with a session of its own in the Unreal frame."""
    with live_server(tmp_path_factory.mktemp("mesh")) as server:
        api = BurrRest(server.url, server.token)
        s = api.create_session("phantom:workpiece", voxel_mm=0.2,
                               parameters={"frame": "unreal"})
        yield server, api, s
        api.close()


def _cut(server, s, y_mm: float) -> int:
    """A short groove over UDP (unreal frame: cm, y mirrored); returns the last bone
    version."""
    host, port = server.udp
    version = 0
    with BurrClient(host, port, s["id"], s["key"], timeout_s=1.0) as c:
        for i in range(300):
            x_cm = (3.0 + 0.01 * i) / 10.0
            r = c.exchange((x_cm, -y_mm / 10.0, 0.17), rpm=60_000.0)
            version = r.reply.bone_version
    return version


def test_rest_pages_and_errors(live):
    server, api, s = live
    m = ChunkedMesh()
    pages = sync_rest(api, s["id"], m, winding="cw", max_bytes=MAX_BYTES_MIN)
    assert pages > 1 and m.have == 0 and m.chunks
    version = _cut(server, s, 0.0)
    assert version > 0
    before = {k: c.positions.copy() for k, c in m.chunks.items()}
    sync_rest(api, s["id"], m, winding="cw")
    assert m.have >= 1 and m.replaced > 0
    assert any(k not in before or len(before[k]) != len(c.positions)
               for k, c in m.chunks.items())
    for bad in ({"chunk_bricks": 0}, {"winding": "left"}, {"frame": "unity"},
                {"max_bytes": 10}, {"since": -1}):
        with pytest.raises(RestError) as err:
            api.mesh_chunks(s["id"], **bad)
        assert err.value.status == 422
    with pytest.raises(RestError) as err:
        api.mesh_chunks(999)
    assert err.value.status == 404
    unauthorized = BurrRest(server.url, "wrong")
    with pytest.raises(RestError) as err:
        unauthorized.mesh_chunks(s["id"])
    assert err.value.status == 401


def test_websocket_pushes_each_cut(live):
    server, api, s = live
    m = ChunkedMesh()
    stream = watch(server.url, server.token, s["id"], winding="cw", interval_ms=10)
    try:
        while not m.apply(next(stream)):
            pass
        start = m.have
        version = _cut(server, s, 3.0)
        deadline = time.monotonic() + 20.0
        while m.have < version:
            assert time.monotonic() < deadline, "the push channel fell behind"
            m.apply(next(stream))
    finally:
        stream.close()
    assert m.have >= version > start
    rest_copy = ChunkedMesh()
    sync_rest(api, s["id"], rest_copy, winding="cw")
    assert rest_copy.chunks.keys() == m.chunks.keys()


def test_websocket_refuses_a_wrong_token_and_session(live):
    from websockets.exceptions import ConnectionClosed

    server, _, s = live
    for token, session, query, code, says in (
            ("wrong", s["id"], {}, 4401, "token"),
            (server.token, 999, {}, 4404, "no session 999"),
            (server.token, s["id"], {"chunk_bricks": 9}, 4422, "chunk_bricks must be in 1..8"),
            (server.token, s["id"], {"winding": "left"}, 4422, "winding must be one of"),
            (server.token, s["id"], {"interval_ms": "soon"}, 4422, "must be an integer"),
            # A digit int() refuses (it was a crash of the handler, not a 4422).
            (server.token, "%C2%B2", {}, 4422, "session id must be an integer")):
        with pytest.raises(ConnectionClosed) as err:
            next(watch(server.url, token, session, **query))
        assert err.value.rcvd.code == code and says in err.value.rcvd.reason


def test_websocket_starts_over_when_the_placement_moves(live):
    server, api, s = live
    stream = watch(server.url, server.token, s["id"], interval_ms=10)
    try:
        first = next(stream)
        assert first.full
        while first.more:
            first = next(stream)
        api.set_parameters(s["id"], placement_position=[1.0, 0.0, 0.0])  # cm (unreal)
        moved = next(stream)
        assert moved.full and moved.chunks
        before = {c.index: c for c in _rest_chunks(api, s["id"])}
    finally:
        stream.close()
        api.set_parameters(s["id"], placement_position=[0.0, 0.0, 0.0])
    c = moved.chunks[0]
    assert np.allclose(c.positions, before[c.index].positions, atol=1e-5)


def _rest_chunks(api, session):
    m = ChunkedMesh()
    sync_rest(api, session, m)
    return list(m.chunks.values())


def test_placement_beyond_a_poses_reach_is_refused(live):
    _, api, s = live
    with pytest.raises(RestError) as err:
        api.set_parameters(s["id"], placement_position=[1e10, 0.0, 0.0])
    assert err.value.status == 422 and "placement_position" in str(err.value)


def _full_sync(api, session: int, m: ChunkedMesh) -> list:
    """sync_rest, returning the decoded pages too (to see FULL)."""
    pages = []
    original = api.mesh_chunks

    def spy(*args, **kwargs):
        data = original(*args, **kwargs)
        pages.append(decode(data))
        return data
    api.mesh_chunks = spy
    try:
        sync_rest(api, session, m, winding="cw")
    finally:
        del api.mesh_chunks
    return pages


def test_rest_and_websocket_start_over_after_a_reset_and_a_load(live):
    server, api, s = live
    sid = s["id"]
    m = ChunkedMesh()
    _full_sync(api, sid, m)
    generation = api.session(sid)["bone"]["generation"]
    assert m.generation == generation and m.have is not None
    _cut(server, s, -3.0)
    _full_sync(api, sid, m)
    old = (m.generation, m.have)
    assert old[1] > 0
    for replace in (lambda: api.reset(sid),
                    lambda: api.load_bone(sid, "library:block.bone.npz")):
        replace()
        bone = api.session(sid)["bone"]
        assert bone["generation"] not in (None, old[0])
        _cut(server, s, 2.0)  # the new bone past the old copy's version, or not
        # The old pair asked for by hand: FULL, and the new generation in the header.
        page = decode(api.mesh_chunks(sid, since=old[1], generation=old[0],
                                      format_version=2))
        assert page.full and page.generation == bone["generation"]
        pages = _full_sync(api, sid, m)
        assert pages[0].full and m.generation == bone["generation"]
        fresh = ChunkedMesh()
        sync_rest(api, sid, fresh, winding="cw")
        assert m.chunks.keys() == fresh.chunks.keys() and m.have == fresh.have
        # The WebSocket, reopened with the old pair, starts over too.
        stream = watch(server.url, server.token, sid, since=old[1], generation=old[0],
                       winding="cw")
        try:
            first = next(stream)
        finally:
            stream.close()
        assert first.full and first.generation == bone["generation"]
        old = (m.generation, m.have)
    # Version 1 clients are served as before (no generation in the header).
    v1 = decode(api.mesh_chunks(sid))
    assert v1.generation is None and v1.full
    for bad in ({"format_version": 3}, {"generation": -1}):
        with pytest.raises(RestError) as err:
            api.mesh_chunks(sid, **bad)
        assert err.value.status == 422


def test_websocket_sends_the_new_generation_when_the_bone_is_replaced(live):
    server, api, s = live
    sid = s["id"]
    stream = watch(server.url, server.token, sid, interval_ms=10)
    try:
        first = next(stream)
        while first.more:
            first = next(stream)
        before = api.session(sid)["bone"]["generation"]
        assert first.generation == before
        api.reset(sid)
        after = api.session(sid)["bone"]["generation"]
        assert after != before
        deadline = time.monotonic() + 20.0
        while True:
            assert time.monotonic() < deadline, "no update for the new bone"
            m = next(stream)
            if m.generation == after:
                break
            assert m.generation == before
        assert m.full
    finally:
        stream.close()
