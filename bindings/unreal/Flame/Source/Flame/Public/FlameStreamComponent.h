// A component that plays continuous motion from a timeline of prompts with a libflame stream
// (flame_stream_*): Blueprints push segments (a prompt for some seconds or frames, or an
// FFlameStage with part texts) and interrupt the current one; every tick pumps at most
// StepsPerTick denoiser steps on a background thread and moves the playhead with game time at
// the model's frame rate, and Pose holds the frame under the playhead. With bCleanup the frames
// are read cleaned (flame_stream_read_cleaned: feet, floor, root motion, frame rate) as they
// settle, and the playhead moves at the cleanup's frame rate.

#pragma once

#include "CoreMinimal.h"
#include "Components/ActorComponent.h"
#include "FlameMotionComponent.h" // FFlameStage

#include "FlameStreamComponent.generated.h"

struct FFlameStreamJob;
struct FFlameModelRef;
struct FFlameRigSpec;
class UPoseableMeshComponent;

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

	/** Frames to keep generated ahead of the playhead; 0 = 60 (3 s at 20 fps). With a cleanup,
	 *  timeline frames settled ahead of it: the stream generates on while frames wait to
	 *  settle. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Stream", meta = (ClampMin = "0"))
	int32 Lookahead = 0;

	/** Frames kept behind the playhead (older ones are dropped); 0 = 1200. Timeline frames:
	 *  with a cleanup FrameRate the component keeps as many seconds of Pose's frames. */
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

	// ---- Cleanup (flame_stream_read_cleaned) -----------------------------------------------

	/** Read the frames cleaned, with the settings below (UFlameMotionComponent's, the same
	 *  defaults): Pose, RootLocation and RootBoneLocation then hold the cleaned frames, at
	 *  PoseFrameRate, each once it has settled (its cleanup final: with bLockFeet, once its
	 *  foot contact span or swing has ended; EndTimeline settles the last ones). Read by
	 *  StartStream; off by default (the raw frames, as before). With Layout 0 (the raw
	 *  features, never post-processed) the frames stay raw. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Cleanup")
	bool bCleanup = false;

	/** Cleanup: pin each planted foot where it stands, the leg solved by two-bone IK. The
	 *  cleanup settings are passed with every read; the stream keeps those of its first read
	 *  (made by StartStream): a change while streaming is refused (LastError, the log) and
	 *  the frames go on with the first settings. StopStream and StartStream to change them. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Cleanup")
	bool bLockFeet = true;

	/** Cleanup: put the first chunk's lowest foot contact at height 0 (the floor is fixed for
	 *  the whole stream). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Cleanup")
	bool bGround = true;

	/** Cleanup: frames per second of Pose, 1 to 240 (30 or 60 for a game); 0 = the model's.
	 *  Cleaned frame k is at k / FrameRate seconds of the timeline: CurrentFrame, ReadyFrames,
	 *  FirstHeldFrame and GetFramePose count frames at this rate (115 frames at 20 fps are
	 *  172 at 30). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Cleanup", meta = (ClampMin = "0", ClampMax = "240"))
	float FrameRate = 0.f;

	/** Cleanup: where the horizontal travel goes. Separate fills RootBoneLocation. (No loop
	 *  wrap: a stream has no end to wrap.) */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Cleanup")
	EFlameRootMotion RootMotion = EFlameRootMotion::Keep;

	/** Cleanup, with InPlace or Separate root motion: also remove the heading's drift. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Cleanup")
	bool bRemoveYaw = false;

	// ---- Retarget onto a character (flame_retarget_read_stream), read by StartStream -------

	/** The character to drive (as UFlameMotionComponent::RetargetMesh): its skeletal mesh's
	 *  reference skeleton becomes libflame's rig at StartStream; every frame received is also
	 *  put onto it (the same frames as Pose, cleaned with bCleanup), and each tick the frame
	 *  under the playhead goes into its BoneSpaceTransforms. None (default): no retarget. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Retarget")
	UPoseableMeshComponent* RetargetMesh = nullptr;

	/** Bone map JSON entries over libflame's automatic map (UFlameMotionComponent::BoneMapJson). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Retarget")
	FString BoneMapJson;

	/** Two-bone IK on the character's legs (planted feet stay planted on its proportions). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Retarget")
	bool bRetargetFeetIk = true;

	// ---- Playback, read every tick --------------------------------------------------------

	/** The most denoiser steps one tick's pump may run (on a background thread; the next pump
	 *  starts at a later tick once it is done). 0 pauses generation. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Stream", meta = (ClampMin = "0"))
	int32 StepsPerTick = 4;

	/** The playhead moves with game time while true. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Stream")
	bool bPlaying = true;

	/** Playback speed: 1 = real time (the model's frame rate, or the cleanup's). */
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

	/** Declares the timeline complete (flame_stream_close, at the next pump): once the pushed
	 *  segments are generated every frame settles, so with bCleanup the last frames, whose
	 *  contact spans or swings were still open, arrive. Pushes and interrupts are refused
	 *  afterwards (StartStream starts a new timeline). False, with LastError, when the stream
	 *  is not started. */
	UFUNCTION(BlueprintCallable, Category = "Flame|Stream")
	bool EndTimeline();

	// ---- Output ---------------------------------------------------------------------------

	/** The frame under the playhead in Layout and Convention: GetValuesPerFrame() floats
	 *  (empty until the first frames are generated). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	TArray<float> Pose;

	/** The root joint's position in that frame (in Convention; centimetres by default). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	FVector RootLocation = FVector::ZeroVector;

	/** With RootMotion Separate (and bCleanup), the root bone's position in that frame (on the
	 *  ground: height 0, in Convention); zero otherwise. The pelvis (RootLocation) plus this is
	 *  the pelvis's path with RootMotion Keep. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Cleanup")
	FVector RootBoneLocation = FVector::ZeroVector;

	/** The frame in Pose (-1 before the first frame): a timeline frame, or with a cleanup a
	 *  cleaned frame at PoseFrameRate. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Stream")
	int64 CurrentFrame = -1;

	/** Frames the component can play (the playhead never passes them): the timeline frames
	 *  generated so far, or with a cleanup the cleaned frames settled so far (at
	 *  PoseFrameRate). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Stream")
	int64 ReadyFrames = 0;

	/** Timeline frames generated so far (at Fps): ReadyFrames without a cleanup. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Stream")
	int64 GeneratedFrames = 0;

	/** EndTimeline was called: the timeline takes no more segments. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Stream")
	bool bTimelineEnded = false;

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

	/** Frames per second of Pose and CurrentFrame: the cleanup's FrameRate with bCleanup, or
	 *  Fps (0 until the stream has started). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Cleanup")
	float PoseFrameRate = 0.f;

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

	/** The root bone's position in a held frame (RootBoneLocation's; zero without it). */
	UFUNCTION(BlueprintPure, Category = "Flame|Cleanup")
	FVector GetRootBoneLocationAt(int64 Frame) const;

	/** With RetargetMesh: the frame in Pose put onto its skeleton, per RigBoneNames bone the
	 *  local rotation (x, y, z, w; 4 floats) and translation (centimetres; 3), in Unreal's
	 *  convention; empty otherwise. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Retarget")
	TArray<float> BoneRotations;

	UPROPERTY(BlueprintReadOnly, Category = "Flame|Retarget")
	TArray<float> BoneTranslations;

	/** RetargetMesh's reference skeleton bones, in its order (set by StartStream). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Retarget")
	TArray<FString> RigBoneNames;

	/** A bone's retargeted local rotation in a held frame (identity when not held). */
	UFUNCTION(BlueprintPure, Category = "Flame|Retarget")
	FQuat GetBoneRotationAt(int64 Frame, int32 Bone) const;

	/** A bone's retargeted translation in a held frame (zero when not held). */
	UFUNCTION(BlueprintPure, Category = "Flame|Retarget")
	FVector GetBoneTranslationAt(int64 Frame, int32 Bone) const;

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
	/** Pose, RootLocation and RootBoneLocation from the frames received, for CurrentFrame. */
	void UpdatePose();

	/** The running stream, shared with its pumps (null when stopped). */
	TSharedPtr<FFlameStreamJob, ESPMode::ThreadSafe> Job;
	/** The loaded model, reused while ModelPath stays the same. */
	TSharedPtr<FFlameModelRef, ESPMode::ThreadSafe> Model;
	/** The frames received from the pumps, frame-major, from frame CacheFirst on (timeline
	 *  frames, or cleaned frames at PoseFrameRate): CacheFrames × ValuesPerFrame values in
	 *  Layout, and × 3 root locations (and root bone locations with RootMotion Separate). */
	TArray<float> Cache;
	TArray<float> RootCache;
	TArray<float> RootBoneCache;
	/** With a rig: the retargeted frames, CacheFrames × bones × 4 rotations and × 3 translations. */
	TArray<float> BoneRotationCache;
	TArray<float> BoneTranslationCache;
	/** The rig of the running stream (null without a RetargetMesh). */
	TSharedPtr<FFlameRigSpec, ESPMode::ThreadSafe> Rig;
	int64 CacheFirst = 0;
	int64 CacheFrames = 0;
	int32 ValuesPerFrame = 0;
	/** Held frames behind the playhead (the stream's window, in Pose's frames). */
	int64 KeepBehind = 1200;
	/** Seconds played: the playhead is at PlayTime × PoseFrameRate. */
	double PlayTime = 0.0;
	/** The playhead the last pump was given, and whether it ran steps or failed. */
	int64 SentPlayhead = -1;
	bool bLastPumpIdle = false;
	bool bPumpFailed = false;
};
