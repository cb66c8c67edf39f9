// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors

using System.IO;
using UnrealBuildTool;

public class BurrforceHaptics : ModuleRules
{
	public BurrforceHaptics(ReadOnlyTargetRules Target) : base(Target)
	{
		PCHUsage = PCHUsageMode.UseExplicitOrSharedPCHs;

		// The core library (client/cpp/include) reports REST and mesh-format failures with
		// C++ exceptions; the component catches them and logs. Unreal disables them by default.
		bEnableExceptions = true;

		PublicDependencyModuleNames.AddRange(new string[] {
			"Core", "CoreUObject", "Engine", "ProceduralMeshComponent" });

		// The header-only core. A release copies client/cpp/include into
		// Source/ThirdParty/burrforce/include (client/unreal/stage_core.sh); working from a
		// checkout of the repository, the plugin uses client/cpp/include where it lies.
		string Staged = Path.Combine(ModuleDirectory, "..", "ThirdParty", "burrforce", "include");
		string InRepo = Path.GetFullPath(Path.Combine(ModuleDirectory, "..", "..", "..", "..",
			"cpp", "include"));
		string Core = Directory.Exists(Staged) ? Staged : InRepo;
		if (!File.Exists(Path.Combine(Core, "burrforce", "burrforce.hpp")))
		{
			throw new BuildException("burrforce core headers not found: run " +
				"client/unreal/stage_core.sh (or copy client/cpp/include to " + Staged + ")");
		}
		PublicIncludePaths.Add(Core);

		// The core opens its own UDP and TCP sockets (Winsock on Windows).
		if (Target.Platform == UnrealTargetPlatform.Win64)
		{
			PublicSystemLibraries.Add("ws2_32.lib");
		}
	}
}
