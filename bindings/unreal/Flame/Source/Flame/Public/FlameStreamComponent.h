// A component that plays continuous motion from a timeline of prompts with a libflame stream
// (flame_stream_*): Blueprints push segments (a prompt for some seconds or frames, or an
// FFlameStage with part texts) and interrupt the current one; every tick pumps at most
// StepsPerTick denoiser steps on a background thread and moves the playhead with game time at
// the model's frame rate, and Pose holds the frame under the playhead.

#pragma once

#include "CoreMinimal.h"
#include "Components/ActorComponent.h"
#include "FlameMotionComponent.h" // FFlameStage

#include "FlameStreamComponent.generated.h"

struct FFlameStreamJob;
struct FFlameModelRef;

DECLARE_DYNAMIC_MULTICAST_DELEGATE_OneParam(FFlameStreamStartedSignature, bool, bSucceeded);
DECLARE_DYNAMIC_MULTICAST_DELEGATE(FFlameStreamStarvingSignature);

UCLASS(ClassGroup = (Animation), meta = (BlueprintSpawnableComponent))
class FLAME_API UFlameStreamComponent : public UActorComponent
{
	GENERATED_BODY()

public:
	UFlameStreamComponent();

	// ---- Settings, read by StartStream ----------------------------------------------------

	/** The model file: absolute, or relative to the project's Content directory (see
	 *  UFlameMotionComponent::ModelPath). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	FString ModelPath = TEXT("Flame/flame_demo.safetensors");

	/** Start the stream in BeginPlay (otherwise call StartStream). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	bool bAutoStart = true;

	/** Frames per chunk, the kept ones included; 0 = the model's default frame count. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Stream", meta = (ClampMin = "0"))
	int32 Chunk = 0;

	/** Frames of the motion so far each chunk keeps and continues from; 0 = 20. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Stream", meta = (ClampMin = "0"))
	int32 Overlap = 0;

	/** Frames to keep generated ahead of the playhead; 0 = 60 (3 s at 20 fps). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Stream", meta = (ClampMin = "0"))
	int32 Lookahead = 0;

	/** Frames kept behind the playhead (older ones are dropped); 0 = 1200. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Stream", meta = (ClampMin = "0"))
	int32 Window = 0;

	/** Sampler steps per chunk; 0 = the model's default (often 1000: set a small number with
	 *  DDIM). Fewer steps keep up with playback more easily. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame", meta = (ClampMin = "0"))
	int32 Steps = 10;

	/** DDIM (few steps) instead of the model's default sampler. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	bool bUseDdim = true;

	/** Classifier-free guidance scale; negative = the model's default. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	float Guidance = -1.f;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame", meta = (ClampMin = "0"))
	int32 Seed = 0;

	/** Worker threads of the stream; 0 = one per core. Leave some for the game. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame", meta = (ClampMin = "0"))
	int32 Threads = 2;

	/** Pose's layout, a FlameLayout value of flame.h (2 = FLAME_LAYOUT_LOCAL_QUAT_XYZW, the
	 *  default: parent-relative quaternions x, y, z, w per joint; 0 = raw features). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	int32 Layout = 2;

	/** The convention of Pose and RootLocation, a FlameConvention value (2 =
	 *  FLAME_CONVENTION_UNREAL, the default: Z up, X forward, left-handed, centimetres). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	int32 Convention = 2;

	// ---- Playback, read every tick --------------------------------------------------------

	/** The most denoiser steps one tick's pump may run (on a background thread; the next pump
	 *  starts at a later tick once it is done). 0 pauses generation. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Stream", meta = (ClampMin = "0"))
	int32 StepsPerTick = 4;

	/** The playhead moves with game time while true. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Stream")
	bool bPlaying = true;

	/** Playback speed: 1 = the model's frame rate in game time. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Stream", meta = (ClampMin = "0"))
	float PlayRate = 1.f;

	// ---- Control --------------------------------------------------------------------------

	/** Loads the model (once per ModelPath, on a background thread) and starts an empty
	 *  stream with the settings above. False if one is running or libflame is unavailable
	 *  (see LastError); OnStarted reports whether the stream could be made. */
	UFUNCTION(BlueprintCallable, Category = "Flame")
	bool StartStream();

	/** Ends the stream: a pump running is cancelled within one layer of the network, the
	 *  timeline and the frames are gone. StartStream starts afresh. */
	UFUNCTION(BlueprintCallable, Category = "Flame")
	void StopStream();

	/** Between StartStream (loading included) and StopStream, EndPlay or a failed start. */
	UFUNCTION(BlueprintPure, Category = "Flame")
	bool IsStreaming() const { return Job.IsValid(); }

	/** Appends a segment: Prompt for Seconds of motion (at the model's frame rate, at least
	 *  one frame). False, with LastError, when the stream is not started or Seconds is not
	 *  positive. */
	UFUNCTION(BlueprintCallable, Category = "Flame|Stream")
	bool PushSegment(const FString& Prompt, float Seconds);

	/** Appends a segment of Frames frames (at least 1). */
	UFUNCTION(BlueprintCallable, Category = "Flame|Stream")
	bool PushSegmentFrames(const FString& Prompt, int32 Frames);

	/** Ends the current segment at the next chunk boundary (the chunk being generated
	 *  finishes), drops the queued segments and plays Prompt for Seconds after it. */
	UFUNCTION(BlueprintCallable, Category = "Flame|Stream")
	bool InterruptSegment(const FString& Prompt, float Seconds);

	UFUNCTION(BlueprintCallable, Category = "Flame|Stream")
	bool InterruptSegmentFrames(const FString& Prompt, int32 Frames);

	/** Appends a segment with part texts: Stage.Text for Stage.Frames frames, and what single
	 *  body parts do. Only FineMoGen models read part texts; other models refuse them
	 *  (INVALID_ARGUMENT in LastError). */
	UFUNCTION(BlueprintCallable, Category = "Flame|Stream")
	bool PushStage(const FFlameStage& Stage);

	/** InterruptSegmentFrames with part texts (see PushStage). */
	UFUNCTION(BlueprintCallable, Category = "Flame|Stream")
	bool InterruptStage(const FFlameStage& Stage);

	// ---- Output ---------------------------------------------------------------------------

	/** The frame under the playhead in Layout and Convention: GetValuesPerFrame() floats
	 *  (empty until the first frames are generated). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	TArray<float> Pose;

	/** The root joint's position in that frame (in Convention; centimetres by default). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	FVector RootLocation = FVector::ZeroVector;

	/** The timeline frame in Pose (-1 before the first frame). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Stream")
	int64 CurrentFrame = -1;

	/** Frames generated so far on the timeline (the playhead never passes them). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Stream")
	int64 ReadyFrames = 0;

	/** The first frame GetFramePose can still return (older ones were dropped: Window). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Stream")
	int64 FirstHeldFrame = 0;

	/** The playhead is held at the last frame generated: the stream is behind or starving. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Stream")
	bool bWaitingForFrames = false;

	/** Fewer than Lookahead frames are ready ahead of the playhead and no segment is left to
	 *  generate them from: push more (OnStarving fires when this becomes true). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Stream")
	bool bStarving = false;

	/** Denoiser steps the last pump ran, and all pumps of this stream. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Stream")
	int32 StepsLastPump = 0;

	UPROPERTY(BlueprintReadOnly, Category = "Flame|Stream")
	int64 StepsTotal = 0;

	/** The model's frame rate (0 until it is loaded). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	float Fps = 0.f;

	UFUNCTION(BlueprintPure, Category = "Flame")
	int32 GetValuesPerFrame() const { return ValuesPerFrame; }

	/** A joint's rotation in Pose, when Layout is a quaternion x, y, z, w layout (2 or 7);
	 *  identity otherwise. */
	UFUNCTION(BlueprintPure, Category = "Flame")
	FQuat GetJointRotation(int32 Joint) const { return GetJointRotationAt(CurrentFrame, Joint); }

	/** The values of a held frame, FirstHeldFrame to ReadyFrames - 1 once received (empty
	 *  otherwise): e.g. the next frame, to blend between frames. */
	UFUNCTION(BlueprintPure, Category = "Flame")
	TArray<float> GetFramePose(int64 Frame) const;

	UFUNCTION(BlueprintPure, Category = "Flame")
	FQuat GetJointRotationAt(int64 Frame, int32 Joint) const;

	UFUNCTION(BlueprintPure, Category = "Flame")
	FVector GetRootLocationAt(int64 Frame) const;

	/** The model's skeleton (from flame_model_info), filled once the stream has started. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	TArray<FString> JointNames;

	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	TArray<int32> JointParents;

	/** libflame's status name and message of the last failure ("" if none). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	FString LastError;

	/** When the stream has been made (true) or could not be (false, see LastError). */
	UPROPERTY(BlueprintAssignable, Category = "Flame")
	FFlameStreamStartedSignature OnStarted;

	/** When bStarving becomes true: push the next segment. */
	UPROPERTY(BlueprintAssignable, Category = "Flame")
	FFlameStreamStarvingSignature OnStarving;

	virtual void BeginPlay() override;
	virtual void TickComponent(float DeltaTime, ELevelTick TickType, FActorComponentTickFunction* ThisTickFunction) override;
	virtual void EndPlay(const EEndPlayReason::Type EndPlayReason) override;

private:
	/** Queues a segment for the stream's next pump (Seconds > 0: converted with the model's
	 *  frame rate; otherwise Stage.Frames). */
	bool Queue(const FFlameStage& Stage, float Seconds, bool bInterrupt, bool bStage);
	/** Starts the next pump on a background thread. */
	void Launch();
	/** Pose and RootLocation from the frames received, for CurrentFrame. */
	void UpdatePose();

	/** The running stream, shared with its pumps (null when stopped). */
	TSharedPtr<FFlameStreamJob, ESPMode::ThreadSafe> Job;
	/** The loaded model, reused while ModelPath stays the same. */
	TSharedPtr<FFlameModelRef, ESPMode::ThreadSafe> Model;
	/** The frames received from the pumps, frame-major, from timeline frame CacheFirst on:
	 *  CacheFrames × ValuesPerFrame values in Layout, and × 3 root locations. */
	TArray<float> Cache;
	TArray<float> RootCache;
	int64 CacheFirst = 0;
	int64 CacheFrames = 0;
	int32 ValuesPerFrame = 0;
	/** Held frames behind the playhead (the stream's window). */
	int64 KeepBehind = 1200;
	/** Seconds played: the playhead is at PlayTime × Fps. */
	double PlayTime = 0.0;
	/** The playhead the last pump was given, and whether it ran steps or failed. */
	int64 SentPlayhead = -1;
	bool bLastPumpIdle = false;
	bool bPumpFailed = false;
};
