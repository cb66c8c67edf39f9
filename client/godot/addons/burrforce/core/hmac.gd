# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# HMAC-SHA256 (RFC 2104) truncated to 16 bytes: the datagram tag (SPEC 4). Godot has SHA-256
# (HashingContext) but no HMAC. The padded keys are computed once per key; one context is
# reused, so an instance belongs to one thread.

const C = preload("compat.gd")
const BLOCK = 64

var _ipad
var _opad
var _ctx


func _init(key):
	var k = key
	if k.size() > BLOCK:
		k = _sha256(k)
	_ipad = C.bytes(BLOCK)
	_opad = C.bytes(BLOCK)
	for i in range(BLOCK):
		var b = k[i] if i < k.size() else 0
		_ipad[i] = b ^ 0x36
		_opad[i] = b ^ 0x5c
	_ctx = HashingContext.new()


static func _sha256(data):
	var h = HashingContext.new()
	h.start(HashingContext.HASH_SHA256)
	h.update(data)
	return h.finish()


# The full 32-byte MAC of data.
func mac(data):
	_ctx.start(HashingContext.HASH_SHA256)
	_ctx.update(_ipad)
	if data.size() > 0:
		_ctx.update(data)
	var inner = _ctx.finish()
	_ctx.start(HashingContext.HASH_SHA256)
	_ctx.update(_opad)
	_ctx.update(inner)
	return _ctx.finish()


# The 16-byte tag of data (the datagram's bytes before the tag, c4 10 included).
func tag(data):
	var m = mac(data)
	m.resize(16)
	return m


# A tagged datagram: ends in c4 10 + the tag of everything before it. Compared in constant
# time (every byte is looked at) so that timing does not reveal how much of a forged tag is right.
func verify(datagram) -> bool:
	var n = datagram.size()
	if n < 18 or datagram[n - 18] != 0xc4 or datagram[n - 17] != 0x10:
		return false
	var expected = tag(C.slice(datagram, 0, n - 16))
	var diff = 0
	for i in range(16):
		diff = diff | (expected[i] ^ datagram[n - 16 + i])
	return diff == 0
