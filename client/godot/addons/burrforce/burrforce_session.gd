# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Godot 4 only (annotations, Callable, Node3D). A burrforce session in the scene: streams the
# tool node's pose to the server at a fixed haptic rate on a background Thread and exposes
# the newest force, torque, vibration and status. All protocol logic is in core/.
#
# Frame: the session is created (or must have been created) with frame "godot": metres,
# right-handed, y up; the tool's local +Y points from the burr centre toward the handle.
extends Node

## Emitted each frame with the newest good force (N, Godot axes; zero when stale).
signal force_updated(force: Vector3, torque: Vector3, status: int)
## Emitted each frame with the vibration to render (amplitude N, frequency Hz, axis).
signal vibration_updated(amplitude_n: float, frequency_hz: float, axis: Vector3)
## Emitted when the status bits change (messages.gd STATUS_*).
signal status_changed(status: int)
## Emitted when the bone changed (REPLY bone_version): the mesh node polls on it.
signal bone_version_changed(version: int)
## Emitted once the session is known (created over REST or given).
signal session_ready(session_id: int)
signal session_failed(detail: String)

const Streamer = preload("core/streamer.gd")
const Rest = preload("core/rest.gd")
const C = preload("core/compat.gd")
const M = preload("core/messages.gd")

@export var tool_node: Node3D
@export_group("Existing session (from burrforce serve)")
## A connection JSON written by `burrforce serve`
## (host, udp_port, session, key_hex, http_url, token).
@export_file("*.json") var connection_file := ""
@export var host := "127.0.0.1"
@export var udp_port := 0
@export var session_id := 0
@export var key_hex := ""
@export_group("Create a session over REST")
## When set (and session_id is 0), a new session is created on this server at start.
@export var rest_url := ""
@export var rest_token := ""
@export var bone_source := "phantom:workpiece"
@export var delete_session_on_exit := true
@export_group("Stream")
@export_range(100.0, 4000.0) var rate_hz := 1000.0
@export var rpm := 60000.0
@export var spindle_on := true
## Send the tool's frame-to-frame velocity with each pose (see _publish). Turn off when the
## tool node is updated at the haptic rate itself (a device driver thread).
@export var send_velocity := true

var streamer = null
var rest = null
var last := {}
var _thread: Thread
var _status := -1
var _bone_version := -1
var _created := false
var _prev_origin := Vector3.ZERO
var _prev_us := -1


func _ready() -> void:
	if Engine.is_editor_hint():
		return
	if connection_file != "":
		_read_connection(connection_file)
	if session_id == 0 and rest_url != "":
		# Blocks while the bone loads (a phantom: well under a second; a CT: seconds).
		rest = Rest.new(rest_url, rest_token)
		var r = rest.create_session(bone_source, "godot")
		if not r["ok"]:
			push_error("burrforce: " + r["detail"])
			session_failed.emit(r["detail"])
			return
		session_id = int(r["json"]["id"])
		key_hex = str(r["json"]["key"])
		host = str(r["json"]["udp"]["host"])
		udp_port = int(r["json"]["udp"]["port"])
		_created = true
	elif rest_url != "":
		# For set_parameters only: a restarted game needs no REST call to stream again (the
		# streamer asks the server for a new stream whatever its seq and clock).
		rest = Rest.new(rest_url, rest_token)
	start()


func _read_connection(path: String) -> void:
	var f = FileAccess.open(path, FileAccess.READ)
	if f == null:
		push_error("burrforce: cannot read " + path)
		return
	var c = C.json_parse(f.get_as_text())
	if typeof(c) != TYPE_DICTIONARY:
		return
	host = str(c.get("host", host))
	udp_port = int(c.get("udp_port", udp_port))
	session_id = int(c.get("session", session_id))
	key_hex = "" if c.get("key_hex") == null else str(c["key_hex"])
	if c.get("http_url") != null:
		rest_url = str(c["http_url"])
		rest_token = str(c.get("token", ""))
	if str(c.get("frame", "godot")) != "godot":
		push_warning("burrforce: session %d uses frame %s, not godot: poses will be misread"
			% [session_id, c.get("frame")])


## Starts streaming (called by _ready; call again after stop()).
func start() -> void:
	if streamer != null:
		return
	streamer = Streamer.new(host, udp_port, session_id, key_hex)
	streamer.rate_hz = rate_hz
	if streamer.open() != OK:
		push_error("burrforce: cannot open UDP to %s:%d" % [host, udp_port])
		streamer = null
		return
	_publish()
	_thread = Thread.new()
	_thread.start(Callable(streamer, "run"))
	session_ready.emit(session_id)


func stop() -> void:
	if streamer == null:
		return
	streamer.stop()
	_thread.wait_to_finish()
	streamer.close()
	streamer = null


func _exit_tree() -> void:
	stop()
	if _created and delete_session_on_exit and rest != null:
		rest.delete_session(session_id)


func _process(_delta: float) -> void:
	if streamer == null:
		return
	_publish()
	last = streamer.snapshot()
	var f: Array = last["force"]
	var t: Array = last["torque"]
	force_updated.emit(Vector3(f[0], f[1], f[2]), Vector3(t[0], t[1], t[2]), last["status"])
	var ax: Array = last["vibration_axis"]
	vibration_updated.emit(last["vibration_amplitude"], last["vibration_frequency_hz"],
		Vector3(ax[0], ax[1], ax[2]))
	if last["status"] != _status:
		_status = last["status"]
		status_changed.emit(_status)
	if last["bone_version"] != _bone_version:
		_bone_version = last["bone_version"]
		bone_version_changed.emit(_bone_version)


# The tool's global transform as the stream samples it: position in metres, the rotation as
# Godot's Quaternion components (x, y, z, w), sent unchanged (SPEC 6.3). The node moves once a
# frame while the stream samples it every millisecond: the server's own velocity estimate
# (two stamped poses) would see the tool stand still, then jump. So the frame-to-frame
# velocity (m/s, Godot axes) goes with the pose, and the server uses it instead (SPEC 5.4).
func _publish() -> void:
	if tool_node == null:
		return
	var g := tool_node.global_transform
	var q := g.basis.get_rotation_quaternion()
	var now_us := Time.get_ticks_usec()
	var velocity = null
	if send_velocity and _prev_us >= 0 and now_us > _prev_us:
		var v := (g.origin - _prev_origin) / ((now_us - _prev_us) * 1.0e-6)
		velocity = [v.x, v.y, v.z]
	_prev_origin = g.origin
	_prev_us = now_us
	streamer.publish([g.origin.x, g.origin.y, g.origin.z], [q.x, q.y, q.z, q.w], rpm, spindle_on,
		velocity)


## The newest good force (N, Godot axes), zero when stale or after an error REPLY.
func get_force() -> Vector3:
	var f: Array = last.get("force", [0.0, 0.0, 0.0])
	return Vector3(f[0], f[1], f[2])


## Counters: sent, replies, error_replies, notices by code, dropped by reason, late/skipped
## ticks, hellos (ticks sent while waiting for a stream), streams opened, the stream in use.
func get_counters() -> Dictionary:
	return {} if streamer == null else streamer.counters()


## Sets model parameters over REST (e.g. {"us_n_mm2": 1610.2}); returns the server's answer.
func set_parameters(fields: Dictionary) -> Dictionary:
	if rest == null:
		return {"ok": false, "detail": "no REST URL"}
	return rest.set_parameters(session_id, fields)
