# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# The golden vectors (proto/vectors/vectors.json, passed in exact form by the pytest):
# encode each to its bytes, decode its bytes to its fields bit for bit, verify its tag with
# its key and reject it with another key and after every single-byte change.
# Usage: godot --no-window -s test_vectors.gd -- --vectors=PATH

extends SceneTree

const C = preload("../addons/burrforce/core/compat.gd")
const T = preload("testlib.gd")
const Codec = preload("../addons/burrforce/core/codec.gd")
const Hmac = preload("../addons/burrforce/core/hmac.gd")


func _init():
	var a = T.args()
	var vectors = C.json_parse(T.read_text(a["vectors"]))
	var failures = []
	var checked = {"encoded": 0, "decoded": 0, "verified": 0, "rejected_key": 0,
		"rejected_bytes": 0}
	for v in vectors:
		var name = v["name"]
		var data = C.hex_decode(v["hex"])
		var mac = null
		if typeof(v["key_hex"]) == TYPE_STRING:
			mac = Hmac.new(C.hex_decode(v["key_hex"]))
		var fields = {}
		for k in v["fields"].keys():
			fields[k] = T.exact(v["fields"][k])
		# The wire version (2; 1 for the v1-shaped BAD_VERSION notice), a JSON double here.
		var version = int(v["version"])
		fields["version"] = version
		var enc
		if v["type"] == "pose":
			enc = Codec.encode_pose_fields(fields, mac)
		elif v["type"] == "reply":
			enc = Codec.encode_reply_fields(fields, mac)
		else:
			enc = Codec.encode_notice_fields(fields, mac)
		if enc.hex_encode() != v["hex"]:
			failures.append("%s: encoded %s" % [name, enc.hex_encode()])
		else:
			checked["encoded"] += 1
		var d = Codec.decode(data, 1024)
		if not d["ok"]:
			failures.append("%s: decode failed: %s" % [name, d["reason"]])
		else:
			var bad = []
			for k in v["fields"].keys():
				if not d.has(k) or not T.same(d[k], v["fields"][k]):
					bad.append(k)
			if {"pose": 1, "reply": 2, "notice": 3}[v["type"]] != d["type"]:
				bad.append("type")
			if d["version"] != version:
				bad.append("version")
			if (mac == null) != (typeof(d["tag"]) == TYPE_NIL):
				bad.append("tag")
			if bad.size() > 0:
				failures.append("%s: fields differ: %s" % [name, str(bad)])
			else:
				checked["decoded"] += 1
		if mac != null:
			if mac.verify(data):
				checked["verified"] += 1
			else:
				failures.append("%s: tag does not verify" % name)
			var other_key = C.hex_decode(v["key_hex"])
			other_key[0] = other_key[0] ^ 1
			if Hmac.new(other_key).verify(data):
				failures.append("%s: verifies with another key" % name)
			else:
				checked["rejected_key"] += 1
			var accepted = 0
			for i in range(data.size()):
				var changed = C.slice(data, 0, data.size())
				changed[i] = changed[i] ^ 0x01
				if mac.verify(changed):
					accepted += 1
				changed[i] = data[i] ^ 0x80
				if mac.verify(changed):
					accepted += 1
			if accepted > 0:
				failures.append("%s: %d changed datagrams verify" % [name, accepted])
			else:
				checked["rejected_bytes"] += 1
	checked["vectors"] = vectors.size()
	checked["failures"] = failures
	T.finish(self, checked)
