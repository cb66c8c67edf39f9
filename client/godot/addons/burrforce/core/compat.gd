# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# The few engine calls whose names differ between Godot 3 and Godot 4, looked up at run
# time so that every core script parses and runs on both (no type names that exist in only
# one of them, no methods called by a name one of them lacks).

const _HEX = "0123456789abcdef"


static func major() -> int:
	return int(Engine.get_version_info()["major"])


# Monotonic µs. Godot 4 has Time.get_ticks_usec and dropped OS.get_ticks_usec; Godot 3 has no
# Time singleton. Both count from engine start: a restarted engine's clock starts over, which
# the server does not mind (a restarted client asks for a new stream, SPEC 5.2).
static func now_us() -> int:
	if Engine.has_singleton("Time"):
		return int(Engine.get_singleton("Time").call("get_ticks_usec"))
	return int(OS.call("get_ticks_usec"))


# An empty byte array of the engine's own type (PoolByteArray / PackedByteArray).
static func bytes(n: int = 0):
	var b = StreamPeerBuffer.new().data_array
	if n > 0:
		b.resize(n)
		for i in range(n):
			b[i] = 0
	return b


# Method names that differ between the versions are called on untyped variables: each
# parser then leaves the lookup to run time, and only the branch of the running version runs.

# b[from, to) as a new array.
static func slice(b, from: int, to: int):
	if to <= from:
		return bytes()
	if major() >= 4:
		return b.slice(from, to)
	return b.subarray(from, to - 1)


static func utf8(text):
	if major() >= 4:
		return text.to_utf8_buffer()
	return text.to_utf8()


# Hex text to bytes; null when it is not an even number of hex digits.
static func hex_decode(text: String):
	var s = text.strip_edges().to_lower()
	if s.length() % 2 != 0:
		return null
	var out = bytes(s.length() / 2)
	for i in range(0, s.length(), 2):
		var hi = _HEX.find(s[i])
		var lo = _HEX.find(s[i + 1])
		if hi < 0 or lo < 0:
			return null
		out[i / 2] = hi * 16 + lo
	return out


static func hex_encode(b) -> String:
	return b.hex_encode()


# JSON text to a value (null on a syntax error). Numbers come back as floats in Godot 3.
static func json_parse(text: String):
	if major() >= 4:
		var j = ClassDB.call("instantiate", "JSON")
		if j.call("parse", text) != OK:
			return null
		return j.get("data")
	var r = Engine.get_singleton("JSON").call("parse", text)
	if r.error != OK:
		return null
	return r.result


# A value as JSON text. Written here rather than by the engine so that both versions write
# the same text; floats keep 17 significant digits (the server parses float64).
static func json_stringify(v) -> String:
	match typeof(v):
		TYPE_NIL:
			return "null"
		TYPE_BOOL:
			return "true" if v else "false"
		TYPE_INT:
			return str(v)
		3:  # float (TYPE_REAL in Godot 3, TYPE_FLOAT in 4: the same value, different names)
			return _json_float(v)
		TYPE_STRING:
			return _json_string(v)
		TYPE_ARRAY:
			var parts = []
			for x in v:
				parts.append(json_stringify(x))
			return "[" + _join(parts) + "]"
		TYPE_DICTIONARY:
			var parts = []
			for k in v.keys():
				parts.append(_json_string(str(k)) + ":" + json_stringify(v[k]))
			return "{" + _join(parts) + "}"
	return _json_string(str(v))


static func _json_float(x: float) -> String:
	if is_nan(x) or is_inf(x):
		return "null"  # JSON has no NaN: the server answers 422, which says more than a crash
	if x == floor(x) and abs(x) < 1e15:
		return str(int(x)) + ".0"
	# str() keeps 6 decimals in Godot 3: write 17 significant digits as mantissa and exponent
	# (the division by a power of ten can cost the last unit in the last place).
	var e = int(floor(log(abs(x)) / log(10.0)))
	var m = x / pow(10.0, e)
	if abs(m) >= 10.0:
		m /= 10.0
		e += 1
	elif abs(m) < 1.0:
		m *= 10.0
		e -= 1
	return ("%.16f" % m) + "e" + str(e)


static func _json_string(s: String) -> String:
	return "\"" + s.replace("\\", "\\\\").replace("\"", "\\\"").replace("\n", "\\n") \
		.replace("\r", "\\r").replace("\t", "\\t") + "\""


static func _join(parts: Array) -> String:
	var out = ""
	for i in range(parts.size()):
		if i > 0:
			out += ","
		out += parts[i]
	return out

