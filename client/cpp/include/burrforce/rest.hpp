// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The REST control plane (`/v1`, bearer token): create and delete sessions, read and change
// parameters, restart a stream, fetch binary resources (mesh chunks). Every call blocks:
// call it from a worker thread, never the haptic or the render thread. Failures throw
// RestError with the server's own `detail` text.
#pragma once

#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

#include "burrforce/hmac.hpp"
#include "burrforce/http.hpp"
#include "burrforce/json.hpp"

namespace burrforce {

class RestError : public std::runtime_error {
 public:
  RestError(int status, const std::string& detail, const std::string& what)
      : std::runtime_error(what), status_(status), detail_(detail) {}
  /// The HTTP status (0: no answer at all).
  int status() const { return status_; }
  /// The server's `detail` text.
  const std::string& detail() const { return detail_; }

 private:
  int status_;
  std::string detail_;
};

/// A session as created: what the Streamer needs.
struct SessionInfo {
  uint32_t id = 0;
  std::string key_hex;        ///< empty for a session without a key
  std::vector<uint8_t> key;
  std::string udp_host;
  uint16_t udp_port = 0;
  std::string frame;
  std::string state;
  json::Value raw;            ///< the whole answer
};

class Rest {
 public:
  /// `base_url`: the server's REST URL without `/v1` (what `burrforce serve` prints).
  Rest(const std::string& base_url, std::string token, int timeout_ms = 30000)
      : url_(http::Url::parse(base_url)), token_(std::move(token)), timeout_ms_(timeout_ms) {}

  const http::Url& url() const { return url_; }

  /// POST /v1/sessions?wait=true. `bone`: "phantom:workpiece", "library:PATH", ...;
  /// `parameters_json`: extra fields of the parameters object as JSON text without braces
  /// (e.g. `"us_n_mm2": 1610.2`), or empty.
  SessionInfo create_session(const std::string& bone, const std::string& frame,
                             const std::string& parameters_json = "",
                             bool authenticated = true, int load_timeout_ms = 300000) {
    std::string params = "\"frame\": " + json::quote(frame);
    if (!parameters_json.empty()) params += ", " + parameters_json;
    std::string body = "{\"bone\": {\"source\": " + json::quote(bone) +
                       "}, \"authenticated\": " + (authenticated ? "true" : "false") +
                       ", \"parameters\": {" + params + "}}";
    json::Value v = call("POST", "/sessions?wait=true", body, load_timeout_ms);
    return session_info(v);
  }

  json::Value session(uint32_t id) { return call("GET", "/sessions/" + std::to_string(id)); }
  json::Value sessions() { return call("GET", "/sessions"); }
  void delete_session(uint32_t id) { call("DELETE", "/sessions/" + std::to_string(id)); }
  json::Value parameters(uint32_t id) {
    return call("GET", "/sessions/" + std::to_string(id) + "/parameters");
  }
  /// PATCH with a JSON object's text, e.g. `{"us_n_mm2": 1610.2}`.
  json::Value set_parameters(uint32_t id, const std::string& json_object) {
    return call("PATCH", "/sessions/" + std::to_string(id) + "/parameters", json_object);
  }
  void restart_stream(uint32_t id) {
    call("POST", "/sessions/" + std::to_string(id) + "/restart-stream", "");
  }
  json::Value health() { return call("GET", "/health"); }

  /// GET a binary resource under /v1 (e.g. mesh chunks); the body as bytes.
  std::string get_bytes(const std::string& target) {
    http::Response r = raw("GET", "/v1" + target, "", timeout_ms_);
    return r.body;
  }

  /// Any call under /v1 with a JSON answer (null for 204).
  json::Value call(const std::string& method, const std::string& target,
                   const std::string& body = "", int timeout_ms = 0) {
    http::Response r = raw(method, "/v1" + target, body, timeout_ms ? timeout_ms : timeout_ms_);
    if (r.status == 204 || r.body.empty()) return json::Value();
    try {
      return json::parse(r.body);
    } catch (const json::ParseError& e) {
      throw RestError(r.status, e.what(), method + " " + target + ": bad JSON: " + e.what());
    }
  }

 private:
  http::Response raw(const std::string& method, const std::string& target,
                     const std::string& body, int timeout_ms) {
    http::Request req;
    req.method = method;
    req.target = target;
    req.body = body;
    req.timeout_ms = timeout_ms;
    req.headers["Authorization"] = "Bearer " + token_;
    req.headers["Accept"] = "application/json, application/vnd.burrforce.mesh-chunks";
    if (!body.empty()) req.headers["Content-Type"] = "application/json";
    http::Response r;
    try {
      r = http::send(url_, req);
    } catch (const http::Error& e) {
      throw RestError(0, e.what(), method + " " + target + ": " + e.what());
    }
    if (!r.ok()) {
      std::string detail = detail_of(r);
      throw RestError(r.status, detail,
                      method + " " + target + ": " + std::to_string(r.status) + " " + detail);
    }
    return r;
  }

  /// FastAPI's `detail`: a string, or a list of validation errors with `msg` fields.
  static std::string detail_of(const http::Response& r) {
    try {
      json::Value v = json::parse(r.body);
      if (v.has("detail")) {
        const json::Value& d = v["detail"];
        if (d.is_string()) return d.as_string();
        if (d.is_array()) {
          std::string out;
          for (const json::Value& item : d.as_array()) {
            if (!item.has("msg")) continue;
            if (!out.empty()) out += "; ";
            out += item["msg"].as_string();
          }
          if (!out.empty()) return out;
        }
      }
    } catch (const std::exception&) {
    }
    return r.body.empty() ? r.reason : r.body.substr(0, 500);
  }

  SessionInfo session_info(const json::Value& v) {
    SessionInfo s;
    s.raw = v;
    s.id = static_cast<uint32_t>(v["id"].as_int());
    if (v.has("key") && v["key"].is_string()) {
      s.key_hex = v["key"].as_string();
      if (!parse_hex(s.key_hex, s.key)) throw RestError(0, "bad key", "session key is not hex");
    }
    const json::Value& udp = v["udp"];
    s.udp_host = udp["host"].as_string();
    // A wildcard bind address is not where to send: the REST host is.
    if (s.udp_host.empty() || s.udp_host == "0.0.0.0" || s.udp_host == "::")
      s.udp_host = url_.host;
    s.udp_port = static_cast<uint16_t>(udp["port"].as_int());
    if (v.has("frame") && v["frame"].is_string()) s.frame = v["frame"].as_string();
    if (v.has("state") && v["state"].is_string()) s.state = v["state"].as_string();
    return s;
  }

  http::Url url_;
  std::string token_;
  int timeout_ms_;
};

}  // namespace burrforce
