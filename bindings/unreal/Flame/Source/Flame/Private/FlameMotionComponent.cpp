#include "FlameMotionComponent.h"

#include "Async/Async.h"
#include "FlameModule.h"
#include "HAL/CriticalSection.h"
#include "Misc/Paths.h"
#include "Misc/ScopeLock.h"

#include <cmath>
#include <limits>

// Last: FlameCommon.h includes the C header, which defines a few unprefixed names.
#include "FlameCommon.h"

/** A finished generation's session, kept for UFlameMotionComponent::ExportGltf. */
struct FFlameFinishedSession
{
	FFlameWorkerCount WorkerCount; // first member, so destroyed last: after the session
	FlameSession* Handle;
	uint32 Flags; // the read flags of the generation
	FlameCleanupParams Cleanup; // its cleanup, when bCleanup
	bool bCleanup;

	FFlameFinishedSession(FlameSession* InHandle, uint32 InFlags, const FlameCleanupParams& InCleanup, bool bInCleanup)
		: Handle(InHandle), Flags(InFlags), Cleanup(InCleanup), bCleanup(bInCleanup) {}
	~FFlameFinishedSession() { flame_session_free(Handle); }
};

/**
 * One generation, shared by the component (game thread) and its worker. The worker owns the
 * session: it creates, steps and frees it. The game thread only cancels it, under Lock, which
 * the worker also holds whenever it publishes or changes Session, so the session is never
 * cancelled after it was freed. The worker never holds Lock while stepping.
 */
/** Params with `respacing` set to Spec, for one call. */
static const FlameSessionParams* WithRespacing(FlameSessionParams& Params, const ANSICHAR* Spec)
{
	Params.respacing = Spec;
	return &Params;
}

struct FFlameJob
{
	/** Counts this job in FFlameModule::ActiveWorkers. First member, so destroyed last: after
	 *  Model, whose destructor may be the job's last libflame call. */
	FFlameWorkerCount WorkerCount;

	// Inputs, fixed before the worker starts.
	FString Path;
	FString Prompt;
	TArray<FFlameStage> Stages; // used instead of Prompt when not empty
	FlameSessionParams Params; // respacing stays null here: see Respacing
	FString Respacing;         // empty = none; passed as UTF-8 for flame_session_new only
	int32 Layout = 0;
	int32 Convention = 0;
	uint32 Flags = 0;
	FlameCleanupParams Cleanup; // applied to pose reads and the export when bCleanup
	bool bCleanup = false;      // false for the raw features (Layout 0), never post-processed
	bool bRootBone = false;     // Separate root motion: the root bone's track is read too
	bool bPreviewEstimate = true;
	int32 EditTask = -1; // -1: no edit
	TArray<float> EditReference;
	FlameEditParams EditParams;
	TArray<int32> TargetFrames;
	TArray<int32> TargetJoints;
	TArray<FVector> TargetLocations;
	FlameTargetParams TargetParams;

	FCriticalSection Lock;
	// Guarded by Lock:
	TSharedPtr<FFlameModelRef, ESPMode::ThreadSafe> Model; // in: a cached model or null; out: the model used
	FlameSession* Session = nullptr;
	bool bStop = false;
	TArray<float> Latest;
	TArray<float> LatestRoot;
	TArray<float> LatestRootBone;
	float LatestFrameRate = 0.f;
	bool bLatestIsNew = false;
	int32 LatestFrames = 0; // frames of Latest and LatestRoot, as flame_session_read_frames says
	int32 StepsDone = 0;
	int32 StepsTotal = 0;
	bool bFinished = false;
	bool bSucceeded = false;
	FString Error;
	TArray<FString> JointNames;
	TArray<int32> JointParents;
	bool bPromptInfoNew = false; // the fields below were set and not yet taken by the component
	bool bPromptTruncated = false;
	uint32 PromptTokens = 0;
	uint32 PromptKept = 0;
	FString PromptDropped;
	double TargetLoss = -1.0; // after the last step; -1 without targets
	TSharedPtr<FFlameFinishedSession, ESPMode::ThreadSafe> Finished; // the session, after a success
	TArray<float> LatestBoneRotations; // with Rig: the retarget of the latest poses
	TArray<float> LatestBoneTranslations;
	int32 LatestBoneFrames = 0;

	// The character's rig (RetargetMesh's, null without one), fixed before the worker starts,
	// and the worker's retarget of it.
	TSharedPtr<FFlameRigSpec, ESPMode::ThreadSafe> Rig;
	FFlameRetargetRef Retarget;

	void Cancel()
	{
		FScopeLock Guard(&Lock);
		bStop = true;
		if (Session != nullptr)
		{
			flame_session_cancel(Session);
		}
	}

	void Run()
	{
		FString Failure;
		const bool bOk = Generate(Failure);
		FScopeLock Guard(&Lock);
		bFinished = true;
		bSucceeded = bOk;
		Error = Failure;
	}

private:
	bool Generate(FString& Failure)
	{
		TSharedPtr<FFlameModelRef, ESPMode::ThreadSafe> M;
		{
			FScopeLock Guard(&Lock);
			M = Model;
		}
		if (!M.IsValid())
		{
			FlameModel* Handle = nullptr;
			const FlameStatus Status = flame_model_load(TCHAR_TO_UTF8(*Path), nullptr, &Handle);
			if (Status != FLAME_STATUS_OK)
			{
				Failure = FlameFailure(Status);
				return false;
			}
			M = MakeShared<FFlameModelRef, ESPMode::ThreadSafe>(Handle, Path);
		}

		FlameModelInfo Info;
		FMemory::Memzero(Info);
		Info.struct_size = sizeof(Info);
		FlameStatus Status = flame_model_info(M->Handle, &Info);
		if (Status != FLAME_STATUS_OK)
		{
			Failure = FlameFailure(Status);
			return false;
		}
		FlameSession* S = nullptr;
		// The UTF-8 temporary lives until the end of the full expression, past the call.
		Status = flame_session_new(M->Handle, WithRespacing(Params, Respacing.IsEmpty() ? nullptr : TCHAR_TO_UTF8(*Respacing)), &S);
		if (Status != FLAME_STATUS_OK)
		{
			Failure = FlameFailure(Status);
			return false;
		}
		{
			FScopeLock Guard(&Lock);
			Model = M;
			for (uint32 J = 0; Info.joint_names != nullptr && J < Info.joint_count; J++)
			{
				JointNames.Add(UTF8_TO_TCHAR(Info.joint_names[J]));
				JointParents.Add(Info.joint_parents != nullptr ? Info.joint_parents[J] : -1);
			}
			if (bStop)
			{
				flame_session_free(S);
				Failure = TEXT("cancelled");
				return false;
			}
			Session = S;
		}
		FrameRate = bCleanup && Cleanup.fps > 0.f ? Cleanup.fps : Info.fps;
		const bool bOk = MakeRetarget(M->Handle, Failure) && Edit(S, Info.feature_dim, Failure) &&
			Targets(S, Info.joint_count, Failure) && Step(S, Failure);
		double Loss = -1.0;
		if (bOk && TargetFrames.Num() > 0 && flame_session_target_loss(S, &Loss) != FLAME_STATUS_OK)
		{
			Loss = -1.0; // scale 0: no step was guided
		}
		{
			FScopeLock Guard(&Lock);
			Session = nullptr;
			TargetLoss = Loss;
			if (bOk)
			{
				// Kept for ExportGltf: the component takes it over when it sees bFinished.
				// The export takes the cleanup whatever the Layout (a glTF file has poses, not features).
				Finished = MakeShared<FFlameFinishedSession, ESPMode::ThreadSafe>(S, Flags, Cleanup, true);
				S = nullptr;
			}
		}
		if (S != nullptr)
		{
			flame_session_free(S);
		}
		return bOk;
	}

	/** The retarget onto Rig, when there is one: made here, where the model is. */
	bool MakeRetarget(FlameModel* Model, FString& Failure)
	{
		if (!Rig.IsValid())
		{
			return true;
		}
		Retarget.Handle = Rig->Make(Model, Failure);
		return Retarget.Handle != nullptr;
	}

	/** Every frame of Which put onto the rig (flame_retarget_read, with the generation's read
	 *  flags and its cleanup whatever the Layout: a rig takes poses, as the export does). */
	FlameStatus ReadRig(FlameSession* S, int32 Which, TArray<float>& Rotations, TArray<float>& Translations, int32& OutFrames) const
	{
		size_t Frames = 0, Bones = 0;
		FlameStatus Status = flame_retarget_bone_count(Retarget.Handle, &Bones);
		if (Status == FLAME_STATUS_OK)
		{
			// The frame count first: a cleanup's frame rate changes it.
			Status = flame_retarget_read(Retarget.Handle, S, Which, Flags, &Cleanup, 0, 0, nullptr, 0, nullptr, 0, &Frames);
		}
		if (Status == FLAME_STATUS_OK)
		{
			Rotations.SetNumUninitialized((int32)(Frames * Bones * 4));
			Translations.SetNumUninitialized((int32)(Frames * Bones * 3));
			Status = flame_retarget_read(Retarget.Handle, S, Which, Flags, &Cleanup, 0, Frames, Rotations.GetData(),
				(size_t)Rotations.Num(), Translations.GetData(), (size_t)Translations.Num(), &Frames);
		}
		OutFrames = (int32)Frames;
		return Status;
	}

	/** Sets the edit (parameters, reference, task mask) when EditTask asks for one. */
	bool Edit(FlameSession* S, uint32 Dim, FString& Failure)
	{
		if (EditTask < 0)
		{
			return true;
		}
		if (Dim == 0 || EditReference.Num() % (int32)Dim != 0)
		{
			Failure = FString::Printf(TEXT("EditReference has %d values, not frames x %u features"), EditReference.Num(), Dim);
			return false;
		}
		FlameStatus Status = flame_session_set_edit_params(S, &EditParams);
		if (Status == FLAME_STATUS_OK && EditReference.Num() > 0)
		{
			Status = flame_session_set_reference(S, EditReference.GetData(), (uint32)(EditReference.Num() / (int32)Dim), Dim);
		}
		if (Status == FLAME_STATUS_OK)
		{
			Status = flame_session_set_task_mask(S, EditTask);
		}
		if (Status != FLAME_STATUS_OK)
		{
			Failure = FlameFailure(Status);
			return false;
		}
		return true;
	}

	/** Sets the position targets when there are any: frames × joints × 3 values, NaN where
	 *  no target (or a target's NaN component) leaves a value free. */
	bool Targets(FlameSession* S, uint32 Joints, FString& Failure)
	{
		const int32 N = TargetFrames.Num();
		if (N == 0 && TargetJoints.Num() == 0 && TargetLocations.Num() == 0)
		{
			return true;
		}
		if (TargetJoints.Num() != N || TargetLocations.Num() != N)
		{
			Failure = FString::Printf(TEXT("TargetFrames, TargetJoints and TargetLocations hold %d, %d and %d entries, not the same number"),
				N, TargetJoints.Num(), TargetLocations.Num());
			return false;
		}
		int32 Frames = 0;
		for (int32 I = 0; I < N; I++)
		{
			if (TargetFrames[I] < 0 || TargetJoints[I] < 0 || TargetJoints[I] >= (int32)Joints)
			{
				Failure = FString::Printf(TEXT("position target %d: frame %d, joint %d (the model has %u joints)"),
					I, TargetFrames[I], TargetJoints[I], Joints);
				return false;
			}
			Frames = FMath::Max(Frames, TargetFrames[I] + 1);
		}
		TArray<float> Values;
		Values.SetNumUninitialized(Frames * (int32)Joints * 3);
		for (int32 I = 0; I < Values.Num(); I++)
		{
			Values[I] = std::numeric_limits<float>::quiet_NaN();
		}
		for (int32 I = 0; I < N; I++)
		{
			float* V = Values.GetData() + ((int64)TargetFrames[I] * Joints + TargetJoints[I]) * 3;
			V[0] = (float)TargetLocations[I].X;
			V[1] = (float)TargetLocations[I].Y;
			V[2] = (float)TargetLocations[I].Z;
		}
		FlameTargetParams Params;
		FlameStatus Status = flame_session_target_params(S, &Params);
		if (Status == FLAME_STATUS_OK)
		{
			Params.scale = TargetParams.scale;
			if (TargetParams.schedule >= 0)
			{
				Params.schedule = TargetParams.schedule;
			}
			Status = flame_session_set_target_params(S, &Params);
		}
		if (Status == FLAME_STATUS_OK)
		{
			Status = flame_session_set_position_targets(S, Values.GetData(), (size_t)Values.Num(), nullptr, 0, Convention);
		}
		if (Status != FLAME_STATUS_OK)
		{
			Failure = FlameFailure(Status);
			return false;
		}
		return true;
	}

	/** Sets Stages through flame_session_set_prompt_stages, their texts as UTF-8 for the call. */
	bool SetStages(FlameSession* S, FString& Failure)
	{
		const int32 N = Stages.Num();
		const int32 TextsPerStage = 8; // the text, then the parts in FlameStage's order
		TArray<TArray<ANSICHAR>> Texts;
		for (int32 I = 0; I < N; I++)
		{
			const FFlameStage& Stage = Stages[I];
			if (Stage.Frames < 0)
			{
				Failure = FString::Printf(TEXT("PromptStages[%d].Frames is %d"), I, Stage.Frames);
				return false;
			}
			const FString* Fields[TextsPerStage] = {&Stage.Text, &Stage.Head, &Stage.Stem, &Stage.LeftArm,
				&Stage.RightArm, &Stage.LeftLeg, &Stage.RightLeg, &Stage.Pelvis};
			for (int32 F = 0; F < TextsPerStage; F++)
			{
				Texts.Add(Utf8Z(*Fields[F]));
			}
		}
		// Pointers into Texts only once it is complete (adding may move its buffers).
		TArray<FlameStage> Raw;
		Raw.SetNumUninitialized(N);
		for (int32 I = 0; I < N; I++)
		{
			FlameStage& R = Raw[I];
			TArray<ANSICHAR>* T = &Texts[I * TextsPerStage];
			R.struct_size = sizeof(FlameStage);
			R.frames = (uint32)Stages[I].Frames;
			R.text = T[0].GetData();
			R.head = T[1].GetData();
			R.stem = T[2].GetData();
			R.left_arm = T[3].GetData();
			R.right_arm = T[4].GetData();
			R.left_leg = T[5].GetData();
			R.right_leg = T[6].GetData();
			R.pelvis = T[7].GetData();
		}
		const FlameStatus Status = flame_session_set_prompt_stages(S, Raw.GetData(), (size_t)N);
		if (Status != FLAME_STATUS_OK)
		{
			Failure = FlameFailure(Status);
			return false;
		}
		return true;
	}

	/** Sets the prompt (and reports how it fitted the text encoder's window). */
	bool SetPrompt(FlameSession* S, FString& Failure)
	{
		FlameStatus Status = flame_session_set_prompt(S, TCHAR_TO_UTF8(*Prompt));
		FlamePromptInfo PromptInfo;
		FMemory::Memzero(PromptInfo);
		PromptInfo.struct_size = sizeof(PromptInfo);
		if (Status == FLAME_STATUS_OK)
		{
			Status = flame_session_prompt_info(S, &PromptInfo);
		}
		if (Status != FLAME_STATUS_OK)
		{
			Failure = FlameFailure(Status);
			return false;
		}
		{
			// Copied now: `dropped` belongs to the session. The component logs it on its tick.
			FScopeLock Guard(&Lock);
			bPromptInfoNew = true;
			bPromptTruncated = PromptInfo.truncated != 0;
			PromptTokens = PromptInfo.tokens;
			PromptKept = PromptInfo.kept;
			PromptDropped = FString(UTF8_TO_TCHAR(PromptInfo.dropped != nullptr ? PromptInfo.dropped : ""));
		}
		return true;
	}

	float FrameRate = 0.f; // of the poses read: the cleanup's, or the model's

	bool Step(FlameSession* S, FString& Failure)
	{
		if (!(Stages.Num() > 0 ? SetStages(S, Failure) : SetPrompt(S, Failure)))
		{
			return false;
		}
		FlameStatus Status = FLAME_STATUS_OK;
		TArray<float> Buffer, RootBuffer, RootBoneBuffer, BoneRotations, BoneTranslations;
		int32 BoneFrames = 0;
		uint32 Left = 1;
		while (Left > 0)
		{
			Status = flame_session_step(S, &Left);
			if (Status != FLAME_STATUS_OK)
			{
				// CANCELLED included: Cancel() only runs when the generation is to stop.
				Failure = FlameFailure(Status);
				return false;
			}
			const int32 Which = (bPreviewEstimate && Left > 0) ? FLAME_WHICH_ESTIMATE : FLAME_WHICH_SAMPLE;
			// The frames of this read: the session's, or the length a latent model decodes,
			// which may change from step to step.
			uint32 ReadFrames = 0;
			Status = flame_session_read_frames(S, Which, &ReadFrames);
			if (Status == FLAME_STATUS_OK)
			{
				Status = Read(S, Which, Layout, Buffer);
			}
			if (Status == FLAME_STATUS_OK)
			{
				Status = Read(S, Which, FLAME_LAYOUT_ROOT_TRANSLATION, RootBuffer);
			}
			if (Status == FLAME_STATUS_OK && bRootBone)
			{
				Status = Read(S, Which, FLAME_LAYOUT_ROOT_BONE, RootBoneBuffer);
			}
			if (Status == FLAME_STATUS_OK && Retarget.Handle != nullptr)
			{
				Status = ReadRig(S, Which, BoneRotations, BoneTranslations, BoneFrames);
			}
			if (Status == FLAME_STATUS_OK && bCleanup)
			{
				// A cleanup's frame rate changes the frame count: three values per frame.
				ReadFrames = (uint32)(RootBuffer.Num() / 3);
			}
			if (Status != FLAME_STATUS_OK)
			{
				Failure = FlameFailure(Status);
				return false;
			}
			// Buffers this generation does not read are swapped too: emptied, so that what the
			// game thread swapped back (a previous generation's track) is not published again.
			if (!bRootBone)
			{
				RootBoneBuffer.Reset();
			}
			if (Retarget.Handle == nullptr)
			{
				BoneRotations.Reset();
				BoneTranslations.Reset();
			}
			uint32 Done = 0, Total = 0;
			flame_session_progress(S, &Done, &Total);

			FScopeLock Guard(&Lock);
			Swap(Latest, Buffer); // the worker refills the game thread's previous buffers
			Swap(LatestRoot, RootBuffer);
			Swap(LatestRootBone, RootBoneBuffer);
			Swap(LatestBoneRotations, BoneRotations);
			Swap(LatestBoneTranslations, BoneTranslations);
			LatestBoneFrames = BoneFrames;
			LatestFrames = (int32)ReadFrames;
			LatestFrameRate = FrameRate;
			bLatestIsNew = true;
			StepsDone = (int32)Done;
			StepsTotal = (int32)Total;
			if (bStop)
			{
				Failure = TEXT("cancelled");
				return false;
			}
		}
		return true;
	}

	/** One flame_session_read_cleaned (the cleanup, or NULL: raw) into Out, sized by a length
	 *  query first. */
	FlameStatus Read(FlameSession* S, int32 Which, int32 InLayout, TArray<float>& Out) const
	{
		const FlameCleanupParams* C = bCleanup ? &Cleanup : nullptr;
		size_t Needed = 0;
		FlameStatus Status = flame_session_read_cleaned(S, Which, InLayout, Convention, Flags, C, nullptr, 0, &Needed);
		if (Status == FLAME_STATUS_OK)
		{
			Out.SetNumUninitialized((int32)Needed);
			Status = flame_session_read_cleaned(S, Which, InLayout, Convention, Flags, C, Out.GetData(), Needed, &Needed);
		}
		return Status;
	}
};

UFlameMotionComponent::UFlameMotionComponent()
{
	PrimaryComponentTick.bCanEverTick = true;
}

bool UFlameMotionComponent::Generate()
{
	if (Job.IsValid())
	{
		LastError = TEXT("a generation is already running");
		return false;
	}
	if (!FFlameModule::Get().IsAvailable())
	{
		LastError = TEXT("libflame is not available (see the log)");
		return false;
	}
	const FString Path = FPaths::IsRelative(ModelPath) ? FPaths::Combine(FPaths::ProjectContentDir(), ModelPath) : ModelPath;

	TSharedPtr<FFlameJob, ESPMode::ThreadSafe> NewJob = MakeShared<FFlameJob, ESPMode::ThreadSafe>();
	NewJob->Path = FPaths::ConvertRelativePathToFull(Path);
	NewJob->Prompt = Prompt;
	NewJob->Stages = PromptStages;
	flame_session_params_default(&NewJob->Params);
	NewJob->Params.frames = (uint32)FMath::Max(Frames, 0);
	NewJob->Params.steps = (uint32)FMath::Max(Steps, 0);
	NewJob->Params.sampler = bUseDdim ? FLAME_SAMPLER_DDIM : FLAME_SAMPLER_DEFAULT;
	NewJob->Params.guidance = Guidance;
	NewJob->Respacing = Respacing;
	NewJob->Params.seed = (uint64)FMath::Max(Seed, 0);
	NewJob->Params.threads = (uint32)FMath::Max(Threads, 0);
	NewJob->Params.looped = bLoop ? 1u : 0u;
	NewJob->Layout = Layout;
	NewJob->Convention = Convention;
	NewJob->Flags = (uint32)FMath::Max(ReadFlags, 0);
	NewJob->bPreviewEstimate = bPreviewEstimate;
	flame_cleanup_params_default(&NewJob->Cleanup);
	NewJob->Cleanup.feet = bLockFeet ? 1 : 0; // FlameFeet: 0 off, 1 lock
	NewJob->Cleanup.ground = bGround ? 1u : 0u;
	NewJob->Cleanup.fps = FrameRate;
	NewJob->Cleanup.root_motion = (int32)RootMotion; // EFlameRootMotion has FlameRootMotion's values
	NewJob->Cleanup.remove_yaw = bRemoveYaw ? 1u : 0u;
	// The raw features are never post-processed: with them the root locations stay raw too, so
	// both span the same frames.
	NewJob->bCleanup = Layout != FLAME_LAYOUT_FEATURES;
	NewJob->bRootBone = NewJob->bCleanup && RootMotion == EFlameRootMotion::Separate;
	NewJob->EditTask = EditTask;
	NewJob->EditReference = EditReference;
	flame_edit_params_default(&NewJob->EditParams);
	NewJob->EditParams.method = EditMethod;
	NewJob->EditParams.edit_till = EditTill;
	NewJob->EditParams.paste = bEditPaste ? 1u : 0u;
	NewJob->EditParams.seam_frames = (uint32)FMath::Max(EditSeamFrames, 0);
	NewJob->TargetFrames = TargetFrames;
	NewJob->TargetJoints = TargetJoints;
	NewJob->TargetLocations = TargetLocations;
	flame_target_params_default(&NewJob->TargetParams);
	NewJob->TargetParams.scale = TargetScale;
	NewJob->TargetParams.schedule = TargetSchedule;
	if (Model.IsValid() && Model->Path == NewJob->Path)
	{
		NewJob->Model = Model;
	}
	// The character's rig, read here: the mesh is a game-thread object.
	TSharedPtr<FFlameRigSpec, ESPMode::ThreadSafe> NewRig;
	if (RetargetMesh != nullptr)
	{
		NewRig = MakeShared<FFlameRigSpec, ESPMode::ThreadSafe>();
		FString Failure;
		if (!NewRig->FromMesh(RetargetMesh, Failure))
		{
			LastError = Failure;
			return false;
		}
		NewRig->BoneMapJson = BoneMapJson;
		NewRig->bFeetIk = bRetargetFeetIk;
	}
	NewJob->Rig = NewRig;

	LastError.Reset();
	Rig = NewRig;
	RigBoneNames = Rig.IsValid() ? Rig->Names : TArray<FString>();
	BoneRotations.Reset();
	BoneTranslations.Reset();
	RigFrames = 0;
	PlayTime = 0.0;
	MeshFrame = -1;
	Finished.Reset(); // the previous motion is no longer exportable
	TargetLoss = -1.f;
	bPromptTruncated = false;
	PromptDropped.Reset();
	StepsDone = 0;
	StepsTotal = 0;
	Job = NewJob;
	// A dedicated thread, not a task-graph worker: a generation may run for seconds. The
	// lambda holds the job, never the component, so the component may go away first.
	Async(EAsyncExecution::Thread, [NewJob]() { NewJob->Run(); });
	return true;
}

void UFlameMotionComponent::AddJointTarget(int32 Frame, int32 Joint, FVector Location)
{
	TargetFrames.Add(Frame);
	TargetJoints.Add(Joint);
	TargetLocations.Add(Location);
}

void UFlameMotionComponent::AddPromptStage(const FFlameStage& Stage)
{
	PromptStages.Add(Stage);
}

void UFlameMotionComponent::ClearPromptStages()
{
	PromptStages.Reset();
}

void UFlameMotionComponent::ClearJointTargets()
{
	TargetFrames.Reset();
	TargetJoints.Reset();
	TargetLocations.Reset();
}

void UFlameMotionComponent::Cancel()
{
	if (Job.IsValid())
	{
		Job->Cancel();
	}
}

TArray<float> UFlameMotionComponent::GetFramePose(int32 Frame) const
{
	const int32 PerFrame = GetValuesPerFrame();
	TArray<float> Values;
	if (Frame >= 0 && Frame < PoseFrames && PerFrame > 0)
	{
		Values.Append(Pose.GetData() + (int64)Frame * PerFrame, PerFrame);
	}
	return Values;
}

FQuat UFlameMotionComponent::GetJointRotation(int32 Frame, int32 Joint) const
{
	const bool bQuatXyzw = Layout == FLAME_LAYOUT_LOCAL_QUAT_XYZW || Layout == FLAME_LAYOUT_GLOBAL_QUAT_XYZW;
	const int32 Joints = GetValuesPerFrame() / 4;
	if (!bQuatXyzw || Frame < 0 || Frame >= PoseFrames || Joint < 0 || Joint >= Joints)
	{
		return FQuat::Identity;
	}
	const float* Q = Pose.GetData() + ((int64)Frame * Joints + Joint) * 4;
	return FQuat(Q[0], Q[1], Q[2], Q[3]);
}

FVector UFlameMotionComponent::GetRootLocation(int32 Frame) const
{
	if (Frame < 0 || (int64)Frame * 3 + 3 > RootLocations.Num())
	{
		return FVector::ZeroVector;
	}
	const float* P = RootLocations.GetData() + (int64)Frame * 3;
	return FVector(P[0], P[1], P[2]);
}

FVector UFlameMotionComponent::GetRootBoneLocation(int32 Frame) const
{
	if (Frame < 0 || (int64)Frame * 3 + 3 > RootBoneLocations.Num())
	{
		return FVector::ZeroVector;
	}
	const float* P = RootBoneLocations.GetData() + (int64)Frame * 3;
	return FVector(P[0], P[1], P[2]);
}

bool UFlameMotionComponent::ApplyRetargetFrame(int32 Frame)
{
	if (!Rig.IsValid() || Frame < 0 || Frame >= RigFrames || !Rig->Apply(RetargetMesh, BoneRotations, BoneTranslations, Frame))
	{
		return false;
	}
	MeshFrame = Frame;
	return true;
}

FQuat UFlameMotionComponent::GetBoneRotation(int32 Frame, int32 Bone) const
{
	const int32 N = RigBoneNames.Num();
	if (Frame < 0 || Frame >= RigFrames || Bone < 0 || Bone >= N || ((int64)Frame * N + Bone) * 4 + 4 > BoneRotations.Num())
	{
		return FQuat::Identity;
	}
	const float* Q = BoneRotations.GetData() + ((int64)Frame * N + Bone) * 4;
	return FQuat(Q[0], Q[1], Q[2], Q[3]);
}

FVector UFlameMotionComponent::GetBoneTranslation(int32 Frame, int32 Bone) const
{
	const int32 N = RigBoneNames.Num();
	if (Frame < 0 || Frame >= RigFrames || Bone < 0 || Bone >= N || ((int64)Frame * N + Bone) * 3 + 3 > BoneTranslations.Num())
	{
		return FVector::ZeroVector;
	}
	const float* T = BoneTranslations.GetData() + ((int64)Frame * N + Bone) * 3;
	return FVector(T[0], T[1], T[2]);
}

void UFlameMotionComponent::PlayOnMesh(float DeltaTime)
{
	if (!bPlayOnMesh || !Rig.IsValid() || RetargetMesh == nullptr || RigFrames <= 0 || PoseFrameRate <= 0.f)
	{
		return;
	}
	if (MeshFrame >= 0)
	{
		PlayTime += (double)DeltaTime * (double)(PlayRate > 0.f ? PlayRate : 0.f);
	}
	// Looping: a generated clip plays over and over (bLoop makes its ends meet).
	const int64 Frame = (int64)std::floor(PlayTime * (double)PoseFrameRate + 1e-9) % RigFrames;
	ApplyRetargetFrame((int32)Frame);
}

bool UFlameMotionComponent::ExportGltf(bool bBinary, TArray<uint8>& OutBytes)
{
	OutBytes.Reset();
	if (!Finished.IsValid())
	{
		LastError = IsGenerating() ? FString(TEXT("ExportGltf: a generation is running; export after OnFinished(true)"))
		                           : FString(TEXT("ExportGltf: no finished generation to export"));
		UE_LOG(LogFlame, Warning, TEXT("%s"), *LastError);
		return false;
	}
	FlameGltfParams Params;
	FlameStatus Status = flame_gltf_params_default(&Params);
	Params.container = bBinary ? FLAME_GLTF_CONTAINER_GLB : FLAME_GLTF_CONTAINER_GLTF;
	Params.flags = Finished->Flags;
	Params.cleanup = Finished->bCleanup ? &Finished->Cleanup : nullptr;
	size_t Needed = 0;
	if (Status == FLAME_STATUS_OK)
	{
		Status = flame_session_write_gltf(Finished->Handle, FLAME_WHICH_SAMPLE, &Params, nullptr, 0, &Needed);
	}
	if (Status == FLAME_STATUS_OK && Needed > (size_t)std::numeric_limits<int32>::max())
	{
		LastError = FString::Printf(TEXT("ExportGltf: a %u MiB file does not fit a TArray"), (unsigned)(Needed >> 20));
		UE_LOG(LogFlame, Warning, TEXT("%s"), *LastError);
		return false;
	}
	if (Status == FLAME_STATUS_OK)
	{
		OutBytes.SetNumUninitialized((int32)Needed);
		Status = flame_session_write_gltf(Finished->Handle, FLAME_WHICH_SAMPLE, &Params, OutBytes.GetData(), Needed, &Needed);
	}
	if (Status != FLAME_STATUS_OK)
	{
		LastError = FString(TEXT("ExportGltf: ")) + FlameFailure(Status);
		OutBytes.Reset();
		UE_LOG(LogFlame, Warning, TEXT("%s"), *LastError);
		return false;
	}
	OutBytes.SetNumUninitialized((int32)Needed);
	return true;
}

void UFlameMotionComponent::TickComponent(float DeltaTime, ELevelTick TickType, FActorComponentTickFunction* ThisTickFunction)
{
	Super::TickComponent(DeltaTime, TickType, ThisTickFunction);
	if (!Job.IsValid())
	{
		PlayOnMesh(DeltaTime);
		return;
	}
	bool bNewPose = false, bFinished = false, bSucceeded = false, bWarnTruncated = false;
	uint32 PromptTokens = 0, PromptKept = 0;
	{
		FScopeLock Guard(&Job->Lock);
		if (Job->bPromptInfoNew)
		{
			Job->bPromptInfoNew = false;
			bPromptTruncated = Job->bPromptTruncated;
			PromptDropped = Job->PromptDropped;
			bWarnTruncated = bPromptTruncated;
			PromptTokens = Job->PromptTokens;
			PromptKept = Job->PromptKept;
		}
		if (Job->bLatestIsNew)
		{
			Swap(Pose, Job->Latest);
			Swap(RootLocations, Job->LatestRoot);
			Swap(RootBoneLocations, Job->LatestRootBone);
			Swap(BoneRotations, Job->LatestBoneRotations);
			Swap(BoneTranslations, Job->LatestBoneTranslations);
			RigFrames = Job->LatestBoneFrames;
			PoseFrames = Job->LatestFrames;
			PoseFrameRate = Job->LatestFrameRate;
			Job->bLatestIsNew = false;
			bNewPose = true;
			JointNames = Job->JointNames;
			JointParents = Job->JointParents;
		}
		StepsDone = Job->StepsDone;
		StepsTotal = Job->StepsTotal;
		if (Job->bFinished)
		{
			bFinished = true;
			bSucceeded = Job->bSucceeded;
			LastError = Job->Error;
			Model = Job->Model;
			TargetLoss = (float)Job->TargetLoss;
			Finished = Job->Finished;
			Job->Finished.Reset();
		}
	}
	if (bWarnTruncated)
	{
		UE_LOG(LogFlame, Warning, TEXT("the prompt has %u tokens; the text encoder keeps its first %u and ignores \"%s\""),
			PromptTokens, PromptKept, *PromptDropped);
	}
	PlayOnMesh(DeltaTime);
	// Broadcast outside the lock: a handler may call Generate or Cancel.
	if (bNewPose)
	{
		OnProgress.Broadcast(StepsDone, StepsTotal);
	}
	if (bFinished)
	{
		Job.Reset();
		if (!bSucceeded)
		{
			UE_LOG(LogFlame, Warning, TEXT("generation ended: %s"), *LastError);
		}
		OnFinished.Broadcast(bSucceeded);
	}
}

void UFlameMotionComponent::EndPlay(const EEndPlayReason::Type EndPlayReason)
{
	// No wait: the worker notices within one step, frees its session and exits by itself.
	Cancel();
	Job.Reset();
	Finished.Reset();
	Super::EndPlay(EndPlayReason);
}
