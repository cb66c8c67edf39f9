# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# A strict, bounded msgpack reader for the protocol's subset (SPEC 2.2, 2.4): every format a
# sender may use is accepted; maps, ext, over-long arrays, str or bin, truncation and trailing
# bytes are errors. Bounds are checked before every read, so garbage gives an error, never
# an engine error message or a crash.
#
# Values: int, float, bool, null, Array; bin as {"bin": bytes}; str as {"str": length} (never
# valid in a field, kept only so the shape can be reported). A uint 64 at or above 2^63 does
# not fit a GDScript int: it becomes {"u64big": float value}.

const C = preload("compat.gd")
const MAX_ARRAY = 32
const MAX_BIN = 64
const MAX_DEPTH = 4

var error = ""
var _b
var _raw
var _sp
var _pos = 0
var _n = 0


# One msgpack object filling all of data; null with `error` set when it is not one.
func read_all(data):
	_raw = data
	_b = Array(data)  # indexing a Godot 3 PoolByteArray takes a lock per read; an Array does not
	_n = data.size()
	_pos = 0
	error = ""
	_sp = StreamPeerBuffer.new()
	_sp.big_endian = true
	_sp.data_array = data
	var v = _value(0)
	if error == "" and _pos != _n:
		error = "%d trailing bytes" % (_n - _pos)
	return null if error != "" else v


func _need(k: int) -> bool:
	if _n - _pos < k:
		if error == "":
			error = "truncated at byte %d" % _pos
		return false
	return true


func _fail(msg: String):
	if error == "":
		error = msg
	return null


func _value(depth: int):
	if not _need(1):
		return null
	var t = _b[_pos]
	_pos += 1
	# The canonical forms first (float 64, fixint, fixarray): GDScript's match tests its
	# branches one after the other, and a REPLY is mostly float 64s.
	if t == 0xcb:
		if not _need(8):
			return null
		_sp.seek(_pos)
		_pos += 8
		return _sp.get_double()
	if t <= 0x7f:
		return t
	if t >= 0xe0:
		return t - 256
	if t >= 0x90 and t <= 0x9f:
		return _array(t & 0x0f, depth)
	if t >= 0x80 and t <= 0x8f:
		return _fail("map at byte %d" % (_pos - 1))
	if t >= 0xa0 and t <= 0xbf:
		return _str(t & 0x1f)
	match t:
		0xc0:
			return null
		0xc2:
			return false
		0xc3:
			return true
		0xc4:
			return _bin(_uint(1))
		0xc5:
			return _bin(_uint(2))
		0xc6:
			return _bin(_uint(4))
		0xca:
			if not _need(4):
				return null
			_sp.seek(_pos)
			_pos += 4
			return _sp.get_float()
		0xcb:
			if not _need(8):
				return null
			_sp.seek(_pos)
			_pos += 8
			return _sp.get_double()
		0xcc:
			return _uint(1)
		0xcd:
			return _uint(2)
		0xce:
			return _uint(4)
		0xcf:
			if not _need(8):
				return null
			_sp.seek(_pos)
			_pos += 8
			var u = _sp.get_u64()
			if u < 0:
				return {"u64big": float(u) + 18446744073709551616.0}
			return u
		0xd0, 0xd1, 0xd2, 0xd3:
			var k = 1 << (t - 0xd0)
			if not _need(k):
				return null
			_sp.seek(_pos)
			_pos += k
			if k == 1:
				return _sp.get_8()
			if k == 2:
				return _sp.get_16()
			if k == 4:
				return _sp.get_32()
			return _sp.get_64()
		0xd9:
			return _str(_uint(1))
		0xda:
			return _str(_uint(2))
		0xdb:
			return _str(_uint(4))
		0xdc:
			return _array(_uint(2), depth)
		0xdd:
			return _array(_uint(4), depth)
		0xde, 0xdf:
			return _fail("map at byte %d" % (_pos - 1))
		0xc7, 0xc8, 0xc9, 0xd4, 0xd5, 0xd6, 0xd7, 0xd8:
			return _fail("ext at byte %d" % (_pos - 1))
	return _fail("reserved byte %02x at %d" % [t, _pos - 1])


# An unsigned big-endian integer of k bytes (k <= 4), or -1 when truncated.
func _uint(k: int) -> int:
	if not _need(k):
		return -1
	var v = 0
	for i in range(k):
		v = (v << 8) | _b[_pos + i]
	_pos += k
	return v


func _array(count: int, depth: int):
	if count < 0:
		return null
	if count > MAX_ARRAY:
		return _fail("array of %d elements" % count)
	if depth >= MAX_DEPTH:
		return _fail("arrays nested too deep")
	var out = []
	out.resize(count)
	for i in range(count):
		# Inlined float 64 and fixint: a GDScript call costs about a microsecond, and a REPLY
		# holds some 50 values.
		if _n - _pos >= 9 and _b[_pos] == 0xcb:
			_sp.seek(_pos + 1)
			out[i] = _sp.get_double()
			_pos += 9
		elif _pos < _n and _b[_pos] <= 0x7f:
			out[i] = _b[_pos]
			_pos += 1
		else:
			out[i] = _value(depth + 1)
			if error != "":
				return null
	return out


func _bin(count: int):
	if count < 0:
		return null
	if count > MAX_BIN:
		return _fail("bin of %d bytes" % count)
	if not _need(count):
		return null
	var b = C.slice(_raw, _pos, _pos + count)
	_pos += count
	return {"bin": b}


func _str(count: int):
	if count < 0:
		return null
	if count > MAX_BIN:
		return _fail("str of %d bytes" % count)
	if not _need(count):
		return null
	_pos += count
	return {"str": count}
