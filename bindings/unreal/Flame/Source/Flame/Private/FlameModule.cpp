#include "FlameModule.h"

#include "HAL/PlatformProcess.h"
#include "Interfaces/IPluginManager.h"
#include "Misc/Paths.h"

#include "flame.h"

DEFINE_LOG_CATEGORY(LogFlame);

FThreadSafeCounter FFlameModule::ActiveWorkers;

void FFlameModule::StartupModule()
{
#if PLATFORM_WINDOWS
	// flame.dll is delay-loaded: load it from where Build.cs stages it before the first call.
	const TSharedPtr<IPlugin> Plugin = IPluginManager::Get().FindPlugin(TEXT("Flame"));
	const FString DllPath = FPaths::Combine(Plugin->GetBaseDir(), TEXT("ThirdParty/flame/lib/Win64/flame.dll"));
	LibraryHandle = FPlatformProcess::GetDllHandle(*DllPath);
	if (LibraryHandle == nullptr)
	{
		UE_LOG(LogFlame, Error, TEXT("cannot load %s; see the plugin's README"), *DllPath);
		return;
	}
#endif
	// Linux and Mac link libflame directly: it is loaded with this module.
	const uint32 Abi = flame_abi_version();
	if (Abi != FLAME_ABI_VERSION)
	{
		UE_LOG(LogFlame, Error, TEXT("libflame ABI %u, but this plugin was built against flame.h ABI %d: rebuild the plugin"),
			Abi, FLAME_ABI_VERSION);
		return;
	}
	bAvailable = true;
	UE_LOG(LogFlame, Log, TEXT("libflame %s"), UTF8_TO_TCHAR(flame_version_string()));
}

void FFlameModule::ShutdownModule()
{
	bAvailable = false;
	if (LibraryHandle != nullptr)
	{
		// Unloading under a thread still inside libflame would crash it; leaking the handle at
		// exit is harmless.
		if (ActiveWorkers.GetValue() == 0)
		{
			FPlatformProcess::FreeDllHandle(LibraryHandle);
		}
		LibraryHandle = nullptr;
	}
}

IMPLEMENT_MODULE(FFlameModule, Flame)
