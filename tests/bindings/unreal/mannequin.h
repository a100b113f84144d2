/*
 * What the Unreal plugin's retarget tests share: a reference skeleton named as the UE5
 * Mannequin's, and the retarget onto it made straight through flame.h (the independent path
 * the components' results are compared with). Include after the plugin's headers.
 */
#pragma once

#include <array>
#include <string>
#include <vector>

#include "flame.h"

/* A reference skeleton named as the UE5 Mannequin's (root, pelvis, spine_01..03, neck_01,
 * head, clavicle/upperarm/lowerarm/hand, thigh/calf/foot/ball, an upper-arm twist bone), in
 * Unreal's convention: Z up, facing +X, its left at -Y, centimetres; parents first as a
 * reference skeleton lists them. Rest rotations identity, translations from world positions. */
static void Mannequin(USkinnedAsset& asset) {
    FReferenceSkeleton& ref = asset.RefSkeleton;
    std::vector<std::array<double, 3>> world;
    auto add = [&](const char* name, int parent, double x, double y, double z) {
        ref.Names.Add(FName(UTF8_TO_TCHAR(name)));
        ref.Parents.Add(parent);
        const std::array<double, 3> p = parent < 0 ? std::array<double, 3>{0, 0, 0} : world[(size_t)parent];
        ref.Pose.Add(FTransform(FQuat::Identity, FVector(x - p[0], y - p[1], z - p[2]), FVector(1, 1, 1)));
        world.push_back({x, y, z});
        return ref.Names.Num() - 1;
    };
    add("root", -1, 0, 0, 0);
    const int pelvis = add("pelvis", 0, 0, 0, 100);
    const int s1 = add("spine_01", pelvis, 0, 0, 110);
    const int s2 = add("spine_02", s1, 0, 0, 125);
    const int s3 = add("spine_03", s2, 0, 0, 140);
    const int neck = add("neck_01", s3, 0, 0, 150);
    add("head", neck, 1, 0, 162);
    for (const char* side : {"l", "r"}) {
        const double m = side[0] == 'l' ? -1 : 1;
        auto n = [&](const char* bone) { static std::string s; s = std::string(bone) + "_" + side; return s.c_str(); };
        const int clav = add(n("clavicle"), s3, 0, m * 4, 145);
        const int upper = add(n("upperarm"), clav, 0, m * 17, 145);
        add(n("upperarm_twist_01"), upper, 0, m * 30, 145);
        const int lower = add(n("lowerarm"), upper, 0, m * 45, 145);
        add(n("hand"), lower, 0, m * 70, 145);
        const int thigh = add(n("thigh"), pelvis, 0, m * 10, 94);
        const int calf = add(n("calf"), thigh, 1, m * 10, 50);
        const int foot = add(n("foot"), calf, 0, m * 10, 8);
        add(n("ball"), foot, 13, m * 10, 0);
    }
}

/* The retarget of model's poses onto asset's reference skeleton through flame.h alone:
 * flame_rig_from_bones in FLAME_CONVENTION_UNREAL, the automatic bone map, the default params
 * (feet IK on). NULL on failure. */
static FlameRetarget* SkeletonRetarget(FlameModel* model, const USkinnedAsset& asset) {
    const FReferenceSkeleton& ref = asset.GetRefSkeleton();
    std::vector<std::string> names;
    for (int i = 0; i < ref.GetNum(); i++) names.push_back(ref.GetBoneName(i).ToString().Utf8());
    std::vector<FlameRigBone> bones((size_t)ref.GetNum());
    for (int i = 0; i < ref.GetNum(); i++) {
        const FTransform& t = ref.GetRefBonePose()[i];
        bones[(size_t)i] = FlameRigBone{sizeof(FlameRigBone), ref.GetParentIndex(i), names[(size_t)i].c_str(),
                                        {(float)t.Translation.X, (float)t.Translation.Y, (float)t.Translation.Z},
                                        {(float)t.Rotation.X, (float)t.Rotation.Y, (float)t.Rotation.Z, (float)t.Rotation.W},
                                        {(float)t.Scale3D.X, (float)t.Scale3D.Y, (float)t.Scale3D.Z}};
    }
    FlameRig* rig = nullptr;
    FlameRetarget* r = nullptr;
    if (flame_rig_from_bones(bones.data(), bones.size(), FLAME_CONVENTION_UNREAL, &rig) == FLAME_STATUS_OK)
        flame_retarget_new(model, rig, nullptr, &r);
    flame_rig_free(rig);
    return r;
}
