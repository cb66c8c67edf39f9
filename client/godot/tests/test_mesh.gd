# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# The carved mesh through the SDK: a session in Godot's frame created with the REST helper,
# the chunked mesh fetched (REST pages, winding cw as Godot draws it), the groove cut by the
# streamer on its thread while the main thread keeps the mesh current, then the mesh caught
# up with the last REPLY's bone_version and written as OBJ.
# --channel=ws takes the WebSocket push channel instead of REST pages. Godot 3 has
# WebSocketClient, Godot 4 WebSocketPeer (used by burrforce_bone_mesh.gd): this transport is
# the test's own; the parser and the chunk store it feeds are the SDK's.
# Usage: godot --no-window -s tests/test_mesh.gd -- --url=HTTP_URL --token=T --obj=PATH
#   [--channel=rest|ws] [--plunge=… --feed=… --rpm=… --angle=…]

extends SceneTree

const C = preload("../addons/burrforce/core/compat.gd")
const T = preload("testlib.gd")
const Rest = preload("../addons/burrforce/core/rest.gd")
const MeshSync = preload("../addons/burrforce/core/mesh_sync.gd")
const Frames = preload("../addons/burrforce/core/frames.gd")
const Streamer = preload("../addons/burrforce/core/streamer.gd")
const MeshStore = preload("../addons/burrforce/core/mesh_store.gd")

var plunge = 1000
var feed = 1200
var rpm = 60000.0
var tf
var q
var rtts = []


func on_event(e: Dictionary) -> void:
	if e["kind"] == "reply":
		rtts.append(e["rtt_us"])


func pose_at(i: int, _t_us: int):
	var p = [3.0, 0.0, 2.5 - 0.001 * i] if i <= plunge else [3.0 + 0.005 * (i - plunge), 0.0, 1.5]
	return {"position": tf.point_out(p), "orientation": q, "rpm": rpm, "spindle_on": true}


# The push channel through Godot 3's WebSocketClient, feeding a MeshStore.
class WsChannel:
	var ws
	var store
	var messages = 0
	var last_error = ""
	var pages = 0
	var bytes_received = 0

	func _init(url: String, mesh_store):
		store = mesh_store
		# Godot 3 sizes the client's buffers from project settings read at construction;
		# a page is up to 4 MiB.
		ProjectSettings.set_setting("network/limits/websocket_client/max_in_buffer_kb", 65536)
		ProjectSettings.set_setting("network/limits/websocket_client/max_in_packets", 4096)
		ws = ClassDB.instance("WebSocketClient")
		var err = ws.connect_to_url(url)
		if err != OK:
			last_error = "connect_to_url: %d" % err

	# Takes what has arrived; returns the number of completed updates.
	func poll() -> int:
		ws.poll()
		var done = 0
		var peer = ws.get_peer(1)
		while peer.is_connected_to_host() and peer.get_available_packet_count() > 0:
			var data = peer.get_packet()
			pages += 1
			bytes_received += data.size()
			var a = store.apply_bytes(data)
			if a["error"] != "":
				last_error = a["error"]
			elif not a["more"]:
				done += 1
		return done

	func update() -> bool:
		return poll() > 0

	func close() -> void:
		ws.disconnect_from_host(1000, "done")
		ws.poll()


func fail(why: String) -> void:
	T.finish(self, {"error": why})


func _init():
	var a = T.args()
	plunge = int(a.get("plunge", "1000"))
	feed = int(a.get("feed", "1200"))
	rpm = float(a.get("rpm", "60000"))
	var angle = float(a.get("angle", "60")) * PI / 180.0
	var rest = Rest.new(a["url"], a["token"])
	var created = rest.create_session("phantom:workpiece", "godot")
	if not created["ok"]:
		return fail(created["detail"])
	var info = created["json"]
	var sid = int(info["id"])
	var out = {"session": sid, "frame": info["frame"]}
	var channel = a.get("channel", "rest")
	out["channel"] = channel
	var sync
	var t = C.now_us()
	if channel == "ws":
		var base = a["url"].replace("http://", "ws://")
		var token = a["token"].percent_encode() if C.major() < 4 else a["token"].uri_encode()
		var url = "%s/v1/sessions/%d/mesh/ws?chunk_bricks=2&frame=session&winding=cw" % [base, sid]
		sync = WsChannel.new(url + "&interval_ms=33&token=" + token, MeshStore.new())
		var until = C.now_us() + 30 * 1000000
		while sync.store.have < 0 and sync.last_error == "" and C.now_us() < until:
			sync.poll()
			OS.delay_msec(5)
		if sync.store.have < 0:
			out["error"] = "no first update over the WebSocket: " + sync.last_error
			return T.finish(self, out)
	else:
		sync = MeshSync.new(rest, sid, "cw")
		if not sync.update():
			out["error"] = sync.last_error
			return T.finish(self, out)
	out["initial_ms"] = (C.now_us() - t) / 1000
	out["initial_chunks"] = sync.store.chunks.size()
	out["initial_triangles"] = sync.store.triangle_count()
	out["initial_have"] = sync.store.have

	tf = Frames.new("godot")
	q = tf.orientation_for_axis([-cos(angle), 0.0, sin(angle)])
	var s = Streamer.new(info["udp"]["host"], int(info["udp"]["port"]), sid, info["key"])
	s.max_ticks = plunge + feed + 1
	s.catch_up = true
	s.linger_us = 1000000  # meshing on the server can hold replies back: wait for them
	s.set_pose_source(self, "pose_at")
	s.set_listener(self, "on_event")
	s.open()
	var th = Thread.new()
	th.start(s, "run")
	var during = 0
	while s.is_running() or during == 0:
		if sync.update():
			during += 1
		OS.delay_msec(30 if channel == "rest" else 5)
	th.wait_to_finish()
	var last = s.snapshot()
	var target = int(last["bone_version"])
	var deadline = C.now_us() + 60 * 1000000
	while sync.store.have < target and C.now_us() < deadline:
		sync.update()
		OS.delay_msec(20 if channel == "rest" else 5)
	if channel == "ws":
		sync.close()
	var f = ClassDB.call("instance", "_File") if C.major() < 4 else null
	if f == null or f.call("open", a["obj"], 2) != OK:
		out["error"] = "cannot write " + a["obj"]
		return T.finish(self, out)
	sync.store.write_obj(f, "store_string")
	f.call("close")
	var c = s.counters()
	out["sent"] = c["sent"]
	out["late_ticks"] = c["late_ticks"]
	out["replies"] = c["replies"]
	rtts.sort()
	out["rtt_p50_us"] = rtts[rtts.size() / 2] if rtts.size() > 0 else 0
	out["rtt_p99_us"] = rtts[rtts.size() * 99 / 100] if rtts.size() > 0 else 0
	out["rtt_max_us"] = rtts[rtts.size() - 1] if rtts.size() > 0 else 0
	out["last_bone_version"] = target
	out["have"] = sync.store.have
	out["updates_during_cut"] = during
	out["chunks"] = sync.store.chunks.size()
	out["triangles"] = sync.store.triangle_count()
	out["replaced"] = sync.store.replaced
	out["added"] = sync.store.added
	out["removed"] = sync.store.removed
	out["pages"] = sync.pages
	out["mesh_bytes"] = sync.bytes_received
	out["last_error"] = sync.last_error
	T.finish(self, out)
