// The Flame module: makes libflame available (on Windows, loads flame.dll from the plugin's
// ThirdParty directory) and checks that its ABI is the one this plugin was built against.

#pragma once

#include "CoreMinimal.h"
#include "HAL/ThreadSafeCounter.h"
#include "Modules/ModuleInterface.h"
#include "Modules/ModuleManager.h"

FLAME_API DECLARE_LOG_CATEGORY_EXTERN(LogFlame, Log, All);

class FLAME_API FFlameModule : public IModuleInterface
{
public:
	virtual void StartupModule() override;
	virtual void ShutdownModule() override;

	static FFlameModule& Get() { return FModuleManager::LoadModuleChecked<FFlameModule>("Flame"); }

	/** Whether libflame was loaded and has the expected ABI; call nothing in it otherwise. */
	bool IsAvailable() const { return bAvailable; }

	/** Worker threads still inside libflame. While any runs, the DLL is not unloaded. */
	static FThreadSafeCounter ActiveWorkers;

private:
	void* LibraryHandle = nullptr;
	bool bAvailable = false;
};
