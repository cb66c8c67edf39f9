# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Helpers of the test programs (run headless by tests/sdk/test_godot.py): arguments after
# "--", files, exact numbers from the harness's JSON ("f:<16 hex digits>" float64 bits,
# "i:<decimal>" integers, which JSON's doubles could round), and the one-line JSON result.

const C = preload("../addons/burrforce/core/compat.gd")


static func args() -> Dictionary:
	var out = {}
	var a = OS.get_cmdline_args()
	var seen = false
	for i in range(a.size()):
		if a[i] == "--":
			seen = true
			continue
		if seen and a[i].begins_with("--") and a[i].find("=") > 0:
			var k = a[i].substr(2, a[i].find("=") - 2)
			out[k] = a[i].substr(a[i].find("=") + 1, a[i].length())
	return out


# File access differs by name between Godot 3 (File) and 4 (FileAccess); the tests run on
# Godot 3 here, and fall back to FileAccess (Godot 4.4+) through ClassDB.
static func read_text(path: String) -> String:
	if C.major() >= 4:
		var f = ClassDB.call("class_call_static", "FileAccess", "open", path, 1)
		return f.call("get_as_text")
	var g = ClassDB.call("instance", "_File")
	if g.call("open", path, 1) != OK:
		return ""
	var text = g.call("get_as_text")
	g.call("close")
	return text


static func write_text(path: String, text: String) -> bool:
	if C.major() >= 4:
		var f = ClassDB.call("class_call_static", "FileAccess", "open", path, 2)
		f.call("store_string", text)
		f.call("close")
		return true
	var g = ClassDB.call("instance", "_File")
	if g.call("open", path, 2) != OK:
		return false
	g.call("store_string", text)
	g.call("close")
	return true


static func f64_bits(x: float) -> String:
	var w = StreamPeerBuffer.new()
	w.big_endian = true
	w.put_double(x)
	return w.data_array.hex_encode()


static func f64_from_bits(h: String) -> float:
	var r = StreamPeerBuffer.new()
	r.big_endian = true
	r.data_array = C.hex_decode(h)
	return r.get_double()


static func parse_int(s: String) -> int:
	var v = 0
	for i in range(s.length()):
		v = v * 10 + ("0123456789".find(s[i]))
	return v


# "f:…"/"i:…" strings (and arrays of them) to values.
static func exact(x):
	if typeof(x) == TYPE_STRING:
		if x.begins_with("f:"):
			return f64_from_bits(x.substr(2, 16))
		if x.begins_with("i:"):
			return parse_int(x.substr(2, x.length()))
	if typeof(x) == TYPE_ARRAY:
		var out = []
		for y in x:
			out.append(exact(y))
		return out
	return x


# A decoded value against the harness's exact form: floats bit for bit.
static func same(decoded, expected) -> bool:
	if typeof(expected) == TYPE_ARRAY:
		if typeof(decoded) != TYPE_ARRAY or decoded.size() != expected.size():
			return false
		for i in range(expected.size()):
			if not same(decoded[i], expected[i]):
				return false
		return true
	if typeof(expected) == TYPE_STRING and expected.begins_with("f:"):
		return typeof(decoded) == 3 and f64_bits(decoded) == expected.substr(2, 16)
	if typeof(expected) == TYPE_STRING and expected.begins_with("i:"):
		return typeof(decoded) == TYPE_INT and decoded == parse_int(expected.substr(2, expected.length()))
	if typeof(expected) == TYPE_NIL:
		return typeof(decoded) == TYPE_NIL
	if typeof(expected) == TYPE_BOOL:
		return typeof(decoded) == TYPE_BOOL and decoded == expected
	return false


static func finish(tree, result: Dictionary) -> void:
	print(C.json_stringify(result))
	tree.quit(0)
