// A component that generates a motion from a prompt with libflame on a background thread and
// exposes its poses on the game thread: every step publishes the current pose buffer (the
// clean-motion estimate as a preview, the final sample at the end), copied into Pose at the
// next tick.

#pragma once

#include "CoreMinimal.h"
#include "Components/ActorComponent.h"

#include "FlameMotionComponent.generated.h"

struct FFlameJob;
struct FFlameModelRef;
struct FFlameFinishedSession;
struct FFlameRigSpec;
class UPoseableMeshComponent;

/** One time stage of a prompt (FlameStage): what the whole body does for Frames frames, and
 *  optionally what single body parts do (the HuMMan-MoGen annotation's fields; empty = the
 *  part follows Text). FineMoGen models compose stages and read the part texts; other models
 *  take one stage without part texts. */
USTRUCT(BlueprintType)
struct FLAME_API FFlameStage
{
	GENERATED_BODY()

	FFlameStage() = default;
	FFlameStage(const FString& InText, int32 InFrames) : Text(InText), Frames(InFrames) {}

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	FString Text;

	/** Frames of this stage (at least 1); the stages' frames add up to the component's Frames. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	int32 Frames = 0;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Parts")
	FString Head;

	/** The spine. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Parts")
	FString Stem;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Parts")
	FString LeftArm;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Parts")
	FString RightArm;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Parts")
	FString LeftLeg;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Parts")
	FString RightLeg;

	/** The root's trajectory. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Parts")
	FString Pelvis;
};

/** Where a clip's horizontal travel goes (FlameCleanupParams.root_motion). */
UENUM(BlueprintType)
enum class EFlameRootMotion : uint8
{
	/** On the pelvis, as the model made it. */
	Keep = 0 UMETA(DisplayName = "Keep"),
	/** Removed: the pelvis stays over the origin (an in-place clip). */
	InPlace = 1 UMETA(DisplayName = "In Place"),
	/** On a root bone on the ground under the pelvis (RootBoneLocations; the glTF export's
	 *  "root" node): the pelvis reads in place. What the Mannequin's root bone carries. */
	Separate = 2 UMETA(DisplayName = "Separate Root Bone"),
};

DECLARE_DYNAMIC_MULTICAST_DELEGATE_TwoParams(FFlameProgressSignature, int32, StepsDone, int32, StepsTotal);
DECLARE_DYNAMIC_MULTICAST_DELEGATE_OneParam(FFlameFinishedSignature, bool, bSucceeded);

UCLASS(ClassGroup = (Animation), meta = (BlueprintSpawnableComponent))
class FLAME_API UFlameMotionComponent : public UActorComponent
{
	GENERATED_BODY()

public:
	UFlameMotionComponent();

	/** The model file: absolute, or relative to the project's Content directory. Packaged
	 *  builds need its folder in Project Settings > Packaging > Additional Non-Asset
	 *  Directories to Copy. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	FString ModelPath = TEXT("Flame/flame_demo.safetensors");

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	FString Prompt = TEXT("a person walks forward and waves.");

	/** Prompts per time stage, in order, used instead of Prompt when not empty; their Frames
	 *  add up to Frames (which must then be set). FineMoGen models compose them (Pose still
	 *  holds Frames frames, the stages one after the other); other models take exactly one
	 *  stage without part texts, and fail the generation for more (see LastError). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Stages")
	TArray<FFlameStage> PromptStages;

	/** Appends a stage to PromptStages, for the next Generate. */
	UFUNCTION(BlueprintCallable, Category = "Flame|Stages")
	void AddPromptStage(const FFlameStage& Stage);

	/** Empties PromptStages: the next Generate uses Prompt. */
	UFUNCTION(BlueprintCallable, Category = "Flame|Stages")
	void ClearPromptStages();

	/** Frames to generate; 0 = the model's default. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame", meta = (ClampMin = "0"))
	int32 Frames = 0;

	/** Generate a loop of Frames frames whose end flows into its start, position and velocity
	 *  of every joint (FlameSessionParams.looped; a walk keeps its travel as root motion): the
	 *  library samples twice (a generation, then an edit keeping 0.5 s on both sides of the
	 *  wrap), so Generate takes two passes' steps; Pose holds the cycle. Latent models (MLD,
	 *  MoLA), prompt stages, editing and targets refuse it: Generate fails with the library's
	 *  message in LastError. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	bool bLoop = false;

	/** Sampler steps; 0 = the model's default (often 1000: set a small number with DDIM). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame", meta = (ClampMin = "0"))
	int32 Steps = 50;

	/** Which training steps to sample, as a guided-diffusion respacing string: "ddim50" (every
	 *  20th of 1000), "50" (50 evenly spread) or section counts "15,15,8,6,6"; empty = none. It
	 *  sets the step count (a nonzero Steps must agree). FLAME and MDM models only. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	FString Respacing;

	/** DDIM (few steps) instead of the model's default sampler. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	bool bUseDdim = true;

	/** Classifier-free guidance scale; negative = the model's default. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	float Guidance = -1.f;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame", meta = (ClampMin = "0"))
	int32 Seed = 0;

	/** Worker threads of the generation; 0 = one per core. Leave some for the game. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame", meta = (ClampMin = "0"))
	int32 Threads = 2;

	/** Publish the clean-motion estimate while stepping (a preview) rather than the noisy sample. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	bool bPreviewEstimate = true;

	/** Pose's layout, a FlameLayout value of flame.h passed through as an integer. The default,
	 *  2 = FLAME_LAYOUT_LOCAL_QUAT_XYZW: parent-relative quaternions x, y, z, w per joint
	 *  (GetJointRotation). 0 = the model's raw features. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	int32 Layout = 2;

	/** The coordinate convention of Pose and RootLocations, a FlameConvention value. The
	 *  default, 2 = FLAME_CONVENTION_UNREAL: Z up, X forward, left-handed, centimetres. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	int32 Convention = 2;

	/** flame_session_read flags: 1 = FLAME_READ_SMOOTH (FLAME's temporal smoothing, sigma = 1
	 *  frame; what the flame CLI applies by default to smpl24_6d models such as the demo model),
	 *  2 = FLAME_READ_RAW_SIGNS. 0 = the unsmoothed sample. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame")
	int32 ReadFlags = 0;

	/** Cleanup (flame_session_read_cleaned): pin each planted foot where it stands, the leg
	 *  solved by two-bone IK (no foot sliding). The cleanup settings apply to Pose,
	 *  RootLocations and ExportGltf; with Layout 0 (the raw features, never post-processed)
	 *  Pose and RootLocations stay raw. The defaults are libflame's game-ready ones
	 *  (flame_cleanup_params_default): feet locked, on the ground, root motion kept. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Cleanup")
	bool bLockFeet = true;

	/** Cleanup: put the clip's lowest foot contact at height 0. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Cleanup")
	bool bGround = true;

	/** Cleanup: frames per second of Pose, 1 to 240 (30 or 60 for a game); 0 = the model's (20
	 *  for FLAME models). Changes the frame count (GetFrameCount): the first and last frames'
	 *  times are kept, 40 frames at 20 fps are 59 at 30. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Cleanup", meta = (ClampMin = "0", ClampMax = "240"))
	float FrameRate = 0.f;

	/** Cleanup: where the horizontal travel goes. Separate fills RootBoneLocations. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Cleanup")
	EFlameRootMotion RootMotion = EFlameRootMotion::Keep;

	/** Cleanup, with InPlace or Separate root motion: also remove the heading's drift. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Cleanup")
	bool bRemoveYaw = false;

	/** Editing: a FlameEditTask value of flame.h, or -1 (the default) for plain generation.
	 *  0 = in-betweening (keep all but the middle half of the frames), 1 = prediction (keep
	 *  the first quarter), 2 = upper body (keep root path, pelvis and legs), 3 = path (keep
	 *  the root path). The kept values come from EditReference. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Editing")
	int32 EditTask = -1;

	/** The reference motion as the model's raw features, frame-major: frames × feature_dim
	 *  floats, at most Frames frames (e.g. a previous Pose read with Layout = 0). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Editing")
	TArray<float> EditReference;

	/** A FlameEditMethod value: 0 = the model family's own (the default). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Editing")
	int32 EditMethod = 0;

	/** Flow models: the fraction of the steps, from the noise end, that rewrite the trajectory. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Editing", meta = (ClampMin = "0", ClampMax = "1"))
	float EditTill = 0.2f;

	/** Paste the kept values exactly into the final motion and blend the seams (libflame's
	 *  default); off = the official methods' behaviour (kept values only close). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Editing")
	bool bEditPaste = true;

	/** Frames over which a seam's offset fades out (0 = no blending). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Editing", meta = (ClampMin = "0"))
	int32 EditSeamFrames = 4;

	/** Position targets (MoLA's MPGD guidance): the frames, joints and locations of joints to
	 *  steer the motion toward, entry i being joint TargetJoints[i] at frame TargetFrames[i]
	 *  at TargetLocations[i], in Convention (centimetres by default). A NaN component leaves
	 *  that axis free. Empty = no targets. See AddJointTarget. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Targets")
	TArray<int32> TargetFrames;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Targets")
	TArray<int32> TargetJoints;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Targets")
	TArray<FVector> TargetLocations;

	/** How strongly targets steer, in [0, 100] (0 = off; libflame's default 0.6). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Targets", meta = (ClampMin = "0", ClampMax = "100"))
	float TargetScale = 0.6f;

	/** A FlameTargetSchedule value: 0 = MPGD (4·τ·(1 − τ)), 1 = constant, -1 (default) = the
	 *  model family's (MPGD for latent models, constant for the others). */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Targets")
	int32 TargetSchedule = -1;

	/** Pins a joint (an index of JointNames) at a frame to a location in Convention, for the
	 *  next Generate. */
	UFUNCTION(BlueprintCallable, Category = "Flame|Targets")
	void AddJointTarget(int32 Frame, int32 Joint, FVector Location);

	/** Removes every position target. */
	UFUNCTION(BlueprintCallable, Category = "Flame|Targets")
	void ClearJointTargets();

	/** The targets' loss after the last generation's final step (metres, summed over the
	 *  targets' joints and frames); -1 when it had no targets. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Targets")
	float TargetLoss = -1.f;

	// ---- Retarget onto a character (flame_retarget_*) ---------------------------------------

	/** The character to drive: a Poseable Mesh component whose skeletal mesh's reference
	 *  skeleton (bone names, parents, reference pose) becomes libflame's rig at Generate, in
	 *  Unreal's convention. Each step then also fills BoneRotations and BoneTranslations with
	 *  the motion (Pose's, with the cleanup) put onto that skeleton, and with bPlayOnMesh every
	 *  tick writes the frame under the playhead into its BoneSpaceTransforms. None (default):
	 *  no retarget. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Retarget")
	UPoseableMeshComponent* RetargetMesh = nullptr;

	/** Which bone is which humanoid bone, as JSON with VRM 1.0 humanBone names as keys:
	 *  {"hips": "pelvis", "leftHand": "hand_l"} (null leaves a bone unmapped). Its entries go
	 *  over libflame's automatic map, which reads the Mannequin's (UE4 and UE5), Mixamo's,
	 *  Unity's and other common names: name only what that map gets wrong or misses. Empty
	 *  (default): the automatic map. A bone the mesh lacks fails Generate with the nearest
	 *  names in LastError. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Retarget")
	FString BoneMapJson;

	/** Two-bone IK on the character's legs: each ankle where the source's is (scaled to the
	 *  character), so planted feet stay planted on other proportions. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Retarget")
	bool bRetargetFeetIk = true;

	/** Every tick, pose RetargetMesh with the frame at the playhead (looping at PoseFrameRate,
	 *  from the first pose published); off: call ApplyRetargetFrame yourself. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Retarget")
	bool bPlayOnMesh = true;

	/** Playback speed of bPlayOnMesh: 1 = real time. */
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Flame|Retarget", meta = (ClampMin = "0"))
	float PlayRate = 1.f;

	/** The retargeted poses of the latest Pose: per frame and RigBoneNames bone the local
	 *  rotation, quaternion x, y, z, w (set it as the bone's rotation), frame-major:
	 *  GetFrameCount() × RigBoneNames.Num() × 4 floats, in Unreal's convention. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Retarget")
	TArray<float> BoneRotations;

	/** The same bones' translations relative to their parents (centimetres): the reference
	 *  pose's, except where the retarget moves a bone (the pelvis). × 3 floats a bone. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Retarget")
	TArray<float> BoneTranslations;

	/** RetargetMesh's reference skeleton bones, in its order (set by Generate). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Retarget")
	TArray<FString> RigBoneNames;

	/** The frame bPlayOnMesh (or ApplyRetargetFrame) last wrote to RetargetMesh; -1 before. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Retarget")
	int32 MeshFrame = -1;

	/** Writes a frame of BoneRotations and BoneTranslations into RetargetMesh's bone-space
	 *  transforms. False (and nothing written) when there is no such frame or the mesh is not
	 *  the one Generate took the rig from. */
	UFUNCTION(BlueprintCallable, Category = "Flame|Retarget")
	bool ApplyRetargetFrame(int32 Frame);

	/** A bone's retargeted local rotation in a frame (identity when out of range). */
	UFUNCTION(BlueprintPure, Category = "Flame|Retarget")
	FQuat GetBoneRotation(int32 Frame, int32 Bone) const;

	/** A bone's retargeted translation in a frame (zero when out of range). */
	UFUNCTION(BlueprintPure, Category = "Flame|Retarget")
	FVector GetBoneTranslation(int32 Frame, int32 Bone) const;

	/** Starts a generation on a background thread (the model is loaded there once and kept).
	 *  False if one is already running or libflame is unavailable (see LastError). */
	UFUNCTION(BlueprintCallable, Category = "Flame")
	bool Generate();

	/** Stops the running generation within one step; OnFinished(false) follows. */
	UFUNCTION(BlueprintCallable, Category = "Flame")
	void Cancel();

	UFUNCTION(BlueprintPure, Category = "Flame")
	bool IsGenerating() const { return Job.IsValid(); }

	/** The latest pose buffer, frame-major: GetFrameCount() × GetValuesPerFrame() floats. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	TArray<float> Pose;

	/** Frames of the latest Pose: Frames (or the model's default) resampled to FrameRate,
	 *  except for a latent model, whose decoder decides the length. */
	UFUNCTION(BlueprintPure, Category = "Flame")
	int32 GetFrameCount() const { return PoseFrames; }

	UFUNCTION(BlueprintPure, Category = "Flame")
	int32 GetValuesPerFrame() const { return PoseFrames > 0 ? Pose.Num() / PoseFrames : 0; }

	/** One frame's values of Pose (empty when out of range). */
	UFUNCTION(BlueprintPure, Category = "Flame")
	TArray<float> GetFramePose(int32 Frame) const;

	/** A joint's rotation in a frame, when Layout is a quaternion x, y, z, w layout (2 or 7);
	 *  identity otherwise or out of range. With the default Convention, an FQuat for the
	 *  bone's parent-relative rotation. */
	UFUNCTION(BlueprintPure, Category = "Flame")
	FQuat GetJointRotation(int32 Frame, int32 Joint) const;

	/** The root joint's position in a frame (in Convention; centimetres by default). */
	UFUNCTION(BlueprintPure, Category = "Flame")
	FVector GetRootLocation(int32 Frame) const;

	/** The root joint's positions, frame-major: GetFrameCount() × 3 floats. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	TArray<float> RootLocations;

	/** With RootMotion Separate, the root bone's positions (on the ground: height 0),
	 *  frame-major: GetFrameCount() × 3 floats in Convention; empty otherwise. The pelvis
	 *  (RootLocations) plus this is the pelvis's path with RootMotion Keep. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Cleanup")
	TArray<float> RootBoneLocations;

	/** The root bone's position in a frame (zero when out of range or without Separate). */
	UFUNCTION(BlueprintPure, Category = "Flame|Cleanup")
	FVector GetRootBoneLocation(int32 Frame) const;

	/** Frames per second of the latest Pose: FrameRate, or the model's. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame|Cleanup")
	float PoseFrameRate = 0.f;

	/** The model's skeleton (from flame_model_info), filled once the model is loaded. */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	TArray<FString> JointNames;

	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	TArray<int32> JointParents;

	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	int32 StepsDone = 0;

	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	int32 StepsTotal = 0;

	/** The last generation's prompt was longer than the text encoder's window, which kept
	 *  only its first tokens (a warning is logged too). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	bool bPromptTruncated = false;

	/** The part of the last prompt the window cut off, which the model ignored ("" if none). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	FString PromptDropped;

	/** libflame's status name and message of the last failure ("" if none). */
	UPROPERTY(BlueprintReadOnly, Category = "Flame")
	FString LastError;

	/** The last successful generation's final motion as a glTF 2.0 file
	 *  (flame_session_write_gltf), in OutBytes: bBinary = binary glTF (.glb), else JSON glTF
	 *  (.gltf) with the buffer embedded. The skeleton's joints are nodes named as JointNames,
	 *  with a skinned box figure and one animation (root translation and joint rotations, in
	 *  glTF's convention: Y up, metres) read with the generation's ReadFlags and cleanup (its
	 *  FrameRate, feet and ground; RootMotion Separate adds a node "root"); the prompt, seed and libflame version are in asset.extras. Unreal's glTF
	 *  importer (and Blender, Godot, three.js) loads it. Runs on the calling thread, a few
	 *  milliseconds. False, with OutBytes empty and the reason in LastError, when there is no
	 *  such motion: before the first generation succeeded, while one runs, after one failed or
	 *  was cancelled, after EndPlay. */
	UFUNCTION(BlueprintCallable, Category = "Flame|Export")
	bool ExportGltf(bool bBinary, TArray<uint8>& OutBytes);

	/** On the game thread, at the first tick after one or more steps finished, with the latest
	 *  pose in Pose: StepsDone may advance by more than one between calls when steps are faster
	 *  than ticks. */
	UPROPERTY(BlueprintAssignable, Category = "Flame")
	FFlameProgressSignature OnProgress;

	/** When a generation ends: true = Pose holds the final motion. */
	UPROPERTY(BlueprintAssignable, Category = "Flame")
	FFlameFinishedSignature OnFinished;

	virtual void TickComponent(float DeltaTime, ELevelTick TickType, FActorComponentTickFunction* ThisTickFunction) override;
	virtual void EndPlay(const EEndPlayReason::Type EndPlayReason) override;

private:
	/** The running generation, shared with its worker thread (null when idle). */
	TSharedPtr<FFlameJob, ESPMode::ThreadSafe> Job;
	/** The loaded model, reused while ModelPath stays the same. */
	TSharedPtr<FFlameModelRef, ESPMode::ThreadSafe> Model;
	/** The last successful generation's session, kept for ExportGltf until the next Generate
	 *  or EndPlay (null otherwise). Used on the game thread only, once its worker is done. */
	TSharedPtr<FFlameFinishedSession, ESPMode::ThreadSafe> Finished;
	int32 PoseFrames = 0;
	/** The rig of the last Generate with a RetargetMesh (null without one). */
	TSharedPtr<FFlameRigSpec, ESPMode::ThreadSafe> Rig;
	/** Frames of BoneRotations. */
	int32 RigFrames = 0;
	/** Seconds played by bPlayOnMesh since the first retargeted pose of this generation. */
	double PlayTime = 0.0;
	/** Advances the playhead and poses RetargetMesh (bPlayOnMesh). */
	void PlayOnMesh(float DeltaTime);
};
