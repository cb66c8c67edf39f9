# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# RFC 1982 serial numbers for uint32 seq (SPEC 5.1). GDScript ints are signed 64-bit, so the
# difference is masked to 32 bits instead of cast.

const MASK = 0xFFFFFFFF


# a is newer than b: 0 < (a - b) mod 2^32 < 2^31 (exactly 2^31 apart counts as stale).
static func newer(a: int, b: int) -> bool:
	var d = (a - b) & MASK
	return d != 0 and d < 0x80000000


static func next(a: int) -> int:
	return (a + 1) & MASK
