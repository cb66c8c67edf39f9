# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Protocol version 1 constants (proto/SPEC.md sections 2-3).

const VERSION = 1
const TYPE_POSE = 1
const TYPE_REPLY = 2
const TYPE_NOTICE = 3
const POSE_ELEMENTS = 12
const REPLY_ELEMENTS = 24
const NOTICE_ELEMENTS = 7

const FLAG_RESET_VELOCITY = 1
const FLAG_NO_CARVE = 2
const FLAG_NEW_STREAM = 4

const STATUS_CUTTING = 1
const STATUS_CONTACT = 2
const STATUS_FORBIDDEN = 4
const STATUS_CLAMPED = 8
const STATUS_STALE = 16
const STATUS_SHAFT_CONTACT = 32
const STATUS_SLOW_SPINDLE = 64

const OK_CODE = 0
const MALFORMED = 1
const TOO_BIG = 2
const BAD_VERSION = 3
const BAD_TYPE = 4
const UNKNOWN_SESSION = 5
const BAD_TAG = 6
const BAD_VALUE = 7
const INTERNAL = 10

const ERROR_NAMES = {0: "OK", 1: "MALFORMED", 2: "TOO_BIG", 3: "BAD_VERSION", 4: "BAD_TYPE",
	5: "UNKNOWN_SESSION", 6: "BAD_TAG", 7: "BAD_VALUE", 10: "INTERNAL"}

# A tagged POSE is at most 148 bytes (a uint64 clock and a velocity); 512 is the server's
# limit. Server datagrams are at most 1024 bytes (a REPLY is at most 327).
const MAX_POSE_BYTES = 512
const MAX_SERVER_BYTES = 1024
const TAG_BYTES = 16
const MAX_ARRAY = 32
const MAX_BIN = 64

# Field names in wire order after the header (elements 0-4), tag excluded.
const POSE_FIELDS = ["position", "orientation", "rpm", "spindle_on", "velocity", "flags"]
const REPLY_FIELDS = ["t_recv_us", "t_send_us", "error", "status", "force", "resistive",
	"torque", "power_w", "vibration_amplitude", "vibration_frequency_hz", "vibration_axis",
	"proxy_position", "proxy_velocity", "coupling_stiffness", "coupling_damping",
	"removed_mm3", "bone_version", "feed_velocity"]
const NOTICE_FIELDS = ["error"]

# Field kinds (SPEC 2.2) of the REPLY's fields, in REPLY_FIELDS order.
const REPLY_KINDS = ["u64", "u64", "u16", "u32", "v3", "v3", "v3", "f", "f", "f", "v3", "v3",
	"v3", "f", "f", "f", "u64", "v3"]


static func error_name(code: int) -> String:
	return ERROR_NAMES.get(code, "ERROR_%d" % code)
