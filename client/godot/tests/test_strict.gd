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
const M = preload("../addons/burrforce/core/messages.gd")

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


static func notice(mac, session: int, seq: int, t_us: int, error: int, stream: int):
	return Codec.encode_notice_fields({"session": session, "seq": seq, "t_client_us": t_us,
		"error": error, "stream": stream}, mac)


static func reply_fields(session: int, seq: int, t_us: int) -> Dictionary:
	return {"session": session, "seq": seq, "t_client_us": t_us, "t_recv_us": 5000000017,
		"t_send_us": 5000000042, "error": 0, "status": 3, "force": [1.25, -0.5, 2.75],
		"resistive": [0.75, -0.125, 1.5], "torque": [-0.0625, 0.03125, 0.25], "power_w": 12.5,
		"vibration_amplitude": 0.375, "vibration_frequency_hz": 1000.0,
		"vibration_axis": [0.0, 0.6, 0.8], "proxy_position": [0.0, 0.0, 0.0],
		"proxy_velocity": [0.0, 0.0, 0.0], "coupling_stiffness": 0.0, "coupling_damping": 0.0,
		"removed_mm3": 0.05, "bone_version": 17, "feed_velocity": [4.0, -2.5, -1.0]}


# The next POSE of `rules` (at stamp t_us), decoded: its seq and stream.
static func next_pose(rules, t_us: int) -> Dictionary:
	return Codec.decode(rules.pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], 0.0, false, null, 0,
		t_us), 512)


# The client's side of the stream handshake, without a server: which NEW_STREAM and
# WRONG_STREAM notices move the stream, and which are ignored. Returns the steps' outcomes
# (the pytest checks them too).
func handshake_checks() -> Dictionary:
	var key = C.hex_decode("00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff")
	var mac = Hmac.new(key)
	var other = C.hex_decode("ff112233445566778899aabbccddeeff00112233445566778899aabbccddeeff")
	var r = Rules.new(7, key, 10)
	var out = {}
	var h1 = next_pose(r, 5000)
	check(h1["stream"] == 0 and h1["seq"] == 10, "a new client says hello: " + str(h1))
	var kinds = []
	for n in [notice(Hmac.new(other), 7, 10, 5000, M.NEW_STREAM, 40),  # forged
			notice(null, 7, 10, 5000, M.NEW_STREAM, 40),  # untagged on a keyed session
			notice(mac, 8, 10, 5000, M.NEW_STREAM, 40),  # another session's
			notice(mac, 7, 11, 5000, M.NEW_STREAM, 40),  # a seq never sent
			notice(mac, 7, 10, 5001, M.NEW_STREAM, 40),  # the hello's seq, another stamp
			notice(mac, 7, 10, 5000, M.NEW_STREAM, 0),  # no stream in it
			notice(mac, 7, 10, 5000, M.WRONG_STREAM, 0)]:  # no stream to lose
		var e = r.accept(n, 6000)
		kinds.append(e.get("reason", "changed" if e.get("changed", false) else "ignored"))
	out["refused_offers"] = kinds
	check(r.stream == 0, "no refused offer gives a stream")
	# The hello's answer is not a REPLY: a REPLY to a hello's seq is believed by nobody.
	var to_hello = Codec.encode_reply_fields(reply_fields(7, 10, 5000), mac)
	out["reply_to_hello"] = r.accept(to_hello, 6000).get("reason", "believed")
	var h2 = next_pose(r, 6000)
	var adopt = r.accept(notice(mac, 7, 10, 5000, M.NEW_STREAM, 40), 6500)
	out["adopted"] = [adopt["kind"], adopt.get("changed", false), r.stream]
	var p1 = next_pose(r, 7000)
	check(h2["stream"] == 0 and p1["stream"] == 40 and p1["seq"] == 12,
		"the stream goes in the POSE after the offer: %s %s" % [str(h2), str(p1)])
	# Once streaming: a second answer (to the other hello) and a WRONG_STREAM about another
	# stream change nothing; a REPLY on the stream is believed.
	var late = r.accept(notice(mac, 7, 11, 6000, M.NEW_STREAM, 41), 7100)
	var elsewhere = r.accept(notice(mac, 7, 12, 7000, M.WRONG_STREAM, 39), 7200)
	var rep = r.accept(Codec.encode_reply_fields(reply_fields(7, 12, 7000), mac), 7300)
	out["while_streaming"] = [late.get("changed", false), elsewhere.get("changed", false),
		rep["kind"], r.stream]
	# An unverified WRONG_STREAM for the stream in use is dropped; a verified one closes it.
	var forged = r.accept(notice(Hmac.new(other), 7, 12, 7000, M.WRONG_STREAM, 40), 7400)
	var closed = r.accept(notice(mac, 7, 12, 7000, M.WRONG_STREAM, 40), 7500)
	out["closed"] = [forged.get("reason", ""), closed.get("changed", false), r.stream]
	var h3 = next_pose(r, 8000)
	# The answers to hellos of before the last stream belong to that round: not adopted.
	var old_round = r.accept(notice(mac, 7, 11, 6000, M.NEW_STREAM, 41), 8100)
	var reopened = r.accept(notice(mac, 7, 13, 8000, M.NEW_STREAM, 42), 8200)
	var p2 = next_pose(r, 9000)
	out["reopened"] = [h3["stream"], old_round.get("changed", false),
		reopened.get("changed", false), p2["stream"], p2["seq"]]
	check(h3["seq"] == 13 and p2["seq"] == 14, "seq counts on across streams")
	# A session without a key: the notices are untagged and believed.
	var u = Rules.new(9, null, 1)
	next_pose(u, 100)
	var untagged = u.accept(notice(null, 9, 1, 100, M.NEW_STREAM, 5), 200)
	out["unkeyed"] = [untagged.get("changed", false), u.stream]
	# v1's BAD_VERSION notice (the server speaks v1) reaches the application as a notice.
	var v1 = r.accept(Codec.encode_notice_fields({"version": 1, "session": 7, "seq": 14,
		"t_client_us": 9000, "error": M.BAD_VERSION}, null), 9500)
	out["v1_bad_version"] = [v1["kind"], v1.get("error", -1), v1.get("version", -1)]
	return out


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
	# array 16 header. POSE [2, 1, 7, 2, 1000, [3, 0.5f, 1s16], array16 [0, 0, 0, 1.0],
	# 60000 as uint 16, true, nil, 4 as uint 64, 9 as int 32, nil].
	var nc = "9d" + "02" + "01" + "d30000000000000007" + "cd0002" + "cd03e8"
	nc += "93" + "03" + "ca3f000000" + "d10001"
	nc += "dc0004" + "00" + "00" + "00" + "cb3ff0000000000000"
	nc += "cdea60" + "c3" + "c0" + "cf0000000000000004" + "d200000009" + "c0"
	var d = Codec.decode(C.hex_decode(nc), 512)
	check(d["ok"] and d["session"] == 7 and d["seq"] == 2 and d["t_client_us"] == 1000
		and d["position"] == [3.0, 0.5, 1.0] and d["orientation"] == [0.0, 0.0, 0.0, 1.0]
		and typeof(d["rpm"]) == 3 and d["rpm"] == 60000.0 and d["flags"] == 4
		and d["stream"] == 9, "non-canonical POSE: " + str(d))
	# v1's BAD_VERSION NOTICE (a v1 server's answer to our POSEs) is read, as version 1.
	d = Codec.decode(C.hex_decode("97010307020003c0"))
	check(d["ok"] and d["version"] == 1 and d["type"] == 3 and d["error"] == 3
		and d["stream"] == 0 and d["session"] == 7, "v1 BAD_VERSION notice: " + str(d))
	# What must be refused, and whether the header was still readable (a NOTICE is possible).
	var head = "9d0201070203" + "93000000" + "9400000001"  # POSE header, position, orientation
	var refused = {
		"spindle as 1": [head + "00" + "01" + "c0" + "00" + "00" + "c0", true],
		"velocity of 2": [head + "00" + "c3" + "920000" + "00" + "00" + "c0", true],
		"str as rpm": [head + "a131" + "c3" + "c0" + "00" + "00" + "c0", true],
		"stream 2^32": [head + "00" + "c3" + "c0" + "00" + "cf0000000100000000" + "c0", true],
		"negative stream": [head + "00" + "c3" + "c0" + "00" + "ff" + "c0", true],
		"POSE without stream": ["9c0201070203" + "93000000" + "9400000001" + "00c3c000c0",
			true],
		"v1 POSE": ["9c0101070203" + "93000000" + "9400000001" + "00c3c000c0", true],
		"v1 notice not BAD_VERSION": ["97010307020006c0", true],
		"v1-shaped v2 notice": ["97020307020003c0", true],
		"bin 9 tag": ["9802030702000500" + "c409" + "000000000000000000", true],
		"negative error": ["980203070200" + "ff" + "00" + "c0", true],
		"notice stream 2^32": ["98020307020005" + "cf0000000100000000" + "c0", true],
		"negative t_client_us": ["9802030702" + "d3ffffffffffffffff" + "0500c0", false],
		"t_client_us 2^63": ["9802030702" + "cf8000000000000000" + "0500c0", false],
		"seq 2^32": ["98020307" + "cf0000000100000000" + "000500c0", false],
		"map": ["8101", false],
		"array of 33": ["dc0021", false],
		"truncated": ["980203070200", false],
		"trailing byte": ["9802030702000500c0c0", false],
		"nested too deep": ["9191919191919191", false],
		"ext": ["d40100", false],
	}
	for what in refused:
		var r = Codec.decode(C.hex_decode(refused[what][0]), 512)
		check(not r["ok"], "accepted: " + what)
		check(r["addressable"] == refused[what][1], "addressable wrong: %s: %s" % [what, str(r)])
	# A 16-byte tag in a bin 16 form decodes but never verifies (SPEC 2.2, 4.3).
	var bin16 = "9802030702000600" + "c50010" + "00000000000000000000000000000000"
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
			b[0] = 0x90 + rng.randi_range(5, 13)
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

	var handshake = handshake_checks()

	# Cost per tick on this machine: a tagged POSE encoded, a tagged REPLY believed.
	var key = C.hex_decode("00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff")
	var mac = Hmac.new(key)
	var rules = Rules.new(7, key, 1)
	rules.pose([12.5, -0.25, 30.0], [0.0, 0.0, 0.7, 0.7], 60000.0, true, null, 0, 999000)
	rules.accept(notice(mac, 7, 1, 999000, M.NEW_STREAM, 77), 999500)
	check(rules.stream == 77, "the cost loop streams on 77")
	var n_iter = 2000
	var t0 = C.now_us()
	for i in range(n_iter):
		rules.pose([12.5, -0.25, 30.0], [0.0, 0.0, 0.7, 0.7], 60000.0, true, null, 0, 1000000 + i, i)
	var pose_us = float(C.now_us() - t0) / n_iter
	var reply = reply_fields(7, 0, 0)
	var datagrams = []
	for i in range(n_iter):
		reply["seq"] = i + 2
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
		"handshake": handshake,
		"pose_encode_us": pose_us, "reply_accept_us": reply_us, "replies_believed": believed})
