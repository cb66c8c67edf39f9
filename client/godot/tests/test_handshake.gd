# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# The stream handshake (SPEC 5.2) against a live server: a client A streams; a new client B
# starting at seq 1 right after gets a stream of its own on its first hello (v1 made it wait
# out a 1 s idle restart); A's captured datagrams replayed are refused (WRONG_STREAM) and
# disturb neither client's state; a REST restart-stream sends a running streamer back to
# hello, and it streams on.
# Usage: godot --no-window -s tests/test_handshake.gd -- --host=H --port=P --session=S
#   --key=HEX --url=URL --token=T

extends SceneTree

const C = preload("../addons/burrforce/core/compat.gd")
const T = preload("testlib.gd")
const M = preload("../addons/burrforce/core/messages.gd")
const Rules = preload("../addons/burrforce/core/rules.gd")
const Rest = preload("../addons/burrforce/core/rest.gd")
const Streamer = preload("../addons/burrforce/core/streamer.gd")

const POS = [3.0, 0.0, 10.0]  # well above the workpiece: no contact
const Q = [0.0, 0.0, 0.0, 1.0]

var host = ""
var port = 0


func socket():
	var udp = PacketPeerUDP.new()
	udp.connect_to_host(host, port)
	return udp


func send_pose(udp, rules):
	var d = rules.pose(POS, Q, 60000.0, true, null, 0, C.now_us())
	udp.put_packet(d)
	return d


# The datagrams that arrive within wait_ms, or as soon as `count` have.
static func receive(udp, count: int, wait_ms: int) -> Array:
	var out = []
	var end = C.now_us() + wait_ms * 1000
	while C.now_us() < end and out.size() < count:
		while udp.get_available_packet_count() > 0:
			out.append(udp.get_packet())
		OS.delay_usec(500)
	return out


# What each of `rules` (an Array of Rules) makes of each datagram: [kind or drop reason,
# error, seq, stream, changed, status].
static func judged(datagrams: Array, rules_list: Array) -> Array:
	var out = []
	for d in datagrams:
		var row = []
		for rules in rules_list:
			var e = rules.accept(d, C.now_us())
			var kind = e["kind"] if e["kind"] != "drop" else "drop:" + e["reason"]
			row.append([kind, e.get("error", -1), e.get("seq", -1), e.get("stream", -1),
				e.get("changed", false), e.get("status", -1)])
		out.append(row)
	return out


# One POSE (a hello when `rules` has no stream) and what it got back: at most one answer is
# expected, so the wait ends with the first.
func exchange(udp, rules, others: Array = []) -> Array:
	send_pose(udp, rules)
	return judged(receive(udp, 1, 1000), [rules] + others)


func _init():
	var a = T.args()
	host = a["host"]
	port = int(a["port"])
	var session = int(a["session"])
	var key = C.hex_decode(a["key"])
	var result = {}

	# A: a hello, then 20 POSEs on its stream. Its last POSE and its hello are kept to replay.
	var ua = socket()
	var ra = Rules.new(session, key, 1)
	var a_hello = send_pose(ua, ra)
	result["a_hello"] = judged(receive(ua, 1, 1000), [ra])
	var a_stream = ra.stream
	var a_replies = 0
	var a_last = null
	for i in range(20):
		a_last = send_pose(ua, ra)
		for row in judged(receive(ua, 1, 1000), [ra]):
			if row[0][0] == "reply":
				a_replies += 1
	result["a"] = {"stream": a_stream, "replies": a_replies, "next_seq": ra.seq}

	# B, right after, from seq 1 again: one hello, a stream, and its POSEs answered although
	# their seqs are below A's.
	var ub = socket()
	var rb = Rules.new(session, key, 1)
	result["b_hello"] = exchange(ub, rb)
	var b_stream = rb.stream
	var b = []
	for i in range(3):
		b.append(exchange(ub, rb))
	result["b"] = {"stream": b_stream, "poses": b}

	# A's captured POSE replayed: WRONG_STREAM for A's stream. A's rules go back to hello,
	# B's keep their stream; B's next POSE is answered.
	ua.put_packet(a_last)
	result["replayed_pose"] = judged(receive(ua, 1, 1000), [ra, rb])
	result["after_replayed_pose"] = exchange(ub, rb)
	# A's captured hello replayed: the server offers a stream (idempotent: its offer), which
	# neither client takes (A said that hello before its last stream, B has a stream), and
	# B's stream is untouched.
	ua.put_packet(a_hello)
	result["replayed_hello"] = judged(receive(ua, 1, 1000), [ra, rb])
	result["after_replayed_hello"] = exchange(ub, rb)
	result["states"] = {"a": ra.stream, "b": rb.stream}

	# A streamer, and the REST restart-stream while it runs: WRONG_STREAM, a hello, a new
	# stream, and it streams on. The deadlines only keep a broken server from hanging the test.
	var s = Streamer.new(host, port, session, a["key"], 1)
	s.rate_hz = 500.0
	s.publish(POS, Q, 60000.0, true)
	s.open()
	var th = Thread.new()
	th.start(s, "run")
	var deadline = C.now_us() + 20000000
	while s.counters()["replies"] < 20 and C.now_us() < deadline:
		OS.delay_msec(5)
	var before = s.counters()
	var rest = Rest.new(a["url"], a["token"])
	var restarted = rest.restart_stream(session)
	while C.now_us() < deadline:
		var c = s.counters()
		if c["streams"] >= 2 and c["replies"] >= before["replies"] + 20:
			break
		OS.delay_msec(5)
	s.stop()
	th.wait_to_finish()
	s.close()
	var after = s.counters()
	result["streamer"] = {"restart_status": restarted["status"],
		"before": {"streams": before["streams"], "stream": before["stream"],
			"replies": before["replies"]},
		"after": {"streams": after["streams"], "stream": after["stream"],
			"replies": after["replies"], "hellos": after["hellos"],
			"new_stream": after["notices"].get(M.NEW_STREAM, 0),
			"wrong_stream": after["notices"].get(M.WRONG_STREAM, 0),
			"dropped": after["dropped"]}}
	T.finish(self, result)
