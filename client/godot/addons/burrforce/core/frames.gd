# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Engine frames and units (SPEC 6): server_vector = M · engine_vector, s mm per engine unit,
# plus the session's placement (p0, P). A Transform is built once per session; vectors are
# Arrays of floats (float64; Godot's Vector3 is float32 and would round the poses).

const FRAMES = {
	"si_mm": {"m": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "s": 1.0, "unit": "mm",
		"tool_axis": [0.0, 0.0, 1.0], "right_handed": true},
	"unity": {"m": [[0, 0, 1], [-1, 0, 0], [0, 1, 0]], "s": 1000.0, "unit": "m",
		"tool_axis": [0.0, 1.0, 0.0], "right_handed": false},
	"unreal": {"m": [[1, 0, 0], [0, -1, 0], [0, 0, 1]], "s": 10.0, "unit": "cm",
		"tool_axis": [0.0, 0.0, 1.0], "right_handed": false},
	"godot": {"m": [[0, 0, -1], [-1, 0, 0], [0, 1, 0]], "s": 1000.0, "unit": "m",
		"tool_axis": [0.0, 1.0, 0.0], "right_handed": true},
	"ros": {"m": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "s": 1000.0, "unit": "m",
		"tool_axis": [0.0, 0.0, 1.0], "right_handed": true},
}

var name = ""
var scale = 1.0  # mm per engine unit
var det = 1.0
var tool_axis = [0.0, 0.0, 1.0]
var _a = []  # A = (M P Mᵀ)ᵀ M: engine axes -> server axes, placement included
var _b = [0.0, 0.0, 0.0]  # server-frame offset (mm)


# frame_name one of FRAMES; placement_position in engine units, placement_orientation an
# engine quaternion (x, y, z, w): the server frame's origin and rotation in the engine world.
func _init(frame_name: String = "si_mm", placement_position = [0.0, 0.0, 0.0],
		placement_orientation = [0.0, 0.0, 0.0, 1.0]):
	assert(FRAMES.has(frame_name))
	var f = FRAMES[frame_name]
	name = frame_name
	scale = float(f["s"])
	tool_axis = f["tool_axis"].duplicate()
	var m = f["m"]
	var p = quat_matrix(placement_orientation)
	var r_place = mat_mul(mat_mul(m, p), transpose(m))
	var t_place = []
	for i in range(3):
		t_place.append(scale * (m[i][0] * placement_position[0] + m[i][1] * placement_position[1]
			+ m[i][2] * placement_position[2]))
	var rt = transpose(r_place)
	_a = mat_mul(rt, m)
	_b = []
	for i in range(3):
		_b.append(-(rt[i][0] * t_place[0] + rt[i][1] * t_place[1] + rt[i][2] * t_place[2]))
	det = 1.0 if f["right_handed"] else -1.0


static func has_frame(frame_name: String) -> bool:
	return FRAMES.has(frame_name)


# --- engine -> server ---

func point_in(p) -> Array:
	var x = p[0] * scale
	var y = p[1] * scale
	var z = p[2] * scale
	return [_a[0][0] * x + _a[0][1] * y + _a[0][2] * z + _b[0],
		_a[1][0] * x + _a[1][1] * y + _a[1][2] * z + _b[1],
		_a[2][0] * x + _a[2][1] * y + _a[2][2] * z + _b[2]]


func direction_in(d) -> Array:
	return [_a[0][0] * d[0] + _a[0][1] * d[1] + _a[0][2] * d[2],
		_a[1][0] * d[0] + _a[1][1] * d[1] + _a[1][2] * d[2],
		_a[2][0] * d[0] + _a[2][1] * d[1] + _a[2][2] * d[2]]


# The tool axis (toward the handle) in server axes for an engine orientation.
func tool_axis_in(q) -> Array:
	var d = direction_in(quat_rotate(q, tool_axis))
	return normalized(d)


# --- server -> engine ---

# A force (N) or a direction: Aᵀ, A is orthogonal.
func direction_out(d) -> Array:
	return [_a[0][0] * d[0] + _a[1][0] * d[1] + _a[2][0] * d[2],
		_a[0][1] * d[0] + _a[1][1] * d[1] + _a[2][1] * d[2],
		_a[0][2] * d[0] + _a[1][2] * d[1] + _a[2][2] * d[2]]


func vector_out(v) -> Array:
	var d = direction_out(v)
	return [d[0] / scale, d[1] / scale, d[2] / scale]


func point_out(p) -> Array:
	return vector_out([p[0] - _b[0], p[1] - _b[1], p[2] - _b[2]])


# A torque (pseudovector) N·mm, server axes -> N·L, engine axes.
func torque_out(t) -> Array:
	var d = direction_out(t)
	var k = det / scale
	return [d[0] * k, d[1] * k, d[2] * k]


# The engine orientation that points the tool axis along server direction axis_server
# (the shortest arc from the local tool axis).
func orientation_for_axis(axis_server) -> Array:
	return shortest_arc(tool_axis, direction_out(axis_server))


# --- quaternion and matrix helpers (x, y, z, w) ---

# rotate(q, v) = v + w t + q_xyz × t, t = 2 q_xyz × v, q normalized first (SPEC 6.3).
static func quat_rotate(q, v) -> Array:
	var n = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
	var x = q[0] / n
	var y = q[1] / n
	var z = q[2] / n
	var w = q[3] / n
	var tx = 2.0 * (y * v[2] - z * v[1])
	var ty = 2.0 * (z * v[0] - x * v[2])
	var tz = 2.0 * (x * v[1] - y * v[0])
	return [v[0] + w * tx + (y * tz - z * ty), v[1] + w * ty + (z * tx - x * tz),
		v[2] + w * tz + (x * ty - y * tx)]


# The quaternion rotating unit vector a onto unit vector b.
static func shortest_arc(a, b) -> Array:
	var dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
	if dot < -1.0 + 1e-12:
		var other = [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0]
		var axis = normalized(cross(a, other))
		return [axis[0], axis[1], axis[2], 0.0]
	var c = cross(a, b)
	var w = 1.0 + dot
	var n = sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2] + w * w)
	return [c[0] / n, c[1] / n, c[2] / n, w / n]


static func quat_matrix(q) -> Array:
	var cols = [quat_rotate(q, [1.0, 0.0, 0.0]), quat_rotate(q, [0.0, 1.0, 0.0]),
		quat_rotate(q, [0.0, 0.0, 1.0])]
	return transpose(cols)


static func cross(a, b) -> Array:
	return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


static func normalized(v) -> Array:
	var n = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
	if n == 0.0:
		return [0.0, 0.0, 0.0]
	return [v[0] / n, v[1] / n, v[2] / n]


static func transpose(a) -> Array:
	return [[a[0][0], a[1][0], a[2][0]], [a[0][1], a[1][1], a[2][1]], [a[0][2], a[1][2], a[2][2]]]


static func mat_mul(a, b) -> Array:
	var out = []
	for i in range(3):
		var row = []
		for j in range(3):
			row.append(float(a[i][0]) * b[0][j] + float(a[i][1]) * b[1][j] + float(a[i][2]) * b[2][j])
		out.append(row)
	return out
