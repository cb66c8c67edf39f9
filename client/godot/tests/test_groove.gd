# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# The groove every SDK cuts (tests/sdk/conftest.py), through the SDK's streamer on a
# background Thread: the pose source returns tick i's pose in the session's engine frame,
# stamped by the streamer with its scheduled time; replies are collected as they arrive.
# Prints the summary JSON (the fields of conftest.summarize, plus the streamer's counters).
# Usage: godot --no-window -s tests/test_groove.gd -- --host=H --port=P --session=S --key=HEX
#   --frame=F --rate=HZ --plunge=1000 --feed=1200 --steady-from=1240 --rpm=60000 --angle=60

extends SceneTree

const C = preload("../addons/burrforce/core/compat.gd")
const T = preload("testlib.gd")
const M = preload("../addons/burrforce/core/messages.gd")
const Frames = preload("../addons/burrforce/core/frames.gd")
const Streamer = preload("../addons/burrforce/core/streamer.gd")

var plunge = 1000
var feed = 1200
var rpm = 60000.0
var tf
var q
var records = []  # [tick, status, resistive, force, rtt_us, removed_mm3]
var first_reply_us = -1


func position_mm(i: int) -> Array:
	if i <= plunge:
		return [3.0, 0.0, 2.5 - 0.001 * i]
	return [3.0 + 0.005 * (i - plunge), 0.0, 1.5]


func pose_at(tick: int, _t_us: int):
	return {"position": tf.point_out(position_mm(tick)), "orientation": q, "rpm": rpm,
		"spindle_on": true, "velocity": null, "flags": 0}


func on_event(e: Dictionary) -> void:
	if e["kind"] == "reply":
		records.append([e["tick"], e["status"], e["resistive"], e["force"], e["rtt_us"],
			e["removed_mm3"]])


static func percentile(sorted_values: Array, p: float) -> float:
	# numpy's default (linear interpolation between closest ranks)
	if sorted_values.size() == 0:
		return 0.0
	var x = (sorted_values.size() - 1) * p / 100.0
	var lo = int(floor(x))
	var hi = min(lo + 1, sorted_values.size() - 1)
	return sorted_values[lo] + (sorted_values[hi] - sorted_values[lo]) * (x - lo)


func _init():
	var a = T.args()
	plunge = int(a.get("plunge", "1000"))
	feed = int(a.get("feed", "1200"))
	rpm = float(a.get("rpm", "60000"))
	var steady_from = int(a.get("steady-from", "1240"))
	var angle = float(a.get("angle", "60")) * PI / 180.0
	var ticks = plunge + feed + 1
	tf = Frames.new(a.get("frame", "si_mm"))
	q = tf.orientation_for_axis([-cos(angle), 0.0, sin(angle)])
	var s = Streamer.new(a["host"], int(a["port"]), int(a["session"]), a.get("key", ""))
	s.rate_hz = float(a.get("rate", "1000"))
	s.max_ticks = ticks
	s.catch_up = true  # a trajectory: every tick is sent, a late one still carries its due time
	s.set_pose_source(self, "pose_at")
	s.set_listener(self, "on_event")
	if s.open() != OK:
		T.finish(self, {"error": "cannot open UDP"})
		return
	var th = Thread.new()
	var started = C.now_us()
	th.start(s, "run")
	var busy = 0
	if a.get("busy-main", "0") == "1":
		# A main thread that never sleeps (an engine rendering flat out): does the stream
		# thread keep its schedule?
		while s.is_running():
			for i in range(1000):
				busy += i % 7
	th.wait_to_finish()
	var elapsed_s = (C.now_us() - started) / 1e6
	s.close()
	var steady = 0
	var mean_r = [0.0, 0.0, 0.0]
	var mean_f = [0.0, 0.0, 0.0]
	var mag = 0.0
	var removed = 0.0
	var rtts = []
	for r in records:
		removed += r[5]
		rtts.append(float(r[4]))
		if r[0] >= steady_from and (r[1] & M.STATUS_CUTTING) != 0:
			steady += 1
			for j in range(3):
				mean_r[j] += r[2][j]
				mean_f[j] += r[3][j]
			mag += sqrt(r[3][0] * r[3][0] + r[3][1] * r[3][1] + r[3][2] * r[3][2])
	if steady > 0:
		for j in range(3):
			mean_r[j] /= steady
			mean_f[j] /= steady
		mag /= steady
	rtts.sort()
	var c = s.counters()
	T.finish(self, {"session": int(a["session"]), "frame": tf.name, "ticks": c["sent"],
		"replies": records.size(), "lost": c["sent"] - records.size(), "steady_ticks": steady,
		"steady_feed_N": mean_r[0], "steady_lateral_N": mean_r[1], "steady_normal_N": mean_r[2],
		"steady_force_N": mag, "steady_force_engine_N": mean_f,
		"steady_force_server_N": tf.direction_in(mean_f), "removed_mm3": removed,
		"rtt_p50_us": percentile(rtts, 50.0), "rtt_p99_us": percentile(rtts, 99.0),
		"rate_hz": s.rate_hz, "achieved_hz": c["sent"] / elapsed_s if elapsed_s > 0 else 0.0,
		"late_ticks": c["late_ticks"], "skipped_ticks": c["skipped_ticks"],
		"error_replies": c["error_replies"], "dropped": c["dropped"], "notices": c["notices"],
		"elapsed_s": elapsed_s, "godot": Engine.get_version_info()["string"]})
