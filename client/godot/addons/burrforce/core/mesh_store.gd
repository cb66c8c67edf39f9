# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# A chunked copy of the bone's surface kept current (proto/MESH.md section 4): a map from chunk
# index to its mesh, and `have`, the bone version the copy is complete at. Apply messages in
# the order they came; the store follows FULL (drop everything first), MORE (an update spans
# pages) and sets have to the lowest bone_version of an update's messages once its last
# page is in. Not thread-safe: apply and read from one thread (the engine layer swaps the
# drawn meshes on the main thread).

const MeshMessage = preload("mesh_message.gd")

var chunks = {}  # "a,b,c" -> chunk Dictionary (mesh_message.gd)
var have = -1  # -1: unset (nothing held yet: ask without since)
var session = -1
var chunk_cells = 0
var cw = false
var session_frame = true
var updates = 0  # completed updates
var replaced = 0  # chunks that replaced one held
var added = 0
var removed = 0
var changed_keys = {}  # keys touched since the last take_changed()
var _low = -1  # lowest bone_version of the update in progress, -1: none in progress


func clear() -> void:
	chunks.clear()
	have = -1
	_low = -1


# Apply one parsed message; returns true when it completed an update (no MORE).
func apply(msg: Dictionary) -> bool:
	if msg["full"]:
		for k in chunks.keys():
			changed_keys[k] = true
		chunks.clear()
	session = msg["session"]
	chunk_cells = msg["chunk_cells"]
	cw = msg["cw"]
	session_frame = msg["session_frame"]
	for c in msg["chunks"]:
		var k = c["key"]
		changed_keys[k] = true
		if c["vertex_count"] == 0 or c["triangle_count"] == 0:
			if chunks.has(k):
				chunks.erase(k)
				removed += 1
			continue
		if chunks.has(k):
			replaced += 1
		else:
			added += 1
		chunks[k] = c
	if _low < 0 or msg["bone_version"] < _low:
		_low = msg["bone_version"]
	if msg["more"]:
		return false
	have = _low
	_low = -1
	updates += 1
	return true


# Parse and apply bytes: {"error": "" or why the message was refused (nothing of it is
# applied then), "more": another page follows, "next_cursor", "bone_version"}.
func apply_bytes(data) -> Dictionary:
	var msg = MeshMessage.parse(data)
	if not msg["ok"]:
		return {"error": msg["reason"], "more": false, "next_cursor": 0, "bone_version": 0}
	apply(msg)
	return {"error": "", "more": msg["more"], "next_cursor": msg["next_cursor"],
		"bone_version": msg["bone_version"]}


# Keys changed since the last call (the engine layer rebuilds those chunks' meshes).
func take_changed() -> Array:
	var keys = changed_keys.keys()
	changed_keys = {}
	return keys


func triangle_count() -> int:
	var t = 0
	for k in chunks:
		t += chunks[k]["triangle_count"]
	return t


# The union of the chunks as Wavefront OBJ ("v x y z" then "f a b c" with 1-based indices,
# chunk after chunk, coordinates as delivered): writer.method(line) per line, newline
# included (a whole bone is tens of MB: a file, not a String).
func write_obj(writer, method: String) -> void:
	var base = 1
	var keys = chunks.keys()
	keys.sort()
	for k in keys:
		var c = chunks[k]
		for p in c["positions"]:
			writer.call(method, "v %.10f %.10f %.10f\n" % [p.x, p.y, p.z])
		var t = c["triangles"]
		for i in range(0, t.size(), 3):
			writer.call(method, "f %d %d %d\n" % [t[i] + base, t[i + 1] + base, t[i + 2] + base])
		base += c["vertex_count"]
