// What the plugin's components share: a reference-counted model, the count of holders of
// libflame's threads, libflame's failure message and UTF-8 copies of FStrings. Private to the
// module; include it after the engine headers (it includes flame.h, which defines a few
// unprefixed names).

#pragma once

#include "CoreMinimal.h"
#include "FlameModule.h"
#include "FlameMotionComponent.h" // FFlameStage

#include "flame.h"

/** A loaded model; freed when the last holder (component or worker) lets go. */
struct FFlameModelRef
{
	FlameModel* Handle;
	FString Path;

	FFlameModelRef(FlameModel* InHandle, const FString& InPath) : Handle(InHandle), Path(InPath) {}
	~FFlameModelRef() { flame_model_free(Handle); }
};

/** Counts a holder of libflame's threads in FFlameModule::ActiveWorkers, which keeps the
 *  library loaded: a generation's worker, a finished session or a stream (whose own threads
 *  live inside libflame until it is freed). */
struct FFlameWorkerCount
{
	FFlameWorkerCount() { FFlameModule::ActiveWorkers.Increment(); }
	~FFlameWorkerCount() { FFlameModule::ActiveWorkers.Decrement(); }
};

/** libflame's status name and message; call right after the failing call, on its thread. */
inline FString FlameFailure(FlameStatus Status)
{
	return FString::Printf(TEXT("%s: %s"), UTF8_TO_TCHAR(flame_status_string((int32_t)Status)), UTF8_TO_TCHAR(flame_last_error()));
}

/** S as NUL-terminated UTF-8 that outlives the expression (unlike TCHAR_TO_UTF8's). */
inline TArray<ANSICHAR> Utf8Z(const FString& S)
{
	FTCHARToUTF8 Utf8(*S);
	TArray<ANSICHAR> Out;
	Out.Append((const ANSICHAR*)Utf8.Get(), Utf8.Length());
	Out.Add('\0');
	return Out;
}

/** A stage's texts as UTF-8 and the FlameStage pointing into them, for one libflame call.
 *  Empty part texts are passed as NULL (the part follows Text). Not copyable: Raw points into
 *  Texts. */
struct FFlameStageUtf8
{
	static const int32 TextsPerStage = 8; // the text, then the parts in FlameStage's order

	explicit FFlameStageUtf8(const FFlameStage& Stage, uint32 Frames)
	{
		const FString* Fields[TextsPerStage] = {&Stage.Text, &Stage.Head, &Stage.Stem, &Stage.LeftArm,
			&Stage.RightArm, &Stage.LeftLeg, &Stage.RightLeg, &Stage.Pelvis};
		for (int32 F = 0; F < TextsPerStage; F++)
		{
			Texts.Add(Utf8Z(*Fields[F]));
		}
		// Pointers into Texts only once it is complete (adding may move its buffers).
		const ANSICHAR* P[TextsPerStage];
		for (int32 F = 0; F < TextsPerStage; F++)
		{
			P[F] = (F > 0 && Fields[F]->IsEmpty()) ? nullptr : Texts[F].GetData();
		}
		FMemory::Memzero(Raw);
		Raw.struct_size = sizeof(FlameStage);
		Raw.frames = Frames;
		Raw.text = P[0];
		Raw.head = P[1];
		Raw.stem = P[2];
		Raw.left_arm = P[3];
		Raw.right_arm = P[4];
		Raw.left_leg = P[5];
		Raw.right_leg = P[6];
		Raw.pelvis = P[7];
	}
	FFlameStageUtf8(const FFlameStageUtf8&) = delete;
	FFlameStageUtf8& operator=(const FFlameStageUtf8&) = delete;

	TArray<TArray<ANSICHAR>> Texts;
	FlameStage Raw;
};
