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
};

/**
 * One stream, shared by the component (game thread) and its pumps. Pumps run one at a time on
 * a background thread (the component starts the next one only when the last is done); only a
 * pump calls into the stream, except flame_stream_cancel, which the game thread calls under
 * Lock. The stream is freed with the job, by whichever side lets go of it last, so it is never
 * cancelled after it was freed. A pump never holds Lock while pumping.
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

	FCriticalSection Lock;
	// Guarded by Lock:
	TSharedPtr<FFlameModelRef, ESPMode::ThreadSafe> Model; // in: a cached model or null; out: the model used
	FlameStream* Stream = nullptr;
	bool bStop = false;
	bool bBusy = false; // a pump is queued or running
	TArray<FFlameStreamCommand> Commands; // for the next pump
	int64 Playhead = 0; // the next pump's
	uint32 Budget = 0; // the next pump's
	// Results of the last pump, taken by the game thread:
	bool bStartedNew = false;
	bool bStartOk = false;
	float Fps = 0.f;
	TArray<FString> JointNames;
	TArray<int32> JointParents;
	TArray<float> NewValues;
	TArray<float> NewRoots;
	int64 NewFirst = 0;
	int64 NewFrames = 0;
	bool bStatusNew = false;
	FlameStreamStatus Status;
	bool bPumpFailed = false; // the pump (or its read) failed: the component waits for a new segment
	bool bPumpIdle = false; // the pump had a budget and ran no step: nothing to do until something changes
	TArray<FString> Errors;

	// The pumps' own (one at a time):
	int64 ReadEnd = 0; // frames before it were read and handed over

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
		float Rate = 0.f;
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
		}
		if (S == nullptr)
		{
			FString Failure;
			S = Start(Failure, Rate);
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
		FlameStatus Result = flame_stream_set_playhead(S, (uint64)(Head > 0 ? Head : 0));
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
		// The frames that became ready, in the component's layout and as root locations
		// (quaternion tracks keep their signs across reads: libflame anchors them per track).
		TArray<float> Values, Roots;
		const int64 First = ReadEnd > (int64)St.first_frame ? ReadEnd : (int64)St.first_frame;
		int64 Count = (int64)St.ready - First;
		if (Count > 0)
		{
			const int64 MaxFrames = 1 << 16; // per read; the rest comes with the next pump
			Count = Count < MaxFrames ? Count : MaxFrames;
			FlameStatus R = Read(S, First, (uint32)Count, Layout, Values);
			if (R == FLAME_STATUS_OK)
			{
				R = Read(S, First, (uint32)Count, FLAME_LAYOUT_ROOT_TRANSLATION, Roots);
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
				NewFrames += Count;
			}
			else
			{
				Swap(NewValues, Values);
				Swap(NewRoots, Roots);
				NewFirst = First;
				NewFrames = Count;
			}
		}
		Status = St;
		bStatusNew = true;
		bPumpFailed = bFailed;
		bPumpIdle = St.steps == 0 && Steps > 0 && ReadEnd >= (int64)St.ready;
		bBusy = false;
	}

private:
	/** Loads the model (unless cached) and makes the stream; null on failure. */
	FlameStream* Start(FString& Failure, float& OutFps)
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
		if (Status != FLAME_STATUS_OK)
		{
			Failure = FlameFailure(Status);
			FScopeLock Guard(&Lock);
			Model = M; // loaded: cached for the next start even though this one failed
			return nullptr;
		}
		OutFps = Info.fps;
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

	/** Frames First..First + Count in InLayout and the component's convention. */
	FlameStatus Read(FlameStream* S, int64 First, uint32 Count, int32 InLayout, TArray<float>& Out) const
	{
		size_t Needed = 0;
		FlameStatus Status = flame_stream_read(S, (uint64)First, Count, InLayout, Convention, 0, nullptr, 0, &Needed);
		if (Status == FLAME_STATUS_OK)
		{
			Out.SetNumUninitialized((int32)Needed);
			Status = flame_stream_read(S, (uint64)First, Count, InLayout, Convention, 0, Out.GetData(), Needed, &Needed);
		}
		return Status;
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
	if (Model.IsValid() && Model->Path == NewJob->Path)
	{
		NewJob->Model = Model;
	}

	LastError.Reset();
	Pose.Reset();
	RootLocation = FVector::ZeroVector;
	Cache.Reset();
	RootCache.Reset();
	CacheFirst = 0;
	CacheFrames = 0;
	ValuesPerFrame = 0;
	PlayTime = 0.0;
	CurrentFrame = -1;
	ReadyFrames = 0;
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

void UFlameStreamComponent::UpdatePose()
{
	Pose = GetFramePose(CurrentFrame);
	RootLocation = GetRootLocationAt(CurrentFrame);
}

void UFlameStreamComponent::Launch()
{
	{
		FScopeLock Guard(&Job->Lock);
		Job->Playhead = CurrentFrame > 0 ? CurrentFrame : 0;
		Job->Budget = (uint32)FMath::Max(StepsPerTick, 0);
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
	TArray<FString> Errors;
	TArray<float> NewValues, NewRoots;
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
			JointNames = Job->JointNames;
			JointParents = Job->JointParents;
		}
		Swap(Errors, Job->Errors);
		Swap(NewValues, Job->NewValues);
		Swap(NewRoots, Job->NewRoots);
		NewFirst = Job->NewFirst;
		NewFrames = Job->NewFrames;
		Job->NewFrames = 0;
		if (Job->bStatusNew)
		{
			Job->bStatusNew = false;
			const FlameStreamStatus& St = Job->Status;
			ReadyFrames = (int64)St.ready;
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
			CacheFirst = NewFirst;
			CacheFrames = 0;
			ValuesPerFrame = PerFrame;
		}
		Cache.Append(NewValues.GetData(), NewValues.Num());
		RootCache.Append(NewRoots.GetData(), NewRoots.Num());
		CacheFrames += NewFrames;
	}

	// 2. The playhead: game time at the model's frame rate, held at the last frame received.
	if (CacheFrames > 0 && Fps > 0.f)
	{
		if (bPlaying && CurrentFrame >= 0)
		{
			PlayTime += (double)DeltaTime * (double)(PlayRate > 0.f ? PlayRate : 0.f);
		}
		const int64 Last = CacheFirst + CacheFrames - 1;
		int64 Frame = (int64)std::floor(PlayTime * (double)Fps + 1e-9);
		Frame = Frame < CacheFirst ? CacheFirst : Frame;
		bWaitingForFrames = Frame > Last;
		if (bWaitingForFrames)
		{
			Frame = Last;
			PlayTime = (double)Last / (double)Fps;
		}
		CurrentFrame = Frame;
		// Frames more than the window behind the playhead go, as they do in the stream.
		const int64 Drop = CurrentFrame - KeepBehind - CacheFirst;
		if (Drop > 0)
		{
			Cache.RemoveAt(0, (int32)(Drop * ValuesPerFrame));
			RootCache.RemoveAt(0, (int32)(Drop * 3));
			CacheFirst += Drop;
			CacheFrames -= Drop;
		}
		FirstHeldFrame = CacheFirst;
		UpdatePose();
	}

	// 3. The next pump, once the last is done, when there is something to do: new segments,
	// a new playhead, or steps left (the last pump ran some, or had no budget). After a failed
	// pump only a new segment (an interrupt replaces the one that failed) starts another.
	const bool bWork = bCommandsWaiting || CurrentFrame != SentPlayhead || (StepsPerTick > 0 && !bLastPumpIdle);
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
