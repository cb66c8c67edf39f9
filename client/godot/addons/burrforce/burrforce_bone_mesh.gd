# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Godot 4 only. The carved bone, drawn as one MeshInstance3D + ArrayMesh per chunk
# (proto/MESH.md) and kept current while the burr cuts: a worker thread reads the WebSocket
# push channel (or polls REST pages when the socket cannot be opened) and parses each
# message; the main thread applies them to the chunk store and swaps the changed chunks'
# meshes (scene-tree changes belong to the main thread).
#
# Place this node at the world origin with an identity transform: chunk positions arrive in
# the session's engine frame (metres, placement applied). Winding: cw, which Godot draws as
# front faces (MESH.md section 5).
extends Node3D

const MeshMessage = preload("core/mesh_message.gd")
const MeshStore = preload("core/mesh_store.gd")
const C = preload("core/compat.gd")

## The BurrforceSession node whose session is drawn.
@export var session_node: Node
@export var material: Material
@export_range(1, 8) var chunk_bricks := 2
## Shortest time between two pushed updates, ms (the server's interval_ms, 10-1000).
@export_range(10, 1000) var interval_ms := 33
## Budget of chunk meshes rebuilt per frame (the rest wait for the next frame).
@export var max_chunks_per_frame := 64
## Vertex colours by material label (labels missing here are white).
@export var label_colors: Dictionary = {}

var store := MeshStore.new()
var status := ""  # the last problem, for display
var _instances := {}  # chunk key -> MeshInstance3D
var _queue: Array = []  # parsed messages, worker -> main thread
var _pending: Array = []  # chunk keys waiting for a rebuild
var _mutex := Mutex.new()
var _thread: Thread
var _stop := false


func _ready() -> void:
	if session_node == null:
		push_error("burrforce bone mesh: set session_node")
		return
	if session_node.session_id == 0:
		session_node.session_ready.connect(func(_id): _start(), CONNECT_ONE_SHOT)
	else:
		_start()


func _start() -> void:
	_thread = Thread.new()
	_thread.start(_worker)


func _exit_tree() -> void:
	_mutex.lock()
	_stop = true
	_mutex.unlock()
	if _thread != null and _thread.is_started():
		_thread.wait_to_finish()


func _stopping() -> bool:
	_mutex.lock()
	var s = _stop
	_mutex.unlock()
	return s


func _enqueue(msg: Dictionary) -> void:
	_mutex.lock()
	_queue.append(msg)
	_mutex.unlock()


# Worker thread: the push channel, and REST polling when it cannot be used.
func _worker() -> void:
	var base: String = session_node.rest_url
	if base.ends_with("/"):
		base = base.substr(0, base.length() - 1)
	if base.ends_with("/v1"):
		base = base.substr(0, base.length() - 3)
	var sid: int = session_node.session_id
	while not _stopping():
		if _run_websocket(base, sid):
			OS.delay_msec(500)  # closed after working (server restart, session gone): retry calmly
		else:
			# REST: ask only when a REPLY says the bone changed since what we hold.
			var bone_version = session_node.last.get("bone_version", -1)
			if store.have < 0 or bone_version != store.have:
				_poll_rest_once(sid)
			OS.delay_msec(interval_ms)


# Returns false when the socket could not be used (then REST is polled for a while).
func _run_websocket(base: String, sid: int) -> bool:
	var ws := WebSocketPeer.new()
	ws.inbound_buffer_size = 64 * 1024 * 1024  # a full page is up to max_bytes (4 MiB default)
	ws.max_queued_packets = 4096
	var url := (
		"%s/v1/sessions/%d/mesh/ws?chunk_bricks=%d&frame=session&winding=cw&interval_ms=%d"
		% [base.replace("http://", "ws://").replace("https://", "wss://"), sid, chunk_bricks,
			interval_ms]
		+ "&token=" + session_node.rest_token.uri_encode())
	if store.have >= 0:
		url += "&since=%d" % store.have
	if ws.connect_to_url(url) != OK:
		status = "websocket: cannot connect"
		return false
	var opened := false
	while not _stopping():
		ws.poll()
		var state := ws.get_ready_state()
		if state == WebSocketPeer.STATE_OPEN:
			opened = true
			while ws.get_available_packet_count() > 0:
				var data := ws.get_packet()
				var msg := MeshMessage.parse(data)
				if msg["ok"]:
					_enqueue(msg)
				else:
					status = "mesh message refused: " + msg["reason"]
		elif state == WebSocketPeer.STATE_CLOSED:
			status = "websocket closed: %d %s" % [ws.get_close_code(), ws.get_close_reason()]
			# 1001: the session was deleted or the server stops; 44xx: refused (MESH.md 2).
			return opened
		OS.delay_msec(5)
	ws.close()
	return true


func _poll_rest_once(sid: int) -> void:
	var rest = session_node.rest
	if rest == null:
		return
	var cursor := 0
	var since: int = store.have  # read racily: at worst a chunk is fetched twice (harmless)
	while true:
		var r = rest.mesh_page(sid, since, cursor, chunk_bricks, "session", "cw")
		if not r["ok"]:
			status = r["detail"]
			return
		var msg := MeshMessage.parse(r["body"])
		if not msg["ok"]:
			status = "mesh page refused: " + msg["reason"]
			return
		_enqueue(msg)
		if not msg["more"]:
			return
		cursor = msg["next_cursor"]


func _process(_delta: float) -> void:
	_mutex.lock()
	var msgs := _queue
	_queue = []
	_mutex.unlock()
	for msg in msgs:
		store.apply(msg)
	for k in store.take_changed():
		if not _pending.has(k):
			_pending.append(k)
	var n := 0
	while _pending.size() > 0 and n < max_chunks_per_frame:
		_rebuild(_pending.pop_front())
		n += 1


func _rebuild(key: String) -> void:
	var mi: MeshInstance3D = _instances.get(key)
	if not store.chunks.has(key):
		if mi != null:
			mi.queue_free()
			_instances.erase(key)
		return
	var c: Dictionary = store.chunks[key]
	var arrays := []
	arrays.resize(Mesh.ARRAY_MAX)
	arrays[Mesh.ARRAY_VERTEX] = c["positions"]
	arrays[Mesh.ARRAY_NORMAL] = c["normals"]
	arrays[Mesh.ARRAY_INDEX] = c["triangles"]
	if not label_colors.is_empty():
		var colors := PackedColorArray()
		colors.resize(c["vertex_count"])
		var labels: PackedByteArray = c["materials"]
		for i in labels.size():
			colors[i] = label_colors.get(labels[i], Color.WHITE)
		arrays[Mesh.ARRAY_COLOR] = colors
	var mesh := ArrayMesh.new()
	mesh.add_surface_from_arrays(Mesh.PRIMITIVE_TRIANGLES, arrays)
	if material != null:
		mesh.surface_set_material(0, material)
	if mi == null:
		mi = MeshInstance3D.new()
		mi.name = "chunk_" + key.replace(",", "_").replace("-", "m")
		add_child(mi)
		_instances[key] = mi
	mi.mesh = mesh
