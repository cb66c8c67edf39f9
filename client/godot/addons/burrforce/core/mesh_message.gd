# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# One mesh-chunk message (proto/MESH.md section 3), parsed strictly: bad magic or version,
# a count larger than the bytes left, an index out of range or trailing bytes make the
# whole message an error (nothing of it is applied).
#
# Chunk arrays come back as the engine's own packed arrays, ready for an ArrayMesh:
# positions and normals PoolVector3Array / PackedVector3Array (float32, as sent), materials
# bytes, triangles PoolIntArray / PackedInt32Array. They are made natively: the little-endian
# f32 and u32 runs of the message are exactly the payload of Godot's own binary
# serialization of those array types (a type id and a count before them), which
# Marshalls.base64_to_variant decodes in both versions; a per-element loop in GDScript would
# take seconds for a whole bone.

const C = preload("compat.gd")

const MAGIC = "42464d43"
const FORMAT_VERSION = 1
const HEADER_BYTES = 40
const FLAG_MORE = 1
const FLAG_FULL = 2
const FLAG_CW = 4
const FLAG_SESSION_FRAME = 8


# Godot's Variant type ids in binary serialization (Godot 3 / Godot 4).
static func _type_id(kind: String) -> int:
	if C.major() >= 4:
		return {"vec3": 36, "int32": 30}[kind]
	return {"vec3": 25, "int32": 21}[kind]


# bytes b[from, from + count·width) as a packed array of kind.
static func _packed(b, from: int, count: int, kind: String, width: int):
	var w = StreamPeerBuffer.new()
	w.big_endian = false
	w.put_u32(_type_id(kind))
	w.put_u32(count)
	if count > 0:
		w.put_data(C.slice(b, from, from + count * width))
	var v = Marshalls.base64_to_variant(Marshalls.raw_to_base64(w.data_array))
	if typeof(v) != _type_id(kind):
		return null  # an engine whose serialization differs: refuse rather than misread
	return v


# Returns {"ok": true, "flags", "more", "full", "cw", "session_frame", "session",
# "chunk_cells", "bone_version", "since", "next_cursor", "chunks": [chunk…]} with each chunk
# {"index": [a, b, c], "key": "a,b,c", "vertex_count", "triangle_count", "positions",
# "normals", "materials", "triangles"}; or {"ok": false, "reason": text}.
static func parse(data) -> Dictionary:
	var n = data.size()
	if n < HEADER_BYTES:
		return _bad("%d bytes, shorter than the header" % n)
	if C.slice(data, 0, 4).hex_encode() != MAGIC:
		return _bad("bad magic")
	var r = StreamPeerBuffer.new()
	r.big_endian = false
	r.data_array = data
	r.seek(4)
	var version = r.get_u16()
	if version != FORMAT_VERSION:
		return _bad("format version %d" % version)
	var flags = r.get_u16()
	var out = {"ok": true, "flags": flags, "more": (flags & FLAG_MORE) != 0,
		"full": (flags & FLAG_FULL) != 0, "cw": (flags & FLAG_CW) != 0,
		"session_frame": (flags & FLAG_SESSION_FRAME) != 0}
	out["session"] = r.get_u32()
	out["chunk_cells"] = r.get_u32()
	out["bone_version"] = r.get_u64()
	out["since"] = r.get_u64()
	out["next_cursor"] = r.get_u32()
	var count = r.get_u32()
	if out["bone_version"] < 0 or out["since"] < 0:
		return _bad("version beyond 2^63")
	# Each chunk takes at least 20 bytes: a count beyond that is a lie, refused before looping.
	if count > (n - HEADER_BYTES) / 20:
		return _bad("%d chunks cannot fit %d bytes" % [count, n - HEADER_BYTES])
	var pos = HEADER_BYTES
	var chunks = []
	for ci in range(count):
		if n - pos < 20:
			return _bad("chunk %d: truncated header" % ci)
		r.seek(pos)
		var a = r.get_32()
		var b = r.get_32()
		var c = r.get_32()
		var v = r.get_u32()
		var t = r.get_u32()
		var pad = (4 - (25 * v) % 4) % 4
		var size = 20 + 25 * v + pad + 12 * t
		if size > n - pos:
			return _bad("chunk %d: %d vertices and %d triangles overrun the message" % [ci, v, t])
		if v > 0 and t == 0:
			return _bad("chunk %d: %d vertices and no triangles" % [ci, v])
		var p0 = pos + 20
		var n0 = p0 + 12 * v
		var m0 = n0 + 12 * v
		var t0 = m0 + v + pad
		var tris = _packed(data, t0, 3 * t, "int32", 4)
		if typeof(tris) == TYPE_NIL or tris.size() != 3 * t:
			return _bad("chunk %d: triangles unreadable" % ci)
		# Every index must name a vertex of this chunk (u32 read as i32: negative = too big).
		for x in tris:
			if x < 0 or x >= v:
				return _bad("chunk %d: vertex index %d out of 0..%d" % [ci, x, v - 1])
		var positions = _packed(data, p0, v, "vec3", 12)
		var normals = _packed(data, n0, v, "vec3", 12)
		if typeof(positions) == TYPE_NIL or typeof(normals) == TYPE_NIL or positions.size() != v \
				or normals.size() != v:
			return _bad("chunk %d: vertices unreadable" % ci)
		chunks.append({"index": [a, b, c], "key": "%d,%d,%d" % [a, b, c], "vertex_count": v,
			"triangle_count": t, "positions": positions, "normals": normals,
			"materials": C.slice(data, m0, m0 + v), "triangles": tris})
		pos += size
	if pos != n:
		return _bad("%d trailing bytes" % (n - pos))
	out["chunks"] = chunks
	return out


static func _bad(reason: String) -> Dictionary:
	return {"ok": false, "reason": reason}
