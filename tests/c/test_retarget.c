/*
 * Retargeting through the C ABI: rigs from engine bones and files, bone maps, retargets and
 * their reads.
 *
 * - A humanoid of SMPL's proportions (Mixamo names, a rest roll on every bone) given in glTF's
 *   convention, and the same character as Unreal holds it (left-handed, Z up, centimetres: the
 *   mirror image of the numbers, converted here by hand): driven by one session, the forward
 *   kinematics of each read (in its own convention, the Unreal one brought back to glTF axes
 *   by hand) put every joint at the same place (no front/back mirroring), and the glTF rig's
 *   legs and arms point where the session's own joint positions (flame_session_read_cleaned,
 *   GLOBAL_POSITIONS) point.
 * - tests/fixtures/rigs/mixamo.glb when present: loaded (guessed and named), mapped
 *   automatically, driven; truncated copies refused.
 * - Bone maps: JSON round trip, a JSON naming a missing bone and a rig lacking a required bone
 *   refused with the names in the message, then mended with a JSON map.
 * - NULL pointers, wrong struct_size, absurd counts, buffers too small, a read before any step.
 *
 * usage: test_retarget FIXTURES_DIR
 */
#define _POSIX_C_SOURCE 200809L

#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "flame.h"

#include "check.h"
#include "util.h"

#define INV FLAME_STATUS_INVALID_ARGUMENT
#define BONES 22
#define JOINTS 24 /* smpl24_6d */
#define FRAMES 20

/* SMPL-24's joints 0..21 under Mixamo's names, their parents and rest offsets (SMPL's neutral
 * body, metres, Y up, +Z forward, +X left: glTF's axes; src/motion/skeleton.rs). */
static const char *NAMES[BONES] = {
    "Hips",       "LeftUpLeg",    "RightUpLeg",    "Spine",       "LeftLeg",   "RightLeg",
    "Spine1",     "LeftFoot",     "RightFoot",     "Spine2",      "LeftToeBase", "RightToeBase",
    "Neck",       "LeftShoulder", "RightShoulder", "Head",        "LeftArm",   "RightArm",
    "LeftForeArm", "RightForeArm", "LeftHand",     "RightHand"};
static const int PARENTS[BONES] = {-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7,
                                   8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19};
static const double OFFSETS[BONES][3] = {
    {-0.00179506, -0.22333345, 0.02821913}, {0.06951974, -0.09140623, -0.00681534},
    {-0.06767048, -0.09052168, -0.00431982}, {-0.00253286, 0.10896323, -0.02669631},
    {0.03427655, -0.37519860, -0.00449580}, {-0.03829005, -0.38256901, -0.00885003},
    {0.00548703, 0.13518043, 0.00109247},   {-0.01359570, -0.39796036, -0.04369333},
    {0.01577377, -0.39841465, -0.04231180}, {0.00145700, 0.05292223, 0.02542457},
    {0.02635814, -0.05579088, 0.11928840},  {-0.02537175, -0.04814396, 0.12334795},
    {-0.00277839, 0.21387036, -0.04285703}, {0.07884474, 0.12174930, -0.03408961},
    {-0.08175919, 0.11883283, -0.03861529}, {0.00515184, 0.06496961, 0.05134897},
    {0.09097693, 0.03046890, -0.00886815},  {-0.09601238, 0.03255117, -0.00914307},
    {0.25961225, -0.01277206, -0.02745644}, {-0.25374196, -0.01332922, -0.02140098},
    {0.24923363, 0.00898603, -0.00117092},  {-0.25529808, 0.00777229, -0.00555919}};

/* Quaternions x, y, z, w. */
static void qmul(const double a[4], const double b[4], double out[4]) {
    double r[4] = {a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
                   a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
                   a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
                   a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2]};
    memcpy(out, r, sizeof r);
}

static void qrot(const double q[4], const double v[3], double out[3]) {
    double p[4] = {v[0], v[1], v[2], 0}, c[4] = {-q[0], -q[1], -q[2], q[3]}, t[4];
    double n = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    qmul(q, p, t);
    qmul(t, c, t);
    for (int i = 0; i < 3; i++) {
        out[i] = t[i] / n;
    }
}

static double angle_deg(const double a[3], const double b[3]) {
    double d = 0, na = 0, nb = 0;
    for (int i = 0; i < 3; i++) {
        d += a[i] * b[i];
        na += a[i] * a[i];
        nb += b[i] * b[i];
    }
    double c = d / sqrt(na * nb);
    return acos(c > 1 ? 1 : c < -1 ? -1 : c) * 57.29577951308232;
}

/* The humanoid in glTF's convention: rest world rotation of bone b a turn of 0.15·b rad about
 * a tilted axis (a rig whose bones all have rest rotations, as Mixamo's do), world positions
 * SMPL's with the hips at 0.95 m; local transforms derived from those. `gltf` gets them as
 * glTF holds them, `unreal` as Unreal does (x_ue = z, y_ue = −x, z_ue = y, ×100 cm; a
 * rotation about axis a turns about det(M)·M·a = −M·a). */
static void humanoid(FlameRigBone gltf[BONES], FlameRigBone unreal[BONES]) {
    double world[BONES][4], pos[BONES][3];
    const double len = sqrt(0.3 * 0.3 + 1.0 + 0.2 * 0.2);
    const double axis[3] = {0.3 / len, 1.0 / len, 0.2 / len};
    for (int b = 0; b < BONES; b++) {
        double h = 0.075 * b;
        world[b][0] = axis[0] * sin(h);
        world[b][1] = axis[1] * sin(h);
        world[b][2] = axis[2] * sin(h);
        world[b][3] = cos(h);
        int p = PARENTS[b];
        for (int i = 0; i < 3; i++) {
            pos[b][i] = (p < 0 ? (i == 1 ? 0.95 : 0.0) : pos[p][i]) + OFFSETS[b][i];
        }
    }
    for (int b = 0; b < BONES; b++) {
        int p = PARENTS[b];
        double q[4], t[3];
        if (p < 0) {
            memcpy(q, world[b], sizeof q);
            memcpy(t, pos[b], sizeof t);
        } else {
            double inv[4] = {-world[p][0], -world[p][1], -world[p][2], world[p][3]};
            double d[3] = {pos[b][0] - pos[p][0], pos[b][1] - pos[p][1], pos[b][2] - pos[p][2]};
            qmul(inv, world[b], q);
            qrot(inv, d, t);
        }
        FlameRigBone g = {sizeof(FlameRigBone), PARENTS[b], NAMES[b],
                          {(float)t[0], (float)t[1], (float)t[2]},
                          {(float)q[0], (float)q[1], (float)q[2], (float)q[3]},
                          {1, 1, 1}};
        FlameRigBone u = {sizeof(FlameRigBone), PARENTS[b], NAMES[b],
                          {(float)(100 * t[2]), (float)(-100 * t[0]), (float)(100 * t[1])},
                          {(float)-q[2], (float)q[0], (float)-q[1], (float)q[3]},
                          {1, 1, 1}};
        gltf[b] = g;
        unreal[b] = u;
    }
}

/* World positions of `bones` from local rotations and translations (one frame). */
static void fk(const float *rot, const float *tr, int bones, const int32_t *parents,
               double pos[][3]) {
    double world[256][4];
    for (int b = 0; b < bones; b++) {
        double q[4] = {rot[4 * b], rot[4 * b + 1], rot[4 * b + 2], rot[4 * b + 3]};
        double t[3] = {tr[3 * b], tr[3 * b + 1], tr[3 * b + 2]};
        int p = parents[b];
        if (p < 0) {
            memcpy(world[b], q, sizeof q);
            memcpy(pos[b], t, sizeof t);
        } else {
            double v[3];
            qmul(world[p], q, world[b]);
            qrot(world[p], t, v);
            for (int i = 0; i < 3; i++) {
                pos[b][i] = pos[p][i] + v[i];
            }
        }
    }
}

static FlameSession *start_session(const FlameModel *model, uint32_t steps) {
    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = FRAMES;
    p.steps = 10;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.seed = 11;
    p.threads = 1;
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(model, &p, &s));
    CHECK_OK(flame_session_set_prompt(s, "a person walks forward and waves."));
    for (uint32_t i = 0; i < steps; i++) {
        CHECK_OK(flame_session_step(s, NULL));
    }
    return s;
}

static FlameRetarget *retarget(const FlameModel *model, const FlameRig *rig) {
    FlameRetarget *r = NULL;
    CHECK_OK(flame_retarget_new(model, rig, NULL, &r));
    return r;
}

/* The mirror pair, driven; the glTF rig checked against the session's joints. */
static void mirrored_rigs(const FlameModel *model, FlameSession *s) {
    FlameRigBone g[BONES], u[BONES];
    humanoid(g, u);
    FlameRig *rg = NULL, *ru = NULL;
    CHECK_OK(flame_rig_from_bones(g, BONES, FLAME_CONVENTION_GLTF, &rg));
    CHECK_OK(flame_rig_from_bones(u, BONES, FLAME_CONVENTION_UNREAL, &ru));
    FlameRetarget *a = retarget(model, rg), *b = retarget(model, ru);
    size_t n = 0, frames = 0;
    CHECK_OK(flame_retarget_bone_count(a, &n));
    CHECK(n == BONES);
    FlameCleanupParams c;
    flame_cleanup_params_default(&c);
    CHECK_OK(flame_retarget_read(a, s, FLAME_WHICH_SAMPLE, 0, &c, 0, 0, NULL, 0, NULL, 0,
                                 &frames));
    CHECK(frames == FRAMES);
    size_t nr = FRAMES * BONES * 4, nt = FRAMES * BONES * 3;
    float *ra = malloc(nr * sizeof(float)), *ta = malloc(nt * sizeof(float));
    float *rb = malloc(nr * sizeof(float)), *tb = malloc(nt * sizeof(float));
    CHECK_OK(flame_retarget_read(a, s, FLAME_WHICH_SAMPLE, 0, &c, 0, FRAMES, ra, nr, ta, nt,
                                 NULL));
    CHECK_OK(flame_retarget_read(b, s, FLAME_WHICH_SAMPLE, 0, &c, 0, FRAMES, rb, nr, tb, nt,
                                 NULL));
    /* The session's own joints, glTF axes, same cleanup. */
    size_t np = 0;
    CHECK_OK(flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_POSITIONS,
                                        FLAME_CONVENTION_GLTF, 0, &c, NULL, 0, &np));
    CHECK(np == FRAMES * JOINTS * 3);
    float *src = malloc(np * sizeof(float));
    CHECK_OK(flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_POSITIONS,
                                        FLAME_CONVENTION_GLTF, 0, &c, src, np, &np));
    int32_t parents[BONES];
    for (int k = 0; k < BONES; k++) {
        CHECK_OK(flame_rig_bone_parent(rg, (size_t)k, &parents[k]));
    }
    CHECK(parents[0] == -1 && parents[20] == 18);
    double apart = 0, moved = 0, worst_dir = 0;
    /* Limbs as (joint, child joint): thighs, shins, upper arms, forearms. */
    const int limbs[8][2] = {{1, 4}, {4, 7}, {2, 5}, {5, 8}, {16, 18}, {18, 20}, {17, 19}, {19, 21}};
    for (int t = 0; t < FRAMES; t++) {
        double pa[BONES][3], pb[BONES][3];
        fk(ra + t * BONES * 4, ta + t * BONES * 3, BONES, parents, pa);
        fk(rb + t * BONES * 4, tb + t * BONES * 3, BONES, parents, pb);
        for (int k = 0; k < BONES; k++) {
            double back[3] = {-pb[k][1] / 100, pb[k][2] / 100, pb[k][0] / 100};
            for (int i = 0; i < 3; i++) {
                apart = fmax(apart, fabs(back[i] - pa[k][i]));
            }
            if (t > 0) {
                double p0[BONES][3];
                fk(ra, ta, BONES, parents, p0);
                for (int i = 0; i < 3; i++) {
                    moved = fmax(moved, fabs(pa[k][i] - p0[k][i]));
                }
            }
        }
        for (int l = 0; l < 8; l++) {
            int j = limbs[l][0], e = limbs[l][1];
            const float *sp = src + (size_t)t * JOINTS * 3;
            double want[3], got[3];
            for (int i = 0; i < 3; i++) {
                want[i] = sp[3 * e + i] - sp[3 * j + i];
                got[i] = pa[e][i] - pa[j][i];
            }
            worst_dir = fmax(worst_dir, angle_deg(want, got));
        }
    }
    printf("mirror: joints apart by %.3g m; the motion moves them up to %.3g m; limbs off "
           "the source by %.3g deg\n",
           apart, moved, worst_dir);
    CHECK(moved > 0.05);
    CHECK(apart < 1e-4);
    CHECK(worst_dir < 0.05);

    /* One frame from any source: frame 3's poses handed back give frame 3. */
    size_t nq = 0;
    CHECK_OK(flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_QUAT_XYZW,
                                        FLAME_CONVENTION_GLTF, 0, &c, NULL, 0, &nq));
    float *quats = malloc(nq * sizeof(float));
    CHECK_OK(flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_QUAT_XYZW,
                                        FLAME_CONVENTION_GLTF, 0, &c, quats, nq, &nq));
    float one_r[BONES * 4], one_t[BONES * 3];
    CHECK_OK(flame_retarget_pose(a, quats + 3 * JOINTS * 4, JOINTS * 4, src + 3 * JOINTS * 3,
                                 JOINTS * 3, one_r, BONES * 4, one_t, BONES * 3));
    double off = 0;
    for (int i = 0; i < BONES * 4; i++) {
        off = fmax(off, fabs(one_r[i] - ra[3 * BONES * 4 + i]));
    }
    CHECK(off < 1e-4);
    CHECK_STATUS(flame_retarget_pose(a, quats, JOINTS * 4 - 1, src, JOINTS * 3, one_r,
                                     BONES * 4, NULL, 0),
                 INV);
    CHECK_STATUS(flame_retarget_pose(a, quats, JOINTS * 4, src, JOINTS * 3, one_r, BONES * 4 - 1,
                                     NULL, 0),
                 FLAME_STATUS_BUFFER_TOO_SMALL);
    CHECK_STATUS(flame_retarget_pose(a, NULL, JOINTS * 4, src, JOINTS * 3, NULL, 0, NULL, 0),
                 INV);

    /* Reads: sizes, ranges, NULLs. */
    CHECK_STATUS(flame_retarget_read(a, s, 0, 0, &c, 0, FRAMES, ra, nr - 1, NULL, 0, NULL),
                 FLAME_STATUS_BUFFER_TOO_SMALL);
    CHECK_STATUS(flame_retarget_read(a, s, 0, 0, &c, FRAMES - 1, 2, ra, nr, NULL, 0, NULL), INV);
    CHECK_STATUS(flame_retarget_read(a, s, 0, 0, &c, 0, SIZE_MAX / 3, ra, nr, NULL, 0, NULL), INV);
    CHECK_STATUS(flame_retarget_read(a, s, 7, 0, &c, 0, 1, ra, nr, NULL, 0, NULL), INV);
    CHECK_STATUS(flame_retarget_read(NULL, s, 0, 0, &c, 0, 1, ra, nr, NULL, 0, NULL), INV);
    CHECK_STATUS(flame_retarget_read(a, NULL, 0, 0, &c, 0, 1, ra, nr, NULL, 0, NULL), INV);
    FlameCleanupParams bad = c;
    bad.struct_size = 4;
    CHECK_STATUS(flame_retarget_read(a, s, 0, 0, &bad, 0, 1, ra, nr, NULL, 0, NULL), INV);

    /* Outputs in another convention: Unity (x mirrored) of the glTF rig. */
    FlameRetargetParams p;
    CHECK_OK(flame_retarget_params_default(&p));
    CHECK(p.feet == 1 && p.hands == 0 && p.map == NULL && p.convention == 0);
    p.convention = FLAME_CONVENTION_UNITY;
    FlameRetarget *unity = NULL;
    CHECK_OK(flame_retarget_new(model, rg, &p, &unity));
    float ur[BONES * 4], ut[BONES * 3];
    CHECK_OK(flame_retarget_read(unity, s, 0, 0, &c, 5, 1, ur, BONES * 4, ut, BONES * 3, NULL));
    double mism = 0;
    for (int k = 0; k < BONES; k++) {
        const float *q = ra + (5 * BONES + k) * 4, *t = ta + (5 * BONES + k) * 3;
        /* Unity = glTF with x negated: t = (−x, y, z), q = (x, −y, −z, w). */
        float want[7] = {-t[0], t[1], t[2], q[0], -q[1], -q[2], q[3]};
        float got[7] = {ut[3 * k], ut[3 * k + 1], ut[3 * k + 2],
                        ur[4 * k], ur[4 * k + 1], ur[4 * k + 2], ur[4 * k + 3]};
        for (int i = 0; i < 7; i++) {
            mism = fmax(mism, fabs(want[i] - got[i]));
        }
    }
    CHECK(mism < 1e-6);
    flame_retarget_free(unity);
    p.struct_size = sizeof p - 1;
    FlameRetarget *none = NULL;
    CHECK_STATUS(flame_retarget_new(model, rg, &p, &none), INV);
    p.struct_size = sizeof p;
    p.convention = 99;
    CHECK_STATUS(flame_retarget_new(model, rg, &p, &none), INV);
    CHECK(none == NULL);

    free(quats);
    free(src);
    free(ra);
    free(ta);
    free(rb);
    free(tb);
    flame_retarget_free(a);
    flame_retarget_free(b);
    flame_rig_free(rg);
    flame_rig_free(ru);
}

static void bone_maps(const FlameModel *model) {
    FlameRigBone g[BONES], u[BONES];
    humanoid(g, u);
    /* The left hand renamed: nothing maps it. */
    g[20].name = "Prop_L";
    FlameRig *rig = NULL;
    CHECK_OK(flame_rig_from_bones(g, BONES, FLAME_CONVENTION_GLTF, &rig));
    FlameRetarget *r = NULL;
    CHECK_ERROR_MENTIONS(flame_retarget_new(model, rig, NULL, &r), INV, "leftHand");
    FlameBoneMap *m = NULL;
    CHECK_ERROR_MENTIONS(flame_bone_map_from_json(rig, "{\"leftHand\": \"Hand_L\"}", NULL, &m),
                         INV, "Hand_L");
    CHECK_ERROR_MENTIONS(flame_bone_map_from_json(rig, "{\"leftHand\": ", NULL, &m), INV,
                         "JSON");
    FlameBoneMap *autom = NULL;
    CHECK_OK(flame_bone_map_auto(rig, &autom));
    CHECK_OK(flame_bone_map_from_json(rig, "{\"leftHand\": \"Prop_L\"}", autom, &m));
    FlameRetargetParams p;
    flame_retarget_params_default(&p);
    p.map = m;
    CHECK_OK(flame_retarget_new(model, rig, &p, &r));
    /* JSON round trip through the size query. */
    size_t len = 0;
    CHECK_OK(flame_bone_map_to_json(m, rig, NULL, 0, &len));
    char *json = malloc(len);
    CHECK_STATUS(flame_bone_map_to_json(m, rig, json, len - 1, &len),
                 FLAME_STATUS_BUFFER_TOO_SMALL);
    CHECK_OK(flame_bone_map_to_json(m, rig, json, len, &len));
    CHECK(json[len - 1] == '\0' && strstr(json, "\"leftHand\": \"Prop_L\"") != NULL);
    FlameBoneMap *again = NULL;
    CHECK_OK(flame_bone_map_from_json(rig, json, NULL, &again));
    char json2[4096];
    size_t len2 = 0;
    CHECK_OK(flame_bone_map_to_json(again, rig, json2, sizeof json2, &len2));
    CHECK(len2 == len && strcmp(json, json2) == 0);
    /* A map of another rig. */
    FlameRig *other = NULL;
    g[20].name = "LeftHand";
    CHECK_OK(flame_rig_from_bones(g, BONES, FLAME_CONVENTION_GLTF, &other));
    FlameRetarget *r2 = NULL;
    CHECK_ERROR_MENTIONS(flame_retarget_new(model, other, &p, &r2), INV, "another rig");
    CHECK_STATUS(flame_bone_map_to_json(m, other, NULL, 0, &len), INV);
    CHECK_STATUS(flame_bone_map_auto(NULL, &m), INV);
    CHECK_STATUS(flame_bone_map_from_json(rig, NULL, NULL, &m), INV);
    free(json);
    flame_bone_map_free(again);
    flame_bone_map_free(autom);
    flame_bone_map_free(m);
    flame_bone_map_free(NULL);
    flame_retarget_free(r);
    flame_rig_free(rig);
    flame_rig_free(other);
}

static void engine_bone_refusals(void) {
    FlameRigBone g[BONES], u[BONES];
    humanoid(g, u);
    FlameRig *rig = NULL;
    CHECK_STATUS(flame_rig_from_bones(NULL, BONES, FLAME_CONVENTION_GLTF, &rig), INV);
    CHECK_STATUS(flame_rig_from_bones(g, BONES, FLAME_CONVENTION_GLTF, NULL), INV);
    CHECK_STATUS(flame_rig_from_bones(g, 0, FLAME_CONVENTION_GLTF, &rig), INV);
    CHECK_STATUS(flame_rig_from_bones(g, (size_t)1 << 40, FLAME_CONVENTION_GLTF, &rig), INV);
    CHECK_ERROR_MENTIONS(flame_rig_from_bones(g, BONES, FLAME_CONVENTION_NATIVE, &rig), INV,
                         "native");
    CHECK_STATUS(flame_rig_from_bones(g, BONES, 42, &rig), INV);
    FlameRigBone keep = g[5];
    g[5].struct_size = 8;
    CHECK_ERROR_MENTIONS(flame_rig_from_bones(g, BONES, FLAME_CONVENTION_GLTF, &rig), INV,
                         "bones[5]");
    g[5] = keep;
    g[5].parent = 99;
    CHECK_ERROR_MENTIONS(flame_rig_from_bones(g, BONES, FLAME_CONVENTION_GLTF, &rig), INV,
                         "RightLeg");
    g[5] = keep;
    g[5].rotation[0] = g[5].rotation[1] = g[5].rotation[2] = g[5].rotation[3] = 0;
    CHECK_ERROR_MENTIONS(flame_rig_from_bones(g, BONES, FLAME_CONVENTION_GLTF, &rig), INV,
                         "RightLeg");
    g[5] = keep;
    g[5].name = "Hips";
    CHECK_ERROR_MENTIONS(flame_rig_from_bones(g, BONES, FLAME_CONVENTION_GLTF, &rig), INV,
                         "Hips");
    g[5] = keep;
    g[5].name = NULL;
    CHECK_STATUS(flame_rig_from_bones(g, BONES, FLAME_CONVENTION_GLTF, &rig), INV);
    g[5] = keep;
    g[0].parent = 3; /* a cycle: Hips under Spine under Hips */
    CHECK_ERROR_MENTIONS(flame_rig_from_bones(g, BONES, FLAME_CONVENTION_GLTF, &rig), INV,
                         "cycle");
    CHECK(rig == NULL);
    /* Listed children first: numbered as given. */
    FlameRigBone rev[BONES];
    for (int b = 0; b < BONES; b++) {
        rev[b] = u[BONES - 1 - b];
        rev[b].parent = u[BONES - 1 - b].parent < 0 ? -1 : BONES - 1 - u[BONES - 1 - b].parent;
    }
    CHECK_OK(flame_rig_from_bones(rev, BONES, FLAME_CONVENTION_UNREAL, &rig));
    const char *name = NULL;
    int32_t parent = 0;
    CHECK_OK(flame_rig_bone_name(rig, 0, &name));
    CHECK(name && strcmp(name, "RightHand") == 0);
    CHECK_OK(flame_rig_bone_parent(rig, 0, &parent));
    CHECK(parent == BONES - 1 - 19);
    CHECK_OK(flame_rig_bone_parent(rig, BONES - 1, &parent));
    CHECK(parent == -1);
    CHECK_STATUS(flame_rig_bone_name(rig, BONES, &name), INV);
    CHECK_STATUS(flame_rig_bone_name(rig, 0, NULL), INV);
    CHECK_STATUS(flame_rig_bone_count(NULL, NULL), INV);
    flame_rig_free(rig);
    flame_rig_free(NULL);
}

static void files(const FlameModel *model, FlameSession *s, const char *dir) {
    static const char BVH[] = "HIERARCHY\nROOT Hips\n{\n OFFSET 0 95 0\n"
                              " CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation "
                              "Yrotation\n JOINT Spine\n {\n  OFFSET 0 10 0\n"
                              "  CHANNELS 3 Zrotation Xrotation Yrotation\n"
                              "  End Site\n  {\n   OFFSET 0 10 0\n  }\n }\n}\n"
                              "MOTION\nFrames: 0\nFrame Time: 0.05\n";
    FlameRig *rig = NULL;
    size_t n = 0;
    CHECK_OK(flame_rig_load((const uint8_t *)BVH, strlen(BVH), FLAME_RIG_FORMAT_GUESS, NULL,
                            &rig));
    CHECK_OK(flame_rig_bone_count(rig, &n));
    CHECK(n == 2);
    /* Two bones are no humanoid: refused with what is missing. */
    FlameRetarget *r = NULL;
    CHECK_ERROR_MENTIONS(flame_retarget_new(model, rig, NULL, &r), INV, "leftUpperLeg");
    flame_rig_free(rig);
    rig = NULL;
    CHECK_STATUS(flame_rig_load((const uint8_t *)BVH, 40, FLAME_RIG_FORMAT_BVH, NULL, &rig), INV);
    CHECK_STATUS(flame_rig_load((const uint8_t *)BVH, strlen(BVH), FLAME_RIG_FORMAT_BVH, "skin",
                                &rig),
                 INV);
    CHECK_STATUS(flame_rig_load((const uint8_t *)"garbage", 7, 0, NULL, &rig), INV);
    CHECK_STATUS(flame_rig_load((const uint8_t *)BVH, strlen(BVH), 9, NULL, &rig), INV);
    CHECK_STATUS(flame_rig_load(NULL, 10, 0, NULL, &rig), INV);
    CHECK_STATUS(flame_rig_load((const uint8_t *)BVH, strlen(BVH), 0, NULL, NULL), INV);
    CHECK(rig == NULL);

    char path[4096];
    snprintf(path, sizeof path, "%s/rigs/mixamo.glb", dir);
    size_t len = 0;
    unsigned char *glb = read_file(path, &len);
    if (!glb) {
        printf("skip mixamo.glb (not in %s/rigs)\n", dir);
        return;
    }
    CHECK_OK(flame_rig_load(glb, len, FLAME_RIG_FORMAT_GUESS, NULL, &rig));
    CHECK_OK(flame_rig_bone_count(rig, &n));
    int hips = -1;
    for (size_t b = 0; b < n; b++) {
        const char *name = NULL;
        CHECK_OK(flame_rig_bone_name(rig, b, &name));
        if (name && strstr(name, "Hips")) {
            hips = (int)b;
        }
    }
    CHECK(hips >= 0);
    r = retarget(model, rig);
    float *rot = malloc(FRAMES * n * 4 * sizeof(float));
    float *tr = malloc(FRAMES * n * 3 * sizeof(float));
    FlameCleanupParams c;
    flame_cleanup_params_default(&c);
    CHECK_OK(flame_retarget_read(r, s, 0, 0, &c, 0, FRAMES, rot, FRAMES * n * 4, tr,
                                 FRAMES * n * 3, NULL));
    double travel = 0;
    for (int i = 0; i < 3 && hips >= 0; i++) {
        travel = fmax(travel, fabs(tr[((FRAMES - 1) * n + (size_t)hips) * 3 + i] -
                                   tr[(size_t)hips * 3 + i]));
    }
    printf("mixamo.glb: %zu bones, the hips travel %.3g units\n", n, travel);
    CHECK(travel > 0.01);
    flame_retarget_free(r);
    flame_rig_free(rig);
    /* Truncated copies: refused, never a crash. */
    size_t cuts[] = {0, 4, 12, 20, len / 3, len / 2, len - 1};
    for (size_t k = 0; k < sizeof cuts / sizeof cuts[0]; k++) {
        rig = NULL;
        FlameStatus st = flame_rig_load(glb, cuts[k], FLAME_RIG_FORMAT_GLTF, NULL, &rig);
        CHECK_STATUS(st, INV);
        CHECK(rig == NULL);
    }
    free(rot);
    free(tr);
    free(glb);
}

int main(int argc, char **argv) {
    if (argc < 2) {
        fprintf(stderr, "usage: %s FIXTURES_DIR\n", argv[0]);
        return 2;
    }
    char path[4096];
    snprintf(path, sizeof path, "%s/flame_tiny.safetensors", argv[1]);
    FlameModel *model = NULL;
    CHECK_OK(flame_model_load(path, NULL, &model));
    if (!model) {
        return check_summary();
    }
    /* Before the first step there is no sample: reading it is out of order. */
    FlameSession *early = start_session(model, 0);
    FlameRigBone g[BONES], u[BONES];
    humanoid(g, u);
    FlameRig *rig = NULL;
    CHECK_OK(flame_rig_from_bones(g, BONES, FLAME_CONVENTION_GLTF, &rig));
    FlameRetarget *r = retarget(model, rig);
    float buf[BONES * 4];
    CHECK_STATUS(flame_retarget_read(r, early, 0, 0, NULL, 0, 1, buf, BONES * 4, NULL, 0, NULL),
                 FLAME_STATUS_WRONG_STATE);
    CHECK_STATUS(flame_retarget_read(r, early, 1, 0, NULL, 0, 1, buf, BONES * 4, NULL, 0, NULL),
                 FLAME_STATUS_WRONG_STATE);
    flame_retarget_free(r);
    flame_rig_free(rig);
    flame_session_free(early);

    /* Two of ten steps: the tiny model's final motion saturates (see test_cleanup). */
    FlameSession *s = start_session(model, 2);
    mirrored_rigs(model, s);
    bone_maps(model);
    engine_bone_refusals();
    files(model, s, argv[1]);
    flame_retarget_free(NULL);
    flame_session_free(s);
    flame_model_free(model);
    return check_summary();
}
