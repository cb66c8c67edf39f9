# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# The haptic stream: sends one POSE per tick at a fixed rate on an absolute schedule (tick k is
# due at t0 + k·period and stamped with that time, SPEC 5.3), independent of the engine's frame
# rate, and takes the replies in between without ever blocking on one.
#
# Threading: run() is the body of one background Thread; everything it touches that the
# engine's main thread also touches (the published pose, the newest output, the counters) is
# behind one Mutex, held for a few copies only. The pose comes either from publish() (the
# main thread's newest tool pose, sampled by the stream each tick) or from a pose source
# (object + method called on the stream thread with the tick and its scheduled time).
#
# After a stall (a GC pause, a breakpoint, a slow frame on a one-core machine) the missed
# ticks are skipped and counted, never sent in a burst: a burst would reach the server as
# poses sampled at once. With catch_up (playing back a recorded trajectory) every tick is sent,
# late ones as soon as possible, still stamped with their scheduled times.
#
# Streams (SPEC 5.2): the first ticks are hellos until the server's NEW_STREAM arrives (a round
# trip: a tick or two on a LAN), and again after a WRONG_STREAM (the server restarted, or the
# stream was restarted over REST). A hello's pose is not ticked and gets no REPLY, so the
# output stays stale until the stream is open. Nothing else is needed to restart: a new
# streamer, a restarted game or engine, may begin at any seq and any clock.

const C = preload("compat.gd")
const M = preload("messages.gd")
const Rules = preload("rules.gd")
# REPLY fields the output keeps.
const _COPIED = ["force", "resistive", "torque", "power_w", "vibration_amplitude",
	"vibration_frequency_hz", "vibration_axis", "proxy_position", "proxy_velocity",
	"coupling_stiffness", "coupling_damping", "feed_velocity", "status", "error", "seq",
	"bone_version", "rtt_us", "offset_us", "t_client_us"]

# Settings (set before run()).
var rate_hz = 1000.0
var max_ticks = -1  # stop after this many ticks (-1: until stop())
var catch_up = false
var linger_us = 50000  # after the last tick: how long to keep taking replies
var stale_us = 50000  # no good REPLY for this long: render nothing (SPEC 7.6)
var spin_us = 150  # sleep until this close to a due time, then spin (sleep overshoots)
var poll_us = 100  # longest nap between two looks at the socket

var rules
var _udp
var _host = ""
var _port = 0
var _mutex
var _stop = false
var _running = false

var _src_obj = null
var _src_method = ""
var _lis_obj = null
var _lis_method = ""

# The main thread's newest pose (engine frame and units), under _mutex.
var _pub_position = [0.0, 0.0, 0.0]
var _pub_orientation = [0.0, 0.0, 0.0, 1.0]
var _pub_rpm = 0.0
var _pub_spindle = false
var _pub_velocity = null
var _pub_flags = 0
var _pub_valid = false

# The newest good REPLY and the counters, under _mutex.
var _out = {}
var _last_good_us = -1
var _last_error = 0
var _counters = {}


# key: hex text, bytes, or null (a session without a key).
func _init(host: String, port: int, session: int, key, first_seq: int = 1):
	_host = host
	_port = port
	var k = key
	if typeof(key) == TYPE_STRING:
		k = C.hex_decode(key) if key != "" else null
	rules = Rules.new(session, k, first_seq)
	_mutex = Mutex.new()
	_out = _empty_output()
	_counters = {"ticks": 0, "sent": 0, "send_errors": 0, "replies": 0, "error_replies": 0,
		"notices": {}, "dropped": {}, "late_ticks": 0, "skipped_ticks": 0, "no_pose_ticks": 0,
		"hellos": 0, "streams": 0, "stream": 0}


# Opens the socket; 0 (OK) or the engine's error code.
func open() -> int:
	_udp = PacketPeerUDP.new()
	return _udp.connect_to_host(_host, _port)


func close() -> void:
	if _udp != null:
		_udp.close()


# Main thread: the tool's pose now (engine frame: position in L, orientation x, y, z, w).
# flags: one-shot flags for the next tick (FLAG_RESET_VELOCITY after a teleport, say).
func publish(position, orientation, rpm: float, spindle_on: bool, velocity = null,
		flags: int = 0) -> void:
	_mutex.lock()
	for i in range(3):
		_pub_position[i] = float(position[i])
	for i in range(4):
		_pub_orientation[i] = float(orientation[i])
	_pub_rpm = rpm
	_pub_spindle = spindle_on
	_pub_velocity = null if typeof(velocity) == TYPE_NIL else [float(velocity[0]),
		float(velocity[1]), float(velocity[2])]
	_pub_flags = _pub_flags | flags
	_pub_valid = true
	_mutex.unlock()


# obj.method(tick: int, t_us: int) -> Dictionary with position, orientation, rpm, spindle_on
# and optional velocity, flags; or null for "no pose this tick".
func set_pose_source(obj, method: String) -> void:
	_src_obj = obj
	_src_method = method


# obj.method(event: Dictionary), on the stream thread, for each believed REPLY
# ("kind" "reply") and NOTICE ("kind" "notice"; "changed" true on the NEW_STREAM that opened
# the stream and the WRONG_STREAM that closed it).
func set_listener(obj, method: String) -> void:
	_lis_obj = obj
	_lis_method = method


func stop() -> void:
	_mutex.lock()
	_stop = true
	_mutex.unlock()


func is_running() -> bool:
	_mutex.lock()
	var r = _running
	_mutex.unlock()
	return r


# The thread body (Godot 3 passes one userdata argument, Godot 4 none).
func run(_userdata = null) -> void:
	_mutex.lock()
	_running = true
	_stop = false
	_mutex.unlock()
	var period_us = 1000000.0 / rate_hz
	var t0 = C.now_us()
	var k = 0
	while true:
		_mutex.lock()
		var stopping = _stop
		_mutex.unlock()
		if stopping or (max_ticks >= 0 and k >= max_ticks):
			break
		var due = t0 + int(round(k * period_us))
		var now = C.now_us()
		if now < due:
			# Short naps between looks at the socket: a REPLY is taken (and its round trip
			# measured) within about poll_us of its arrival. Godot 3's PacketPeerUDP.wait()
			# has no timeout, so it cannot be used to sleep until "a packet or the next tick".
			_receive()
			var rem = due - C.now_us()
			if rem > spin_us:
				OS.delay_usec(min(rem - spin_us, poll_us))
			continue
		if now - due > period_us:
			if not catch_up:
				var missed = int((now - due) / period_us)
				if max_ticks >= 0:
					# Ticks past the last one were never going to be sent: not skipped ones.
					missed = min(missed, max_ticks - k)
				k += missed
				_count("skipped_ticks", missed)
				continue
			_count("late_ticks", 1)
		_tick(k, due)
		k += 1
		_receive()
	var end = C.now_us() + linger_us
	while C.now_us() < end:
		_receive()
		OS.delay_usec(200)
	_mutex.lock()
	_running = false
	_mutex.unlock()


func _tick(k: int, t_us: int) -> void:
	var p
	if _src_obj != null:
		p = _src_obj.call(_src_method, k, t_us)
	else:
		_mutex.lock()
		if _pub_valid:
			p = {"position": _pub_position.duplicate(), "orientation": _pub_orientation.duplicate(),
				"rpm": _pub_rpm, "spindle_on": _pub_spindle, "velocity": _pub_velocity,
				"flags": _pub_flags}
			_pub_flags = 0
		_mutex.unlock()
	if typeof(p) != TYPE_DICTIONARY:
		_count("no_pose_ticks", 1)
		return
	var hello = rules.hello()
	var d = rules.pose(p["position"], p["orientation"], float(p["rpm"]), bool(p["spindle_on"]),
		p.get("velocity", null), int(p.get("flags", 0)), t_us, k)
	var err = _udp.put_packet(d)
	_mutex.lock()
	_counters["ticks"] += 1
	if hello:
		_counters["hellos"] += 1
	if err == OK:
		_counters["sent"] += 1
	else:
		_counters["send_errors"] += 1
	_mutex.unlock()


# Everything that has arrived, without waiting.
func _receive() -> void:
	while _udp.get_available_packet_count() > 0:
		var data = _udp.get_packet()
		var arrived = C.now_us()
		if _udp.get_packet_error() != OK:
			continue
		var e = rules.accept(data, arrived)
		var kind = e["kind"]
		_mutex.lock()
		if kind == "reply":
			_counters["replies"] += 1
			if e["error"] != 0:
				_counters["error_replies"] += 1
				_last_error = e["error"]
			else:
				_last_error = 0
				_last_good_us = arrived
			_store(e)
		elif kind == "notice":
			var code = e["error"]
			_counters["notices"][code] = _counters["notices"].get(code, 0) + 1
			if e.get("changed", false):
				_counters["stream"] = rules.stream
				if rules.stream != M.HELLO_STREAM:
					_counters["streams"] += 1
		else:
			var r = e["reason"]
			_counters["dropped"][r] = _counters["dropped"].get(r, 0) + 1
		_mutex.unlock()
		if kind != "drop" and _lis_obj != null:
			_lis_obj.call(_lis_method, e)


# Under _mutex.
func _store(e: Dictionary) -> void:
	for name in _COPIED:
		_out[name] = e[name]
	_out["removed_mm3_total"] += e["removed_mm3"]
	_out["removed_mm3"] = e["removed_mm3"]


func _count(name: String, n: int) -> void:
	_mutex.lock()
	_counters[name] += n
	_mutex.unlock()


static func _empty_output() -> Dictionary:
	return {"force": [0.0, 0.0, 0.0], "resistive": [0.0, 0.0, 0.0], "torque": [0.0, 0.0, 0.0],
		"power_w": 0.0, "vibration_amplitude": 0.0, "vibration_frequency_hz": 0.0,
		"vibration_axis": [0.0, 0.0, 0.0], "proxy_position": [0.0, 0.0, 0.0],
		"proxy_velocity": [0.0, 0.0, 0.0], "coupling_stiffness": 0.0, "coupling_damping": 0.0,
		"feed_velocity": [0.0, 0.0, 0.0], "status": 0, "error": 0, "seq": -1, "bone_version": 0,
		"rtt_us": 0, "offset_us": 0.0, "t_client_us": 0, "removed_mm3": 0.0,
		"removed_mm3_total": 0.0}


# Any thread: the newest REPLY's fields (engine axes), with "fresh" false and force, torque
# and vibration zeroed when the newest REPLY was an error or no good one came for stale_us.
func snapshot() -> Dictionary:
	var now = C.now_us()
	_mutex.lock()
	var s = _out.duplicate(true)
	var fresh = _last_good_us >= 0 and _last_error == 0 and now - _last_good_us <= stale_us
	s["age_us"] = now - _last_good_us if _last_good_us >= 0 else -1
	_mutex.unlock()
	s["fresh"] = fresh
	if not fresh:
		s["force"] = [0.0, 0.0, 0.0]
		s["torque"] = [0.0, 0.0, 0.0]
		s["vibration_amplitude"] = 0.0
		s["vibration_frequency_hz"] = 0.0
	return s


# Any thread: sent, replies, error_replies, notices (by code), dropped (by reason), late,
# skipped and no-pose ticks; hellos (ticks sent without a stream), streams (streams opened),
# stream (the one in use, 0 while saying hello).
func counters() -> Dictionary:
	_mutex.lock()
	var c = _counters.duplicate(true)
	_mutex.unlock()
	return c
