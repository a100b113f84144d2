// What the plugin's components share: a reference-counted model, the count of holders of
// libflame's threads, libflame's failure message and UTF-8 copies of FStrings. Private to the
// module; include it after the engine headers (it includes flame.h, which defines a few
// unprefixed names).

#pragma once

#include "Components/PoseableMeshComponent.h"
#include "CoreMinimal.h"
#include "Engine/SkinnedAsset.h"
#include "FlameModule.h"
#include "FlameMotionComponent.h" // FFlameStage
#include "ReferenceSkeleton.h"

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

/**
 * A skeletal mesh's reference skeleton as libflame's rig (flame_rig_from_bones in
 * FLAME_CONVENTION_UNREAL: libflame carries the left-handed Z-up centimetres into its own axes
 * and gives poses back in them), copied on the game thread so a worker can make the retarget
 * once the model is loaded. Bones keep the reference skeleton's indices, so pose bone i is
 * BoneSpaceTransforms[i].
 */
struct FFlameRigSpec
{
	TArray<FString> Names;
	TArray<int32> Parents;
	TArray<FTransform> Rest;
	FString BoneMapJson; // entries over libflame's automatic map (Mannequin, Mixamo, ... names); empty: that map
	bool bFeetIk = true;

	bool IsSet() const { return Names.Num() > 0; }

	/** The reference skeleton of Mesh's skinned asset (its bone names, parents and
	 *  GetRefBonePose transforms); false with the reason when there is none. */
	bool FromMesh(const UPoseableMeshComponent* Mesh, FString& Failure)
	{
		const USkinnedAsset* Asset = Mesh != nullptr ? Mesh->GetSkinnedAsset() : nullptr;
		if (Asset == nullptr)
		{
			Failure = TEXT("RetargetMesh has no skeletal mesh: set one before Generate");
			return false;
		}
		const FReferenceSkeleton& Ref = Asset->GetRefSkeleton();
		const TArray<FTransform>& Pose = Ref.GetRefBonePose();
		Names.Reset();
		Parents.Reset();
		Rest.Reset();
		for (int32 I = 0; I < Ref.GetNum() && I < Pose.Num(); I++)
		{
			Names.Add(Ref.GetBoneName(I).ToString());
			Parents.Add(Ref.GetParentIndex(I));
			Rest.Add(Pose[I]);
		}
		if (Names.Num() == 0)
		{
			Failure = TEXT("RetargetMesh's skeletal mesh has no bones");
			return false;
		}
		return true;
	}

	/** The retarget of Model's poses onto this rig (rig, bone map and retarget made and the
	 *  first two freed again: the retarget keeps copies); null with libflame's message. */
	FlameRetarget* Make(FlameModel* Model, FString& Failure) const
	{
		TArray<TArray<ANSICHAR>> Utf8;
		for (int32 I = 0; I < Names.Num(); I++)
		{
			Utf8.Add(Utf8Z(Names[I]));
		}
		// Pointers into Utf8 only once it is complete (adding may move its buffers).
		TArray<FlameRigBone> Bones;
		Bones.SetNumUninitialized(Names.Num());
		for (int32 I = 0; I < Names.Num(); I++)
		{
			FlameRigBone& B = Bones[I];
			FMemory::Memzero(B);
			B.struct_size = sizeof(FlameRigBone);
			B.parent = Parents[I];
			B.name = Utf8[I].GetData();
			const FVector T = Rest[I].GetTranslation(), S = Rest[I].GetScale3D();
			const FQuat R = Rest[I].GetRotation();
			const double Values[10] = {T.X, T.Y, T.Z, R.X, R.Y, R.Z, R.W, S.X, S.Y, S.Z};
			for (int32 K = 0; K < 3; K++)
			{
				B.translation[K] = (float)Values[K];
				B.scale[K] = (float)Values[7 + K];
			}
			for (int32 K = 0; K < 4; K++)
			{
				B.rotation[K] = (float)Values[3 + K];
			}
		}
		FlameRig* Rig = nullptr;
		FlameBoneMap* Map = nullptr;
		FlameRetarget* Out = nullptr;
		FlameStatus Status = flame_rig_from_bones(Bones.GetData(), (size_t)Bones.Num(), FLAME_CONVENTION_UNREAL, &Rig);
		if (Status == FLAME_STATUS_OK && !BoneMapJson.IsEmpty())
		{
			// The JSON's entries over the automatic map: naming the one bone it misses is enough.
			FlameBoneMap* Auto = nullptr;
			Status = flame_bone_map_auto(Rig, &Auto);
			if (Status == FLAME_STATUS_OK)
			{
				const TArray<ANSICHAR> Json = Utf8Z(BoneMapJson);
				Status = flame_bone_map_from_json(Rig, Json.GetData(), Auto, &Map);
			}
			flame_bone_map_free(Auto);
		}
		FlameRetargetParams Params;
		if (Status == FLAME_STATUS_OK)
		{
			Status = flame_retarget_params_default(&Params);
		}
		if (Status == FLAME_STATUS_OK)
		{
			Params.feet = bFeetIk ? 1u : 0u;
			Params.map = Map; // NULL: the automatic map
			Status = flame_retarget_new(Model, Rig, &Params, &Out);
		}
		if (Status != FLAME_STATUS_OK)
		{
			Failure = FString(TEXT("retarget onto RetargetMesh: ")) + FlameFailure(Status);
		}
		flame_bone_map_free(Map);
		flame_rig_free(Rig);
		return Out;
	}

	/** Writes Frame of a retarget's poses (Rotations: frames × bones × 4, x, y, z, w;
	 *  Translations: × 3, centimetres; Unreal's convention) into Mesh's bone-space transforms,
	 *  rest scale kept, and marks them for refresh. False when Frame is not in them or the
	 *  mesh's bones are no longer this rig's (another mesh was set). */
	bool Apply(UPoseableMeshComponent* Mesh, const TArray<float>& Rotations, const TArray<float>& Translations, int32 Frame) const
	{
		const int32 N = Names.Num();
		if (Mesh == nullptr || N == 0 || Mesh->BoneSpaceTransforms.Num() != N || Frame < 0 ||
			(int64)Rotations.Num() < ((int64)Frame + 1) * N * 4 || (int64)Translations.Num() < ((int64)Frame + 1) * N * 3)
		{
			return false;
		}
		for (int32 B = 0; B < N; B++)
		{
			const float* Q = Rotations.GetData() + ((int64)Frame * N + B) * 4;
			const float* T = Translations.GetData() + ((int64)Frame * N + B) * 3;
			Mesh->BoneSpaceTransforms[B] = FTransform(FQuat(Q[0], Q[1], Q[2], Q[3]), FVector(T[0], T[1], T[2]), Rest[B].GetScale3D());
		}
		Mesh->MarkRefreshTransformDirty();
		return true;
	}
};

/** Owns a retarget for one worker. */
struct FFlameRetargetRef
{
	FlameRetarget* Handle = nullptr;
	~FFlameRetargetRef() { flame_retarget_free(Handle); }
};
