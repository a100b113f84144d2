// The Flame module: the libflame C ABI (ThirdParty/flame) plus a small component over it.
//
// ThirdParty/flame/include/flame.h      include/flame.h of the libflame checkout
// ThirdParty/flame/lib/Win64/           flame.dll, flame.dll.lib (cargo build --release, MSVC)
// ThirdParty/flame/lib/Linux/           libflame.so
// ThirdParty/flame/lib/Mac/             libflame.dylib
// (bindings/unreal/stage.sh copies them there.)

using System.IO;
using UnrealBuildTool;

public class Flame : ModuleRules
{
	public Flame(ReadOnlyTargetRules Target) : base(Target)
	{
		PCHUsage = PCHUsageMode.UseExplicitOrSharedPCHs;

		PublicDependencyModuleNames.AddRange(new string[] { "Core", "CoreUObject", "Engine" });
		// IPluginManager, to find the DLL under the plugin's directory on Windows.
		PrivateDependencyModuleNames.Add("Projects");

		string ThirdPartyDir = Path.Combine(PluginDirectory, "ThirdParty", "flame");
		PublicIncludePaths.Add(Path.Combine(ThirdPartyDir, "include"));

		// RuntimeDependencies name the shared library so that packaged builds stage it (at the
		// same path relative to the plugin); without it a packaged game fails to load libflame.
		if (Target.Platform == UnrealTargetPlatform.Win64)
		{
			string LibDir = Path.Combine(ThirdPartyDir, "lib", "Win64");
			PublicAdditionalLibraries.Add(Path.Combine(LibDir, "flame.dll.lib"));
			// Loaded by FFlameModule::StartupModule from the plugin directory, which is not on
			// the DLL search path; the delay-load binds to that already loaded module.
			PublicDelayLoadDLLs.Add("flame.dll");
			RuntimeDependencies.Add("$(PluginDir)/ThirdParty/flame/lib/Win64/flame.dll");
		}
		else if (Target.Platform == UnrealTargetPlatform.Linux)
		{
			// UBT adds an $ORIGIN-relative rpath for this directory. The library needs an SONAME
			// (stage.sh sets one), or the binary records this absolute build-machine path.
			string LibDir = Path.Combine(ThirdPartyDir, "lib", "Linux");
			PublicAdditionalLibraries.Add(Path.Combine(LibDir, "libflame.so"));
			RuntimeDependencies.Add("$(PluginDir)/ThirdParty/flame/lib/Linux/libflame.so");
		}
		else if (Target.Platform == UnrealTargetPlatform.Mac)
		{
			// rustc gives the dylib the install name @rpath/libflame.dylib.
			string LibDir = Path.Combine(ThirdPartyDir, "lib", "Mac");
			PublicAdditionalLibraries.Add(Path.Combine(LibDir, "libflame.dylib"));
			RuntimeDependencies.Add("$(PluginDir)/ThirdParty/flame/lib/Mac/libflame.dylib");
		}
	}
}
