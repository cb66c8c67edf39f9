// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// Unreal defines function-like macros with common names (check, verify, ensure, ...). The
// core is included after them in the plugin, so it must not use those names as functions:
// this file fails to compile if it does.
#define check(expr) static_assert(false, "Unreal's check macro expanded")
#define checkf(expr, ...) static_assert(false, "Unreal's checkf macro expanded")
#define verify(expr) static_assert(false, "Unreal's verify macro expanded")
#define verifyf(expr, ...) static_assert(false, "Unreal's verifyf macro expanded")
#define ensure(expr) static_assert(false, "Unreal's ensure macro expanded")
#define ensureMsgf(expr, ...) static_assert(false, "Unreal's ensureMsgf macro expanded")
#define TEXT(x) static_assert(false, "Unreal's TEXT macro expanded")

#include "burrforce/burrforce.hpp"

int main() { return burrforce::kVersion == 2 ? 0 : 1; }
