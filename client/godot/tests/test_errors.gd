# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# SPEC 3.4's answers as the SDK sees them, against a live server: UNKNOWN_SESSION and
# BAD_TAG notices (to hellos: both come before the stream is looked at), a BAD_VALUE error
# REPLY (its seq consumed, zero force rendered), silence for a duplicate datagram, a MALFORMED
# notice for a wrong element count, a v1-shaped BAD_VERSION notice for a v1 POSE.
# Usage: godot --no-window -s tests/test_errors.gd -- --host=H --port=P --session=S --key=HEX

extends SceneTree

const C = preload("../addons/burrforce/core/compat.gd")
const T = preload("testlib.gd")
const M = preload("../addons/burrforce/core/messages.gd")
const Codec = preload("../addons/burrforce/core/codec.gd")
const Rules = preload("../addons/burrforce/core/rules.gd")
const Streamer = preload("../addons/burrforce/core/streamer.gd")

const POS = [3.0, 0.0, 10.0]  # well above the workpiece: no contact
const Q = [0.0, 0.0, 0.0, 1.0]

var host = ""
var port = 0
var bad_value_tick = 40
var stall_tick = 100
var stalled_at = -1  # the first tick sent from stall_tick on: a busy machine may skip 100
var call_times = []


# Everything `rules` believes within wait_ms (a NOTICE or REPLY each), as decoded events.
func collect(udp, rules, wait_ms: int) -> Array:
	var out = []
	var end = C.now_us() + wait_ms * 1000
	while C.now_us() < end:
		while udp.get_available_packet_count() > 0:
			var e = rules.accept(udp.get_packet(), C.now_us())
			if e["kind"] != "drop":
				out.append(e)
		OS.delay_usec(500)
	return out


# Says hello until the server's NEW_STREAM is adopted (each hello waits up to 500 ms for it).
func open_stream(udp, rules) -> bool:
	for i in range(4):
		send_pose(udp, rules)
		var end = C.now_us() + 500000
		while C.now_us() < end and rules.hello():
			while udp.get_available_packet_count() > 0:
				rules.accept(udp.get_packet(), C.now_us())
			OS.delay_usec(500)
		if not rules.hello():
			return true
	return false


func socket():
	var udp = PacketPeerUDP.new()
	udp.connect_to_host(host, port)
	return udp


func send_pose(udp, rules, position = POS):
	var d = rules.pose(position, Q, 60000.0, true, null, 0, C.now_us())
	udp.put_packet(d)
	return d


static func summary(events: Array) -> Array:
	var out = []
	for e in events:
		out.append({"kind": e["kind"], "seq": e["seq"], "error": e["error"]})
	return out


func source(tick: int, _t_us: int):
	var p = POS.duplicate()
	if tick >= bad_value_tick:
		p[0] = NAN
	return {"position": p, "orientation": Q, "rpm": 60000.0, "spindle_on": true}


# A pose source that stalls 30 ms once (a GC pause, a breakpoint): the stream must skip the
# missed ticks, not send them in a burst.
func stalling_source(tick: int, t_us: int):
	call_times.append([tick, t_us, C.now_us()])
	if tick >= stall_tick and stalled_at < 0:
		stalled_at = tick
		OS.delay_msec(30)
	return {"position": POS, "orientation": Q, "rpm": 60000.0, "spindle_on": true}


func _init():
	var a = T.args()
	host = a["host"]
	port = int(a["port"])
	var session = int(a["session"])
	var key = C.hex_decode(a["key"])
	var result = {}

	# A session id nobody created.
	var u1 = socket()
	var r1 = Rules.new(4000000000, key)
	send_pose(u1, r1)
	result["unknown_session"] = summary(collect(u1, r1, 500))

	# The right session, another key.
	var wrong = C.hex_decode(a["key"])
	wrong[0] = wrong[0] ^ 0xff
	var u2 = socket()
	var r2 = Rules.new(session, wrong)
	send_pose(u2, r2)
	result["bad_tag"] = summary(collect(u2, r2, 500))

	# A good POSE, then the very same bytes again: answered once.
	var u3 = socket()
	var r3 = Rules.new(session, key, 1000)
	result["opened"] = open_stream(u3, r3)
	var d = send_pose(u3, r3)
	var first = collect(u3, r3, 300)
	u3.put_packet(d)
	var again = collect(u3, r3, 300)
	result["duplicate"] = {"first": summary(first), "again": summary(again)}

	# NaN position: an error REPLY for that seq (consumed: the next seq is answered normally).
	var nan_seq = r3.seq
	send_pose(u3, r3, [NAN, 0.0, 10.0])
	var nan_events = collect(u3, r3, 300)
	var nan_reply = {}
	for e in nan_events:
		if e["kind"] == "reply":
			nan_reply = {"seq": e["seq"], "error": e["error"], "status": e["status"],
				"force": e["force"], "vibration_amplitude": e["vibration_amplitude"]}
	var after = send_pose(u3, r3)
	result["bad_value"] = {"sent_seq": nan_seq, "reply": nan_reply,
		"next": summary(collect(u3, r3, 300))}
	# The same bytes as the NaN POSE's seq again would be a duplicate: the seq was used.
	var replay = Codec.encode_pose(session, nan_seq, C.now_us(), POS, Q, 60000.0, true, null, 0,
		r3.stream, preload("../addons/burrforce/core/hmac.gd").new(key))
	u3.put_packet(replay)
	result["bad_value"]["reused_seq"] = summary(collect(u3, r3, 300))

	# 12 elements instead of 13 (v1's POSE length, without a stream): a valid header, a wrong
	# shape.
	var w = StreamPeerBuffer.new()
	w.big_endian = true
	w.put_u8(0x9c)
	w.put_u8(M.VERSION)
	w.put_u8(1)
	Codec.write_uint(w, session)
	Codec.write_uint(w, r3.seq)
	Codec.write_uint(w, C.now_us())
	Codec.write_vec(w, POS)
	Codec.write_vec(w, Q)
	Codec.write_f64(w, 60000.0)
	w.put_u8(0xc3)
	w.put_u8(0xc0)
	w.put_u8(0x00)
	w.put_u8(0xc0)
	u3.put_packet(w.data_array)
	result["malformed"] = summary(collect(u3, r3, 500))

	# A v1 POSE (an SDK not yet updated): BAD_VERSION, in v1's NOTICE shape so that it can
	# read it.
	w = StreamPeerBuffer.new()
	w.big_endian = true
	w.put_u8(0x9c)
	w.put_u8(1)
	w.put_u8(1)
	Codec.write_uint(w, session)
	Codec.write_uint(w, r3.seq)
	Codec.write_uint(w, C.now_us())
	Codec.write_vec(w, POS)
	Codec.write_vec(w, Q)
	Codec.write_f64(w, 60000.0)
	w.put_u8(0xc3)
	w.put_u8(0xc0)
	w.put_u8(0x00)
	w.put_u8(0xc0)
	u3.put_packet(w.data_array)
	var v1 = []
	for e in collect(u3, r3, 500):
		v1.append({"kind": e["kind"], "error": e["error"], "version": e["version"]})
	result["bad_version"] = v1

	# The streamer renders nothing from error REPLYs: good poses, then NaN from tick 40 on.
	# It starts at seq 1 again right after r3's stream: its hello gets it a stream of its own.
	var s = Streamer.new(host, port, session, a["key"], 1)
	s.rate_hz = 500.0
	s.max_ticks = 60
	s.set_pose_source(self, "source")
	s.open()
	s.run()
	var snap = s.snapshot()
	var c = s.counters()
	result["streamer"] = {"error": snap["error"], "fresh": snap["fresh"], "force": snap["force"],
		"vibration_amplitude": snap["vibration_amplitude"], "replies": c["replies"],
		"error_replies": c["error_replies"], "sent": c["sent"], "streams": c["streams"]}

	var s2 = Streamer.new(host, port, session, a["key"], 5000)
	s2.max_ticks = 300
	s2.set_pose_source(self, "stalling_source")
	s2.open()
	var th = Thread.new()
	th.start(s2, "run")
	th.wait_to_finish()
	var c2 = s2.counters()
	var first_after = -1
	for i in range(call_times.size() - 1):
		if call_times[i][0] == stalled_at:
			first_after = call_times[i + 1][0]
	var close_sends = 0  # sends within 200 µs of the previous one, in the 20 after the stall
	var on_schedule = true
	for i in range(1, call_times.size()):
		if call_times[i - 1][0] > stalled_at and call_times[i - 1][0] <= first_after + 20:
			if call_times[i][2] - call_times[i - 1][2] < 200:
				close_sends += 1
		# every stamp is its own tick's scheduled time
		if call_times[i][1] - call_times[0][1] != (call_times[i][0] - call_times[0][0]) * 1000:
			on_schedule = false
	result["stall"] = {"sent": c2["sent"], "skipped": c2["skipped_ticks"],
		"late": c2["late_ticks"], "replies": c2["replies"], "first_after_stall": first_after,
		"stalled_at": stalled_at,
		"hellos": c2["hellos"], "streams": c2["streams"], "rtt_us": s2.snapshot()["rtt_us"],
		"close_sends_after": close_sends, "stamps_on_schedule": on_schedule}
	T.finish(self, result)
