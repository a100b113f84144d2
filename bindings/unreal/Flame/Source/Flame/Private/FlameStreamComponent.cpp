#include "FlameStreamComponent.h"

#include "Async/Async.h"
#include "FlameModule.h"
#include "HAL/CriticalSection.h"
#include "Misc/Paths.h"
#include "Misc/ScopeLock.h"

#include <cmath>

// Last: FlameCommon.h includes the C header, which defines a few unprefixed names.
#include "FlameCommon.h"

/** A segment for the stream, queued by the game thread for the next pump. */
struct FFlameStreamCommand
{
	FFlameStage Stage; // Text, Frames and (when bStage) the part texts
	float Seconds = 0.f; // > 0: the length, converted with the model's frame rate
	bool bInterrupt = false;
	bool bStage = false; // flame_stream_push_stage / _interrupt_stage
	bool bClose = false; // EndTimeline: flame_stream_close (no segment)
};

/** The component's cleanup settings as a FlameCleanupParams (as UFlameMotionComponent maps
 *  its own). */
static void MakeCleanup(const UFlameStreamComponent& C, FlameCleanupParams& Out)
{
	flame_cleanup_params_default(&Out);
	Out.feet = C.bLockFeet ? FLAME_FEET_LOCK : FLAME_FEET_OFF;
	Out.ground = C.bGround ? 1u : 0u;
	Out.fps = C.FrameRate;
	Out.root_motion = (int32)C.RootMotion; // EFlameRootMotion has FlameRootMotion's values
	Out.remove_yaw = C.bRemoveYaw ? 1u : 0u;
}

/** Whether two cleanups are the same values (libflame compares them so: a stream refuses any
 *  other cleanup than its first). */
static bool SameCleanup(const FlameCleanupParams& A, const FlameCleanupParams& B)
{
	return A.struct_size == B.struct_size && A.feet == B.feet && A.ground == B.ground &&
		A.root_motion == B.root_motion && A.remove_yaw == B.remove_yaw && A.wrap == B.wrap && A.fps == B.fps &&
		A.contact_height == B.contact_height && A.contact_speed == B.contact_speed &&
		A.contact_release == B.contact_release && A.contact_min_span == B.contact_min_span;
}

/**
 * One stream, shared by the component (game thread) and its pumps. Pumps run one at a time on
 * a background thread (the component starts the next one only when the last is done); only a
 * pump calls into the stream, except flame_stream_cancel, which the game thread calls under
 * Lock. The stream is freed with the job, by whichever side lets go of it last, so it is never
 * cancelled after it was freed. A pump never holds Lock while pumping.
 *
 * With a cleanup (bCleaned) the pumps read cleaned frames (flame_stream_read_cleaned), indexed
 * at the cleanup's frame rate, each once it has settled: a frame not settled yet is
 * WRONG_STATE, which only means "later". The stream's cleanup is the one of its first cleaned
 * read, made by Start; a pump given other settings (WantCleanup) reports libflame's refusal
 * once and reads on with the first.
 */
struct FFlameStreamJob
{
	/** Counts this job in FFlameModule::ActiveWorkers. First member, so destroyed last. */
	FFlameWorkerCount WorkerCount;

	// Inputs, fixed by StartStream.
	FString Path;
	FlameStreamParams Params;
	int32 Layout = 0;
	int32 Convention = 0;
	bool bCleaned = false; // frames read cleaned (bCleanup, and a Layout other than features)
	bool bRootBone = false; // RootMotion Separate: the root bone's track is read too
	FlameCleanupParams Cleanup{}; // the stream's cleanup, set by its first read (in Start)
	TSharedPtr<FFlameRigSpec, ESPMode::ThreadSafe> Rig; // RetargetMesh's skeleton, or null

	FCriticalSection Lock;
	// Guarded by Lock:
	TSharedPtr<FFlameModelRef, ESPMode::ThreadSafe> Model; // in: a cached model or null; out: the model used
	FlameStream* Stream = nullptr;
	bool bStop = false;
	bool bBusy = false; // a pump is queued or running
	TArray<FFlameStreamCommand> Commands; // for the next pump
	int64 Playhead = 0; // the next pump's, in the frames read (cleaned ones with a cleanup)
	uint32 Budget = 0; // the next pump's
	FlameCleanupParams WantCleanup{}; // the component's cleanup settings at the next pump
	// Results of the last pump, taken by the game thread:
	bool bStartedNew = false;
	bool bStartOk = false;
	float Fps = 0.f;
	float PoseRate = 0.f; // of the frames read: the cleanup's frame rate, or Fps
	TArray<FString> JointNames;
	TArray<int32> JointParents;
	TArray<float> NewValues;
	TArray<float> NewRoots;
	TArray<float> NewRootBones; // with bRootBone
	TArray<float> NewBoneRotations; // with Rig: the new frames retargeted
	TArray<float> NewBoneTranslations;
	int64 NewFirst = 0;
	int64 NewFrames = 0;
	bool bStatusNew = false;
	FlameStreamStatus Status;
	int64 Playable = 0; // frames that can be read: Status.ready, or the cleaned frames settled
	bool bPumpFailed = false; // the pump (or its read) failed: the component waits for a new segment
	bool bPumpIdle = false; // the pump had a budget and ran no step: nothing to do until something changes
	TArray<FString> Errors;

	// The pumps' own (one at a time):
	int64 ReadEnd = 0; // frames before it were read and handed over (cleaned ones with a cleanup)
	FFlameRetargetRef Retarget; // with Rig, made by Start
	FlameCleanupParams Applied{}; // the stream's cleanup (Cleanup, unless libflame took equal values)
	FlameCleanupParams Refused{}; // the last settings refused, reported once
	bool bRefused = false;

	~FFlameStreamJob() { flame_stream_free(Stream); }

	void Cancel()
	{
		FScopeLock Guard(&Lock);
		bStop = true;
		if (Stream != nullptr)
		{
			flame_stream_cancel(Stream);
		}
	}

	/** One pump: makes the stream the first time, hands it the queued segments and the
	 *  playhead, pumps at most Budget steps and reads the frames that became ready. */
	void Run()
	{
		FlameStream* S = nullptr;
		TArray<FFlameStreamCommand> Cmds;
		int64 Head = 0;
		uint32 Steps = 0;
		float Rate = 0.f, OutRate = 0.f;
		FlameCleanupParams Want;
		{
			FScopeLock Guard(&Lock);
			if (bStop)
			{
				bBusy = false;
				return;
			}
			S = Stream;
			Swap(Cmds, Commands);
			Head = Playhead;
			Steps = Budget;
			Rate = Fps;
			OutRate = PoseRate;
			Want = WantCleanup;
		}
		if (S == nullptr)
		{
			FString Failure;
			S = Start(Failure, Rate, OutRate);
			if (S == nullptr)
			{
				FScopeLock Guard(&Lock);
				bStartedNew = true;
				bStartOk = false;
				Errors.Add(Failure);
				bBusy = false;
				return;
			}
		}
		// A segment refused is reported; the stream goes on with the others.
		TArray<FString> Failures;
		for (int32 I = 0; I < Cmds.Num(); I++)
		{
			const FlameStatus Status = Apply(S, Cmds[I], Rate);
			if (Status != FLAME_STATUS_OK)
			{
				Failures.Add(FlameFailure(Status));
			}
		}
		FlameStreamStatus St;
		FMemory::Memzero(St);
		St.struct_size = sizeof(St);
		FlameStatus Result = flame_stream_set_playhead(S, StreamPlayhead(S, Head, Rate, OutRate));
		if (Result == FLAME_STATUS_OK)
		{
			Result = flame_stream_pump(S, Steps, &St);
		}
		bool bFailed = false;
		if (Result == FLAME_STATUS_CANCELLED)
		{
			// Only StopStream cancels: nothing more to report.
			FScopeLock Guard(&Lock);
			bBusy = false;
			return;
		}
		if (Result != FLAME_STATUS_OK)
		{
			Failures.Add(FlameFailure(Result));
			bFailed = true;
			St.struct_size = sizeof(St);
			flame_stream_status(S, &St);
		}
		// The frames that became ready (or, with a cleanup, settled), in the component's layout
		// and as root locations (quaternion tracks keep their signs across reads: libflame
		// anchors them per track).
		TArray<float> Values, Roots, Bones, BoneRotations, BoneTranslations;
		const int64 MaxFrames = 1 << 16; // per read; the rest comes with the next pump
		int64 First = 0, Count = 0;
		bool bMore = false; // frames left for the next pump to read
		if (!bCleaned)
		{
			First = ReadEnd > (int64)St.first_frame ? ReadEnd : (int64)St.first_frame;
			Count = (int64)St.ready - First;
			Count = Count < MaxFrames ? Count : MaxFrames;
		}
		else if (!bFailed)
		{
			CheckCleanup(S, Want, Failures);
			First = ReadEnd;
			const FlameStatus R = SettledEnd(S, (int64)St.ready, Rate, OutRate, First + MaxFrames, Count, bMore);
			if (R != FLAME_STATUS_OK)
			{
				Failures.Add(FlameFailure(R));
				bFailed = true;
			}
		}
		if (Count > 0)
		{
			const FlameCleanupParams* C = bCleaned ? &Applied : nullptr;
			FlameStatus R = Read(S, First, (uint32)Count, Layout, C, Values);
			if (R == FLAME_STATUS_OK)
			{
				R = Read(S, First, (uint32)Count, FLAME_LAYOUT_ROOT_TRANSLATION, C, Roots);
			}
			if (R == FLAME_STATUS_OK && bRootBone)
			{
				R = Read(S, First, (uint32)Count, FLAME_LAYOUT_ROOT_BONE, C, Bones);
			}
			if (R == FLAME_STATUS_OK && Retarget.Handle != nullptr)
			{
				// The same frames on the character (frame indices as the read's: cleaned ones
				// with a cleanup).
				const int64 N = Count * Rig->Names.Num();
				BoneRotations.SetNumUninitialized((int32)(N * 4));
				BoneTranslations.SetNumUninitialized((int32)(N * 3));
				R = flame_retarget_read_stream(Retarget.Handle, S, (uint64)First, (uint32)Count, C, BoneRotations.GetData(),
					(size_t)BoneRotations.Num(), BoneTranslations.GetData(), (size_t)BoneTranslations.Num());
			}
			if (R != FLAME_STATUS_OK)
			{
				Failures.Add(FlameFailure(R));
				bFailed = true;
				Count = 0;
			}
			else
			{
				ReadEnd = First + Count;
			}
		}
		FScopeLock Guard(&Lock);
		for (int32 I = 0; I < Failures.Num(); I++)
		{
			Errors.Add(Failures[I]);
		}
		if (Count > 0)
		{
			if (NewFrames > 0 && NewFirst + NewFrames == First)
			{
				NewValues.Append(Values.GetData(), Values.Num());
				NewRoots.Append(Roots.GetData(), Roots.Num());
				NewRootBones.Append(Bones.GetData(), Bones.Num());
				NewBoneRotations.Append(BoneRotations.GetData(), BoneRotations.Num());
				NewBoneTranslations.Append(BoneTranslations.GetData(), BoneTranslations.Num());
				NewFrames += Count;
			}
			else
			{
				Swap(NewValues, Values);
				Swap(NewRoots, Roots);
				Swap(NewRootBones, Bones);
				Swap(NewBoneRotations, BoneRotations);
				Swap(NewBoneTranslations, BoneTranslations);
				NewFirst = First;
				NewFrames = Count;
			}
		}
		Status = St;
		Playable = bCleaned ? ReadEnd : (int64)St.ready;
		bStatusNew = true;
		bPumpFailed = bFailed;
		bPumpIdle = St.steps == 0 && Steps > 0 && (bCleaned ? !bMore : ReadEnd >= (int64)St.ready);
		bBusy = false;
	}

private:
	/** Loads the model (unless cached) and makes the stream; null on failure. */
	FlameStream* Start(FString& Failure, float& OutFps, float& OutPoseRate)
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
				return nullptr;
			}
			M = MakeShared<FFlameModelRef, ESPMode::ThreadSafe>(Handle, Path);
		}
		FlameModelInfo Info;
		FMemory::Memzero(Info);
		Info.struct_size = sizeof(Info);
		FlameStatus Status = flame_model_info(M->Handle, &Info);
		FlameStream* S = nullptr;
		if (Status == FLAME_STATUS_OK)
		{
			Status = flame_stream_new(M->Handle, &Params, &S);
		}
		if (Status == FLAME_STATUS_OK && bCleaned)
		{
			// The stream's cleanup is set by its first cleaned read, once: made here, before any
			// frame is generated, so that settings libflame refuses (a frame rate above 240)
			// fail the start. Frame 0 is not settled yet (WRONG_STATE): the cleanup is set all
			// the same. (Never a read of 0 frames: one of a layout other than quaternions fails
			// with INTERNAL while nothing has settled, and leaves the stream unusable.)
			size_t Needed = 0;
			Status = flame_stream_read_cleaned(S, 0, 1, Layout, Convention, &Cleanup, nullptr, 0, &Needed);
			if (Status == FLAME_STATUS_WRONG_STATE)
			{
				Status = FLAME_STATUS_OK;
			}
			Applied = Cleanup;
		}
		bool bRigFailed = false;
		if (Status == FLAME_STATUS_OK && Rig.IsValid())
		{
			Retarget.Handle = Rig->Make(M->Handle, Failure);
			bRigFailed = Retarget.Handle == nullptr;
		}
		if (Status != FLAME_STATUS_OK || bRigFailed)
		{
			if (!bRigFailed)
			{
				Failure = FlameFailure(Status);
			}
			flame_stream_free(S); // NULL when flame_stream_new failed
			FScopeLock Guard(&Lock);
			Model = M; // loaded: cached for the next start even though this one failed
			return nullptr;
		}
		OutFps = Info.fps;
		OutPoseRate = bCleaned && Cleanup.fps > 0.f ? Cleanup.fps : Info.fps;
		FScopeLock Guard(&Lock);
		Model = M;
		Stream = S; // freed with the job from now on
		if (bStop)
		{
			// StopStream came while loading, before there was a stream to cancel.
			Failure = TEXT("stopped");
			return nullptr;
		}
		Fps = Info.fps;
		PoseRate = OutPoseRate;
		for (uint32 J = 0; Info.joint_names != nullptr && J < Info.joint_count; J++)
		{
			JointNames.Add(UTF8_TO_TCHAR(Info.joint_names[J]));
			JointParents.Add(Info.joint_parents != nullptr ? Info.joint_parents[J] : -1);
		}
		bStartedNew = true;
		bStartOk = true;
		return S;
	}

	/** Hands one queued segment to the stream. */
	static FlameStatus Apply(FlameStream* S, const FFlameStreamCommand& C, float Rate)
	{
		if (C.bClose)
		{
			return flame_stream_close(S);
		}
		int64 Frames = C.Stage.Frames;
		if (C.Seconds > 0.f)
		{
			const double F = std::floor((double)C.Seconds * (double)Rate + 0.5);
			Frames = F < 1.0 ? 1 : (F > 4294967295.0 ? (int64)4294967295LL : (int64)F);
		}
		const uint32 N = (uint32)(Frames > 0 ? Frames : 0); // 0 frames: libflame's error
		if (C.bStage)
		{
			const FFlameStageUtf8 Stage(C.Stage, N);
			return C.bInterrupt ? flame_stream_interrupt_stage(S, &Stage.Raw) : flame_stream_push_stage(S, &Stage.Raw);
		}
		const TArray<ANSICHAR> Prompt = Utf8Z(C.Stage.Text);
		return C.bInterrupt ? flame_stream_interrupt(S, Prompt.GetData(), N) : flame_stream_push(S, Prompt.GetData(), N);
	}

	/** Frames First..First + Count in InLayout and the component's convention, after the
	 *  cleanup C (flame_stream_read_cleaned; NULL: the raw frames, exactly flame_stream_read). */
	FlameStatus Read(FlameStream* S, int64 First, uint32 Count, int32 InLayout, const FlameCleanupParams* C,
		TArray<float>& Out) const
	{
		size_t Needed = 0;
		FlameStatus Status = flame_stream_read_cleaned(S, (uint64)First, Count, InLayout, Convention, C, nullptr, 0, &Needed);
		if (Status == FLAME_STATUS_OK)
		{
			Out.SetNumUninitialized((int32)Needed);
			Status = flame_stream_read_cleaned(S, (uint64)First, Count, InLayout, Convention, C, Out.GetData(), Needed, &Needed);
		}
		return Status;
	}

	/** The timeline frame to give the stream as its playhead for the component's frame Head.
	 *  Without a cleanup, Head itself. With one, Head is a cleaned frame (at OutRate): the
	 *  timeline frame at its time, moved on by the frames generated but not settled yet, so
	 *  that the stream's lookahead counts settled frames: it goes on generating while frames
	 *  wait for a contact span to end (otherwise a span longer than the lookahead would hold
	 *  the playhead and the stream for good). */
	uint64 StreamPlayhead(FlameStream* S, int64 Head, float Rate, float OutRate) const
	{
		const int64 At = Head > 0 ? Head : 0;
		if (!bCleaned)
		{
			return (uint64)At;
		}
		FlameStreamStatus Now;
		FMemory::Memzero(Now);
		Now.struct_size = sizeof(Now);
		flame_stream_status(S, &Now);
		const double Scale = Rate > 0.f && OutRate > 0.f ? (double)Rate / (double)OutRate : 1.0;
		const int64 HeadT = (int64)std::floor((double)At * Scale + 1e-9);
		const int64 SettledT = (int64)std::floor((double)ReadEnd * Scale + 1e-9);
		const int64 Ready = (int64)Now.ready;
		const int64 Frame = HeadT + (Ready > SettledT ? Ready - SettledT : 0);
		return (uint64)(Frame < Ready ? Frame : Ready);
	}

	/** With a cleanup: the component's settings Want, when they differ from the stream's, are
	 *  handed to libflame, whose refusal (the cleanup is set once) is reported, once per new
	 *  value; the frames are read on with the stream's cleanup. */
	void CheckCleanup(FlameStream* S, const FlameCleanupParams& Want, TArray<FString>& Failures)
	{
		if (SameCleanup(Want, Applied))
		{
			bRefused = false; // back to the stream's: a later change is reported again
			return;
		}
		if (bRefused && SameCleanup(Want, Refused))
		{
			return;
		}
		// A settled frame, so that only the cleanup can make the read fail.
		size_t Needed = 0;
		const uint64 Probe = ReadEnd > 0 ? (uint64)(ReadEnd - 1) : 0;
		const FlameStatus R = flame_stream_read_cleaned(S, Probe, 1, Layout, Convention, &Want, nullptr, 0, &Needed);
		if (R == FLAME_STATUS_OK)
		{
			Applied = Want; // values libflame holds equal to the stream's
			bRefused = false;
			return;
		}
		Failures.Add(FlameFailure(R) + TEXT(" (the stream keeps the cleanup of its first read and reads on with it; ")
			TEXT("StopStream and StartStream to change it)"));
		Refused = Want;
		bRefused = true;
	}

	/** With a cleanup: the cleaned frames from ReadEnd on that have settled, found by reading
	 *  single frames (a frame is readable once settled, and every frame before it is): OutCount
	 *  of them, at most up to Limit (bOutMore: there may be more). A frame not settled yet is
	 *  WRONG_STATE: no error, the component waits for the next pumps. */
	FlameStatus SettledEnd(FlameStream* S, int64 Ready, float Rate, float OutRate, int64 Limit, int64& OutCount,
		bool& bOutMore) const
	{
		OutCount = 0;
		bOutMore = false;
		if (Ready <= 0)
		{
			return FLAME_STATUS_OK;
		}
		// Past the last cleaned frame the generated frames can give (frame k is at k / OutRate
		// seconds, the last generated one at (Ready - 1) / Rate): 115 frames at 20 fps are
		// 172 at 30. A frame or two more, read in vain, cost nothing.
		const double Scale = Rate > 0.f && OutRate > 0.f ? (double)OutRate / (double)Rate : 1.0;
		const int64 Bound = (int64)std::floor((double)(Ready - 1) * Scale + 1e-9) + 3;
		int64 Lo = ReadEnd; // frames before Lo are settled
		int64 Hi = Bound < Limit ? Bound : Limit; // frames from Hi on are not (or are not asked for)
		while (Lo < Hi)
		{
			const int64 Mid = Lo + (Hi - Lo) / 2;
			size_t Needed = 0;
			const FlameStatus R = flame_stream_read_cleaned(S, (uint64)Mid, 1, Layout, Convention, &Applied, nullptr, 0, &Needed);
			if (R == FLAME_STATUS_OK)
			{
				Lo = Mid + 1;
			}
			else if (R == FLAME_STATUS_WRONG_STATE)
			{
				Hi = Mid; // not settled yet
			}
			else
			{
				return R;
			}
		}
		OutCount = Lo - ReadEnd;
		bOutMore = Lo == Limit && Lo < Bound;
		return FLAME_STATUS_OK;
	}
};

UFlameStreamComponent::UFlameStreamComponent()
{
	PrimaryComponentTick.bCanEverTick = true;
}

void UFlameStreamComponent::BeginPlay()
{
	Super::BeginPlay();
	if (bAutoStart && !Job.IsValid())
	{
		StartStream();
	}
}

bool UFlameStreamComponent::StartStream()
{
	if (Job.IsValid())
	{
		LastError = TEXT("the stream is already running (StopStream first)");
		return false;
	}
	if (!FFlameModule::Get().IsAvailable())
	{
		LastError = TEXT("libflame is not available (see the log)");
		return false;
	}
	const FString Path = FPaths::IsRelative(ModelPath) ? FPaths::Combine(FPaths::ProjectContentDir(), ModelPath) : ModelPath;
	TSharedPtr<FFlameStreamJob, ESPMode::ThreadSafe> NewJob = MakeShared<FFlameStreamJob, ESPMode::ThreadSafe>();
	NewJob->Path = FPaths::ConvertRelativePathToFull(Path);
	flame_stream_params_default(&NewJob->Params);
	KeepBehind = Window > 0 ? Window : (int64)NewJob->Params.window; // 0: the default window
	NewJob->Params.chunk = (uint32)FMath::Max(Chunk, 0);
	NewJob->Params.overlap = (uint32)FMath::Max(Overlap, 0);
	NewJob->Params.lookahead = (uint32)FMath::Max(Lookahead, 0);
	NewJob->Params.window = (uint32)FMath::Max(Window, 0);
	NewJob->Params.steps = (uint32)FMath::Max(Steps, 0);
	NewJob->Params.sampler = bUseDdim ? FLAME_SAMPLER_DDIM : FLAME_SAMPLER_DEFAULT;
	NewJob->Params.guidance = Guidance;
	NewJob->Params.seed = (uint64)FMath::Max(Seed, 0);
	NewJob->Params.threads = (uint32)FMath::Max(Threads, 0);
	NewJob->Layout = Layout;
	NewJob->Convention = Convention;
	MakeCleanup(*this, NewJob->Cleanup);
	// The raw features are never post-processed: with them the frames stay raw (as the motion
	// component's Pose does).
	NewJob->bCleaned = bCleanup && Layout != FLAME_LAYOUT_FEATURES;
	NewJob->bRootBone = NewJob->bCleaned && RootMotion == EFlameRootMotion::Separate;
	NewJob->WantCleanup = NewJob->Cleanup;
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
	Rig = NewRig;
	RigBoneNames = Rig.IsValid() ? Rig->Names : TArray<FString>();
	BoneRotations.Reset();
	BoneTranslations.Reset();
	BoneRotationCache.Reset();
	BoneTranslationCache.Reset();

	LastError.Reset();
	Pose.Reset();
	RootLocation = FVector::ZeroVector;
	RootBoneLocation = FVector::ZeroVector;
	Cache.Reset();
	RootCache.Reset();
	RootBoneCache.Reset();
	CacheFirst = 0;
	CacheFrames = 0;
	ValuesPerFrame = 0;
	PlayTime = 0.0;
	CurrentFrame = -1;
	ReadyFrames = 0;
	GeneratedFrames = 0;
	bTimelineEnded = false;
	PoseFrameRate = 0.f;
	FirstHeldFrame = 0;
	bWaitingForFrames = false;
	bStarving = false;
	StepsLastPump = 0;
	StepsTotal = 0;
	SentPlayhead = -1;
	bLastPumpIdle = false;
	bPumpFailed = false;
	Job = NewJob;
	Launch(); // the first pump loads the model and makes the stream
	return true;
}

void UFlameStreamComponent::StopStream()
{
	if (Job.IsValid())
	{
		// No wait: a running pump returns within one layer and frees the stream with the job.
		Job->Cancel();
		Job.Reset();
	}
}

bool UFlameStreamComponent::Queue(const FFlameStage& Stage, float Seconds, bool bInterrupt, bool bStage)
{
	if (!Job.IsValid())
	{
		LastError = TEXT("the stream is not running: call StartStream (or set bAutoStart)");
		UE_LOG(LogFlame, Warning, TEXT("%s"), *LastError);
		return false;
	}
	if (bTimelineEnded)
	{
		LastError = FString::Printf(TEXT("the timeline was ended (EndTimeline): \"%s\" is not pushed; StartStream starts a new one"),
			*Stage.Text);
		UE_LOG(LogFlame, Warning, TEXT("%s"), *LastError);
		return false;
	}
	if (Seconds < 0.f || (Seconds == 0.f && Stage.Frames <= 0) || !std::isfinite(Seconds))
	{
		LastError = FString::Printf(TEXT("a segment needs a positive length: \"%s\""), *Stage.Text);
		UE_LOG(LogFlame, Warning, TEXT("%s"), *LastError);
		return false;
	}
	FFlameStreamCommand Command;
	Command.Stage = Stage;
	Command.Seconds = Seconds;
	Command.bInterrupt = bInterrupt;
	Command.bStage = bStage;
	{
		FScopeLock Guard(&Job->Lock);
		Job->Commands.Add(Command);
	}
	bPumpFailed = false; // a new segment may unblock a stream whose last pump failed
	return true;
}

bool UFlameStreamComponent::PushSegment(const FString& Prompt, float Seconds)
{
	return Queue(FFlameStage(Prompt, 0), Seconds > 0.f ? Seconds : -1.f, false, false);
}

bool UFlameStreamComponent::PushSegmentFrames(const FString& Prompt, int32 Frames)
{
	return Queue(FFlameStage(Prompt, Frames), 0.f, false, false);
}

bool UFlameStreamComponent::InterruptSegment(const FString& Prompt, float Seconds)
{
	return Queue(FFlameStage(Prompt, 0), Seconds > 0.f ? Seconds : -1.f, true, false);
}

bool UFlameStreamComponent::InterruptSegmentFrames(const FString& Prompt, int32 Frames)
{
	return Queue(FFlameStage(Prompt, Frames), 0.f, true, false);
}

bool UFlameStreamComponent::PushStage(const FFlameStage& Stage)
{
	return Queue(Stage, 0.f, false, true);
}

bool UFlameStreamComponent::InterruptStage(const FFlameStage& Stage)
{
	return Queue(Stage, 0.f, true, true);
}

bool UFlameStreamComponent::EndTimeline()
{
	if (!Job.IsValid())
	{
		LastError = TEXT("the stream is not running: call StartStream (or set bAutoStart)");
		UE_LOG(LogFlame, Warning, TEXT("%s"), *LastError);
		return false;
	}
	if (!bTimelineEnded)
	{
		// flame_stream_close at the next pump, after the segments queued before it (only a
		// pump calls into the stream).
		FFlameStreamCommand Command;
		Command.bClose = true;
		{
			FScopeLock Guard(&Job->Lock);
			Job->Commands.Add(Command);
		}
		bTimelineEnded = true;
	}
	return true;
}

TArray<float> UFlameStreamComponent::GetFramePose(int64 Frame) const
{
	TArray<float> Values;
	if (Frame >= CacheFirst && Frame < CacheFirst + CacheFrames && ValuesPerFrame > 0)
	{
		Values.Append(Cache.GetData() + (Frame - CacheFirst) * ValuesPerFrame, ValuesPerFrame);
	}
	return Values;
}

FQuat UFlameStreamComponent::GetJointRotationAt(int64 Frame, int32 Joint) const
{
	const bool bQuatXyzw = Layout == FLAME_LAYOUT_LOCAL_QUAT_XYZW || Layout == FLAME_LAYOUT_GLOBAL_QUAT_XYZW;
	const int32 Joints = ValuesPerFrame / 4;
	if (!bQuatXyzw || Frame < CacheFirst || Frame >= CacheFirst + CacheFrames || Joint < 0 || Joint >= Joints)
	{
		return FQuat::Identity;
	}
	const float* Q = Cache.GetData() + ((Frame - CacheFirst) * Joints + Joint) * 4;
	return FQuat(Q[0], Q[1], Q[2], Q[3]);
}

FVector UFlameStreamComponent::GetRootLocationAt(int64 Frame) const
{
	if (Frame < CacheFirst || Frame >= CacheFirst + CacheFrames || RootCache.Num() < CacheFrames * 3)
	{
		return FVector::ZeroVector;
	}
	const float* P = RootCache.GetData() + (Frame - CacheFirst) * 3;
	return FVector(P[0], P[1], P[2]);
}

FVector UFlameStreamComponent::GetRootBoneLocationAt(int64 Frame) const
{
	if (Frame < CacheFirst || Frame >= CacheFirst + CacheFrames || CacheFrames == 0 || RootBoneCache.Num() < CacheFrames * 3)
	{
		return FVector::ZeroVector;
	}
	const float* P = RootBoneCache.GetData() + (Frame - CacheFirst) * 3;
	return FVector(P[0], P[1], P[2]);
}

FQuat UFlameStreamComponent::GetBoneRotationAt(int64 Frame, int32 Bone) const
{
	const int32 N = RigBoneNames.Num();
	if (Frame < CacheFirst || Frame >= CacheFirst + CacheFrames || Bone < 0 || Bone >= N ||
		((Frame - CacheFirst) * N + Bone) * 4 + 4 > BoneRotationCache.Num())
	{
		return FQuat::Identity;
	}
	const float* Q = BoneRotationCache.GetData() + ((Frame - CacheFirst) * N + Bone) * 4;
	return FQuat(Q[0], Q[1], Q[2], Q[3]);
}

FVector UFlameStreamComponent::GetBoneTranslationAt(int64 Frame, int32 Bone) const
{
	const int32 N = RigBoneNames.Num();
	if (Frame < CacheFirst || Frame >= CacheFirst + CacheFrames || Bone < 0 || Bone >= N ||
		((Frame - CacheFirst) * N + Bone) * 3 + 3 > BoneTranslationCache.Num())
	{
		return FVector::ZeroVector;
	}
	const float* T = BoneTranslationCache.GetData() + ((Frame - CacheFirst) * N + Bone) * 3;
	return FVector(T[0], T[1], T[2]);
}

void UFlameStreamComponent::UpdatePose()
{
	Pose = GetFramePose(CurrentFrame);
	RootLocation = GetRootLocationAt(CurrentFrame);
	RootBoneLocation = GetRootBoneLocationAt(CurrentFrame);
	const int32 N = RigBoneNames.Num();
	const int64 At = CurrentFrame - CacheFirst;
	BoneRotations.Reset();
	BoneTranslations.Reset();
	if (Rig.IsValid() && N > 0 && At >= 0 && (At + 1) * N * 4 <= BoneRotationCache.Num())
	{
		BoneRotations.Append(BoneRotationCache.GetData() + At * N * 4, N * 4);
		BoneTranslations.Append(BoneTranslationCache.GetData() + At * N * 3, N * 3);
		Rig->Apply(RetargetMesh, BoneRotationCache, BoneTranslationCache, (int32)At);
	}
}

void UFlameStreamComponent::Launch()
{
	{
		FScopeLock Guard(&Job->Lock);
		Job->Playhead = CurrentFrame > 0 ? CurrentFrame : 0;
		Job->Budget = (uint32)FMath::Max(StepsPerTick, 0);
		MakeCleanup(*this, Job->WantCleanup);
		Job->bBusy = true;
	}
	SentPlayhead = CurrentFrame;
	// A pool thread: a pump may take several denoiser steps. The lambda holds the job, never
	// the component, so the component may go away first.
	TSharedPtr<FFlameStreamJob, ESPMode::ThreadSafe> Pumping = Job;
	Async(EAsyncExecution::ThreadPool, [Pumping]() { Pumping->Run(); });
}

void UFlameStreamComponent::TickComponent(float DeltaTime, ELevelTick TickType, FActorComponentTickFunction* ThisTickFunction)
{
	Super::TickComponent(DeltaTime, TickType, ThisTickFunction);
	if (!Job.IsValid())
	{
		return;
	}
	// 1. What the last pump brought.
	bool bBusy = false, bStartedNew = false, bStartOk = false, bBecameStarving = false, bCommandsWaiting = false;
	bool bCleanupChanged = false;
	TArray<FString> Errors;
	TArray<float> NewValues, NewRoots, NewRootBones, NewBoneRotations, NewBoneTranslations;
	FlameCleanupParams Settings;
	MakeCleanup(*this, Settings);
	int64 NewFirst = 0, NewFrames = 0;
	{
		FScopeLock Guard(&Job->Lock);
		bBusy = Job->bBusy;
		if (Job->bStartedNew)
		{
			Job->bStartedNew = false;
			bStartedNew = true;
			bStartOk = Job->bStartOk;
			Model = Job->Model;
			Fps = Job->Fps;
			PoseFrameRate = Job->PoseRate;
			if (Fps > 0.f && PoseFrameRate > 0.f && PoseFrameRate != Fps)
			{
				// The window in Pose's frames: as many seconds as Window's timeline frames.
				KeepBehind = (int64)std::floor((double)KeepBehind * (double)PoseFrameRate / (double)Fps);
			}
			JointNames = Job->JointNames;
			JointParents = Job->JointParents;
		}
		Swap(Errors, Job->Errors);
		Swap(NewValues, Job->NewValues);
		Swap(NewRoots, Job->NewRoots);
		Swap(NewRootBones, Job->NewRootBones);
		Swap(NewBoneRotations, Job->NewBoneRotations);
		Swap(NewBoneTranslations, Job->NewBoneTranslations);
		NewFirst = Job->NewFirst;
		NewFrames = Job->NewFrames;
		Job->NewFrames = 0;
		if (Job->bStatusNew)
		{
			Job->bStatusNew = false;
			const FlameStreamStatus& St = Job->Status;
			ReadyFrames = Job->Playable;
			GeneratedFrames = (int64)St.ready;
			StepsLastPump = (int32)St.steps;
			StepsTotal += St.steps;
			bLastPumpIdle = Job->bPumpIdle;
			bBecameStarving = St.starving != 0 && !bStarving;
			bStarving = St.starving != 0;
			if (Job->bPumpFailed)
			{
				bPumpFailed = true;
			}
		}
		bCommandsWaiting = Job->Commands.Num() > 0;
		bCleanupChanged = Job->bCleaned && !SameCleanup(Settings, Job->WantCleanup);
	}
	for (int32 I = 0; I < Errors.Num(); I++)
	{
		LastError = Errors[I];
		UE_LOG(LogFlame, Warning, TEXT("stream: %s"), *Errors[I]);
	}
	if (bStartedNew && !bStartOk)
	{
		Job.Reset();
		OnStarted.Broadcast(false);
		return;
	}
	if (NewFrames > 0)
	{
		const int32 PerFrame = (int32)(NewValues.Num() / NewFrames);
		if (CacheFrames == 0 || PerFrame != ValuesPerFrame || NewFirst != CacheFirst + CacheFrames)
		{
			Cache.Reset();
			RootCache.Reset();
			RootBoneCache.Reset();
			BoneRotationCache.Reset();
			BoneTranslationCache.Reset();
			CacheFirst = NewFirst;
			CacheFrames = 0;
			ValuesPerFrame = PerFrame;
		}
		Cache.Append(NewValues.GetData(), NewValues.Num());
		RootCache.Append(NewRoots.GetData(), NewRoots.Num());
		RootBoneCache.Append(NewRootBones.GetData(), NewRootBones.Num());
		BoneRotationCache.Append(NewBoneRotations.GetData(), NewBoneRotations.Num());
		BoneTranslationCache.Append(NewBoneTranslations.GetData(), NewBoneTranslations.Num());
		CacheFrames += NewFrames;
	}

	// 2. The playhead: game time at Pose's frame rate (the model's, or the cleanup's: then
	// frames are cleaned frames), held at the last frame received.
	const float Rate = PoseFrameRate;
	if (CacheFrames > 0 && Rate > 0.f)
	{
		if (bPlaying && CurrentFrame >= 0)
		{
			PlayTime += (double)DeltaTime * (double)(PlayRate > 0.f ? PlayRate : 0.f);
		}
		const int64 Last = CacheFirst + CacheFrames - 1;
		int64 Frame = (int64)std::floor(PlayTime * (double)Rate + 1e-9);
		Frame = Frame < CacheFirst ? CacheFirst : Frame;
		bWaitingForFrames = Frame > Last;
		if (bWaitingForFrames)
		{
			Frame = Last;
			PlayTime = (double)Last / (double)Rate;
		}
		CurrentFrame = Frame;
		// Frames more than the window behind the playhead go, as they do in the stream.
		const int64 Drop = CurrentFrame - KeepBehind - CacheFirst;
		if (Drop > 0)
		{
			Cache.RemoveAt(0, (int32)(Drop * ValuesPerFrame));
			RootCache.RemoveAt(0, (int32)(Drop * 3));
			if (RootBoneCache.Num() > 0)
			{
				RootBoneCache.RemoveAt(0, (int32)(Drop * 3));
			}
			if (BoneRotationCache.Num() > 0)
			{
				BoneRotationCache.RemoveAt(0, (int32)(Drop * RigBoneNames.Num() * 4));
				BoneTranslationCache.RemoveAt(0, (int32)(Drop * RigBoneNames.Num() * 3));
			}
			CacheFirst += Drop;
			CacheFrames -= Drop;
		}
		FirstHeldFrame = CacheFirst;
		UpdatePose();
	}

	// 3. The next pump, once the last is done, when there is something to do: new segments
	// (or EndTimeline), a new playhead, steps left (the last pump ran some, or had no budget),
	// or changed cleanup settings (the pump reports their refusal). After a failed pump only a
	// new segment (an interrupt replaces the one that failed) starts another.
	const bool bWork = bCommandsWaiting || CurrentFrame != SentPlayhead || (StepsPerTick > 0 && !bLastPumpIdle) ||
		bCleanupChanged;
	if (!bBusy && bWork && !(bPumpFailed && !bCommandsWaiting))
	{
		Launch();
	}

	// Broadcast last: a handler may push, stop or start.
	if (bStartedNew)
	{
		OnStarted.Broadcast(true);
	}
	if (bBecameStarving && Job.IsValid())
	{
		OnStarving.Broadcast();
	}
}

void UFlameStreamComponent::EndPlay(const EEndPlayReason::Type EndPlayReason)
{
	StopStream();
	Super::EndPlay(EndPlayReason);
}
