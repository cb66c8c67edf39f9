# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Protocol version 2 constants (proto/SPEC.md sections 2-3).

const VERSION = 2
# A v1 server answers a v2 datagram with a BAD_VERSION NOTICE in v1's shape (and a v2 server
# answers v1 datagrams so): the one v1 message the decoder still reads.
const VERSION_1 = 1
const TYPE_POSE = 1
const TYPE_REPLY = 2
const TYPE_NOTICE = 3
const POSE_ELEMENTS = 13
const REPLY_ELEMENTS = 24
const NOTICE_ELEMENTS = 8
const NOTICE_V1_ELEMENTS = 7

# Bit 2 (v1's FLAG_NEW_STREAM) is reserved again: the server hands out streams.
const FLAG_RESET_VELOCITY = 1
const FLAG_NO_CARVE = 2

# A POSE whose stream (element 11) is 0 asks for a stream and is not ticked.
const HELLO_STREAM = 0

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
const NEW_STREAM = 11  # notice: the stream to put in element 11 of the next POSEs
const WRONG_STREAM = 12  # notice: the POSE's stream is not (or no longer) open: say hello

const ERROR_NAMES = {0: "OK", 1: "MALFORMED", 2: "TOO_BIG", 3: "BAD_VERSION", 4: "BAD_TYPE",
	5: "UNKNOWN_SESSION", 6: "BAD_TAG", 7: "BAD_VALUE", 10: "INTERNAL", 11: "NEW_STREAM",
	12: "WRONG_STREAM"}

# A tagged POSE is at most 153 bytes (a uint64 clock and a velocity); 512 is the server's
# limit. Server datagrams are at most 1024 bytes (a REPLY is at most 327).
const MAX_POSE_BYTES = 512
const MAX_SERVER_BYTES = 1024
const TAG_BYTES = 16
const MAX_ARRAY = 32
const MAX_BIN = 64

# Field names in wire order after the header (elements 0-4), tag excluded.
const POSE_FIELDS = ["position", "orientation", "rpm", "spindle_on", "velocity", "flags",
	"stream"]
const REPLY_FIELDS = ["t_recv_us", "t_send_us", "error", "status", "force", "resistive",
	"torque", "power_w", "vibration_amplitude", "vibration_frequency_hz", "vibration_axis",
	"proxy_position", "proxy_velocity", "coupling_stiffness", "coupling_damping",
	"removed_mm3", "bone_version", "feed_velocity"]
const NOTICE_FIELDS = ["error", "stream"]

# Field kinds (SPEC 2.2) of the REPLY's fields, in REPLY_FIELDS order.
const REPLY_KINDS = ["u64", "u64", "u16", "u32", "v3", "v3", "v3", "f", "f", "f", "v3", "v3",
	"v3", "f", "f", "f", "u64", "v3"]


static func error_name(code: int) -> String:
	return ERROR_NAMES.get(code, "ERROR_%d" % code)
