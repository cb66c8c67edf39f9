# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# The REST helper against a live server: create a session in Godot's frame, read and patch
# its parameters, restart its stream, delete it; errors come back with the server's detail.
# Usage: godot --no-window -s tests/test_rest.gd -- --url=HTTP_URL --token=T

extends SceneTree

const T = preload("testlib.gd")
const Rest = preload("../addons/burrforce/core/rest.gd")


func _init():
	var a = T.args()
	var rest = Rest.new(a["url"] + "/v1/", a["token"])  # a trailing /v1/ is accepted
	var out = {}
	var c = rest.create_session("phantom:workpiece", "godot")
	out["create"] = {"ok": c["ok"], "status": c["status"], "detail": c["detail"]}
	if not c["ok"]:
		return T.finish(self, out)
	var sid = int(c["json"]["id"])
	out["session"] = sid
	out["frame"] = c["json"]["frame"]
	out["key_len"] = str(c["json"]["key"]).length()
	out["udp_port"] = int(c["json"]["udp"]["port"])
	var g = rest.get_session(sid)
	out["get"] = {"status": g["status"], "id": int(g["json"]["id"]), "state": g["json"]["state"]}
	var p = rest.get_parameters(sid)
	out["parameters"] = {"status": p["status"], "frame": p["json"]["frame"]}
	var s = rest.set_parameters(sid, {"us_n_mm2": 1610.2})
	out["patch"] = {"status": s["status"], "us_n_mm2": s["json"]["us_n_mm2"]}
	var bad = rest.set_parameters(sid, {"no_such_field": 1.0})
	out["patch_bad"] = {"ok": bad["ok"], "status": bad["status"], "detail": bad["detail"]}
	var r = rest.restart_stream(sid)
	out["restart"] = {"ok": r["ok"], "status": r["status"]}
	var d = rest.delete_session(sid)
	out["delete"] = {"ok": d["ok"], "status": d["status"]}
	var gone = rest.get_session(sid)
	out["get_deleted"] = {"ok": gone["ok"], "status": gone["status"], "detail": gone["detail"]}
	var denied = Rest.new(a["url"], "not-the-token").get_session(sid)
	out["wrong_token"] = {"ok": denied["ok"], "status": denied["status"], "detail": denied["detail"]}
	var nobody = Rest.new("http://127.0.0.1:9", a["token"])
	nobody.timeout_ms = 3000
	var refused = nobody.get_session(1)
	out["no_server"] = {"ok": refused["ok"], "status": refused["status"], "detail": refused["detail"]}
	T.finish(self, out)
