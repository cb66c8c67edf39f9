# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Offline checks: every core script parses (on the Godot running this), sequence comparison,
# the decoder's non-canonical forms and garbage, and the mesh parser's bounds checks.
# Usage: godot --no-window -s tests/test_strict.gd

extends SceneTree

const C = preload("../addons/burrforce/core/compat.gd")
const T = preload("testlib.gd")
const Codec = preload("../addons/burrforce/core/codec.gd")
const Seq = preload("../addons/burrforce/core/sequence.gd")
const MeshMessage = preload("../addons/burrforce/core/mesh_message.gd")
const MeshStore = preload("../addons/burrforce/core/mesh_store.gd")
const Rules = preload("../addons/burrforce/core/rules.gd")
const Hmac = preload("../addons/burrforce/core/hmac.gd")

const CORE = ["compat", "messages", "sequence", "hmac", "msgpack_reader", "codec", "frames",
	"rules", "streamer", "rest", "mesh_message", "mesh_store", "mesh_sync"]

var failures = []


func check(ok: bool, what: String) -> void:
	if not ok:
		failures.append(what)


# A mesh message with one chunk: a single triangle (3 vertices).
func mesh_bytes(flags: int, index_max: int):
	var w = StreamPeerBuffer.new()
	w.big_endian = false
	w.put_data(C.hex_decode("42464d43"))
	w.put_u16(1)
	w.put_u16(flags)
	w.put_u32(7)
	w.put_u32(16)
	w.put_u64(5)
	w.put_u64(0)
	w.put_u32(0)
	w.put_u32(1)
	for x in [1, -2, 3, 3, 1]:
		w.put_32(x)
	for i in range(9):
		w.put_float(i * 0.5)
	for i in range(9):
		w.put_float(1.0 if i % 3 == 2 else 0.0)
	for i in range(3):
		w.put_u8(1)
	w.put_u8(0)  # padding: 20 + 75 = 95 -> 96
	w.put_u32(0)
	w.put_u32(1)
	w.put_u32(index_max)
	return w.data_array


func _init():
	var parsed = []
	for name in CORE:
		var s = load("res://addons/burrforce/core/%s.gd" % name)
		var ok = s != null
		if ok and C.major() < 4:
			ok = s.can_instance()  # Godot 3 returns a script that failed to parse
		if not ok:
			failures.append("core script does not load: " + name)
		else:
			parsed.append(name)

	# RFC 1982
	check(Seq.newer(1, 0) and not Seq.newer(0, 1), "newer 1>0")
	check(Seq.newer(0, 0xffffffff), "wrap: 0 newer than 2^32-1")
	check(not Seq.newer(5, 5), "equal is not newer")
	check(not Seq.newer(0x80000000, 0) and not Seq.newer(0, 0x80000000), "2^31 apart: stale")
	check(Seq.next(0xffffffff) == 0, "next wraps")

	# Non-canonical but valid (SPEC 2.2): int and float 32 floats, signed and wide ints, an
	# array 16 header. POSE [1, 1, 7, 2, 1000, [3, 0.5f, 1s16], array16 [0, 0, 0, 1.0],
	# 60000 as uint 16, true, nil, 4 as uint 64, nil].
	var nc = "9c" + "01" + "01" + "d30000000000000007" + "cd0002" + "cd03e8"
	nc += "93" + "03" + "ca3f000000" + "d10001"
	nc += "dc0004" + "00" + "00" + "00" + "cb3ff0000000000000"
	nc += "cdea60" + "c3" + "c0" + "cf0000000000000004" + "c0"
	var d = Codec.decode(C.hex_decode(nc), 512)
	check(d["ok"] and d["session"] == 7 and d["seq"] == 2 and d["t_client_us"] == 1000
		and d["position"] == [3.0, 0.5, 1.0] and d["orientation"] == [0.0, 0.0, 0.0, 1.0]
		and typeof(d["rpm"]) == 3 and d["rpm"] == 60000.0 and d["flags"] == 4,
		"non-canonical POSE: " + str(d))
	# What must be refused, and whether the header was still readable (a NOTICE is possible).
	var head = "9c0101070203" + "93000000" + "9400000001"  # POSE header, position, orientation
	var refused = {
		"spindle as 1": [head + "00" + "01" + "c0" + "00" + "c0", true],
		"velocity of 2": [head + "00" + "c3" + "920000" + "00" + "c0", true],
		"str as rpm": [head + "a131" + "c3" + "c0" + "00" + "c0", true],
		"bin 9 tag": ["97010307020005" + "c409" + "000000000000000000", true],
		"negative error": ["970103070200" + "ff" + "c0", true],
		"negative t_client_us": ["9701030702" + "d3ffffffffffffffff" + "05c0", false],
		"t_client_us 2^63": ["9701030702" + "cf8000000000000000" + "05c0", false],
		"seq 2^32": ["97010307" + "cf0000000100000000" + "0005c0", false],
		"map": ["8101", false],
		"array of 33": ["dc0021", false],
		"truncated": ["970103070200", false],
		"trailing byte": ["97010307020005c0c0", false],
		"nested too deep": ["9191919191919191", false],
		"ext": ["d40100", false],
	}
	for what in refused:
		var r = Codec.decode(C.hex_decode(refused[what][0]), 512)
		check(not r["ok"], "accepted: " + what)
		check(r["addressable"] == refused[what][1], "addressable wrong: %s: %s" % [what, str(r)])
	# A 16-byte tag in a bin 16 form decodes but never verifies (SPEC 2.2, 4.3).
	var bin16 = "97010307020006" + "c50010" + "00000000000000000000000000000000"
	var key0 = C.hex_decode("00112233")
	check(Codec.decode(C.hex_decode(bin16))["ok"], "bin 16 tag decodes")
	check(not Hmac.new(key0).verify(C.hex_decode(bin16)), "bin 16 tag never verifies")
	# Garbage never crashes the decoder (a fixed-seed stream of random datagrams).
	var rng = RandomNumberGenerator.new()
	rng.seed = 12345
	var decoded = 0
	for n in range(3000):
		var b = C.bytes(rng.randi_range(0, 64))
		for i in range(b.size()):
			b[i] = rng.randi_range(0, 255)
		if n % 2 == 0 and b.size() > 0:
			b[0] = 0x90 + rng.randi_range(5, 12)
		if Codec.decode(b)["ok"]:
			decoded += 1

	# Mesh messages.
	var good = mesh_bytes(2, 2)
	var m = MeshMessage.parse(good)
	check(m["ok"] and m["full"] and m["chunks"].size() == 1 and m["chunks"][0]["key"] == "1,-2,3"
		and m["chunks"][0]["positions"].size() == 3 and m["chunks"][0]["triangles"].size() == 3,
		"mesh parse: " + str(m.get("reason", "")))
	var bad_magic = mesh_bytes(2, 2)
	bad_magic[0] = 0x43
	check(not MeshMessage.parse(bad_magic)["ok"], "mesh bad magic")
	var bad_version = mesh_bytes(2, 2)
	bad_version[4] = 2
	check(not MeshMessage.parse(bad_version)["ok"], "mesh bad version")
	check(not MeshMessage.parse(mesh_bytes(2, 3))["ok"], "mesh index == V refused")
	var huge = mesh_bytes(2, 2)
	huge[52] = 0xff  # vertex_count's low byte: 255 vertices cannot fit
	check(not MeshMessage.parse(huge)["ok"], "mesh vertex count beyond the bytes")
	var many = mesh_bytes(2, 2)
	many[39] = 0x7f  # chunk_count 2^31-ish
	check(not MeshMessage.parse(many)["ok"], "mesh chunk count beyond the bytes")
	var truncations = 0
	for n in range(good.size()):
		if MeshMessage.parse(C.slice(good, 0, n))["ok"]:
			truncations += 1
	check(truncations == 0, "a truncated mesh message parsed")
	var longer = C.slice(good, 0, good.size())
	longer.append(0)
	check(not MeshMessage.parse(longer)["ok"], "mesh trailing byte")
	var no_tris = C.slice(good, 0, good.size() - 12)
	no_tris[56] = 0  # triangle_count 1 -> 0, its 12 bytes dropped: vertices without a surface
	check(not MeshMessage.parse(no_tris)["ok"], "mesh vertices without triangles refused")

	# Store rules: FULL clears, MORE defers `have` to the lowest version of the update.
	var st = MeshStore.new()
	st.apply(MeshMessage.parse(mesh_bytes(2 | 1, 2)))  # FULL + MORE at version 5
	check(st.have == -1 and st.chunks.size() == 1, "have waits for the last page")
	var last = mesh_bytes(0, 2)
	last[16] = 9  # bone_version 9
	st.apply(MeshMessage.parse(last))
	check(st.have == 5 and st.replaced == 1, "have = lowest version of the update")

	# Cost per tick on this machine: a tagged POSE encoded, a tagged REPLY believed.
	var key = C.hex_decode("00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff")
	var rules = Rules.new(7, key, 1)
	var n_iter = 2000
	var t0 = C.now_us()
	for i in range(n_iter):
		rules.pose([12.5, -0.25, 30.0], [0.0, 0.0, 0.7, 0.7], 60000.0, true, null, 0, 1000000 + i, i)
	var pose_us = float(C.now_us() - t0) / n_iter
	var reply = {"session": 7, "seq": 0, "t_client_us": 0, "t_recv_us": 5000000017,
		"t_send_us": 5000000042, "error": 0, "status": 3, "force": [1.25, -0.5, 2.75],
		"resistive": [0.75, -0.125, 1.5], "torque": [-0.0625, 0.03125, 0.25], "power_w": 12.5,
		"vibration_amplitude": 0.375, "vibration_frequency_hz": 1000.0,
		"vibration_axis": [0.0, 0.6, 0.8], "proxy_position": [0.0, 0.0, 0.0],
		"proxy_velocity": [0.0, 0.0, 0.0], "coupling_stiffness": 0.0, "coupling_damping": 0.0,
		"removed_mm3": 0.05, "bone_version": 17, "feed_velocity": [4.0, -2.5, -1.0]}
	var mac = Hmac.new(key)
	var datagrams = []
	for i in range(n_iter):
		reply["seq"] = i + 1
		reply["t_client_us"] = 1000000 + i
		datagrams.append(Codec.encode_reply_fields(reply, mac))
	var believed = 0
	t0 = C.now_us()
	for i in range(n_iter):
		if rules.accept(datagrams[i], 2000000 + i)["kind"] == "reply":
			believed += 1
	var reply_us = float(C.now_us() - t0) / n_iter
	# Only the newest RECENT POSEs are remembered: older ones' replies are not believed.
	check(believed == Rules.RECENT, "replies believed: %d" % believed)
	T.finish(self, {"parsed": parsed, "failures": failures, "garbage_decoded": decoded,
		"pose_encode_us": pose_us, "reply_accept_us": reply_us, "replies_believed": believed})
