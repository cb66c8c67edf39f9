// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The core library, included the way Unreal wants third-party code: its warnings are not
// Unreal's, and on Windows the Winsock headers must see the Windows platform types.
#pragma once

#include "CoreMinimal.h"

#if PLATFORM_WINDOWS
#include "Windows/AllowWindowsPlatformTypes.h"
#endif
THIRD_PARTY_INCLUDES_START
#include "burrforce/burrforce.hpp"
THIRD_PARTY_INCLUDES_END
#if PLATFORM_WINDOWS
#include "Windows/HideWindowsPlatformTypes.h"
#endif

DECLARE_LOG_CATEGORY_EXTERN(LogBurrforce, Log, All);

namespace BurrforceUE
{
	/// Unreal's FVector (cm, left-handed: the session frame `unreal`) as the core's Vec3.
	inline burrforce::Vec3 ToCore(const FVector& V) { return {V.X, V.Y, V.Z}; }
	inline FVector ToUE(const burrforce::Vec3& V) { return FVector(V.x, V.y, V.z); }
	/// FQuat goes out as X, Y, Z, W unchanged (SPEC 6.3).
	inline burrforce::Quat ToCore(const FQuat& Q) { return {Q.X, Q.Y, Q.Z, Q.W}; }
	inline std::string ToStd(const FString& S) { return std::string(TCHAR_TO_UTF8(*S)); }
	inline FString ToUE(const std::string& S) { return FString(UTF8_TO_TCHAR(S.c_str())); }
}
