# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Messages <-> datagrams. Encoders write SPEC 2.3's canonical form byte for byte (the golden
# vectors pin it): smallest unsigned integer forms, every float as cb float64 (integral values
# and -0.0 included), the tag as c4 10 + 16 bytes. The decoder accepts every form SPEC 2.2
# allows and checks each field's kind; messages are Dictionaries keyed by the SPEC's field
# names (vectors as Arrays of floats, so values stay float64 end to end).

const M = preload("messages.gd")
const Reader = preload("msgpack_reader.gd")
const MAX_I63 = 0x7FFFFFFFFFFFFFFF


static func _writer():
	var w = StreamPeerBuffer.new()
	w.big_endian = true
	return w


static func write_uint(w, v: int) -> void:
	if v < 0:
		# A negative value here is a uint64 above 2^63 held in a signed int: write its bits.
		w.put_u8(0xcf)
		w.put_64(v)
	elif v <= 0x7f:
		w.put_u8(v)
	elif v <= 0xff:
		w.put_u8(0xcc)
		w.put_u8(v)
	elif v <= 0xffff:
		w.put_u8(0xcd)
		w.put_u16(v)
	elif v <= 0xffffffff:
		w.put_u8(0xce)
		w.put_u32(v)
	else:
		w.put_u8(0xcf)
		w.put_u64(v)


static func write_f64(w, x: float) -> void:
	w.put_u8(0xcb)
	w.put_double(x)


static func write_vec(w, v) -> void:
	w.put_u8(0x90 | v.size())
	for x in v:
		write_f64(w, float(x))


# Finish a datagram: the tag over every byte so far (c4 10 included), or nil without a key.
static func _finish(w, mac):
	if mac == null:
		w.put_u8(0xc0)
		return w.data_array
	w.put_u8(0xc4)
	w.put_u8(0x10)
	var head = w.data_array
	w.put_data(mac.tag(head))
	return w.data_array


# A POSE datagram. position Array[3] (L), orientation Array[4] (x, y, z, w), velocity null
# or Array[3] (L/s); stream the server's stream number, 0 for a hello; mac a Hmac or null (a
# session without a key).
static func encode_pose(session: int, seq: int, t_client_us: int, position, orientation,
		rpm: float, spindle_on: bool, velocity, flags: int, stream: int, mac):
	var w = _writer()
	w.put_u8(0x90 | M.POSE_ELEMENTS)
	w.put_u8(M.VERSION)
	w.put_u8(M.TYPE_POSE)
	write_uint(w, session)
	write_uint(w, seq)
	write_uint(w, t_client_us)
	write_vec(w, position)
	write_vec(w, orientation)
	write_f64(w, rpm)
	w.put_u8(0xc3 if spindle_on else 0xc2)
	if typeof(velocity) == TYPE_NIL:
		w.put_u8(0xc0)
	else:
		write_vec(w, velocity)
	write_uint(w, flags)
	write_uint(w, stream)
	return _finish(w, mac)


# A POSE from a Dictionary with the SPEC's field names.
static func encode_pose_fields(f: Dictionary, mac):
	return encode_pose(int(f["session"]), int(f["seq"]), int(f["t_client_us"]), f["position"],
		f["orientation"], float(f["rpm"]), bool(f["spindle_on"]), f["velocity"], int(f["flags"]),
		int(f["stream"]), mac)


# A REPLY (what the server sends; here for tests, recorders and fakes of the server).
static func encode_reply_fields(f: Dictionary, mac):
	var w = _writer()
	w.put_u8(0xdc)
	w.put_u16(M.REPLY_ELEMENTS)
	w.put_u8(M.VERSION)
	w.put_u8(M.TYPE_REPLY)
	write_uint(w, int(f["session"]))
	write_uint(w, int(f["seq"]))
	write_uint(w, int(f["t_client_us"]))
	for i in range(M.REPLY_FIELDS.size()):
		var kind = M.REPLY_KINDS[i]
		var v = f[M.REPLY_FIELDS[i]]
		if kind == "v3":
			write_vec(w, v)
		elif kind == "f":
			write_f64(w, float(v))
		else:
			write_uint(w, int(v))
	return _finish(w, mac)


# A NOTICE; f["version"] 1 writes v1's shape [1, 3, session, seq, t_client_us, error, tag]
# (what a server answers a datagram of the other version with, BAD_VERSION).
static func encode_notice_fields(f: Dictionary, mac):
	var v1 = int(f.get("version", M.VERSION)) == M.VERSION_1
	var w = _writer()
	w.put_u8(0x90 | (M.NOTICE_V1_ELEMENTS if v1 else M.NOTICE_ELEMENTS))
	w.put_u8(M.VERSION_1 if v1 else M.VERSION)
	w.put_u8(M.TYPE_NOTICE)
	write_uint(w, int(f["session"]))
	write_uint(w, int(f["seq"]))
	write_uint(w, int(f["t_client_us"]))
	write_uint(w, int(f["error"]))
	if not v1:
		write_uint(w, int(f.get("stream", 0)))
	return _finish(w, mac)


# --- decoding -------------------------------------------------------------------------------

# Any message. Returns a Dictionary: "ok" true with "type" and every field by name plus "tag"
# (bytes or null); or "ok" false with "reason", and "addressable" true when the header
# (session, seq, t_client_us, also returned) could be read. max_bytes: 1024 for what a
# server sends, 512 for a POSE.
static func decode(data, max_bytes: int = M.MAX_SERVER_BYTES) -> Dictionary:
	if data.size() > max_bytes:
		return {"ok": false, "addressable": false, "reason": "%d bytes" % data.size()}
	var r = Reader.new()
	var v = r.read_all(data)
	if r.error != "":
		return {"ok": false, "addressable": false, "reason": r.error}
	if typeof(v) != TYPE_ARRAY or v.size() < 5:
		return {"ok": false, "addressable": false, "reason": "not an array of 5 or more"}
	var out = {"ok": false, "addressable": false}
	var bad = []
	var version = _uint(v[0], MAX_I63, bad)
	var type = _uint(v[1], MAX_I63, bad)
	out["session"] = _uint(v[2], 0xffffffff, bad)
	out["seq"] = _uint(v[3], 0xffffffff, bad)
	out["t_client_us"] = _uint(v[4], MAX_I63, bad)
	if bad.size() > 0:
		out["reason"] = "header: " + bad[0]
		return out
	out["addressable"] = true
	out["version"] = version
	out["type"] = type
	if version == M.VERSION_1 and type == M.TYPE_NOTICE and v.size() == M.NOTICE_V1_ELEMENTS:
		return _v1_notice(v, out, bad)
	if version != M.VERSION:
		out["reason"] = "version %d" % version
		return out
	var n = {M.TYPE_POSE: M.POSE_ELEMENTS, M.TYPE_REPLY: M.REPLY_ELEMENTS,
		M.TYPE_NOTICE: M.NOTICE_ELEMENTS}.get(type, -1)
	if n < 0:
		out["reason"] = "type %d" % type
		return out
	if v.size() != n:
		out["reason"] = "%d elements, want %d" % [v.size(), n]
		return out
	if type == M.TYPE_POSE:
		out["position"] = _vec(v[5], 3, bad)
		out["orientation"] = _vec(v[6], 4, bad)
		out["rpm"] = _float(v[7], bad)
		out["spindle_on"] = _bool(v[8], bad)
		out["velocity"] = null if typeof(v[9]) == TYPE_NIL else _vec(v[9], 3, bad)
		out["flags"] = _uint(v[10], 0xffffffff, bad)
		out["stream"] = _uint(v[11], 0xffffffff, bad)
	elif type == M.TYPE_REPLY:
		for i in range(M.REPLY_FIELDS.size()):
			var kind = M.REPLY_KINDS[i]
			var x = v[5 + i]
			var value
			if kind == "v3":
				value = _vec(x, 3, bad)
			elif kind == "f":
				value = _float(x, bad)
			elif kind == "u16":
				value = _uint(x, 0xffff, bad)
			elif kind == "u32":
				value = _uint(x, 0xffffffff, bad)
			else:
				value = _uint(x, MAX_I63, bad)
			out[M.REPLY_FIELDS[i]] = value
	else:
		out["error"] = _uint(v[5], 0xffff, bad)
		out["stream"] = _uint(v[6], 0xffffffff, bad)
	out["tag"] = _tag(v[n - 1], bad)
	if bad.size() > 0:
		out["reason"] = bad[0]
		return out
	out["ok"] = true
	return out


# v1's NOTICE, read only when it says BAD_VERSION: the answer of a server that does not speak
# this version (a v1 server to our v2 POSEs), which the application should be told of. It
# comes back as a NOTICE with "version" 1 and stream 0.
static func _v1_notice(v: Array, out: Dictionary, bad: Array) -> Dictionary:
	out["error"] = _uint(v[5], 0xffff, bad)
	out["stream"] = 0
	out["tag"] = _tag(v[6], bad)
	if bad.size() == 0 and out["error"] != M.BAD_VERSION:
		bad.append("a version 1 NOTICE other than BAD_VERSION")
	if bad.size() > 0:
		out["reason"] = bad[0]
		return out
	out["ok"] = true
	return out


# An unsigned integer field in 0..hi (hi <= 2^63 - 1: larger uint64 values are refused, a
# GDScript int cannot hold them; the server's clocks and versions stay far below).
static func _uint(x, hi: int, bad: Array) -> int:
	if typeof(x) != TYPE_INT or x < 0 or x > hi:
		bad.append("integer expected, got %s" % str(x))
		return 0
	return x


static func _float(x, bad: Array) -> float:
	var t = typeof(x)
	if t == 3 or t == TYPE_INT:  # 3: float (TYPE_REAL in Godot 3, TYPE_FLOAT in 4)
		return float(x)
	if t == TYPE_DICTIONARY and x.has("u64big"):
		return x["u64big"]
	bad.append("number expected, got %s" % str(x))
	return 0.0


static func _bool(x, bad: Array) -> bool:
	if typeof(x) != TYPE_BOOL:
		bad.append("bool expected, got %s" % str(x))
		return false
	return x


static func _vec(x, count: int, bad: Array):
	if typeof(x) != TYPE_ARRAY or x.size() != count:
		bad.append("array of %d numbers expected" % count)
		return null
	var out = []
	out.resize(count)
	for i in range(count):
		out[i] = _float(x[i], bad)
	return out


static func _tag(x, bad: Array):
	if typeof(x) == TYPE_NIL:
		return null
	if typeof(x) == TYPE_DICTIONARY and x.has("bin") and x["bin"].size() == 16:
		return x["bin"]
	bad.append("tag is neither nil nor 16 bytes of bin")
	return null
