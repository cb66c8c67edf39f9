# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# One session's protocol state without I/O: numbers and tags outgoing POSEs, keeps the stream
# the server gave (SPEC 4.3, 5.1, 5.2), decides which incoming datagrams to believe (7.6, 10).
# Not thread-safe: the streamer's thread owns it.
#
# The stream handshake: while `stream` is 0 every POSE is a hello (not ticked by the server);
# a NOTICE NEW_STREAM that verifies and answers one of the hellos sent since the stream
# became 0 gives the stream; a verified WRONG_STREAM for the current stream takes it back.
# Checking the echo (seq and t_client_us) keeps a replayed NEW_STREAM, an answer to another
# client's hello, from moving this client onto a stream it did not ask for.

const M = preload("messages.gd")
const Codec = preload("codec.gd")
const Hmac = preload("hmac.gd")
const Seq = preload("sequence.gd")

# POSEs remembered to match REPLYs and NEW_STREAMs against: one second at 1 kHz. A REPLY must
# answer one of them (seq and t_client_us), so an old REPLY replayed after a restart is not
# believed.
const RECENT = 1024

var session = 0
var seq = 1
var stream = M.HELLO_STREAM  # the server's stream number; 0: none, POSEs are hellos
var newest = -1  # seq of the newest REPLY used; -1: none yet
var dropped = {"malformed": 0, "bad_tag": 0, "foreign": 0, "stale": 0, "unsolicited": 0}
var _mac = null
var _recent_seq = []
var _recent_t = []
var _recent_tick = []
# Per slot: the hello round it was sent in (_round when stream was 0), or -1 for a POSE on a
# stream. A REPLY never answers a hello; a NEW_STREAM only answers a hello of this round.
var _recent_round = []
var _round = 0


# key: bytes, or null for a session without a key. first_seq: any value: streams start
# wherever the client's sequence is (a restarted client may begin at 1 again).
func _init(session_id: int, key, first_seq: int = 1):
	session = session_id
	seq = first_seq & Seq.MASK
	if key != null and key.size() > 0:
		_mac = Hmac.new(key)
	_recent_seq.resize(RECENT)
	_recent_t.resize(RECENT)
	_recent_tick.resize(RECENT)
	_recent_round.resize(RECENT)
	for i in range(RECENT):
		_recent_seq[i] = -1
		_recent_t[i] = -1
		_recent_tick[i] = -1
		_recent_round[i] = -1


func keyed() -> bool:
	return _mac != null


func hello() -> bool:
	return stream == M.HELLO_STREAM


# The next POSE datagram: on the current stream, or a hello while there is none. tick: the
# caller's index for this pose, handed back with its REPLY.
func pose(position, orientation, rpm: float, spindle_on: bool, velocity, flags: int,
		t_client_us: int, tick: int = -1):
	var s = seq
	seq = Seq.next(seq)
	var slot = s % RECENT
	_recent_seq[slot] = s
	_recent_t[slot] = t_client_us
	_recent_tick[slot] = tick
	_recent_round[slot] = _round if stream == M.HELLO_STREAM else -1
	return Codec.encode_pose(session, s, t_client_us, position, orientation, rpm, spindle_on,
		velocity, flags, stream, _mac)


# What a datagram that arrived at arrived_us says: a Dictionary with "kind" "reply" (the
# decoded REPLY plus "rtt_us", "offset_us", "tick"), "notice" (the decoded NOTICE; for
# NEW_STREAM and WRONG_STREAM also "changed": whether it moved `stream`), or "drop" with
# "reason" (also counted in `dropped`).
func accept(data, arrived_us: int) -> Dictionary:
	var m = Codec.decode(data, M.MAX_SERVER_BYTES)
	if not m["ok"]:
		return _drop("malformed")
	if m["type"] == M.TYPE_POSE:
		return _drop("malformed")
	var code = m.get("error", 0)
	var steers = m["type"] == M.TYPE_NOTICE and (code == M.NEW_STREAM or code == M.WRONG_STREAM)
	if (m["type"] == M.TYPE_REPLY or steers) and not _authentic(data, m["tag"]):
		# A keyed session's REPLYs and stream notices are always tagged: anything else is
		# forged or corrupt. Other NOTICEs pass unverified: they carry no force and change
		# nothing, and a BAD_TAG one is tagged with the server's key, which a client with the
		# wrong key cannot check.
		return _drop("bad_tag")
	if m["session"] != session:
		return _drop("foreign")
	if m["type"] == M.TYPE_NOTICE:
		m["kind"] = "notice"
		if steers:
			m["changed"] = _steer(m)
		return m
	if newest >= 0 and not Seq.newer(m["seq"], newest):
		return _drop("stale")
	var slot = m["seq"] % RECENT
	if (_recent_seq[slot] != m["seq"] or _recent_t[slot] != m["t_client_us"]
			or _recent_round[slot] >= 0):
		return _drop("unsolicited")
	newest = m["seq"]
	m["kind"] = "reply"
	m["tick"] = _recent_tick[slot]
	m["rtt_us"] = arrived_us - m["t_client_us"]
	# NTP's offset, server clock - client clock (SPEC 5.5).
	m["offset_us"] = ((m["t_recv_us"] - m["t_client_us"]) + (m["t_send_us"] - arrived_us)) / 2.0
	return m


# On a session without a key there is nothing to check: the session id (next) is all.
func _authentic(data, tag) -> bool:
	if _mac == null:
		return true
	return typeof(tag) != TYPE_NIL and _mac.verify(data)


# A verified NEW_STREAM or WRONG_STREAM notice of this session: true when it moved `stream`.
func _steer(m: Dictionary) -> bool:
	if m["error"] == M.WRONG_STREAM:
		# Only for the stream in use: one about a stream given up already (an old POSE's
		# answer, or a replay of one) must not throw away the stream that replaced it.
		if stream == M.HELLO_STREAM or m["stream"] != stream:
			return false
		stream = M.HELLO_STREAM
		_round += 1
		return true
	if stream != M.HELLO_STREAM or m["stream"] == M.HELLO_STREAM:
		return false
	var slot = m["seq"] % RECENT
	if (_recent_seq[slot] != m["seq"] or _recent_t[slot] != m["t_client_us"]
			or _recent_round[slot] != _round):
		return false
	stream = m["stream"]
	return true


func _drop(reason: String) -> Dictionary:
	dropped[reason] += 1
	return {"kind": "drop", "reason": reason}
