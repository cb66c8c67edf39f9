"""Exports of a carved bone: NRRD/NPY volumes, marching-cubes meshes and their files, brick
deltas for game engines."""

from __future__ import annotations

import io
import json
import math
import struct

import msgpack
import nrrd
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.proto.bricks import FORMAT, decode_delta, encode_delta
from burrforce.server.bench.accuracy import oblique_rotation
from burrforce.server.bone import (
    BoneEngine,
    BoneGrid,
    LoadOptions,
    ShaftParams,
    load_bone,
    phantom,
    save_bone,
    workpiece_block,
)
from burrforce.server.bone import export as export_module
from burrforce.server.bone.deltas import apply_delta, brick_delta, brick_remaining
from burrforce.server.bone.export import VOLUME_MEDIA_TYPES, write_volume
from burrforce.server.bone.mesh import (
    MESH_FORMATS,
    Mesh,
    empty_mesh,
    surface_mesh,
    write_obj,
    write_ply,
    write_stl,
)

RPM = 30_000.0
BLOCK_LO = (0.0, 0.0, -3.0)
BLOCK_HI = (7.0, 5.0, 0.0)
BLOCK_MM3 = 7.0 * 5.0 * 3.0


# -- helpers ---------------------------------------------------------------------------------
def small_block(direction=None, voxel_mm: float = 0.25) -> BoneGrid:
    """A 7 × 5 × 3 mm block whose faces fall inside voxels (partial volume)."""
    return workpiece_block(voxel_mm, lo_mm=BLOCK_LO, hi_mm=BLOCK_HI, margin_mm=1.0,
                           offset_voxels=(0.31, 0.17, 0.43), direction=direction)


def engine_for(grid: BoneGrid) -> BoneEngine:
    return BoneEngine(grid, shaft=ShaftParams(length_mm=0.0))


def carve_groove(grid: BoneGrid, start, end, n: int = 6, engine: BoneEngine | None = None):
    """Carve with the burr (R = 2 mm, axis +z) at ``n`` points from ``start`` to ``end``."""
    engine = engine or engine_for(grid)
    start, end = np.asarray(start, float), np.asarray(end, float)
    feed = (end - start) if np.any(end != start) else np.array([1.0, 0.0, 0.0])
    for t in np.linspace(0.0, 1.0, n):
        engine.step(start + t * (end - start), (0.0, 0.0, 1.0), feed, RPM)
    return engine


def carved_block(direction=None) -> BoneGrid:
    grid = small_block(direction)
    carve_groove(grid, (1.0, 2.5, 0.8), (6.0, 2.5, 0.8))
    assert grid.version > 0
    return grid


def edge_grid(shape=(21, 19, 13), spacing=0.25) -> BoneGrid:
    """A grid full of bone up to its edges, shape not a multiple of the brick."""
    density = np.full(shape, 255, dtype=np.uint8)
    density[0] = 100  # some partial values
    return BoneGrid(density, spacing, origin_mm=(1.0, -2.0, 0.5))


def directed_edges_ok(faces: np.ndarray) -> bool:
    """Closed and consistently wound: every directed edge occurs once, its reverse once."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = edges[:, 0].astype(np.int64) * (1 << 32) + edges[:, 1]
    rev = edges[:, 1].astype(np.int64) * (1 << 32) + edges[:, 0]
    return len(np.unique(key)) == len(key) and bool(np.isin(rev, key).all())


# -- volumes ---------------------------------------------------------------------------------
@pytest.mark.parametrize("compress", [True, False])
@pytest.mark.parametrize("oblique", [False, True])
def test_nrrd_remaining_round_trip_through_load_bone(tmp_path, compress, oblique):
    grid = carved_block(oblique_rotation() if oblique else None)
    path = tmp_path / "remaining.nrrd"
    with open(path, "wb") as f:
        write_volume(grid, f, "nrrd", "remaining", compress=compress)
    bone = load_bone(path, LoadOptions(kind="density"))
    back = bone.grid
    assert back.shape == grid.shape
    np.testing.assert_array_equal(back.density, grid.remaining_density())
    np.testing.assert_allclose(back.spacing_mm, grid.spacing_mm, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.origin_mm, grid.origin_mm, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.direction, grid.direction, rtol=0, atol=1e-12)
    assert not any("flipped" in note for note in bone.notes)
    header = nrrd.read_header(str(path))
    assert header["space"] == "left-posterior-superior"
    assert header["type"] == "uint8"
    assert header["encoding"] == ("gzip" if compress else "raw")
    np.testing.assert_allclose(header["space directions"],
                               (grid.direction * grid.spacing_mm).T, atol=1e-12)
    assert header["burrforce_bone_version"] == str(grid.version)
    assert header["burrforce_volume"] == "remaining"


def test_nrrd_anisotropic_grid_and_other_arrays(tmp_path):
    rng = np.random.default_rng(1)
    density = rng.integers(0, 256, size=(9, 14, 5), dtype=np.uint8)
    swept = rng.integers(0, 256, size=density.shape, dtype=np.uint8)
    grid = BoneGrid(density, (0.3, 0.2, 0.5), origin_mm=(-12.5, 3.25, 100.0),
                    direction=oblique_rotation(), swept=swept)
    for what, expected in (("swept", swept), ("density", density),
                           ("remaining", grid.remaining_density())):
        path = tmp_path / f"{what}.nrrd"
        with open(path, "wb") as f:
            write_volume(grid, f, "nrrd", what)
        back = load_bone(path, LoadOptions(kind="density")).grid
        np.testing.assert_array_equal(back.density, expected)
        np.testing.assert_allclose(back.spacing_mm, grid.spacing_mm, atol=1e-12)
        np.testing.assert_allclose(back.origin_mm, grid.origin_mm, atol=1e-12)
        np.testing.assert_allclose(back.direction, grid.direction, atol=1e-12)


def test_nrrd_labels_round_trip(tmp_path):
    grid = phantom("temporal", 0.5).grid
    path = tmp_path / "labels.nrrd"
    with open(path, "wb") as f:
        write_volume(grid, f, "nrrd", "labels")
    back = load_bone(path, LoadOptions(kind="labels")).grid
    np.testing.assert_allclose(back.origin_mm, grid.origin_mm, atol=1e-12)
    np.testing.assert_allclose(back.spacing_mm, grid.spacing_mm, atol=1e-12)
    # The loader renumbers label values through the materials file: the regions must survive.
    present = np.unique(grid.labels)
    assert present.tolist() == [0, 1, 2, 3]
    mapped = {}
    for value in present:
        values = np.unique(back.labels[grid.labels == value])
        assert len(values) == 1
        mapped[int(value)] = int(values[0])
    assert mapped[0] == 0 and len(set(mapped.values())) == len(mapped)
    np.testing.assert_array_equal(back.density, np.where(grid.labels > 0, 255, 0))


@pytest.mark.parametrize("what", ["remaining", "labels", "swept", "density"])
def test_npy_is_np_save_of_the_array(tmp_path, what):
    grid = carved_block()
    expected = {"remaining": grid.remaining_density(), "labels": grid.labels,
                "swept": grid.swept, "density": grid.density}[what]
    reference = io.BytesIO()
    np.save(reference, expected)
    path = tmp_path / f"{what}.npy"
    with open(path, "wb") as f:
        write_volume(grid, f, "npy", what)
    assert path.read_bytes() == reference.getvalue()
    loaded = np.load(path)
    assert loaded.dtype == np.uint8
    np.testing.assert_array_equal(loaded, expected)


class _Recorder(io.RawIOBase):
    """A write-only file that keeps only the largest single write and the total."""

    def __init__(self) -> None:
        self.largest = 0
        self.total = 0
        self.digest = io.BytesIO()

    def writable(self) -> bool:
        return True

    def write(self, b) -> int:
        n = len(b)
        self.largest = max(self.largest, n)
        self.total += n
        self.digest.write(bytes(b))
        return n


@pytest.mark.parametrize(("fmt", "compress"), [("nrrd", True), ("nrrd", False), ("npy", True)])
def test_volume_is_written_in_chunks(monkeypatch, fmt, compress):
    grid = edge_grid((37, 23, 11))
    carve_groove(grid, (1.0, -2.0, 3.0), (6.0, 2.0, 3.0))
    whole = io.BytesIO()
    write_volume(grid, whole, fmt, compress=compress)
    monkeypatch.setattr(export_module, "CHUNK_VOXELS", 600)  # a few slabs per chunk
    rec = _Recorder()
    write_volume(grid, rec, fmt, compress=compress)
    size = int(np.prod(grid.shape))
    assert rec.largest <= 2 * 600 + 1024  # header or a chunk, never the whole volume
    assert rec.largest < size // 4
    if compress and fmt == "nrrd":
        # Different chunking gives other deflate blocks: compare what the bytes decode to.
        head = export_module.nrrd_header(grid, "remaining", True)
        import zlib
        for raw in (whole.getvalue(), rec.digest.getvalue()):
            assert raw.startswith(head)
            data = zlib.decompress(raw[len(head):], zlib.MAX_WBITS | 16)
            np.testing.assert_array_equal(
                np.frombuffer(data, np.uint8).reshape(grid.shape[::-1]).T,
                grid.remaining_density())
    else:
        assert rec.digest.getvalue() == whole.getvalue()


def test_write_volume_rejects_unknown_format_and_array():
    grid = small_block()
    with pytest.raises(ValueError, match="format"):
        write_volume(grid, io.BytesIO(), "tiff")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="volume"):
        write_volume(grid, io.BytesIO(), "nrrd", "hu")  # type: ignore[arg-type]
    assert set(VOLUME_MEDIA_TYPES) == {"nrrd", "npy"}
    assert all(suffix.startswith(".") and "/" in media
               for media, suffix in VOLUME_MEDIA_TYPES.values())


# -- meshes ----------------------------------------------------------------------------------
@pytest.mark.parametrize("oblique", [False, True])
def test_block_mesh_is_closed_outward_and_encloses_the_bone(oblique):
    direction = oblique_rotation() if oblique else None
    grid = small_block(direction)
    mesh = surface_mesh(grid)
    assert mesh.vertices_mm.dtype == np.float32 and mesh.vertices_mm.shape[1] == 3
    assert mesh.faces.dtype == np.int32 and mesh.normals.dtype == np.float32
    assert directed_edges_ok(mesh.faces)
    # Positive signed volume: counter-clockwise seen from outside. Marching cubes rounds the
    # block's 12 edges off (≈ 1 % at 0.25 mm voxels).
    volume = mesh.volume_mm3()
    assert volume == pytest.approx(BLOCK_MM3, rel=0.02)
    # World frame: the mesh fills the block's box.
    np.testing.assert_allclose(mesh.vertices_mm.min(axis=0), BLOCK_LO, atol=0.15)
    np.testing.assert_allclose(mesh.vertices_mm.max(axis=0), BLOCK_HI, atol=0.15)
    # Vertex normals agree with the winding and point away from the block's centre.
    centre = 0.5 * (np.asarray(BLOCK_LO) + np.asarray(BLOCK_HI))
    outward = np.einsum("ij,ij->i", mesh.normals, mesh.vertices_mm - centre)
    assert (outward > 0).all()
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-5)
    top = mesh.vertices_mm[:, 2] > -0.01
    assert top.sum() > 100
    assert np.median(mesh.normals[top, 2]) > 0.99
    face_n = mesh.face_normals()
    centroids = mesh.vertices_mm[mesh.faces].mean(axis=1)
    assert (np.einsum("ij,ij->i", face_n, centroids - centre) > 0).mean() > 0.99


def test_sphere_mesh_anisotropic_voxels():
    spacing = np.array([0.2, 0.3, 0.25])
    shape = (60, 40, 50)
    centre = (np.asarray(shape) - 1) * spacing / 2
    idx = np.indices(shape, dtype=np.float64).transpose(1, 2, 3, 0) * spacing
    radius = 4.0
    # Partial volume by 4³ supersampling of each voxel.
    frac = np.zeros(shape)
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    for dx in sub:
        for dy in sub:
            for dz in sub:
                p = idx + np.array([dx, dy, dz]) * spacing - centre
                frac += np.linalg.norm(p, axis=-1) <= radius
    grid = BoneGrid.from_fraction(frac / 64, spacing, origin_mm=(10.0, 20.0, 30.0),
                                  direction=oblique_rotation())
    mesh = surface_mesh(grid)
    assert directed_edges_ok(mesh.faces)
    assert mesh.volume_mm3() == pytest.approx(4 / 3 * math.pi * radius ** 3, rel=0.01)
    world_centre = grid.to_world_point(centre)
    r = np.linalg.norm(mesh.vertices_mm - world_centre, axis=1)
    np.testing.assert_allclose(r, radius, atol=0.1)
    radial = (mesh.vertices_mm - world_centre) / r[:, None]
    assert np.einsum("ij,ij->i", radial, mesh.normals).min() > 0.95


def test_carved_groove_shows_in_the_mesh():
    grid = small_block()
    before = surface_mesh(grid).volume_mm3()
    carve_groove(grid, (1.0, 2.5, 0.8), (6.0, 2.5, 0.8))
    after = surface_mesh(grid)
    assert directed_edges_ok(after.faces)
    removed = before - after.volume_mm3()
    left = grid.bone_volume_by_label_mm3()[1]
    assert removed == pytest.approx(BLOCK_MM3 - left, rel=0.05)


@pytest.mark.parametrize("step", [2, 3])
def test_step_keeps_the_mesh_closed(step):
    grid = edge_grid()  # bone up to every edge of the grid: the padding must close it
    fine = surface_mesh(grid)
    coarse = surface_mesh(grid, step=step)
    assert directed_edges_ok(coarse.faces)
    assert 0 < coarse.n_faces < fine.n_faces
    assert coarse.volume_mm3() > 0


def test_labels_and_region_select_parts():
    density = np.zeros((30, 20, 20), dtype=np.uint8)
    labels = np.zeros_like(density)
    density[2:10, 2:10, 2:10] = 255
    labels[2:10, 2:10, 2:10] = 1
    density[15:27, 5:15, 5:15] = 255
    labels[15:27, 5:15, 5:15] = 2
    grid = BoneGrid(density, 0.5, origin_mm=(-1.0, 2.0, 3.0), labels=labels)
    both = surface_mesh(grid)
    only2 = surface_mesh(grid, labels=[2])
    assert directed_edges_ok(only2.faces)
    cube2 = 12 * 10 * 10 * 0.125
    # Binary voxels: marching cubes at 0.5 puts the faces on the voxel boundaries, minus
    # bevelled edges and corners.
    assert only2.volume_mm3() == pytest.approx(cube2, rel=0.1)
    assert both.volume_mm3() == pytest.approx(cube2 + 8 ** 3 * 0.125, rel=0.1)
    assert surface_mesh(grid, labels=[7]).n_faces == 0
    assert surface_mesh(grid, labels=[]).n_faces == 0
    np.testing.assert_array_equal(surface_mesh(grid, labels=np.array([2])).faces, only2.faces)
    # A region over the first half of cube 2 (x from voxel 15 to 20): capped, closed.
    lo = grid.voxel_centre_mm((15, 0, 0))
    hi = grid.voxel_centre_mm((20, 19, 19))
    half = surface_mesh(grid, region_mm=(lo, hi))
    assert directed_edges_ok(half.faces)
    assert half.vertices_mm[:, 0].min() >= lo[0] - 0.5 and half.vertices_mm[:, 0].max() <= \
        hi[0] + 0.5
    assert 0.3 * cube2 < half.volume_mm3() < 0.6 * cube2
    assert surface_mesh(grid, region_mm=((100, 100, 100), (101, 101, 101))).n_faces == 0


def test_empty_and_refused_meshes():
    empty = BoneGrid(np.zeros((5, 6, 7), dtype=np.uint8), 0.5)
    mesh = surface_mesh(empty)
    assert mesh.n_faces == 0 and mesh.vertices_mm.shape == (0, 3)
    assert mesh.faces.dtype == np.int32
    grid = small_block()
    for level in (0, 1, 1.5, -0.2, float("nan"), True, "0.5"):
        with pytest.raises(ValueError, match="level"):
            surface_mesh(grid, level=level)  # type: ignore[arg-type]
    for step in (0, -1, 1.5):
        with pytest.raises(ValueError, match="step"):
            surface_mesh(grid, step=step)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="labels"):
        surface_mesh(grid, labels=[300])
    with pytest.raises(ValueError, match="region_mm"):
        surface_mesh(grid, region_mm=((1, 1, 1), (0, 0, 0)))
    with pytest.raises(ValueError, match=r"step.*region_mm"):
        surface_mesh(grid, max_faces=100)


def test_mesh_level_moves_the_surface():
    grid = small_block()
    inner = surface_mesh(grid, level=0.9).volume_mm3()
    outer = surface_mesh(grid, level=0.1).volume_mm3()
    assert inner < surface_mesh(grid).volume_mm3() < outer


@pytest.fixture(scope="module")
def block_mesh() -> Mesh:
    grid = small_block(oblique_rotation())
    carve_groove(grid, (1.0, 2.5, 0.8), (6.0, 2.5, 0.8))
    return surface_mesh(grid, step=2)


def test_stl_reads_back(block_mesh):
    buf = io.BytesIO()
    write_stl(block_mesh, buf)
    data = buf.getvalue()
    assert not data.startswith(b"solid")  # would look like ASCII STL
    (count,) = struct.unpack_from("<I", data, 80)
    assert count == block_mesh.n_faces
    assert len(data) == 84 + 50 * count
    facet = np.dtype([("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")])
    assert facet.itemsize == 50
    rows = np.frombuffer(data, dtype=facet, offset=84)
    np.testing.assert_array_equal(rows["v"], block_mesh.vertices_mm[block_mesh.faces])
    v = rows["v"].astype(np.float64)
    cross = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    length = np.linalg.norm(cross, axis=1)
    ok = length > 1e-9
    np.testing.assert_allclose(rows["n"][ok], cross[ok] / length[ok, None], atol=1e-5)
    assert (rows["a"] == 0).all()


def test_ply_reads_back(block_mesh):
    buf = io.BytesIO()
    write_ply(block_mesh, buf)
    data = buf.getvalue()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[:2] == ["ply", "format binary_little_endian 1.0"]
    assert f"element vertex {block_mesh.n_vertices}" in header
    assert f"element face {block_mesh.n_faces}" in header
    assert [h.split()[-1] for h in header if h.startswith("property float")] == \
        ["x", "y", "z", "nx", "ny", "nz"]
    assert "property list uchar int vertex_indices" in header
    n, m = block_mesh.n_vertices, block_mesh.n_faces
    assert len(data) == end + 24 * n + 13 * m
    verts = np.frombuffer(data, dtype="<f4", count=6 * n, offset=end).reshape(n, 6)
    np.testing.assert_array_equal(verts[:, :3], block_mesh.vertices_mm)
    np.testing.assert_array_equal(verts[:, 3:], block_mesh.normals)
    faces = np.frombuffer(data, dtype=np.dtype([("c", "u1"), ("i", "<i4", (3,))]),
                          offset=end + 24 * n)
    assert (faces["c"] == 3).all()
    np.testing.assert_array_equal(faces["i"], block_mesh.faces)


def test_obj_reads_back(block_mesh):
    buf = io.BytesIO()
    write_obj(block_mesh, buf)
    lines = buf.getvalue().decode("ascii").splitlines()
    v = np.array([[float(x) for x in s.split()[1:]] for s in lines if s.startswith("v ")])
    vn = np.array([[float(x) for x in s.split()[1:]] for s in lines if s.startswith("vn ")])
    f = [s.split()[1:] for s in lines if s.startswith("f ")]
    np.testing.assert_array_equal(v.astype(np.float32), block_mesh.vertices_mm)
    np.testing.assert_allclose(vn, block_mesh.normals, atol=1e-5)
    pairs = np.array([[c.split("//") for c in face] for face in f], dtype=np.int64)
    np.testing.assert_array_equal(pairs[:, :, 0], pairs[:, :, 1])
    np.testing.assert_array_equal(pairs[:, :, 0] - 1, block_mesh.faces)


def test_writers_take_an_empty_mesh_and_are_registered():
    for name, (writer, media, suffix) in MESH_FORMATS.items():
        buf = io.BytesIO()
        writer(empty_mesh(), buf)
        assert suffix == "." + name and "/" in media
        assert buf.getvalue()
    buf = io.BytesIO()
    write_stl(empty_mesh(), buf)
    assert len(buf.getvalue()) == 84


# -- brick deltas ----------------------------------------------------------------------------
def test_delta_fields_and_wire_round_trip():
    grid = small_block()
    carve_groove(grid, (1.0, 2.5, 0.8), (6.0, 2.5, 0.8))
    d = brick_delta(grid, 0)
    assert d["format"] == FORMAT and d["format_version"] == 1
    assert d["bone_version"] == grid.version and d["since_version"] == 0
    assert d["complete"] is True and d["reload"] is False and d["next_since"] == grid.version
    assert d["brick"] == 8 and d["grid_shape"] == list(grid.shape)
    assert d["spacing_mm"] == grid.spacing_mm.tolist()
    assert d["origin_mm"] == grid.origin_mm.tolist()
    assert d["direction"] == grid.direction.reshape(-1).tolist()
    changed = grid.changed_bricks(0)
    assert d["count"] == d["changed"] == len(changed) > 0
    assert isinstance(d["bricks"], bytes) and len(d["bricks"]) == 12 * d["count"]
    assert isinstance(d["remaining"], bytes) and len(d["remaining"]) == 512 * d["count"]
    bricks = np.frombuffer(d["bricks"], "<i4").reshape(-1, 3)
    assert {tuple(b) for b in bricks.tolist()} == {tuple(b) for b in changed.tolist()}
    versions = grid.brick_version[tuple(bricks.T)]
    assert (np.diff(versions) >= 0).all()  # oldest change first
    wire = encode_delta(d)
    raw = msgpack.unpackb(wire, raw=False)
    assert isinstance(raw["remaining"], bytes)  # bin, not an array of ints
    back = decode_delta(wire)
    assert back["bricks"].dtype == np.int32 and back["bricks"].shape == (d["count"], 3)
    assert back["remaining"].shape == (d["count"], 8, 8, 8)
    np.testing.assert_array_equal(back["bricks"], bricks)
    a, b, c = (int(x) for x in bricks[0])
    np.testing.assert_array_equal(
        back["remaining"][0], grid.remaining_density()[8 * a:8 * a + 8, 8 * b:8 * b + 8,
                                                       8 * c:8 * c + 8])
    assert decode_delta(encode_delta(back))["remaining"].tobytes() == d["remaining"]
    # Nothing new since the current version.
    none = brick_delta(grid, grid.version)
    assert none["count"] == 0 and none["complete"] and none["next_since"] == grid.version


def test_delta_rejects_bad_versions_and_messages():
    grid = small_block()
    carve_groove(grid, (1.0, 2.5, 0.8), (2.0, 2.5, 0.8), n=2)
    for since, message in ((-1, "≥ 0"), (grid.version + 1, "newer than the bone"),
                           (True, "integer"), (1.5, "integer")):
        with pytest.raises(ValueError, match=message):
            brick_delta(grid, since)  # type: ignore[arg-type]
    for max_bricks in (0, 1 << 17, 2.0):
        with pytest.raises(ValueError, match="max_bricks"):
            brick_delta(grid, 0, max_bricks=max_bricks)  # type: ignore[arg-type]
    good = encode_delta(brick_delta(grid, 0))
    for bad in (b"", b"\xc1", msgpack.packb({"format": "other"}),
                msgpack.packb({**msgpack.unpackb(good), "format_version": 2}),
                msgpack.packb({**msgpack.unpackb(good), "count": 1000}), good[:-5]):
        with pytest.raises(ValueError):
            decode_delta(bad)


def test_partial_bricks_are_zero_padded():
    grid = edge_grid((21, 19, 13))
    carve_groove(grid, (6.0, 2.5, 3.5), (6.0, 2.5, 3.5), n=1)  # the far corner
    d = decode_delta(encode_delta(brick_delta(grid, 0)))
    corner = [i for i, b in enumerate(d["bricks"].tolist()) if b == [2, 2, 1]]
    assert corner, d["bricks"].tolist()
    block = d["remaining"][corner[0]]
    np.testing.assert_array_equal(block[5:], 0)  # voxels 21..23 lie past the grid
    np.testing.assert_array_equal(block[:, 3:], 0)
    np.testing.assert_array_equal(block[:, :, 5:], 0)
    np.testing.assert_array_equal(block[:5, :3, :5], grid.remaining_density()[16:, 16:, 8:])
    np.testing.assert_array_equal(brick_remaining(grid, np.array([[2, 2, 1]]))[0], block)


def test_delta_pages_never_skip_a_brick():
    grid = small_block()
    engine = engine_for(grid)
    carve_groove(grid, (1.0, 1.5, 0.8), (6.0, 1.5, 0.8), n=8, engine=engine)
    since = 2
    copy_at = None
    seen: list[tuple[int, int, int]] = []
    pages = 0
    while True:
        d = decode_delta(encode_delta(brick_delta(grid, since, max_bricks=5)))
        pages += 1
        assert d["count"] <= 5 and not d["reload"]
        assert d["next_since"] > since or d["complete"]
        seen += [tuple(b) for b in d["bricks"].tolist()]
        copy_at = d["next_since"]
        if d["complete"]:
            break
        since = d["next_since"]
    assert copy_at == grid.version and pages > 2
    assert sorted(seen) == sorted(tuple(b) for b in grid.changed_bricks(2).tolist())
    # A single tick changing more bricks than max_bricks cannot be paged: reload.
    d = brick_delta(grid, grid.version - 1, max_bricks=1)
    assert d["changed"] > 1
    assert d["reload"] and d["count"] == 0 and d["next_since"] is None and not d["complete"]
    assert apply_delta(np.zeros(grid.shape, np.uint8), decode_delta(encode_delta(d))) is None


@settings(max_examples=examples(25))
@given(
    first=st.lists(st.tuples(st.floats(0.0, 6.0), st.floats(-2.0, 3.0), st.floats(-1.0, 4.5)),
                   min_size=1, max_size=4),
    second=st.lists(st.tuples(st.floats(0.0, 6.0), st.floats(-2.0, 3.0), st.floats(-1.0, 4.5)),
                    min_size=1, max_size=6),
    max_bricks=st.integers(1, 40),
    wire=st.booleans(),
)
def test_delta_applied_to_an_old_copy_reproduces_the_bone(first, second, max_bricks, wire):
    grid = edge_grid((27, 22, 17))  # partial bricks on every far face
    engine = engine_for(grid)
    for point in first:
        engine.step(point, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), RPM)
    copy = grid.remaining_density()
    since = grid.version
    for point in second:
        engine.step(point, (0.3, 0.0, 1.0), (0.0, 1.0, 0.0), RPM)
    target = grid.remaining_density()
    for _ in range(100):
        d = brick_delta(grid, since, max_bricks=max_bricks)
        if wire:
            d = decode_delta(encode_delta(d))
        assert d["count"] <= max_bricks
        version = apply_delta(copy, d)
        if version is None:  # one tick changed more than max_bricks bricks
            assert d["reload"]
            copy = grid.remaining_density()
            since = grid.version
            continue
        assert version >= since
        since = version
        if d["complete"]:
            break
    else:
        pytest.fail("paging did not finish")
    assert since == grid.version
    np.testing.assert_array_equal(copy, target)


def test_original_density_plus_delta_since_zero_is_the_bone():
    grid = carved_block()
    copy = grid.density.copy()
    apply_delta(copy, brick_delta(grid, 0))
    np.testing.assert_array_equal(copy, grid.remaining_density())


# -- bone generations ------------------------------------------------------------------------
def _follow(grid: BoneGrid, copy: np.ndarray, since, generation, bone_generation: int,
            max_bricks: int = 4096):
    """A client bringing ``copy`` (of bone ``generation`` at ``since``) up to ``grid`` over
    the wire, every page: (copy, version, generation) it ends at."""
    for _ in range(100):
        d = decode_delta(encode_delta(brick_delta(grid, since, max_bricks, bone_generation,
                                                  generation)))
        assert d["generation"] == bone_generation
        if tuple(d["grid_shape"]) != copy.shape:
            assert d["full"]  # another grid is another bone
            copy = np.zeros(d["grid_shape"], np.uint8)
        since, generation = apply_delta(copy, d), d["generation"]
        assert since is not None, "no reload expected here"
        if d["complete"]:
            return copy, since, generation
    pytest.fail("paging did not finish")


@settings(max_examples=examples(15), deadline=None)
@given(old_cut=st.integers(2, 8), new_cut=st.integers(1, 12), max_bricks=st.integers(200, 600))
def test_a_copy_of_another_generation_is_answered_in_full(old_cut, new_cut, max_bricks):
    # The engine's copy is of the old bone at version v; the bone is replaced (versions restart
    # at 0) and carved elsewhere, possibly past v: "since v" would be a wrong delta.
    old = small_block()
    carve_groove(old, (1.0, 1.0, 0.8), (6.0, 1.0, 0.8), n=old_cut)
    copy, since = old.remaining_density(), old.version
    new = small_block()
    carve_groove(new, (1.0, 4.0, 0.5), (6.0, 4.0, 0.5), n=new_cut)
    copy, version, generation = _follow(new, copy, since, 7, 8, max_bricks)
    assert (version, generation) == (new.version, 8)
    np.testing.assert_array_equal(copy, new.remaining_density())
    # Then an ordinary delta of the new generation.
    engine = engine_for(new)
    engine.step((3.0, 2.0, 0.5), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), RPM)
    d = brick_delta(new, version, 4096, 8, generation)
    assert not d["full"] and d["since_version"] == version
    apply_delta(copy, d)
    np.testing.assert_array_equal(copy, new.remaining_density())


def test_full_answers_without_since_and_on_another_grid():
    grid = edge_grid((27, 22, 17))
    carve_groove(grid, (3.0, 2.5, 3.5), (4.0, 2.5, 3.5), n=3)
    d = brick_delta(grid, None, generation=5)
    assert d["full"] and d["since_version"] is None and d["complete"]
    with_bone = {tuple(b) for b in np.argwhere(export_module_bricks(grid)).tolist()}
    sent = {tuple(b) for b in np.frombuffer(d["bricks"], "<i4").reshape(-1, 3).tolist()}
    assert sent == with_bone
    # A copy of another bone with another shape: reallocated, then exact.
    copy, version, generation = _follow(grid, np.full((8, 8, 8), 200, np.uint8), 3, 4, 5)
    np.testing.assert_array_equal(copy, grid.remaining_density())
    assert (version, generation) == (grid.version, 5)
    # A generation the bone does not know (None) cannot vouch for a copy: full too.
    assert brick_delta(grid, 0, client_generation=5)["full"]
    # The same generation with a version the bone never had is still refused.
    with pytest.raises(ValueError, match="newer than the bone"):
        brick_delta(grid, grid.version + 1, generation=5, client_generation=5)
    # But another generation takes any version: it is of the other bone.
    assert brick_delta(grid, grid.version + 100, generation=5, client_generation=4)["full"]
    # Too many never-carved bricks for one page: reload, as for one tick too many.
    d = brick_delta(grid, None, max_bricks=1, generation=5)
    assert d["full"] and d["reload"] and d["count"] == 0 and d["next_since"] is None


def export_module_bricks(grid: BoneGrid) -> np.ndarray:
    """Bricks with any original density, the brute-force way."""
    from burrforce.server.bone.bricks import BRICK, brick_shape

    out = np.zeros(brick_shape(grid.shape), bool)
    for i, j, k in np.argwhere(grid.density > 0):
        out[i // BRICK, j // BRICK, k // BRICK] = True
    return out


def test_bricks_with_bone_matches_brute_force():
    from burrforce.server.bone.deltas import bricks_with_bone

    for grid in (edge_grid((21, 19, 13)), small_block(), edge_grid((8, 9, 1))):
        np.testing.assert_array_equal(bricks_with_bone(grid.density),
                                      export_module_bricks(grid))


def test_nrrd_and_bone_files_name_their_generation(tmp_path):
    bone = phantom("workpiece", 0.5)
    carve_groove(bone.grid, (1.0, 0.0, 1.5), (3.0, 0.0, 1.5), n=3)
    path = tmp_path / "v.nrrd"
    with open(path, "wb") as f:
        write_volume(bone.grid, f, "nrrd", generation=41)
    _, header = nrrd.read(str(path))
    assert header["burrforce_bone_generation"] == "41"
    assert header["burrforce_bone_version"] == str(bone.grid.version)
    assert b"generation" not in export_module.nrrd_header(bone.grid, "remaining", True)
    saved = save_bone(bone, tmp_path / "b", generation=41)
    with np.load(saved) as z:
        meta = json.loads(z["meta"].tobytes().decode())
    assert meta["generation"] == 41 and meta["bone_version"] == bone.grid.version > 0
    back = load_bone(saved)
    assert back.grid.version == bone.grid.version
