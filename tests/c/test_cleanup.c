/*
 * Post-processing through the C ABI: flame_cleanup_params_default, flame_session_read_cleaned
 * (NULL = flame_session_read, byte for byte), the frame rate (40 frames at 20 fps read as 59 at
 * 30, the frames at common times copied exactly), root motion (in place: no horizontal travel;
 * separate: FLAME_LAYOUT_ROOT_BONE on the ground, pelvis + bone = the kept pelvis), every bad
 * value refused with INVALID_ARGUMENT naming it, a struct_size too small refused, and the glTF
 * export's cleanup (a node named "root" with separate root motion; version 1 callers of
 * FlameGltfParams still served).
 *
 * Loop sessions (FlameSessionParams.looped): both passes counted by the steps and the progress,
 * the cycle's frames read (features without the next cycle's first frame), the poses equal to
 * what `flame generate --loop` writes (LOOP_POSITIONS, an .npy the CLI wrote with the same
 * settings), the wrap's jump no larger than the clip's own frame-to-frame moves, and every
 * refusal (latent model, `looped` 2, a reference on a loop session); a version 2 struct (no
 * `looped`) is a plain session.
 *
 * usage: test_cleanup FIXTURES_DIR [LOOP_POSITIONS]
 *   (tests/fixtures: flame_tiny.safetensors, 20 fps; mola_tiny.safetensors)
 *
 * The motion is read after two of ten steps: the tiny model's final motion saturates, where
 * some 6D rotations are degenerate (see test_api's pose checks).
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
#define JOINTS 24 /* smpl24_6d */
#define FRAMES 40
/* 39 intervals of 1/20 s at 30 fps: frames 0..58, the last frame's time kept. */
#define FRAMES_30 59

/* The values FlameFeet and FlameRootMotion give in src/ffi/cleanup.rs (the header does not
 * declare those enums: no function takes them by type). */
enum { FEET_OFF = 0, FEET_LOCK = 1 };
enum { ROOT_KEEP = 0, ROOT_IN_PLACE = 1, ROOT_SEPARATE = 2 };

static FlameSession *new_session(const FlameModel *m) {
    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = FRAMES;
    p.steps = 10;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.seed = 5;
    p.threads = 1;
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(m, &p, &s));
    if (!s) {
        return NULL;
    }
    CHECK_OK(flame_session_set_prompt(s, "a person walks forward and waves."));
    CHECK_OK(flame_session_step(s, NULL));
    CHECK_OK(flame_session_step(s, NULL));
    return s;
}

/* Every step off: with one field set, the poses change in that way alone. */
static FlameCleanupParams raw_cleanup(void) {
    FlameCleanupParams c;
    flame_cleanup_params_default(&c);
    c.feet = FEET_OFF;
    c.ground = 0;
    return c;
}

/* A read (cleanup may be NULL), malloc'd, its length in *n; NULL when the call fails. */
static float *read_cleaned(const FlameSession *s, int32_t layout, int32_t conv,
                           const FlameCleanupParams *c, size_t *n) {
    size_t need = 0;
    *n = 0;
    if (flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, layout, conv, 0, c, NULL, 0, &need) !=
        FLAME_STATUS_OK) {
        return NULL;
    }
    float *out = malloc((need ? need : 1) * sizeof *out);
    if (flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, layout, conv, 0, c, out, need, n) !=
        FLAME_STATUS_OK) {
        free(out);
        return NULL;
    }
    return out;
}

static float *read_raw(const FlameSession *s, int32_t layout, int32_t conv, size_t *n) {
    size_t need = 0;
    *n = 0;
    if (flame_session_read(s, FLAME_WHICH_SAMPLE, layout, conv, 0, NULL, 0, &need) !=
        FLAME_STATUS_OK) {
        return NULL;
    }
    float *out = malloc((need ? need : 1) * sizeof *out);
    if (flame_session_read(s, FLAME_WHICH_SAMPLE, layout, conv, 0, out, need, n) !=
        FLAME_STATUS_OK) {
        free(out);
        return NULL;
    }
    return out;
}

static void test_defaults(void) {
    FlameCleanupParams c;
    memset(&c, 0xAB, sizeof c);
    CHECK_OK(flame_cleanup_params_default(&c));
    CHECK(c.struct_size == sizeof(FlameCleanupParams) && sizeof(FlameCleanupParams) == 44);
    CHECK(c.feet == FEET_LOCK && c.ground == 1 && c.root_motion == ROOT_KEEP);
    CHECK(c.remove_yaw == 0 && c.wrap == 0 && c.fps == 0.0f);
    CHECK(c.contact_height == 0.05f && c.contact_speed == 0.8944272f); /* sqrt(0.8) */
    CHECK(c.contact_release == 1.5f && c.contact_min_span == 0.1f);
    CHECK_ERROR_MENTIONS(flame_cleanup_params_default(NULL), INV, "params");
    /* FlameGltfParams version 2 ends with the cleanup pointer, NULL by default. */
    FlameGltfParams g;
    CHECK_OK(flame_gltf_params_default(&g));
    CHECK(g.struct_size == sizeof(FlameGltfParams) && g.cleanup == NULL);
    CHECK(offsetof(FlameGltfParams, cleanup) == offsetof(FlameGltfParams, name) + sizeof(void *));
}

/* World quaternions are left out: they are made sign-continuous along each track after posing,
 * and the frames in between may change a track's sign (q and -q: the same rotation). */
static const int32_t k_pose_layouts[] = {
    FLAME_LAYOUT_ROOT_TRANSLATION,
    FLAME_LAYOUT_LOCAL_QUAT_XYZW,
    FLAME_LAYOUT_LOCAL_MATRIX,
    FLAME_LAYOUT_GLOBAL_POSITIONS,
};
#define N_POSE_LAYOUTS (sizeof k_pose_layouts / sizeof k_pose_layouts[0])

static void test_null_is_raw(const FlameSession *s) {
    const int32_t layouts[] = {FLAME_LAYOUT_FEATURES, FLAME_LAYOUT_ROOT_TRANSLATION,
                               FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_LAYOUT_GLOBAL_POSITIONS};
    FlameCleanupParams off = raw_cleanup();
    FlameCleanupParams model_fps = raw_cleanup();
    model_fps.fps = 20.0f; /* the model's own rate: no resample */
    for (size_t i = 0; i < sizeof layouts / sizeof layouts[0]; i++) {
        size_t nr = 0, nc = 0, no = 0, nf = 0;
        float *raw = read_raw(s, layouts[i], FLAME_CONVENTION_UNITY, &nr);
        float *clean = read_cleaned(s, layouts[i], FLAME_CONVENTION_UNITY, NULL, &nc);
        float *o = read_cleaned(s, layouts[i], FLAME_CONVENTION_UNITY, &off, &no);
        float *f = read_cleaned(s, layouts[i], FLAME_CONVENTION_UNITY, &model_fps, &nf);
        CHECK(raw && nr > 0 && clean && nc == nr && memcmp(raw, clean, nr * sizeof *raw) == 0);
        CHECK(o && same_bits(raw, nr, o, no));
        CHECK(f && same_bits(raw, nr, f, nf));
        free(raw);
        free(clean);
        free(o);
        free(f);
    }
    /* The raw features are never post-processed. */
    FlameCleanupParams game;
    flame_cleanup_params_default(&game);
    game.fps = 30.0f;
    game.root_motion = ROOT_SEPARATE;
    size_t nr = 0, nc = 0;
    float *raw = read_raw(s, FLAME_LAYOUT_FEATURES, FLAME_CONVENTION_NATIVE, &nr);
    float *clean = read_cleaned(s, FLAME_LAYOUT_FEATURES, FLAME_CONVENTION_NATIVE, &game, &nc);
    CHECK(raw && clean && same_bits(raw, nr, clean, nc));
    free(raw);
    free(clean);
    size_t n = 0;
    CHECK_ERROR_MENTIONS(flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE,
                                                    FLAME_LAYOUT_ROOT_TRANSLATION, 0, 0, &game,
                                                    NULL, 0, NULL),
                         INV, "out_len");
    CHECK_ERROR_MENTIONS(flame_session_read_cleaned(NULL, FLAME_WHICH_SAMPLE,
                                                    FLAME_LAYOUT_ROOT_TRANSLATION, 0, 0, &game,
                                                    NULL, 0, &n),
                         INV, "session");
}

static void test_fps(const FlameSession *s) {
    FlameCleanupParams c = raw_cleanup();
    c.fps = 30.0f;
    for (size_t i = 0; i < N_POSE_LAYOUTS; i++) {
        size_t nr = 0, nc = 0;
        float *raw = read_raw(s, k_pose_layouts[i], FLAME_CONVENTION_GLTF, &nr);
        float *out = read_cleaned(s, k_pose_layouts[i], FLAME_CONVENTION_GLTF, &c, &nc);
        CHECK(raw && out && nr % FRAMES == 0);
        if (!raw || !out || nr % FRAMES) {
            free(raw);
            free(out);
            continue;
        }
        size_t width = nr / FRAMES;
        CHECK(nc == FRAMES_30 * width);
        if (nc != FRAMES_30 * width) {
            free(raw);
            free(out);
            continue;
        }
        /* Output frame 3k is at input frame 2k's time: copied bit for bit. */
        int common = 1;
        for (size_t k = 0; 3 * k < FRAMES_30; k++) {
            common &= memcmp(out + 3 * k * width, raw + 2 * k * width, width * sizeof *out) == 0;
        }
        CHECK(common);
        /* Frame 1 (1/30 s) is new: neither input frame 0 nor 1. */
        CHECK(memcmp(out + width, raw, width * sizeof *out) != 0 &&
              memcmp(out + width, raw + width, width * sizeof *out) != 0);
        free(raw);
        free(out);
    }
    /* A buffer for the raw frame count is too small: the required length comes back. */
    float small[FRAMES * 3];
    size_t n = 0;
    CHECK_STATUS(flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION,
                                            FLAME_CONVENTION_GLTF, 0, &c, small, FRAMES * 3, &n),
                 FLAME_STATUS_BUFFER_TOO_SMALL);
    CHECK(n == FRAMES_30 * 3);
    /* 60 fps: 39 * 3 + 1 frames. */
    c.fps = 60.0f;
    CHECK_OK(flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION,
                                        FLAME_CONVENTION_GLTF, 0, &c, NULL, 0, &n));
    CHECK(n == (39 * 3 + 1) * 3);
    /* Contacts are detected for this smpl24 model and resampled with the poses. */
    FlameCleanupParams game;
    flame_cleanup_params_default(&game);
    game.fps = 30.0f;
    size_t nk = 0;
    float *contacts = read_cleaned(s, FLAME_LAYOUT_FOOT_CONTACTS, FLAME_CONVENTION_NATIVE, &game,
                                   &nk);
    CHECK(contacts && nk == FRAMES_30 * 4);
    int binary = contacts != NULL;
    for (size_t i = 0; contacts && i < nk; i++) {
        binary &= contacts[i] == 0.0f || contacts[i] == 1.0f;
    }
    CHECK(binary);
    free(contacts);
}

static void test_root_motion(const FlameSession *s) {
    size_t nk = 0, ni = 0, nb = 0, np = 0, nu = 0;
    float *keep = read_raw(s, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_GLTF, &nk);
    CHECK(keep && nk == FRAMES * 3);
    if (!keep || nk != FRAMES * 3) {
        free(keep);
        return;
    }
    double travel = 0.0;
    for (int f = 0; f < FRAMES; f++) {
        travel = fmax(travel, fabs(keep[f * 3] - keep[0]));
        travel = fmax(travel, fabs(keep[f * 3 + 2] - keep[2]));
    }
    CHECK(travel > 1e-3); /* the raw pelvis travels: there is something to move */

    /* glTF is Y up: x and z are horizontal. */
    FlameCleanupParams c = raw_cleanup();
    c.root_motion = ROOT_IN_PLACE;
    float *in_place = read_cleaned(s, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_GLTF, &c,
                                   &ni);
    CHECK(in_place && ni == FRAMES * 3);
    int still = in_place && ni == FRAMES * 3, height = still;
    for (int f = 0; still && f < FRAMES; f++) {
        still &= fabsf(in_place[f * 3]) < 1e-6f && fabsf(in_place[f * 3 + 2]) < 1e-6f;
        height &= in_place[f * 3 + 1] == keep[f * 3 + 1];
    }
    CHECK(still);
    CHECK(height);
    free(in_place);

    c.root_motion = ROOT_SEPARATE;
    float *bone = read_cleaned(s, FLAME_LAYOUT_ROOT_BONE, FLAME_CONVENTION_GLTF, &c, &nb);
    float *pelvis = read_cleaned(s, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_GLTF, &c, &np);
    CHECK(bone && nb == FRAMES * 3 && pelvis && np == FRAMES * 3);
    if (bone && pelvis && nb == FRAMES * 3 && np == FRAMES * 3) {
        int ground = 1, sums = 1;
        double moved = 0.0;
        for (int f = 0; f < FRAMES; f++) {
            ground &= bone[f * 3 + 1] == 0.0f;
            moved = fmax(moved, fabs(bone[f * 3]) + fabs(bone[f * 3 + 2]));
            sums &= fabs(bone[f * 3] + pelvis[f * 3] - keep[f * 3]) < 1e-5;
            sums &= fabs(bone[f * 3 + 2] + pelvis[f * 3 + 2] - keep[f * 3 + 2]) < 1e-5;
        }
        CHECK(ground);
        CHECK(moved > 1e-3);
        CHECK(sums);
    }
    /* Unreal: Z up, centimetres; the bone stays at height 0. */
    float *unreal = read_cleaned(s, FLAME_LAYOUT_ROOT_BONE, FLAME_CONVENTION_UNREAL, &c, &nu);
    CHECK(unreal && nu == FRAMES * 3);
    int flat = unreal && nu == FRAMES * 3;
    for (int f = 0; flat && f < FRAMES; f++) {
        flat &= unreal[f * 3 + 2] == 0.0f;
    }
    CHECK(flat);
    free(unreal);
    free(bone);
    free(pelvis);
    free(keep);

    /* The root bone exists only with separate root motion. */
    size_t n = 0;
    FlameCleanupParams game;
    flame_cleanup_params_default(&game);
    CHECK_ERROR_MENTIONS(flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_BONE,
                                                    0, 0, &game, NULL, 0, &n),
                         INV, "root");
    CHECK_ERROR_MENTIONS(flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_BONE,
                                                    0, 0, NULL, NULL, 0, &n),
                         INV, "root");
    CHECK_ERROR_MENTIONS(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_BONE, 0, 0,
                                            NULL, 0, &n),
                         INV, "root");
}

/* One bad cleanup: INVALID_ARGUMENT whose message contains `needle`, for a read and an export. */
static void expect_bad(const FlameSession *s, const FlameCleanupParams *c, const char *needle) {
    size_t n = 0;
    CHECK_ERROR_MENTIONS(flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE,
                                                    FLAME_LAYOUT_ROOT_TRANSLATION,
                                                    FLAME_CONVENTION_GLTF, 0, c, NULL, 0, &n),
                         INV, needle);
    FlameGltfParams g;
    flame_gltf_params_default(&g);
    g.cleanup = c;
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(s, FLAME_WHICH_SAMPLE, &g, NULL, 0, &n), INV,
                         needle);
}

static void test_bad_values(const FlameSession *s) {
    FlameCleanupParams c;
    flame_cleanup_params_default(&c);
    c.fps = NAN;
    expect_bad(s, &c, "got NaN");
    c.fps = 1e9f;
    expect_bad(s, &c, "got 1000000000");
    c.fps = 241.0f;
    expect_bad(s, &c, "got 241");
    c.fps = -30.0f;
    expect_bad(s, &c, "got -30");
    flame_cleanup_params_default(&c);
    c.contact_height = -0.5f;
    expect_bad(s, &c, "contact height (m) must be between 0 and 1, got -0.5");
    flame_cleanup_params_default(&c);
    c.contact_release = 0.5f;
    expect_bad(s, &c, "got 0.5");
    flame_cleanup_params_default(&c);
    c.contact_speed = INFINITY;
    expect_bad(s, &c, "got inf");
    flame_cleanup_params_default(&c);
    c.feet = 7;
    expect_bad(s, &c, "feet mode 7");
    c.feet = -1;
    expect_bad(s, &c, "feet is -1");
    flame_cleanup_params_default(&c);
    c.root_motion = 3;
    expect_bad(s, &c, "root motion 3");

    /* A struct_size below this library's struct is refused: the fields past it are unknown. */
    flame_cleanup_params_default(&c);
    c.struct_size = sizeof c - 4;
    expect_bad(s, &c, "struct_size");
    c.struct_size = 0;
    expect_bad(s, &c, "struct_size is 0");
    /* A larger one (a later version's) is accepted. */
    c.struct_size = sizeof c + 16;
    size_t n = 0;
    CHECK_OK(flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION, 0,
                                        0, &c, NULL, 0, &n));
    CHECK(n == FRAMES * 3);
}

/* The bytes of the GLB's JSON chunk, NUL-terminated (malloc'd), or NULL. */
static char *glb_json(const uint8_t *glb, size_t len) {
    if (len < 20 || memcmp(glb, "glTF", 4) != 0 || memcmp(glb + 16, "JSON", 4) != 0) {
        return NULL;
    }
    uint32_t n;
    memcpy(&n, glb + 12, 4);
    if (20 + (size_t)n > len) {
        return NULL;
    }
    char *json = malloc(n + 1);
    memcpy(json, glb + 20, n);
    json[n] = '\0';
    return json;
}

static char *export_json(const FlameSession *s, const FlameGltfParams *g) {
    size_t need = 0, n = 0;
    if (flame_session_write_gltf(s, FLAME_WHICH_SAMPLE, g, NULL, 0, &need) != FLAME_STATUS_OK) {
        return NULL;
    }
    uint8_t *glb = malloc(need);
    char *json = NULL;
    if (flame_session_write_gltf(s, FLAME_WHICH_SAMPLE, g, glb, need, &n) == FLAME_STATUS_OK) {
        json = glb_json(glb, n);
    }
    free(glb);
    return json;
}

static void test_gltf(const FlameSession *s) {
    FlameGltfParams g;
    flame_gltf_params_default(&g);
    char *plain = export_json(s, &g);
    CHECK(plain && strstr(plain, "\"Pelvis\"") && !strstr(plain, "\"root\""));

    FlameCleanupParams c = raw_cleanup();
    c.root_motion = ROOT_SEPARATE;
    g.cleanup = &c;
    char *separate = export_json(s, &g);
    CHECK(separate && strstr(separate, "\"name\":\"root\""));

    /* Version 1 of FlameGltfParams ended after `name`: such a caller never asked for a cleanup,
     * whatever lies past its struct, and gets the raw export, byte for byte. */
    g.struct_size = (uint32_t)offsetof(FlameGltfParams, cleanup);
    char *v1 = export_json(s, &g);
    CHECK(v1 && plain && strcmp(v1, plain) == 0);

    /* A cleanup's fps sets the animation's: the same file as fps 30 in FlameGltfParams would
     * give after resampling, so it differs from the plain one and from fps = 30 alone (which
     * keeps the 40 keys and only retimes them). */
    flame_gltf_params_default(&g);
    FlameCleanupParams thirty = raw_cleanup();
    thirty.fps = 30.0f;
    g.cleanup = &thirty;
    char *resampled = export_json(s, &g);
    flame_gltf_params_default(&g);
    g.fps = 30.0f;
    char *retimed = export_json(s, &g);
    CHECK(resampled && strstr(resampled, "\"count\":59"));
    CHECK(retimed && !strstr(retimed, "\"count\":59") && strstr(retimed, "\"count\":40"));
    free(plain);
    free(separate);
    free(v1);
    free(resampled);
    free(retimed);
}

#define LOOP_FRAMES 40
#define LOOP_LEAD 10 /* 0.5 s at 20 fps */

/* The CLI's settings for LOOP_POSITIONS (tests/c/run.sh):
 *   flame generate --frames 40 --steps 4 --sampler ddim --seed 5 --threads 1 --loop
 *     --feet off --ground off --positions LOOP_POSITIONS */
static void loop_params(FlameSessionParams *p) {
    flame_session_params_default(p);
    p->frames = LOOP_FRAMES;
    p->steps = 4;
    p->sampler = FLAME_SAMPLER_DDIM;
    p->seed = 5;
    p->threads = 1;
    p->looped = 1;
}

static void test_loop(const FlameModel *m, const char *fixtures, const char *cli_positions) {
    FlameSessionParams p;
    loop_params(&p);
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(m, &p, &s));
    if (!s) {
        return;
    }
    CHECK_OK(flame_session_set_prompt(s, "a person walks forward and waves."));
    /* Both passes: 8 steps, counted down across the edit. */
    uint32_t done = 99, total = 0, left = 0;
    CHECK_OK(flame_session_progress(s, &done, &total));
    CHECK(done == 0 && total == 8);
    int order_ok = 1;
    for (uint32_t want = 7;; want--) {
        if (flame_session_step(s, &left) != FLAME_STATUS_OK || left != want) {
            order_ok = 0;
            break;
        }
        if (want == 0) {
            break;
        }
    }
    CHECK(order_ok);
    CHECK_OK(flame_session_progress(s, &done, &total));
    CHECK(done == 8 && total == 8);
    /* The cycle's frames, raw features without the next cycle's first one. */
    uint32_t frames = 0;
    CHECK_OK(flame_session_read_frames(s, FLAME_WHICH_SAMPLE, &frames));
    CHECK(frames == LOOP_FRAMES);
    size_t n = 0;
    FlameStatus st;
    float *features = read_features(s, FLAME_WHICH_SAMPLE, &n, &st);
    CHECK(features && n == (size_t)LOOP_FRAMES * 147);
    free(features);
    /* A read with no cleanup still wraps: what the CLI wrote with --feet off --ground off. */
    size_t np = 0;
    float *pos = NULL;
    size_t need = 0;
    CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_POSITIONS,
                                FLAME_CONVENTION_NATIVE, FLAME_READ_SMOOTH, NULL, 0, &need));
    pos = malloc((need ? need : 1) * sizeof *pos);
    CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_POSITIONS,
                                FLAME_CONVENTION_NATIVE, FLAME_READ_SMOOTH, pos, need, &np));
    CHECK(np == (size_t)LOOP_FRAMES * JOINTS * 3);
    if (cli_positions) {
        size_t rows = 0, cols = 0;
        float *cli = read_npy_f32(cli_positions, &rows, &cols);
        CHECK(cli && rows * cols == np);
        double worst = 0.0;
        for (size_t i = 0; cli && rows * cols == np && i < np; i++) {
            worst = fmax(worst, fabs((double)cli[i] - pos[i]));
        }
        CHECK(cli && worst < 1e-6);
        printf("loop: C read vs `flame generate --loop` positions: %.3g m at most\n", worst);
        free(cli);
    }
    /* The wrap (last frame to the first, after the loop's own turn and shift) moves no joint
     * farther than the largest move between two frames inside: with the root motion removed
     * (in place, heading kept), frame 0 follows frame 39 as frame 1 follows frame 0. */
    FlameCleanupParams c = raw_cleanup();
    c.root_motion = ROOT_IN_PLACE;
    c.remove_yaw = 1;
    size_t nq = 0;
    float *q = read_cleaned(s, FLAME_LAYOUT_GLOBAL_POSITIONS, FLAME_CONVENTION_NATIVE, &c, &nq);
    CHECK(q && nq == np);
    if (q && nq == np) {
        double inside = 0.0, wrap = 0.0;
        for (int t = 0; t < LOOP_FRAMES; t++) {
            int u = (t + 1) % LOOP_FRAMES;
            for (int j = 0; j < JOINTS; j++) {
                const float *a = q + ((size_t)t * JOINTS + j) * 3, *b = q + ((size_t)u * JOINTS + j) * 3;
                double d = sqrt((a[0] - b[0]) * (a[0] - b[0]) + (a[1] - b[1]) * (a[1] - b[1]) +
                                (a[2] - b[2]) * (a[2] - b[2]));
                if (u == 0) {
                    wrap = fmax(wrap, d);
                } else {
                    inside = fmax(inside, d);
                }
            }
        }
        printf("loop: largest joint move at the wrap %.4f m, inside %.4f m\n", wrap, inside);
        CHECK(wrap <= inside);
    }
    free(q);
    free(pos);
    /* The loop's edit is its own. */
    float row[147] = {0};
    CHECK_ERROR_MENTIONS(flame_session_set_reference(s, row, 1, 147), INV, "its own edit");
    flame_session_free(s);

    /* Refusals when the session is made. */
    loop_params(&p);
    p.looped = 2;
    s = NULL;
    CHECK_ERROR_MENTIONS(flame_session_new(m, &p, &s), INV, "`looped`");
    CHECK(s == NULL);
    loop_params(&p);
    p.frames = 12;
    CHECK_ERROR_MENTIONS(flame_session_new(m, &p, &s), INV, "at least 40 frames");
    /* Version 2 of the struct ended before `looped`: a plain session of the frames asked. */
    loop_params(&p);
    p.struct_size = (uint32_t)offsetof(FlameSessionParams, looped);
    CHECK_OK(flame_session_new(m, &p, &s));
    if (s) {
        CHECK_OK(flame_session_progress(s, &done, &total));
        CHECK(total == 4);
        flame_session_free(s);
        s = NULL;
    }
    char path[4096];
    snprintf(path, sizeof path, "%s/mola_tiny.safetensors", fixtures);
    FlameModel *latent = NULL;
    CHECK_OK(flame_model_load(path, NULL, &latent));
    if (latent) {
        loop_params(&p);
        p.frames = 60;
        CHECK_ERROR_MENTIONS(flame_session_new(latent, &p, &s), INV, "samples a latent");
        CHECK(s == NULL);
        flame_model_free(latent);
    }
}

int main(int argc, char **argv) {
    if (argc != 2 && argc != 3) {
        fprintf(stderr, "usage: %s FIXTURES_DIR [LOOP_POSITIONS]\n", argv[0]);
        return 2;
    }
    char path[4096];
    snprintf(path, sizeof path, "%s/flame_tiny.safetensors", argv[1]);
    FlameModel *m = NULL;
    if (flame_model_load(path, NULL, &m) != FLAME_STATUS_OK) {
        fprintf(stderr, "cannot load %s: %s\n", path, flame_last_error());
        return 2;
    }
    FlameModelInfo info;
    memset(&info, 0, sizeof info);
    info.struct_size = sizeof info;
    CHECK_OK(flame_model_info(m, &info));
    CHECK(info.fps == 20.0f && info.joint_count == JOINTS);
    double t0 = now_seconds();
    test_defaults();
    FlameSession *s = new_session(m);
    if (s) {
        test_null_is_raw(s);
        test_fps(s);
        test_root_motion(s);
        test_bad_values(s);
        test_gltf(s);
    }
    flame_session_free(s);
    test_loop(m, argv[1], argc == 3 ? argv[2] : NULL);
    flame_model_free(m);
    printf("test_cleanup: %.2f s\n", now_seconds() - t0);
    return check_summary();
}
