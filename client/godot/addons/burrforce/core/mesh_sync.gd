# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Keeps a MeshStore current over REST (proto/MESH.md section 4): one update() asks for
# since = have and follows MORE pages with next_cursor. Blocking: run it on a thread of your
# own (the Godot 4 layer uses the WebSocket push channel instead, and this as its fallback).

const MeshStore = preload("mesh_store.gd")

var rest
var session_id = 0
var chunk_bricks = 2  # the server's default: 16 cells, 1.6 mm at 0.1 mm voxels
var frame = "session"
var winding = "cw"  # Godot draws clockwise front faces (MESH.md section 5)
var store
var pages = 0
var bytes_received = 0
var last_error = ""


func _init(rest_client, session: int, win: String = "cw"):
	rest = rest_client
	session_id = session
	winding = win
	store = MeshStore.new()


# One complete update; true when it went through (then store.have is current).
func update() -> bool:
	var since = store.have
	var cursor = 0
	while true:
		var r = rest.mesh_page(session_id, since, cursor, chunk_bricks, frame, winding)
		if not r["ok"]:
			last_error = r["detail"]
			return false
		pages += 1
		bytes_received += r["body"].size()
		var a = store.apply_bytes(r["body"])
		if a["error"] != "":
			last_error = "mesh page refused: " + a["error"]
			return false
		if not a["more"]:
			return true
		cursor = a["next_cursor"]
	return false
