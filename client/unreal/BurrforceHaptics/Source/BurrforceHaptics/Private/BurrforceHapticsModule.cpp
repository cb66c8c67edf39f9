// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

#include "BurrforceCore.h"
#include "Modules/ModuleManager.h"

DEFINE_LOG_CATEGORY(LogBurrforce);

class FBurrforceHapticsModule : public IModuleInterface
{
public:
	virtual void StartupModule() override
	{
		UE_LOG(LogBurrforce, Log, TEXT("burrforce haptics: protocol version %u"),
			burrforce::kVersion);
	}
	virtual void ShutdownModule() override {}
};

IMPLEMENT_MODULE(FBurrforceHapticsModule, BurrforceHaptics)
