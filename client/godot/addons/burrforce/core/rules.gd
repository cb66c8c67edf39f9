# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# One session's protocol state without I/O: numbers and tags outgoing POSEs, decides which
# incoming datagrams to believe (SPEC 4.3, 5.1, 7.6, 10). Not thread-safe: the streamer's
# thread owns it.

const M = preload("messages.gd")
const Codec = preload("codec.gd")
const Hmac = preload("hmac.gd")
const Seq = preload("sequence.gd")

# POSEs remembered to match REPLYs against: one second at 1 kHz. A REPLY must answer one of
# them (seq and t_client_us), so an old REPLY replayed after a restart is not believed.
const RECENT = 1024

var session = 0
var seq = 1
var newest = -1  # seq of the newest REPLY used; -1: none yet (FLAG_NEW_STREAM is set)
var dropped = {"malformed": 0, "bad_tag": 0, "foreign": 0, "stale": 0, "unsolicited": 0}
var _mac = null
var _recent_seq = []
var _recent_t = []
var _recent_tick = []


# key: bytes, or null for a session without a key.
func _init(session_id: int, key, first_seq: int = 1):
	session = session_id
	seq = first_seq & Seq.MASK
	if key != null and key.size() > 0:
		_mac = Hmac.new(key)
	_recent_seq.resize(RECENT)
	_recent_t.resize(RECENT)
	_recent_tick.resize(RECENT)
	for i in range(RECENT):
		_recent_seq[i] = -1
		_recent_t[i] = -1
		_recent_tick[i] = -1


func keyed() -> bool:
	return _mac != null


# The next POSE datagram (FLAG_NEW_STREAM until a REPLY has arrived). tick: the caller's
# index for this pose, handed back with its REPLY.
func pose(position, orientation, rpm: float, spindle_on: bool, velocity, flags: int,
		t_client_us: int, tick: int = -1):
	var s = seq
	seq = Seq.next(seq)
	if newest < 0:
		flags = flags | M.FLAG_NEW_STREAM
	var slot = s % RECENT
	_recent_seq[slot] = s
	_recent_t[slot] = t_client_us
	_recent_tick[slot] = tick
	return Codec.encode_pose(session, s, t_client_us, position, orientation, rpm, spindle_on,
		velocity, flags, _mac)


# What a datagram that arrived at arrived_us says: a Dictionary with "kind" "reply" (the
# decoded REPLY plus "rtt_us", "offset_us", "tick"), "notice" (the decoded NOTICE), or
# "drop" with "reason" (also counted in `dropped`).
func accept(data, arrived_us: int) -> Dictionary:
	var m = Codec.decode(data, M.MAX_SERVER_BYTES)
	if not m["ok"]:
		return _drop("malformed")
	if m["type"] == M.TYPE_POSE:
		return _drop("malformed")
	if m["type"] == M.TYPE_REPLY and _mac != null and (typeof(m["tag"]) == TYPE_NIL
			or not _mac.verify(data)):
		# A keyed session's REPLYs are always tagged: anything else is forged or corrupt.
		# NOTICEs pass unverified: they carry no force, and a BAD_TAG one is tagged with the
		# server's key, which a client with the wrong key cannot check.
		return _drop("bad_tag")
	if m["session"] != session:
		return _drop("foreign")
	if m["type"] == M.TYPE_NOTICE:
		m["kind"] = "notice"
		return m
	if newest >= 0 and not Seq.newer(m["seq"], newest):
		return _drop("stale")
	var slot = m["seq"] % RECENT
	if _recent_seq[slot] != m["seq"] or _recent_t[slot] != m["t_client_us"]:
		return _drop("unsolicited")
	newest = m["seq"]
	m["kind"] = "reply"
	m["tick"] = _recent_tick[slot]
	m["rtt_us"] = arrived_us - m["t_client_us"]
	# NTP's offset, server clock - client clock (SPEC 5.5).
	m["offset_us"] = ((m["t_recv_us"] - m["t_client_us"]) + (m["t_send_us"] - arrived_us)) / 2.0
	return m


func _drop(reason: String) -> Dictionary:
	dropped[reason] += 1
	return {"kind": "drop", "reason": reason}
