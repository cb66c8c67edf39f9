# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# The REST control plane (bearer token): sessions, parameters, stream restarts, mesh pages.
# Calls block until the answer is in or timeout_ms passes: call them from a thread of your
# own, or at start-up (creating a session that loads a CT can take seconds).
#
# Every call returns a Dictionary: "ok", "status" (HTTP status, 0 when nothing came back),
# "detail" (the server's error text, or what went wrong here), "json" (the decoded body, for
# JSON answers) and "body" (the raw bytes).

const C = preload("compat.gd")

var base_url = ""
var token = ""
var timeout_ms = 30000
var _host = ""
var _port = 80
var _prefix = ""
var _http = null


# url: the server's REST root as `burrforce serve` prints it, with or without /v1.
func _init(url: String, bearer_token: String):
	token = bearer_token
	var u = url.strip_edges()
	if u.ends_with("/"):
		u = u.substr(0, u.length() - 1)
	if u.ends_with("/v1"):
		u = u.substr(0, u.length() - 3)
	base_url = u
	var rest = u
	if rest.begins_with("http://"):
		rest = rest.substr(7, rest.length())
	var slash = rest.find("/")
	var hostport = rest if slash < 0 else rest.substr(0, slash)
	_prefix = "" if slash < 0 else rest.substr(slash, rest.length())
	var colon = hostport.rfind(":")
	if colon > 0 and hostport.find("]") < colon:
		_host = hostport.substr(0, colon)
		_port = int(hostport.substr(colon + 1, hostport.length()))
	else:
		_host = hostport
	_host = _host.replace("[", "").replace("]", "")


# --- sessions ---

# A new session on `bone` ("phantom:workpiece", a library name, …) in engine frame `frame`;
# wait: answer once the bone is loaded. json: id, key (hex), udp {host, port}, frame, bone.
func create_session(bone: String, frame: String = "godot", parameters: Dictionary = {},
		wait: bool = true) -> Dictionary:
	var p = parameters.duplicate()
	p["frame"] = frame
	return request("POST", "/v1/sessions" + ("?wait=true" if wait else ""),
		{"bone": {"source": bone}, "parameters": p})


func get_session(session_id: int) -> Dictionary:
	return request("GET", "/v1/sessions/%d" % session_id)


func delete_session(session_id: int) -> Dictionary:
	return request("DELETE", "/v1/sessions/%d" % session_id)


func get_parameters(session_id: int) -> Dictionary:
	return request("GET", "/v1/sessions/%d/parameters" % session_id)


# fields: e.g. {"us_n_mm2": 1610.2}
func set_parameters(session_id: int, fields: Dictionary) -> Dictionary:
	return request("PATCH", "/v1/sessions/%d/parameters" % session_id, fields)


# Closes the session's stream: its client's next POSE gets WRONG_STREAM, and the streamer
# says hello and streams on by itself (kept for compatibility: a new or restarted client
# needs no such call in protocol version 2).
func restart_stream(session_id: int) -> Dictionary:
	return request("POST", "/v1/sessions/%d/restart-stream" % session_id)


# One page of mesh chunks (proto/MESH.md): "body" holds the binary message. since < 0:
# omitted (the whole surface, FULL).
func mesh_page(session_id: int, since: int, cursor: int = 0, chunk_bricks: int = 2,
		frame: String = "session", winding: String = "cw") -> Dictionary:
	var q = "cursor=%d&chunk_bricks=%d&frame=%s&winding=%s" % [cursor, chunk_bricks, frame, winding]
	if since >= 0:
		q = "since=%d&" % since + q
	return request("GET", "/v1/sessions/%d/mesh?%s" % [session_id, q])


# --- transport ---

func request(method: String, path: String, body = null) -> Dictionary:
	var methods = {"GET": HTTPClient.METHOD_GET, "POST": HTTPClient.METHOD_POST,
		"PATCH": HTTPClient.METHOD_PATCH, "DELETE": HTTPClient.METHOD_DELETE,
		"PUT": HTTPClient.METHOD_PUT}
	# split() makes the engine's own string array (PoolStringArray / PackedStringArray),
	# which HTTPClient.request takes in both versions.
	var headers = ("Authorization: Bearer " + token).split("\n")
	headers.append("Accept: application/json, */*")
	var text = ""
	if typeof(body) != TYPE_NIL:
		text = C.json_stringify(body)
		headers.append("Content-Type: application/json")
	var deadline = C.now_us() + timeout_ms * 1000
	var err = _connect(deadline)
	if err != "":
		return _failed(0, err)
	if _http.request(methods[method], _prefix + path, headers, text) != OK:
		_http = null
		return _failed(0, "cannot send %s %s" % [method, path])
	while _http.get_status() == HTTPClient.STATUS_REQUESTING:
		if C.now_us() > deadline:
			_http = null
			return _failed(0, "timed out: %s %s" % [method, path])
		_http.poll()
		OS.delay_usec(500)
	if not _http.has_response():
		_http = null
		return _failed(0, "no response to %s %s" % [method, path])
	var status = _http.get_response_code()
	var content_type = ""
	for h in _http.get_response_headers():
		if h.to_lower().begins_with("content-type:"):
			content_type = h.substr(13, h.length()).strip_edges().to_lower()
	var data = C.bytes()
	while _http.get_status() == HTTPClient.STATUS_BODY:
		if C.now_us() > deadline:
			_http = null
			return _failed(status, "timed out reading %s %s" % [method, path])
		_http.poll()
		var chunk = _http.read_response_body_chunk()
		if chunk.size() == 0:
			OS.delay_usec(200)
		else:
			data.append_array(chunk)
	var out = {"ok": status >= 200 and status < 300, "status": status, "body": data,
		"json": null, "detail": "", "content_type": content_type}
	if content_type.begins_with("application/json") and data.size() > 0:
		out["json"] = C.json_parse(data.get_string_from_utf8())
	if not out["ok"]:
		var detail = "HTTP %d" % status
		if typeof(out["json"]) == TYPE_DICTIONARY and out["json"].has("detail"):
			detail = _readable(out["json"]["detail"])
		out["detail"] = "%s %s: %s" % [method, path, detail]
	return out


func close() -> void:
	if _http != null:
		_http.close()
		_http = null


func _connect(deadline: int) -> String:
	if _http != null and _http.get_status() == HTTPClient.STATUS_CONNECTED:
		return ""
	_http = HTTPClient.new()
	if _http.connect_to_host(_host, _port) != OK:
		return "cannot connect to %s:%d" % [_host, _port]
	while true:
		_http.poll()
		var s = _http.get_status()
		if s == HTTPClient.STATUS_CONNECTED:
			return ""
		if s != HTTPClient.STATUS_CONNECTING and s != HTTPClient.STATUS_RESOLVING:
			_http = null
			return "cannot connect to %s:%d (status %d)" % [_host, _port, s]
		if C.now_us() > deadline:
			_http = null
			return "timed out connecting to %s:%d" % [_host, _port]
		OS.delay_usec(500)
	return ""


# FastAPI's validation details are a list of {loc, msg}: "body.us_n_mm2: msg; …".
static func _readable(detail) -> String:
	if typeof(detail) != TYPE_ARRAY:
		return str(detail)
	var parts = []
	for e in detail:
		if typeof(e) == TYPE_DICTIONARY and e.has("msg"):
			var loc = []
			for x in e.get("loc", []):
				loc.append(str(x))
			parts.append(_dotted(loc) + ": " + str(e["msg"]))
		else:
			parts.append(str(e))
	var out = ""
	for i in range(parts.size()):
		out += ("; " if i > 0 else "") + parts[i]
	return out


static func _dotted(parts: Array) -> String:
	var out = ""
	for i in range(parts.size()):
		out += ("." if i > 0 else "") + parts[i]
	return out


static func _failed(status: int, detail: String) -> Dictionary:
	return {"ok": false, "status": status, "detail": detail, "json": null, "body": C.bytes(),
		"content_type": ""}
