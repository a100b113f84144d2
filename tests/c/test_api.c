/*
 * Every function of include/flame.h and its error paths, through the C ABI only.
 *
 * usage: test_api MODEL REFERENCE_NPY TMPDIR [STEPS]
 *   MODEL          tests/fixtures/flame_tiny.safetensors
 *   REFERENCE_NPY  `flame generate` output for REF_PROMPT with ref_params() (tests/c/run.sh):
 *                  its row count sets ref_frames
 *   TMPDIR         a writable directory for the bad model files this test makes
 *   STEPS          the reference's --steps (default 10; at least 2)
 *
 * FLAME_TEST_QUICK=1 shortens the long generations (for valgrind).
 */
#define _GNU_SOURCE /* memmem */

#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "flame.h"

#include "check.h"
#include "util.h"

static const char *g_model_path;
static const char *g_tmp_dir;
static float *g_ref;   /* the CLI's features */
static size_t g_ref_n; /* frames × 147 */

#define REF_VALUES ((size_t)ref_frames * FLAME_TINY_DIM)

/* "N" as a string, to look for numbers in error messages. */
static const char *num(size_t n) {
    static char buf[8][32];
    static int next;
    char *b = buf[next++ % 8];
    snprintf(b, sizeof buf[0], "%zu", n);
    return b;
}

static FlameModel *load_or_die(const char *path) {
    FlameModel *m = NULL;
    if (flame_model_load(path, NULL, &m) != FLAME_STATUS_OK) {
        fprintf(stderr, "cannot load %s: %s\n", path, flame_last_error());
        exit(2);
    }
    return m;
}

static FlameSession *ref_session(const FlameModel *m) {
    FlameSessionParams p;
    ref_params(&p);
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(m, &p, &s));
    return s;
}

/* Runs the reference generation on `s` (already configured) and compares with the CLI. */
static int matches_reference(FlameSession *s) {
    FlameStatus st = run_to_end(s, REF_PROMPT);
    if (st != FLAME_STATUS_OK) {
        fprintf(stderr, "generation failed: %s\n", flame_last_error());
        return 0;
    }
    size_t n = 0;
    float *x = read_features(s, FLAME_WHICH_SAMPLE, &n, &st);
    int same = same_bits(x, n, g_ref, g_ref_n);
    free(x);
    return same;
}

/* ---- versions and status names --------------------------------------------------------- */

static void test_versions(void) {
    CHECK(flame_abi_version() == FLAME_ABI_VERSION);
    char expected[64];
    snprintf(expected, sizeof expected, "%d.%d.%d", FLAME_VERSION_MAJOR, FLAME_VERSION_MINOR,
             FLAME_VERSION_PATCH);
    CHECK(flame_version_string() != NULL);
    CHECK(strcmp(flame_version_string(), expected) == 0);
    /* A static string: the same pointer every time. */
    CHECK(flame_version_string() == flame_version_string());
}

static void test_status_strings(void) {
    static const char *names[] = {
        "FLAME_STATUS_OK",          "FLAME_STATUS_INVALID_ARGUMENT",
        "FLAME_STATUS_IO",          "FLAME_STATUS_BAD_MODEL_FILE",
        "FLAME_STATUS_WRONG_STATE", "FLAME_STATUS_CANCELLED",
        "FLAME_STATUS_TOKENIZER",   "FLAME_STATUS_BUFFER_TOO_SMALL",
        "FLAME_STATUS_INTERNAL",    "FLAME_STATUS_NOT_FINITE",
    };
    CHECK(FLAME_STATUS_OK == 0 && FLAME_STATUS_NOT_FINITE == 9);
    for (int i = 0; i <= (int)FLAME_STATUS_NOT_FINITE; i++) {
        CHECK(strcmp(flame_status_string(i), names[i]) == 0);
    }
    CHECK(strcmp(flame_status_string(-1), "FLAME_STATUS_UNKNOWN") == 0);
    CHECK(strcmp(flame_status_string(10), "FLAME_STATUS_UNKNOWN") == 0);
    CHECK(strcmp(flame_status_string(INT32_MAX), "FLAME_STATUS_UNKNOWN") == 0);
}

/* ---- parameter defaults ---------------------------------------------------------------- */

static void test_param_defaults(void) {
    CHECK_ERROR_MENTIONS(flame_model_params_default(NULL), FLAME_STATUS_INVALID_ARGUMENT, "params");
    FlameModelParams mp;
    memset(&mp, 0xAB, sizeof mp);
    CHECK_OK(flame_model_params_default(&mp));
    CHECK(mp.struct_size == sizeof(FlameModelParams));
    CHECK(mp.threads == 0);
    CHECK(mp.weights == FLAME_WEIGHTS_F32);

    CHECK_ERROR_MENTIONS(flame_session_params_default(NULL), FLAME_STATUS_INVALID_ARGUMENT,
                         "params");
    FlameSessionParams sp;
    memset(&sp, 0xAB, sizeof sp);
    CHECK_OK(flame_session_params_default(&sp));
    CHECK(sp.struct_size == sizeof(FlameSessionParams));
    CHECK(sp.frames == 0 && sp.steps == 0 && sp.sampler == FLAME_SAMPLER_DEFAULT);
    CHECK(sp.eta < 0.0f && sp.guidance < 0.0f);
    CHECK(sp.seed == 0 && sp.threads == 0);
}

/* ---- loading --------------------------------------------------------------------------- */

static void tmp_path(char *buf, size_t size, const char *name) {
    snprintf(buf, size, "%s/%s", g_tmp_dir, name);
}

/* Loading `bytes` from a file and from memory must both fail with `expected`, leaving the
 * out-pointer untouched. */
static void check_bad_bytes(const char *name, const void *bytes, size_t len, int expected) {
    char path[4096];
    tmp_path(path, sizeof path, name);
    if (!write_file(path, bytes, len)) {
        CHECK(!"cannot write a temporary model file");
        return;
    }
    FlameModel *sentinel = (FlameModel *)(uintptr_t)0x1234;
    FlameModel *m = sentinel;
    CHECK_STATUS(flame_model_load(path, NULL, &m), expected);
    CHECK(m == sentinel);
    m = sentinel;
    CHECK_STATUS(flame_model_load_from_memory((const uint8_t *)bytes, len, NULL, &m), expected);
    CHECK(m == sentinel);
    remove(path);
}

static void test_load_errors(const unsigned char *file, size_t file_len) {
    FlameModelParams mp;
    flame_model_params_default(&mp);
    FlameModel *sentinel = (FlameModel *)(uintptr_t)0x1234;
    FlameModel *m = sentinel;

    /* NULL pointers. */
    CHECK_ERROR_MENTIONS(flame_model_load(NULL, &mp, &m), FLAME_STATUS_INVALID_ARGUMENT, "path");
    CHECK_ERROR_MENTIONS(flame_model_load(g_model_path, &mp, NULL), FLAME_STATUS_INVALID_ARGUMENT,
                         "model");
    CHECK_ERROR_MENTIONS(flame_model_load_from_memory(NULL, file_len, &mp, &m),
                         FLAME_STATUS_INVALID_ARGUMENT, "bytes");
    CHECK_ERROR_MENTIONS(flame_model_load_from_memory(file, file_len, &mp, NULL),
                         FLAME_STATUS_INVALID_ARGUMENT, "model");
    CHECK(m == sentinel);

    /* struct_size too small (0, and one byte short of version 1's 8 bytes). */
    FlameModelParams small = mp;
    small.struct_size = 0;
    CHECK_ERROR_MENTIONS(flame_model_load(g_model_path, &small, &m), FLAME_STATUS_INVALID_ARGUMENT,
                         "struct_size");
    small.struct_size = 7;
    CHECK_STATUS(flame_model_load(g_model_path, &small, &m), FLAME_STATUS_INVALID_ARGUMENT);
    CHECK_STATUS(flame_model_load_from_memory(file, file_len, &small, &m),
                 FLAME_STATUS_INVALID_ARGUMENT);
    CHECK(m == sentinel);

    /* An unknown weight type. */
    FlameModelParams bad_weights = mp;
    bad_weights.weights = 7;
    CHECK_ERROR_MENTIONS(flame_model_load(g_model_path, &bad_weights, &m),
                         FLAME_STATUS_INVALID_ARGUMENT, "weights");
    CHECK_STATUS(flame_model_load_from_memory(file, file_len, &bad_weights, &m),
                 FLAME_STATUS_INVALID_ARGUMENT);
    CHECK(m == sentinel);

    /* A caller built against version 1 of the struct (struct_size 8, no `weights` field): the
     * bytes after it are never read, so garbage there changes nothing. */
    struct {
        FlameModelParams p;
        unsigned char poison[16];
    } v1;
    memset(&v1, 0xA5, sizeof v1);
    v1.p.struct_size = 8;
    v1.p.threads = 1;
    FlameModel *old_abi = NULL;
    CHECK_STATUS(flame_model_load(g_model_path, &v1.p, &old_abi), FLAME_STATUS_OK);
    flame_model_free(old_abi);

    /* Half-precision weights load. */
    for (int w = FLAME_WEIGHTS_F32; w <= FLAME_WEIGHTS_BF16; w++) {
        FlameModelParams hp = mp;
        hp.weights = w;
        FlameModel *half = NULL;
        CHECK_STATUS(flame_model_load(g_model_path, &hp, &half), FLAME_STATUS_OK);
        CHECK(half != NULL);
        flame_model_free(half);
    }

    /* Reduced-precision compute loads where the CPU has its instructions (FLAME_TEST_CPU_*
     * say which: tests/c/run.sh reads /proc/cpuinfo), and is INVALID_ARGUMENT naming them
     * elsewhere. */
    const struct {
        int weights;
        const char *cpu_env, *instruction;
    } reduced[] = {{FLAME_WEIGHTS_BF16_COMPUTE, "FLAME_TEST_CPU_BF16", "AVX512_BF16"},
                   {FLAME_WEIGHTS_INT8, "FLAME_TEST_CPU_INT8", "AVX2"}};
    for (size_t i = 0; i < sizeof reduced / sizeof reduced[0]; i++) {
        FlameModelParams rp = mp;
        rp.weights = reduced[i].weights;
        FlameModel *r = NULL;
        const char *has = getenv(reduced[i].cpu_env);
        if (has && strcmp(has, "1") == 0) {
            CHECK_STATUS(flame_model_load(g_model_path, &rp, &r), FLAME_STATUS_OK);
            CHECK(r != NULL);
            flame_model_free(r);
        } else if (has && strcmp(has, "0") == 0) {
            CHECK_ERROR_MENTIONS(flame_model_load(g_model_path, &rp, &r),
                                 FLAME_STATUS_INVALID_ARGUMENT, reduced[i].instruction);
            CHECK(r == NULL);
        } else {
            printf("  %s not set: weights %d not checked\n", reduced[i].cpu_env, rp.weights);
        }
    }

    /* Files that cannot be read. */
    char path[4096];
    tmp_path(path, sizeof path, "does-not-exist.safetensors");
    CHECK_ERROR_MENTIONS(flame_model_load(path, NULL, &m), FLAME_STATUS_IO, "does-not-exist");
    CHECK_STATUS(flame_model_load(g_tmp_dir, NULL, &m), FLAME_STATUS_IO); /* a directory */
    CHECK_STATUS(flame_model_load("", NULL, &m), FLAME_STATUS_IO);
    CHECK(m == sentinel);

    /* Malformed files: empty, shorter than the header length, cut in the JSON header, cut in
     * the tensor data, one byte short, garbage, an absurd header length, a safetensors file
     * that is not a libflame model. */
    check_bad_bytes("empty.safetensors", file, 0, FLAME_STATUS_BAD_MODEL_FILE);
    check_bad_bytes("cut7.safetensors", file, 7, FLAME_STATUS_BAD_MODEL_FILE);
    check_bad_bytes("cut100.safetensors", file, 100, FLAME_STATUS_BAD_MODEL_FILE);
    check_bad_bytes("half.safetensors", file, file_len / 2, FLAME_STATUS_BAD_MODEL_FILE);
    check_bad_bytes("short1.safetensors", file, file_len - 1, FLAME_STATUS_BAD_MODEL_FILE);

    unsigned char *garbage = (unsigned char *)malloc(4096);
    uint64_t x = 0x9E3779B97F4A7C15ull;
    for (size_t i = 0; i < 4096; i++) {
        x ^= x << 13, x ^= x >> 7, x ^= x << 17;
        garbage[i] = (unsigned char)x;
    }
    check_bad_bytes("garbage.safetensors", garbage, 4096, FLAME_STATUS_BAD_MODEL_FILE);
    memset(garbage, 0xFF, 8); /* header length 2^64 - 1 */
    check_bad_bytes("huge-header.safetensors", garbage, 4096, FLAME_STATUS_BAD_MODEL_FILE);
    free(garbage);

    static const char json[] = "{\"__metadata__\":{\"format\":\"pt\"}}";
    unsigned char foreign[8 + sizeof json - 1];
    uint64_t n = sizeof json - 1;
    for (int i = 0; i < 8; i++) {
        foreign[i] = (unsigned char)(n >> (8 * i));
    }
    memcpy(foreign + 8, json, sizeof json - 1);
    check_bad_bytes("foreign.safetensors", foreign, sizeof foreign, FLAME_STATUS_BAD_MODEL_FILE);

    /* NULL bytes with length 0 is an empty buffer, not a NULL-argument error. */
    CHECK_STATUS(flame_model_load_from_memory(NULL, 0, NULL, &m), FLAME_STATUS_BAD_MODEL_FILE);
    CHECK(m == sentinel);
}

/* Loads from memory, scrubs and frees the caller's buffer (the bytes are copied), and checks
 * the model still generates the reference. Also: explicit params with one load thread. */
static void test_load_from_memory(const unsigned char *file, size_t file_len) {
    unsigned char *copy = (unsigned char *)malloc(file_len);
    memcpy(copy, file, file_len);
    FlameModelParams mp;
    flame_model_params_default(&mp);
    mp.threads = 1;
    FlameModel *m = NULL;
    CHECK_OK(flame_model_load_from_memory(copy, file_len, &mp, &m));
    memset(copy, 0, file_len);
    free(copy);
    CHECK(m != NULL);
    if (!m) {
        return;
    }
    FlameSession *s = ref_session(m);
    CHECK(matches_reference(s));
    flame_session_free(s);
    flame_model_free(m);
}

/* ---- model info ------------------------------------------------------------------------- */

static void test_model_info(const FlameModel *m) {
    FlameModelInfo info;
    memset(&info, 0, sizeof info);
    info.struct_size = sizeof info;
    CHECK_ERROR_MENTIONS(flame_model_info(NULL, &info), FLAME_STATUS_INVALID_ARGUMENT, "model");
    CHECK_ERROR_MENTIONS(flame_model_info(m, NULL), FLAME_STATUS_INVALID_ARGUMENT, "info");

    FlameModelInfo small;
    memset(&small, 0x5A, sizeof small);
    small.struct_size = 0;
    CHECK_ERROR_MENTIONS(flame_model_info(m, &small), FLAME_STATUS_INVALID_ARGUMENT, "struct_size");
    CHECK(small.feature_dim == 0x5A5A5A5Au); /* outputs only on success */
    small.struct_size = sizeof small - 1;
    CHECK_STATUS(flame_model_info(m, &small), FLAME_STATUS_INVALID_ARGUMENT);

    CHECK_OK(flame_model_info(m, &info));
    CHECK(info.struct_size == sizeof info);
    CHECK(info.feature_dim == FLAME_TINY_DIM);
    CHECK(info.max_frames == FLAME_TINY_MAX_FRAMES);
    CHECK(info.architecture && strcmp(info.architecture, "flame") == 0);
    CHECK(info.motion_format && strcmp(info.motion_format, "smpl24_6d") == 0);
    CHECK(info.text_encoder && strcmp(info.text_encoder, "roberta") == 0);
    CHECK(info.fps == 20.0f);
    CHECK(info.default_frames == 200);
    CHECK(info.default_steps == 1000);
    CHECK(info.num_timesteps == 1000);
    CHECK(info.default_sampler == FLAME_SAMPLER_DDPM);
    CHECK(info.default_guidance == 8.0f);
    CHECK(info.default_eta == 0.0f);
    /* The skeleton tables agree with joint_count whatever it is... */
    CHECK(info.joint_count == 0 ? (info.joint_names == NULL && info.joint_parents == NULL)
                                : (info.joint_names != NULL && info.joint_parents != NULL));
    for (uint32_t j = 0; j < info.joint_count; j++) {
        CHECK(info.joint_names[j] != NULL && info.joint_names[j][0] != '\0');
        CHECK(info.joint_parents[j] >= -1 && info.joint_parents[j] < (int32_t)j);
    }
    /* ...and smpl24_6d has SMPL's 24 joints rooted at the pelvis. */
    CHECK(info.joint_count == 24);
    if (info.joint_count == 24 && info.joint_names && info.joint_parents) {
        CHECK(strcmp(info.joint_names[0], "Pelvis") == 0 && info.joint_parents[0] == -1);
        CHECK(strcmp(info.joint_names[23], "R_Hand") == 0 && info.joint_parents[23] == 21);
    }
}

/* ---- session creation ------------------------------------------------------------------- */

static void check_bad_session(const FlameModel *m, const FlameSessionParams *p, const char *needle,
                              int line) {
    FlameSession *sentinel = (FlameSession *)(uintptr_t)0x1234;
    FlameSession *s = sentinel;
    int st = flame_session_new(m, p, &s);
    char err[512];
    check_copy_last_error(err, sizeof err);
    char what[256];
    snprintf(what, sizeof what, "flame_session_new rejects bad params (line %d, \"%s\")", line,
             needle);
    check_record(st == FLAME_STATUS_INVALID_ARGUMENT && s == sentinel && strstr(err, needle),
                 __FILE__, line, what, err);
    if (s != sentinel) {
        flame_session_free(s);
    }
}
#define BAD_SESSION(field, value, needle)            \
    do {                                             \
        FlameSessionParams p_;                       \
        flame_session_params_default(&p_);           \
        p_.field = value;                            \
        check_bad_session(m, &p_, needle, __LINE__); \
    } while (0)

static void test_session_new(const FlameModel *m) {
    FlameSessionParams p;
    flame_session_params_default(&p);
    FlameSession *s = NULL;
    CHECK_ERROR_MENTIONS(flame_session_new(NULL, &p, &s), FLAME_STATUS_INVALID_ARGUMENT, "model");
    CHECK_ERROR_MENTIONS(flame_session_new(m, &p, NULL), FLAME_STATUS_INVALID_ARGUMENT, "session");
    CHECK(s == NULL);

    BAD_SESSION(struct_size, 0, "struct_size");
    /* One byte short of version 1's 40 bytes (version 2 added `respacing`). */
    BAD_SESSION(struct_size, 39, "struct_size");
    BAD_SESSION(frames, FLAME_TINY_MAX_FRAMES + 1, "frames");
    BAD_SESSION(frames, UINT32_MAX, "frames");
    BAD_SESSION(steps, 1001, "steps");
    BAD_SESSION(steps, UINT32_MAX, "steps");
    BAD_SESSION(sampler, 7, "sampler");
    BAD_SESSION(sampler, -1, "sampler");
    BAD_SESSION(guidance, NAN, "guidance");
    BAD_SESSION(guidance, INFINITY, "guidance");
    BAD_SESSION(eta, NAN, "eta");
    {
        FlameSessionParams q;
        flame_session_params_default(&q);
        q.sampler = FLAME_SAMPLER_DDIM;
        q.eta = INFINITY;
        check_bad_session(m, &q, "eta", __LINE__);
    }

    /* A respacing string: "ddim50" keeps every 20th of the 1000 steps; a count no stride
     * gives, or one that disagrees with `steps`, is refused. */
    {
        FlameSessionParams q;
        flame_session_params_default(&q);
        CHECK(q.respacing == NULL);
        q.threads = 1;
        q.respacing = "ddim50";
        FlameSession *r = NULL;
        CHECK_OK(flame_session_new(m, &q, &r));
        uint32_t d = 99, t = 0;
        CHECK_OK(flame_session_progress(r, &d, &t));
        CHECK(d == 0 && t == 50);
        flame_session_free(r);
        q.steps = 40;
        check_bad_session(m, &q, "steps 40 disagrees with respacing", __LINE__);
        q.steps = 0;
        q.respacing = "ddim999";
        check_bad_session(m, &q, "cannot create exactly 999 steps", __LINE__);
    }
    /* A caller built against version 1 (struct_size 40, no `respacing`): the bytes after it
     * are never read, so garbage there changes nothing. */
    {
        struct {
            FlameSessionParams p;
            unsigned char poison[16];
        } v1;
        memset(&v1, 0xA5, sizeof v1);
        flame_session_params_default(&v1.p);
        memset((unsigned char *)&v1.p + 40, 0xA5, sizeof v1 - 40);
        v1.p.struct_size = 40;
        v1.p.threads = 1;
        v1.p.steps = 7;
        FlameSession *r = NULL;
        CHECK_OK(flame_session_new(m, &v1.p, &r));
        uint32_t d = 99, t = 0;
        CHECK_OK(flame_session_progress(r, &d, &t));
        CHECK(t == 7);
        flame_session_free(r);
    }

    /* Boundaries that are allowed: the largest frame count and step count; NULL params. */
    p.frames = FLAME_TINY_MAX_FRAMES;
    p.steps = 1000;
    p.threads = 1;
    CHECK_OK(flame_session_new(m, &p, &s));
    uint32_t done = 99, total = 0;
    CHECK_OK(flame_session_progress(s, &done, &total));
    CHECK(done == 0 && total == 1000);
    flame_session_free(s);
    s = NULL;
    CHECK_OK(flame_session_new(m, NULL, &s));
    CHECK_OK(flame_session_progress(s, NULL, &total));
    CHECK(total == 1000); /* the model's default */
    flame_session_free(s);

    /* frames 0 and steps 0 are the model's defaults (200 frames, 1000 steps). */
    flame_session_params_default(&p);
    p.threads = 1;
    s = NULL;
    CHECK_OK(flame_session_new(m, &p, &s));
    CHECK_OK(flame_session_progress(s, NULL, &total));
    CHECK(total == 1000);
    /* set_noise takes exactly frames × dim values: the frame count without a step. */
    size_t n = (size_t)200 * FLAME_TINY_DIM;
    float *noise = (float *)calloc(n + FLAME_TINY_DIM, sizeof(float));
    CHECK_STATUS(flame_session_set_noise(s, noise, n + FLAME_TINY_DIM),
                 FLAME_STATUS_INVALID_ARGUMENT);
    CHECK_OK(flame_session_set_noise(s, noise, n));
    free(noise);
    if (!quick_mode()) {
        CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
        CHECK_OK(flame_session_step(s, NULL));
        CHECK_OK(
            flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n));
        CHECK(n == (size_t)200 * FLAME_TINY_DIM);
    }
    flame_session_free(s);
}

/* ---- NULL handles and NULL pointer arguments -------------------------------------------- */

static void dummy_progress(void *user_data, uint32_t done, uint32_t total) {
    (void)user_data, (void)done, (void)total;
}

static void test_null_arguments(const FlameModel *m) {
    float *f = (float *)calloc(REF_VALUES, sizeof(float));
    uint8_t *mask = (uint8_t *)calloc(REF_VALUES, 1);
    int32_t joints[1] = {0};
    uint32_t u = 0;
    size_t n = 0;
    const int INV = FLAME_STATUS_INVALID_ARGUMENT;

    CHECK_ERROR_MENTIONS(flame_session_reset(NULL), INV, "session");
    CHECK_ERROR_MENTIONS(flame_session_set_prompt(NULL, "x"), INV, "session");
    CHECK_ERROR_MENTIONS(flame_session_set_noise(NULL, f, REF_VALUES), INV, "session");
    CHECK_ERROR_MENTIONS(flame_session_set_reference(NULL, f, ref_frames, FLAME_TINY_DIM), INV,
                         "session");
    CHECK_ERROR_MENTIONS(flame_session_set_mask(NULL, mask, ref_frames, FLAME_TINY_DIM), INV,
                         "session");
    CHECK_ERROR_MENTIONS(flame_session_keep_frames(NULL, 0, 1), INV, "session");
    CHECK_ERROR_MENTIONS(flame_session_keep_joints(NULL, joints, 1), INV, "session");
    CHECK_ERROR_MENTIONS(flame_session_clear_edit(NULL), INV, "session");
    FlameEditParams ep;
    CHECK_OK(flame_edit_params_default(&ep));
    CHECK_ERROR_MENTIONS(flame_session_set_edit_params(NULL, &ep), INV, "session");
    CHECK_ERROR_MENTIONS(flame_session_keep_part(NULL, FLAME_BODY_PART_ARMS, 0, 1), INV,
                         "session");
    CHECK_ERROR_MENTIONS(flame_session_set_task_mask(NULL, FLAME_EDIT_TASK_PATH), INV, "session");
    CHECK_ERROR_MENTIONS(flame_session_set_reference_poses(NULL, f, 3, f, 24 * 6, 1,
                                                           FLAME_LAYOUT_LOCAL6D, 0),
                         INV, "session");
    CHECK_ERROR_MENTIONS(flame_session_set_progress_callback(NULL, dummy_progress, NULL), INV,
                         "session");
    CHECK_ERROR_MENTIONS(flame_session_step(NULL, &u), INV, "session");
    CHECK_ERROR_MENTIONS(flame_session_cancel(NULL), INV, "session");
    CHECK_ERROR_MENTIONS(flame_session_progress(NULL, &u, &u), INV, "session");
    CHECK_ERROR_MENTIONS(
        flame_session_read(NULL, 0, FLAME_LAYOUT_FEATURES, 0, 0, f, REF_VALUES, &n), INV,
        "session");

    FlameSession *s = ref_session(m);
    CHECK_ERROR_MENTIONS(flame_session_set_prompt(s, NULL), INV, "prompt");
    CHECK_ERROR_MENTIONS(flame_session_set_noise(s, NULL, REF_VALUES), INV, "noise");
    CHECK_ERROR_MENTIONS(flame_session_set_reference(s, NULL, ref_frames, FLAME_TINY_DIM), INV,
                         "features");
    CHECK_ERROR_MENTIONS(flame_session_set_mask(s, NULL, ref_frames, FLAME_TINY_DIM), INV, "mask");
    CHECK_ERROR_MENTIONS(flame_session_keep_joints(s, NULL, 1), INV, "joints");
    CHECK_ERROR_MENTIONS(flame_session_set_edit_params(s, NULL), INV, "params");
    CHECK_ERROR_MENTIONS(flame_session_set_reference_poses(s, NULL, 3, f, 24 * 6, 1,
                                                           FLAME_LAYOUT_LOCAL6D, 0),
                         INV, "root");
    CHECK_ERROR_MENTIONS(flame_session_set_reference_poses(s, f, 3, NULL, 24 * 6, 1,
                                                           FLAME_LAYOUT_LOCAL6D, 0),
                         INV, "rotations");
    CHECK_ERROR_MENTIONS(flame_session_read(s, 0, FLAME_LAYOUT_FEATURES, 0, 0, f, REF_VALUES, NULL),
                         INV, "out_len");
    /* NULL where the header allows it. */
    CHECK_OK(flame_session_keep_joints(s, NULL, 0));
    CHECK_OK(flame_session_set_progress_callback(s, NULL, NULL));
    CHECK_OK(flame_session_set_progress_callback(s, dummy_progress, NULL));
    CHECK_OK(flame_session_progress(s, NULL, NULL));
    CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
    CHECK_OK(flame_session_step(s, NULL));
    flame_session_free(s);

    /* Invalid UTF-8 is an argument error, not a tokenizer error. */
    s = ref_session(m);
    CHECK_ERROR_MENTIONS(flame_session_set_prompt(s, "\xff\xfe walks"), INV, "UTF-8");
    /* An empty prompt is a prompt (the unconditional one); so are non-ASCII text and a prompt
     * far longer than the encoder's window (it is truncated). */
    CHECK_OK(flame_session_set_prompt(s, ""));
    CHECK_OK(flame_session_set_prompt(s, "une personne marche \xe2\x80\x94 vite \xf0\x9f\x9a\xb6"));
    char *long_prompt = (char *)malloc(100001);
    for (int i = 0; i < 100000; i++) {
        long_prompt[i] = "a person walks "[i % 15];
    }
    long_prompt[100000] = '\0';
    CHECK_OK(flame_session_set_prompt(s, long_prompt));
    free(long_prompt);
    flame_session_free(s);
    free(f);
    free(mask);
}

static void test_free_null(void) {
    flame_model_free(NULL);
    flame_session_free(NULL);
    CHECK(1); /* reached: neither crashed */
}

/* ---- last error -------------------------------------------------------------------------- */

static void *fail_on_other_thread(void *arg) {
    (void)arg;
    flame_session_cancel(NULL);
    return NULL;
}

static void test_last_error(void) {
    FlameModelParams mp;
    CHECK_STATUS(flame_model_params_default(NULL), FLAME_STATUS_INVALID_ARGUMENT);
    CHECK(flame_last_error()[0] != '\0');
    CHECK(flame_last_error() != NULL);
    CHECK_OK(flame_model_params_default(&mp)); /* a success clears it */
    CHECK(strcmp(flame_last_error(), "") == 0);

    /* The message is per thread: another thread's failure does not show here. */
    pthread_t t;
    pthread_create(&t, NULL, fail_on_other_thread, NULL);
    pthread_join(t, NULL);
    CHECK(strcmp(flame_last_error(), "") == 0);
}

/* ---- glTF export -------------------------------------------------------------------------- */

static uint32_t le32(const unsigned char *p) {
    return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}

/* The GLB's length protocol, header and chunks; its binary chunk holds the root translation and
 * joint 0's rotation track exactly as flame_session_read gives them in the gltf convention. */
static void test_gltf(const FlameModel *m) {
    const int INV = FLAME_STATUS_INVALID_ARGUMENT;
    FlameSession *s = ref_session(m);
    size_t n = 777;
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(s, FLAME_WHICH_SAMPLE, NULL, NULL, 0, &n),
                         FLAME_STATUS_WRONG_STATE, "no sample yet");
    CHECK(n == 777);
    CHECK_OK(run_to_end(s, REF_PROMPT));

    FlameGltfParams p;
    CHECK_OK(flame_gltf_params_default(&p));
    CHECK(p.struct_size == sizeof(FlameGltfParams));
    CHECK(p.container == FLAME_GLTF_CONTAINER_GLB && p.flags == 0 && p.fps == 0.0f && !p.name);
    CHECK_OK(flame_session_write_gltf(s, FLAME_WHICH_SAMPLE, NULL, NULL, 0, &n));
    size_t size = n;
    CHECK(size > 1000);
    unsigned char *glb = (unsigned char *)malloc(size);
    n = 0;
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(s, FLAME_WHICH_SAMPLE, &p, glb, size - 1, &n),
                         FLAME_STATUS_BUFFER_TOO_SMALL, "bytes needed");
    CHECK(n == size);
    n = 0;
    CHECK_OK(flame_session_write_gltf(s, FLAME_WHICH_SAMPLE, &p, glb, size, &n));
    CHECK(n == size);
    CHECK(memcmp(glb, "glTF", 4) == 0 && le32(glb + 4) == 2 && le32(glb + 8) == size);
    uint32_t jlen = le32(glb + 12);
    CHECK(memcmp(glb + 16, "JSON", 4) == 0 && jlen % 4 == 0 && 20 + jlen + 8 <= size);
    const unsigned char *bin = glb + 20 + jlen;
    CHECK(memcmp(bin + 4, "BIN", 4) == 0 && 20 + jlen + 8 + le32(bin) == size);
    char *json = strndup((const char *)glb + 20, jlen);
    CHECK(strstr(json, "\"prompt\":\"" REF_PROMPT "\"") != NULL);
    CHECK(strstr(json, "\"generator\":\"libflame ") != NULL);
    CHECK(strstr(json, "\"name\":\"L_Wrist\"") != NULL);

    size_t rn = 0, qn = 0;
    CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION,
                                FLAME_CONVENTION_GLTF, 0, NULL, 0, &rn));
    float *root = (float *)malloc(rn * sizeof(float));
    CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION,
                                FLAME_CONVENTION_GLTF, 0, root, rn, &rn));
    CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_QUAT_XYZW,
                                FLAME_CONVENTION_GLTF, 0, NULL, 0, &qn));
    float *quat = (float *)malloc(qn * sizeof(float));
    CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_QUAT_XYZW,
                                FLAME_CONVENTION_GLTF, 0, quat, qn, &qn));
    size_t joints = qn / 4 / ref_frames;
    float *track = (float *)malloc((size_t)ref_frames * 4 * sizeof(float));
    for (uint32_t t = 0; t < ref_frames; t++) {
        memcpy(track + 4 * t, quat + 4 * joints * t, 4 * sizeof(float));
    }
    /* glTF needs unit quaternions: a degenerate rotation (parallel or zero 6D vectors, which this
     * clamped random-weight model outputs) is normalised in the file, in double as here. */
    int degenerate = 0;
    for (uint32_t t = 0; t < ref_frames; t++) {
        float *q = track + 4 * t;
        double n = 0.0;
        for (int k = 0; k < 4; k++) {
            n += (double)q[k] * (double)q[k];
        }
        n = sqrt(n);
        if (fabs(n - 1.0) > 1e-6) {
            degenerate++;
            for (int k = 0; k < 4; k++) {
                q[k] = n > 1e-12 ? (float)((double)q[k] / n) : (k == 3 ? 1.0f : 0.0f);
            }
        }
    }
    printf("  glTF: %d of %u root rotations degenerate (normalised in the file)\n", degenerate,
           ref_frames);
    size_t bin_len = le32(bin);
    CHECK(memmem(bin + 8, bin_len, root, rn * sizeof(float)) != NULL);
    CHECK(memmem(bin + 8, bin_len, track, (size_t)ref_frames * 4 * sizeof(float)) != NULL);

    /* Smoothing changes the animation, as it changes what flame_session_read gives. */
    p.flags = FLAME_READ_SMOOTH;
    CHECK_OK(flame_session_write_gltf(s, FLAME_WHICH_SAMPLE, &p, glb, size, &n));
    CHECK(memmem(glb, n, root, rn * sizeof(float)) == NULL);

    /* The JSON container, a name and a frame rate. */
    CHECK_OK(flame_gltf_params_default(&p));
    p.container = FLAME_GLTF_CONTAINER_GLTF;
    p.name = "my walk!";
    p.fps = 30.0f;
    CHECK_OK(flame_session_write_gltf(s, FLAME_WHICH_ESTIMATE, &p, NULL, 0, &n));
    char *text = (char *)calloc(n + 1, 1);
    CHECK_OK(flame_session_write_gltf(s, FLAME_WHICH_ESTIMATE, &p, (uint8_t *)text, n, &n));
    CHECK(text[0] == '{' && strstr(text, "\"name\":\"my_walk\"") != NULL);
    CHECK(strstr(text, "\"fps\":30.0") != NULL);
    CHECK(strstr(text, "data:application/octet-stream;base64,") != NULL);

    /* Bad arguments: errors that name them, nothing written. */
    CHECK_OK(flame_gltf_params_default(&p));
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(NULL, 0, &p, NULL, 0, &n), INV, "session");
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(s, 0, &p, NULL, 0, NULL), INV, "out_len");
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(s, 2, &p, NULL, 0, &n), INV, "which");
    p.container = 7;
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(s, 0, &p, NULL, 0, &n), INV, "container");
    p.container = INT32_MIN;
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(s, 0, &p, NULL, 0, &n), INV, "container");
    CHECK_OK(flame_gltf_params_default(&p));
    p.flags = 8;
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(s, 0, &p, NULL, 0, &n), INV, "read flags");
    p.flags = 0;
    p.fps = -1.0f;
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(s, 0, &p, NULL, 0, &n), INV, "frame rate");
    p.fps = NAN;
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(s, 0, &p, NULL, 0, &n), INV, "frame rate");
    p.fps = 0.0f;
    p.name = "\xff\xfe";
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(s, 0, &p, NULL, 0, &n), INV, "name");
    p.name = NULL;
    p.struct_size = 4;
    CHECK_ERROR_MENTIONS(flame_session_write_gltf(s, 0, &p, NULL, 0, &n), INV, "params");
    CHECK_STATUS(flame_gltf_params_default(NULL), INV);

    free(text);
    free(track);
    free(quat);
    free(root);
    free(json);
    free(glb);
    flame_session_free(s);
}

/* ---- call order ------------------------------------------------------------------------- */

static void test_wrong_state(const FlameModel *m) {
    FlameSession *s = ref_session(m);
    uint32_t left = 12345;
    float *buf = (float *)malloc(REF_VALUES * sizeof(float));
    size_t n = 777;
    const int WS = FLAME_STATUS_WRONG_STATE;

    CHECK_ERROR_MENTIONS(flame_session_step(s, &left), WS, "prompt");
    CHECK(left == 12345); /* outputs only on success */
    CHECK_STATUS(
        flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n), WS);
    CHECK_STATUS(
        flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, buf, REF_VALUES, &n),
        WS);
    CHECK_STATUS(
        flame_session_read(s, FLAME_WHICH_ESTIMATE, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n), WS);
    CHECK(n == 777);

    CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
    CHECK_STATUS(
        flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n), WS);
    CHECK_STATUS(
        flame_session_read(s, FLAME_WHICH_ESTIMATE, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n), WS);
    CHECK_OK(flame_session_step(s, &left));
    CHECK(left == ref_steps - 1);
    CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n));
    CHECK(n == REF_VALUES);
    CHECK_OK(flame_session_read(s, FLAME_WHICH_ESTIMATE, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n));
    CHECK(n == REF_VALUES);

    float *noise = (float *)calloc(REF_VALUES, sizeof(float));
    CHECK_ERROR_MENTIONS(flame_session_set_noise(s, noise, REF_VALUES), WS, "first step");

    /* The prompt may change between steps. */
    CHECK_OK(flame_session_set_prompt(s, "a person jumps."));
    while (left > 0) {
        CHECK_OK(flame_session_step(s, &left));
    }
    left = 12345;
    CHECK_ERROR_MENTIONS(flame_session_step(s, &left), WS, "finished");
    CHECK(left == 12345);
    CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, buf, REF_VALUES,
                                &n));

    /* reset: back before the first step; noise may be set again. */
    CHECK_OK(flame_session_reset(s));
    uint32_t done = 9, total = 0;
    CHECK_OK(flame_session_progress(s, &done, &total));
    CHECK(done == 0 && total == ref_steps);
    CHECK_STATUS(
        flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n), WS);
    CHECK_OK(flame_session_set_noise(s, noise, REF_VALUES));
    CHECK_OK(flame_session_step(s, &left));
    CHECK(left == ref_steps - 1);
    flame_session_free(s);
    free(buf);
    free(noise);
}

/* reset reproduces the seeded generation; the prompt set before it is kept. */
static void test_reset(const FlameModel *m) {
    FlameSession *s = ref_session(m);
    CHECK(matches_reference(s));
    CHECK_OK(flame_session_reset(s));
    uint32_t left = 1;
    while (left > 0) {
        CHECK_OK(flame_session_step(s, &left));
    }
    FlameStatus st;
    size_t n = 0;
    float *x = read_features(s, FLAME_WHICH_SAMPLE, &n, &st);
    CHECK(same_bits(x, n, g_ref, g_ref_n));
    free(x);
    flame_session_free(s);
}

/* ---- what a prompt became ---------------------------------------------------------------- */

static void test_prompt_info(const FlameModel *m) {
    FlameSession *s = ref_session(m);
    FlamePromptInfo info;
    memset(&info, 0, sizeof info);
    info.struct_size = sizeof info;
    CHECK_ERROR_MENTIONS(flame_session_prompt_info(s, &info), FLAME_STATUS_WRONG_STATE,
                         "no prompt");
    CHECK_ERROR_MENTIONS(flame_session_prompt_info(NULL, &info), FLAME_STATUS_INVALID_ARGUMENT,
                         "session");
    CHECK_ERROR_MENTIONS(flame_session_prompt_info(s, NULL), FLAME_STATUS_INVALID_ARGUMENT,
                         "info");

    /* The tiny model's RoBERTa window is 20 tokens, <s> and </s> included. */
    const char *prompt = "a person walks forward, turns left, raises both arms, waves with the "
                         "right hand, sits down on a chair and then kicks with the right leg";
    CHECK_OK(flame_session_set_prompt(s, prompt));
    info.struct_size = sizeof info - 1;
    CHECK_ERROR_MENTIONS(flame_session_prompt_info(s, &info), FLAME_STATUS_INVALID_ARGUMENT,
                         "struct_size");
    info.struct_size = sizeof info;
    CHECK_OK(flame_session_prompt_info(s, &info));
    CHECK(info.window == 20 && info.kept == 20 && info.tokens > 20);
    CHECK(info.truncated == 1 && info.unconditional == 0);
    CHECK(info.dropped != NULL && strlen(info.dropped) > 0);
    /* The dropped text is the prompt's tail. */
    size_t pl = strlen(prompt), dl = info.dropped ? strlen(info.dropped) : 0;
    CHECK(dl < pl && strcmp(prompt + pl - dl, info.dropped) == 0);
    /* A second query gives the same pointer: it lives until the next prompt. */
    const char *first = info.dropped;
    CHECK_OK(flame_session_prompt_info(s, &info));
    CHECK(info.dropped == first);

    CHECK_OK(flame_session_set_prompt(s, "a person walks"));
    CHECK_OK(flame_session_prompt_info(s, &info));
    CHECK(info.truncated == 0 && info.kept == info.tokens && info.tokens < 20);
    CHECK(info.dropped != NULL && info.dropped[0] == '\0');

    CHECK_OK(flame_session_set_prompt(s, ""));
    CHECK_OK(flame_session_prompt_info(s, &info));
    CHECK(info.unconditional == 1 && info.truncated == 0);
    flame_session_free(s);
}

/* A prompt encoded once serves another session of the same model: the same bits as the CLI's
 * reference run; the prompt report follows; NULLs, a source without a prompt and another model's
 * session are refused. */
static void test_prompt_from(const FlameModel *m) {
    FlameSession *a = ref_session(m), *b = ref_session(m);
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_from(b, a), FLAME_STATUS_WRONG_STATE,
                         "no prompt");
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_from(NULL, a), FLAME_STATUS_INVALID_ARGUMENT,
                         "session");
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_from(b, NULL), FLAME_STATUS_INVALID_ARGUMENT,
                         "source");
    CHECK_OK(flame_session_set_prompt(a, REF_PROMPT));
    CHECK_OK(flame_session_set_prompt_from(a, a));
    CHECK_OK(flame_session_set_prompt_from(b, a));
    FlamePromptInfo ia, ib;
    memset(&ia, 0, sizeof ia);
    memset(&ib, 0, sizeof ib);
    ia.struct_size = ib.struct_size = sizeof ia;
    CHECK_OK(flame_session_prompt_info(a, &ia));
    CHECK_OK(flame_session_prompt_info(b, &ib));
    CHECK(ia.tokens == ib.tokens && ia.kept == ib.kept && ia.truncated == ib.truncated);
    uint32_t left = 1;
    FlameStatus st = FLAME_STATUS_OK;
    while (st == FLAME_STATUS_OK && left > 0) {
        st = flame_session_step(b, &left);
    }
    CHECK_OK(st);
    size_t n = 0;
    float *x = read_features(b, FLAME_WHICH_SAMPLE, &n, &st);
    CHECK(same_bits(x, n, g_ref, g_ref_n));
    free(x);
    FlameModel *other = load_or_die(g_model_path);
    FlameSessionParams p;
    ref_params(&p);
    FlameSession *c = NULL;
    CHECK_OK(flame_session_new(other, &p, &c));
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_from(c, a), FLAME_STATUS_INVALID_ARGUMENT,
                         "another model");
    flame_session_free(c);
    flame_model_free(other);
    flame_session_free(a);
    flame_session_free(b);
}

/* ---- reading ----------------------------------------------------------------------------- */

static void test_read(const FlameModel *m) {
    FlameSession *s = ref_session(m);
    CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
    CHECK_OK(flame_session_step(s, NULL));

    size_t n = 0;
    CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n));
    CHECK(n == REF_VALUES);
    CHECK_OK(
        flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 12345, &n));
    CHECK(n == REF_VALUES);

    /* Too small: BUFFER_TOO_SMALL, the needed length written, the buffer untouched. */
    float small[10];
    for (int i = 0; i < 10; i++) {
        small[i] = -7.0f;
    }
    n = 0;
    CHECK_ERROR_MENTIONS(
        flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, small, 10, &n),
        FLAME_STATUS_BUFFER_TOO_SMALL, num(REF_VALUES));
    CHECK(n == REF_VALUES);
    CHECK(small[0] == -7.0f && small[9] == -7.0f);
    float *big = (float *)malloc((REF_VALUES + 5) * sizeof(float));
    CHECK_STATUS(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, big,
                                    REF_VALUES - 1, &n),
                 FLAME_STATUS_BUFFER_TOO_SMALL);
    CHECK_STATUS(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, big, 0, &n),
                 FLAME_STATUS_BUFFER_TOO_SMALL);

    /* Exact and larger buffers: *out_len is the count written, the tail untouched. */
    for (size_t i = 0; i < REF_VALUES + 5; i++) {
        big[i] = -7.0f;
    }
    n = 0;
    CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, big,
                                REF_VALUES + 5, &n));
    CHECK(n == REF_VALUES);
    CHECK(big[REF_VALUES] == -7.0f && big[REF_VALUES + 4] == -7.0f);
    int finite = 1;
    for (size_t i = 0; i < REF_VALUES; i++) {
        finite &= isfinite(big[i]) != 0;
    }
    CHECK(finite);
    float *exact = (float *)malloc(REF_VALUES * sizeof(float));
    CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 0, exact,
                                REF_VALUES, &n));
    CHECK(memcmp(exact, big, REF_VALUES * sizeof(float)) == 0);
    /* The estimate is a different array from the sample. */
    CHECK_OK(flame_session_read(s, FLAME_WHICH_ESTIMATE, FLAME_LAYOUT_FEATURES, 0, 0, exact,
                                REF_VALUES, &n));
    CHECK(memcmp(exact, big, REF_VALUES * sizeof(float)) != 0);

    /* Unknown `which` and layouts. */
    CHECK_ERROR_MENTIONS(flame_session_read(s, 2, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n),
                         FLAME_STATUS_INVALID_ARGUMENT, "which");
    CHECK_STATUS(flame_session_read(s, -1, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n),
                 FLAME_STATUS_INVALID_ARGUMENT);
    CHECK_ERROR_MENTIONS(flame_session_read(s, FLAME_WHICH_SAMPLE, 99, 0, 0, NULL, 0, &n),
                         FLAME_STATUS_INVALID_ARGUMENT, "layout");
    CHECK_STATUS(flame_session_read(s, FLAME_WHICH_SAMPLE, -1, 0, 0, NULL, 0, &n),
                 FLAME_STATUS_INVALID_ARGUMENT);
    /* INT32_MIN: found by the ffi_params fuzzer (layout - 1 overflowed, a panic caught as
     * INTERNAL in a debug build). */
    CHECK_ERROR_MENTIONS(flame_session_read(s, FLAME_WHICH_SAMPLE, INT32_MIN, 0, 0, NULL, 0, &n),
                         FLAME_STATUS_INVALID_ARGUMENT, "layout");
    CHECK_ERROR_MENTIONS(flame_session_read(s, FLAME_WHICH_SAMPLE, INT32_MAX, 0, 0, NULL, 0, &n),
                         FLAME_STATUS_INVALID_ARGUMENT, "layout");
    /* An unknown convention or flag is rejected even where the layout ignores them. */
    CHECK_ERROR_MENTIONS(
        flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 99, 0, NULL, 0, &n),
        FLAME_STATUS_INVALID_ARGUMENT, "convention 99");
    CHECK_ERROR_MENTIONS(
        flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FEATURES, 0, 4, NULL, 0, &n),
        FLAME_STATUS_INVALID_ARGUMENT, "flags");
    free(big);
    free(exact);
    flame_session_free(s);
}

/* ---- pose layouts ---------------------------------------------------------------------- */

/* Reads `layout` into a malloc'd array of the length the library asks for. */
static float *read_layout(const FlameSession *s, int32_t which, int32_t layout, int32_t conv,
                          uint32_t flags, size_t *n) {
    *n = 0;
    if (flame_session_read(s, which, layout, conv, flags, NULL, 0, n) != FLAME_STATUS_OK) {
        return NULL;
    }
    float *out = (float *)malloc(*n * sizeof(float) + 1);
    size_t written = 0;
    if (flame_session_read(s, which, layout, conv, flags, out, *n, &written) != FLAME_STATUS_OK ||
        written != *n) {
        free(out);
        return NULL;
    }
    return out;
}

static int all_finite(const float *x, size_t n) {
    for (size_t i = 0; i < n; i++) {
        if (!isfinite(x[i])) {
            return 0;
        }
    }
    return 1;
}

static void test_layouts(const FlameModel *m) {
    const size_t F = ref_frames, J = 24;
    /* Values per frame of each FlameLayout for smpl24_6d (foot contacts: none). */
    const size_t per_frame[] = {FLAME_TINY_DIM, 3, J * 4, J * 4, J * 9, J * 6, J * 3, J * 4, J * 4};
    FlameSession *s = ref_session(m);
    CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
    size_t n = 0;
    CHECK_STATUS(
        flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION, 0, 0, NULL, 0, &n),
        FLAME_STATUS_WRONG_STATE);
    CHECK_OK(flame_session_step(s, NULL));

    for (int which = 0; which <= 1; which++) {
        for (int layout = FLAME_LAYOUT_FEATURES; layout <= FLAME_LAYOUT_GLOBAL_QUAT_WXYZ;
             layout++) {
            for (int conv = FLAME_CONVENTION_NATIVE; conv <= FLAME_CONVENTION_GLTF; conv++) {
                /* Only shapes and finiteness: the tiny model's random weights give degenerate
                 * 6D rotations (two equal rows), whose quaternions are not unit. */
                float *x = read_layout(s, which, layout, conv, 0, &n);
                int ok = x && n == F * per_frame[layout] && all_finite(x, n);
                char what[128];
                snprintf(what, sizeof what, "read which %d layout %d convention %d", which, layout,
                         conv);
                check_record(ok, __FILE__, __LINE__, what, flame_last_error());
                free(x);
            }
        }
    }
    /* Flags: each and both are accepted and keep the length; smoothing changes the values. */
    float *plain = read_layout(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_QUAT_XYZW, 0, 0, &n);
    float *smooth =
        read_layout(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_QUAT_XYZW, 0, FLAME_READ_SMOOTH, &n);
    float *raw = read_layout(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_QUAT_XYZW, 0,
                             FLAME_READ_RAW_SIGNS, &n);
    float *both = read_layout(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_QUAT_XYZW, 0,
                              FLAME_READ_SMOOTH | FLAME_READ_RAW_SIGNS, &n);
    CHECK(plain && smooth && raw && both && n == F * J * 4);
    if (plain && smooth && raw) {
        CHECK(memcmp(plain, smooth, n * sizeof(float)) != 0);
        /* RAW_SIGNS: w >= 0 for every quaternion (x y z w order). */
        int w_nonneg = 1;
        for (size_t i = 3; i < n; i += 4) {
            w_nonneg &= raw[i] >= 0.0f;
        }
        CHECK(w_nonneg);
    }
    free(plain);
    free(smooth);
    free(raw);
    free(both);

    /* Unreal positions are in centimetres: 100 times the native metres, axes permuted. */
    size_t nn = 0, nu = 0;
    float *native = read_layout(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_POSITIONS,
                                FLAME_CONVENTION_NATIVE, 0, &nn);
    float *unreal = read_layout(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_POSITIONS,
                                FLAME_CONVENTION_UNREAL, 0, &nu);
    int scaled = native && unreal && nn == nu;
    for (size_t i = 0; scaled && i + 3 <= nn; i += 3) {
        double a = sqrt((double)native[i] * native[i] + (double)native[i + 1] * native[i + 1] +
                        (double)native[i + 2] * native[i + 2]);
        double b = sqrt((double)unreal[i] * unreal[i] + (double)unreal[i + 1] * unreal[i + 1] +
                        (double)unreal[i + 2] * unreal[i + 2]);
        scaled = fabs(b - 100.0 * a) <= 1e-3 * (1.0 + b);
    }
    CHECK(scaled);
    free(native);
    free(unreal);

    /* smpl24_6d's foot contacts are detected (4 per frame); a raw read has no root bone;
     * errors: unknown layouts, conventions and flags; a too-small buffer for a pose layout. */
    CHECK_OK(
        flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FOOT_CONTACTS, 0, 0, NULL, 0, &n));
    CHECK(n == F * 4);
    CHECK_ERROR_MENTIONS(
        flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_BONE, 0, 0, NULL, 0, &n),
        FLAME_STATUS_INVALID_ARGUMENT, "root bone");
    CHECK_STATUS(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_BONE + 1, 0, 0,
                                    NULL, 0, &n),
                 FLAME_STATUS_INVALID_ARGUMENT);
    CHECK_ERROR_MENTIONS(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL6D,
                                            FLAME_CONVENTION_GLTF + 1, 0, NULL, 0, &n),
                         FLAME_STATUS_INVALID_ARGUMENT, "convention");
    CHECK_STATUS(
        flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL6D, -1, 0, NULL, 0, &n),
        FLAME_STATUS_INVALID_ARGUMENT);
    CHECK_ERROR_MENTIONS(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL6D, 0,
                                            0x80000000u, NULL, 0, &n),
                         FLAME_STATUS_INVALID_ARGUMENT, "flags");
    float small[3];
    n = 0;
    CHECK_STATUS(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION, 0, 0,
                                    small, 3, &n),
                 FLAME_STATUS_BUFFER_TOO_SMALL);
    CHECK(n == F * 3);
    flame_session_free(s);
}

/* ---- lengths and values ------------------------------------------------------------------ */

static void test_lengths(const FlameModel *m) {
    const int INV = FLAME_STATUS_INVALID_ARGUMENT;
    /* Buffers larger than any length passed, so every call stays within its contract. */
    size_t cap = (ref_frames + 2) * (FLAME_TINY_DIM + 1);
    const uint32_t F = ref_frames;
    float *f = (float *)calloc(cap, sizeof(float));
    uint8_t *mask = (uint8_t *)calloc(cap, 1);
    FlameSession *s = ref_session(m);

    CHECK_ERROR_MENTIONS(flame_session_set_noise(s, f, REF_VALUES - 1), INV, num(REF_VALUES));
    CHECK_STATUS(flame_session_set_noise(s, f, REF_VALUES + 1), INV);
    CHECK_STATUS(flame_session_set_noise(s, f, 0), INV);
    CHECK_STATUS(flame_session_set_noise(s, NULL, 0), INV);
    f[5] = NAN;
    CHECK_ERROR_MENTIONS(flame_session_set_noise(s, f, REF_VALUES), INV, "NaN");
    f[5] = INFINITY;
    CHECK_STATUS(flame_session_set_noise(s, f, REF_VALUES), INV);
    f[5] = 0.0f;
    CHECK_OK(flame_session_set_noise(s, f, REF_VALUES));

    /* A shorter reference is allowed (prediction); a longer one is not. */
    CHECK_OK(flame_session_set_reference(s, f, F - 1, FLAME_TINY_DIM));
    CHECK_STATUS(flame_session_set_reference(s, f, F + 1, FLAME_TINY_DIM), INV);
    CHECK_STATUS(flame_session_set_reference(s, f, ref_frames, FLAME_TINY_DIM - 1), INV);
    CHECK_STATUS(flame_session_set_reference(s, f, ref_frames, FLAME_TINY_DIM + 1), INV);
    CHECK_STATUS(flame_session_set_reference(s, f, 0, 0), INV);
    CHECK_STATUS(flame_session_set_reference(s, f, UINT32_MAX, UINT32_MAX), INV);
    f[100] = NAN;
    CHECK_ERROR_MENTIONS(flame_session_set_reference(s, f, ref_frames, FLAME_TINY_DIM), INV, "NaN");
    f[100] = 0.0f;
    CHECK_OK(flame_session_set_reference(s, f, ref_frames, FLAME_TINY_DIM));

    CHECK_ERROR_MENTIONS(flame_session_set_mask(s, mask, F - 1, FLAME_TINY_DIM), INV, num(F));
    CHECK_STATUS(flame_session_set_mask(s, mask, F + 1, FLAME_TINY_DIM), INV);
    CHECK_STATUS(flame_session_set_mask(s, mask, ref_frames, FLAME_TINY_DIM + 1), INV);
    CHECK_STATUS(flame_session_set_mask(s, mask, 0, 0), INV);
    CHECK_STATUS(flame_session_set_mask(s, mask, UINT32_MAX, UINT32_MAX), INV);
    CHECK_OK(flame_session_set_mask(s, mask, ref_frames, FLAME_TINY_DIM));

    /* keep_frames: empty, reversed or out-of-range spans. */
    CHECK_ERROR_MENTIONS(flame_session_keep_frames(s, 0, 0), INV, "from 0 to 0");
    CHECK_STATUS(flame_session_keep_frames(s, 5, 3), INV);
    CHECK_STATUS(flame_session_keep_frames(s, 0, F + 1), INV);
    CHECK_STATUS(flame_session_keep_frames(s, F, F + 1), INV);
    CHECK_STATUS(flame_session_keep_frames(s, UINT32_MAX - 1, UINT32_MAX), INV);
    CHECK_OK(flame_session_keep_frames(s, 0, F));
    CHECK_OK(flame_session_keep_frames(s, F - 1, F));

    /* keep_joints: 0..=23 and FLAME_ROOT_TRANSLATION; one bad joint rejects the call. */
    int32_t bad1[] = {24};
    int32_t bad2[] = {-2};
    int32_t bad3[] = {0, 5, INT32_MAX};
    int32_t good[] = {FLAME_ROOT_TRANSLATION, 0, 23};
    CHECK_ERROR_MENTIONS(flame_session_keep_joints(s, bad1, 1), INV, "24");
    CHECK_STATUS(flame_session_keep_joints(s, bad2, 1), INV);
    CHECK_STATUS(flame_session_keep_joints(s, bad3, 3), INV);
    CHECK_OK(flame_session_keep_joints(s, good, 3));
    CHECK_OK(flame_session_clear_edit(s));
    CHECK_OK(flame_session_clear_edit(s)); /* twice is fine */

    free(f);
    free(mask);
    flame_session_free(s);
}

/* ---- editing ------------------------------------------------------------------------------ */

/* A smooth reference motion, away from the generated one. */
static void make_reference(float *r) {
    for (size_t i = 0; i < REF_VALUES; i++) {
        r[i] = 0.5f * sinf(0.01f * (float)i) + 0.25f;
    }
}

static float *edited(const FlameModel *m, const float *r, const uint8_t *mask, int frames_lo,
                     int frames_hi, const int32_t *joints, size_t njoints) {
    FlameSession *s = ref_session(m);
    if (r) {
        CHECK_OK(flame_session_set_reference(s, r, ref_frames, FLAME_TINY_DIM));
    }
    if (mask) {
        CHECK_OK(flame_session_set_mask(s, mask, ref_frames, FLAME_TINY_DIM));
    }
    if (frames_hi > frames_lo) {
        CHECK_OK(flame_session_keep_frames(s, (uint32_t)frames_lo, (uint32_t)frames_hi));
    }
    if (njoints) {
        CHECK_OK(flame_session_keep_joints(s, joints, njoints));
    }
    FlameStatus st = run_to_end(s, REF_PROMPT);
    CHECK_OK(st);
    size_t n = 0;
    float *x = read_features(s, FLAME_WHICH_SAMPLE, &n, &st);
    CHECK(n == REF_VALUES);
    flame_session_free(s);
    return x;
}

/* Largest |x - r| over channels [c0, c1) of every frame. */
static float max_diff(const float *x, const float *r, int c0, int c1) {
    float d = 0.0f;
    for (uint32_t f = 0; f < ref_frames; f++) {
        for (int c = c0; c < c1; c++) {
            float e = fabsf(x[f * FLAME_TINY_DIM + c] - r[f * FLAME_TINY_DIM + c]);
            d = e > d ? e : d;
        }
    }
    return d;
}

static void test_edit(const FlameModel *m) {
    float *r = (float *)malloc(REF_VALUES * sizeof(float));
    make_reference(r);
    uint8_t *zeros = (uint8_t *)calloc(REF_VALUES, 1);
    int32_t root[] = {FLAME_ROOT_TRANSLATION};
    FlameSession *s = NULL;

    /* Without a kept value nothing changes: a reference alone, an all-zero mask. */
    float *x = edited(m, r, NULL, 0, 0, NULL, 0);
    CHECK(same_bits(x, REF_VALUES, g_ref, g_ref_n));
    free(x);
    x = edited(m, r, zeros, 0, 0, NULL, 0);
    CHECK(same_bits(x, REF_VALUES, g_ref, g_ref_n));
    free(x);

    /* Keeping the root translation: those channels follow the reference, the rest is
     * generated (and differs from the unedited run). */
    x = edited(m, r, NULL, 0, 0, root, 1);
    CHECK(!same_bits(x, REF_VALUES, g_ref, g_ref_n));
    CHECK(max_diff(x, r, 0, 3) < 0.1f);
    CHECK(max_diff(g_ref, r, 0, 3) > 0.5f);
    free(x);

    /* Keeping every frame reproduces the reference: the final paste (on by default) copies the
     * kept values exactly. */
    x = edited(m, r, NULL, 0, (int)ref_frames, NULL, 0);
    CHECK(same_bits(x, REF_VALUES, r, REF_VALUES));
    free(x);

    /* A mask that keeps values with no reference to take them from: the step refuses
     * (WRONG_STATE), and goes on once a reference is set. */
    s = ref_session(m);
    CHECK_OK(flame_session_keep_frames(s, 0, ref_frames));
    CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
    uint32_t left = 99;
    CHECK_ERROR_MENTIONS(flame_session_step(s, &left), FLAME_STATUS_WRONG_STATE, "no reference");
    CHECK(left == 99);
    CHECK_OK(flame_session_set_reference(s, r, ref_frames, FLAME_TINY_DIM));
    CHECK_OK(flame_session_step(s, &left));
    CHECK(left == ref_steps - 1);
    flame_session_free(s);

    /* clear_edit after setting everything: the plain generation again, bit for bit. */
    s = ref_session(m);
    CHECK_OK(flame_session_set_reference(s, r, ref_frames, FLAME_TINY_DIM));
    CHECK_OK(flame_session_keep_joints(s, root, 1));
    CHECK_OK(flame_session_clear_edit(s));
    CHECK(matches_reference(s));
    flame_session_free(s);

    /* The reference and the mask may change between steps. */
    FlameSessionParams p;
    ref_params(&p);
    p.steps = 3;
    CHECK_OK(flame_session_new(m, &p, &s));
    CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
    CHECK_OK(flame_session_step(s, NULL));
    CHECK_OK(flame_session_set_reference(s, r, ref_frames, FLAME_TINY_DIM));
    CHECK_OK(flame_session_keep_frames(s, 0, ref_frames / 2));
    CHECK_OK(flame_session_step(s, NULL));
    CHECK_OK(flame_session_clear_edit(s));
    CHECK_OK(flame_session_step(s, NULL));
    flame_session_free(s);

    free(r);
    free(zeros);
}

/* ---- editing: parameters, tasks, body parts, pose references, other model families -------- */

/* The channel a smpl24_6d feature index belongs to: -1 for the root translation, else the
 * joint whose 6D rotation it holds. */
static int smpl_joint_of(int c) {
    return c < 3 ? -1 : (c - 3) / 6;
}

static int is_leg(int j) {
    return j == 1 || j == 2 || j == 4 || j == 5 || j == 7 || j == 8 || j == 10 || j == 11;
}

/* What a FlameEditTask keeps of frame f, channel c in a smpl24_6d session of F frames (the
 * header's definitions, written out independently of the library). */
static int task_keeps(int task, uint32_t F, uint32_t f, int c) {
    int j = smpl_joint_of(c);
    switch (task) {
    case FLAME_EDIT_TASK_INBETWEEN: return f < F / 4 || f >= 3 * F / 4;
    case FLAME_EDIT_TASK_PREDICT: return f < F / 4;
    case FLAME_EDIT_TASK_UPPER_BODY: return j == -1 || j == 0 || is_leg(j);
    case FLAME_EDIT_TASK_PATH: return j == -1;
    default: return 0;
    }
}

/* Compares x with r over a keep-predicate: *kept_diff counts kept values whose bits differ,
 * *free_diff generated values whose bits differ from the reference. */
struct keep_count {
    size_t kept, kept_diff, free_diff;
};

static struct keep_count compare_kept(const float *x, const float *r, uint32_t ref_rows, int task,
                                      uint32_t F) {
    struct keep_count k = {0, 0, 0};
    for (uint32_t f = 0; f < F; f++) {
        for (int c = 0; c < FLAME_TINY_DIM; c++) {
            size_t i = (size_t)f * FLAME_TINY_DIM + (size_t)c;
            int differs = f >= ref_rows || memcmp(&x[i], &r[i], sizeof(float)) != 0;
            if (task_keeps(task, F, f, c)) {
                k.kept++;
                k.kept_diff += differs;
            } else {
                k.free_diff += differs;
            }
        }
    }
    return k;
}

/* Runs `s` to the end and returns its final features (NULL on error). */
static float *finish_features(FlameSession *s) {
    FlameStatus st = run_to_end(s, REF_PROMPT);
    CHECK_OK(st);
    size_t n = 0;
    float *x = st == FLAME_STATUS_OK ? read_features(s, FLAME_WHICH_SAMPLE, &n, &st) : NULL;
    CHECK(x != NULL && n == REF_VALUES);
    return x;
}

static FlameStatus set_params(FlameSession *s, int32_t method, float edit_till, uint32_t paste,
                              uint32_t seam_frames) {
    FlameEditParams p;
    flame_edit_params_default(&p);
    p.method = method;
    p.edit_till = edit_till;
    p.paste = paste;
    p.seam_frames = seam_frames;
    return flame_session_set_edit_params(s, &p);
}

static void test_edit_params(const FlameModel *m) {
    const int INV = FLAME_STATUS_INVALID_ARGUMENT;
    CHECK_ERROR_MENTIONS(flame_edit_params_default(NULL), INV, "params");
    FlameEditParams d;
    memset(&d, 0xAB, sizeof d);
    CHECK_OK(flame_edit_params_default(&d));
    CHECK(d.struct_size == sizeof(FlameEditParams));
    CHECK(d.method == FLAME_EDIT_METHOD_AUTO);
    CHECK(d.edit_till == 0.2f);
    CHECK(d.paste == 1);
    CHECK(d.seam_frames == 4);

    FlameSession *s = ref_session(m);
    CHECK_OK(flame_session_set_edit_params(s, &d));
    FlameEditParams p = d;
    p.struct_size = 0;
    CHECK_ERROR_MENTIONS(flame_session_set_edit_params(s, &p), INV, "struct_size");
    p.struct_size = sizeof(FlameEditParams) - 1;
    CHECK_STATUS(flame_session_set_edit_params(s, &p), INV);

    /* Unknown methods; a method the model cannot run (FLAME is a diffusion model). */
    CHECK_ERROR_MENTIONS(set_params(s, 4, 0.2f, 1, 4), INV, "edit method");
    CHECK_ERROR_MENTIONS(set_params(s, -1, 0.2f, 1, 4), INV, "edit method");
    CHECK_STATUS(set_params(s, INT32_MAX, 0.2f, 1, 4), INV);
    CHECK_ERROR_MENTIONS(set_params(s, FLAME_EDIT_METHOD_REWRITE_TRAJECTORY, 0.2f, 1, 4), INV,
                         "does not apply");
    CHECK_OK(set_params(s, FLAME_EDIT_METHOD_NOISED_REFERENCE, 0.2f, 1, 4));
    CHECK_OK(set_params(s, FLAME_EDIT_METHOD_REPLACE_X0, 0.2f, 1, 4));
    CHECK_OK(set_params(s, FLAME_EDIT_METHOD_AUTO, 0.2f, 1, 4));

    /* edit_till in [0, 1], finite; seam_frames at most 1000; paste any nonzero. */
    CHECK_ERROR_MENTIONS(set_params(s, 0, -0.01f, 1, 4), INV, "edit_till");
    CHECK_ERROR_MENTIONS(set_params(s, 0, 1.01f, 1, 4), INV, "edit_till");
    CHECK_ERROR_MENTIONS(set_params(s, 0, NAN, 1, 4), INV, "edit_till");
    CHECK_STATUS(set_params(s, 0, INFINITY, 1, 4), INV);
    CHECK_STATUS(set_params(s, 0, -INFINITY, 1, 4), INV);
    CHECK_OK(set_params(s, 0, 0.0f, 1, 4));
    CHECK_OK(set_params(s, 0, 1.0f, 1, 4));
    CHECK_ERROR_MENTIONS(set_params(s, 0, 0.2f, 1, 1001), INV, "seam_frames");
    CHECK_STATUS(set_params(s, 0, 0.2f, 1, UINT32_MAX), INV);
    CHECK_OK(set_params(s, 0, 0.2f, 1, 1000));
    CHECK_OK(set_params(s, 0, 0.2f, 1, 0));
    CHECK_OK(set_params(s, 0, 0.2f, 0, 4));
    CHECK_OK(set_params(s, 0, 0.2f, 7, 4));
    /* Settings alone edit nothing: the plain generation. */
    CHECK(matches_reference(s));
    flame_session_free(s);
}

static void test_task_mask_errors(const FlameModel *m) {
    const int INV = FLAME_STATUS_INVALID_ARGUMENT;
    const uint32_t F = ref_frames;
    FlameSession *s = ref_session(m);
    CHECK_ERROR_MENTIONS(flame_session_set_task_mask(s, 4), INV, "task");
    CHECK_STATUS(flame_session_set_task_mask(s, -1), INV);
    CHECK_STATUS(flame_session_set_task_mask(s, INT32_MIN), INV);
    CHECK_ERROR_MENTIONS(flame_session_keep_part(s, 5, 0, F), INV, "body part");
    CHECK_STATUS(flame_session_keep_part(s, -1, 0, F), INV);
    CHECK_STATUS(flame_session_keep_part(s, INT32_MAX, 0, F), INV);
    CHECK_STATUS(flame_session_keep_part(s, FLAME_BODY_PART_ARMS, 0, 0), INV);
    CHECK_STATUS(flame_session_keep_part(s, FLAME_BODY_PART_ARMS, 5, 3), INV);
    CHECK_STATUS(flame_session_keep_part(s, FLAME_BODY_PART_ARMS, 0, F + 1), INV);
    CHECK_STATUS(flame_session_keep_part(s, FLAME_BODY_PART_ARMS, F, F + 1), INV);
    CHECK_STATUS(flame_session_keep_part(s, FLAME_BODY_PART_ARMS, UINT32_MAX - 1, UINT32_MAX),
                 INV);
    for (int32_t part = FLAME_BODY_PART_ROOT_PATH; part <= FLAME_BODY_PART_LEGS; part++) {
        CHECK_OK(flame_session_keep_part(s, part, 0, F));
        CHECK_OK(flame_session_keep_part(s, part, F - 1, F));
    }
    for (int32_t task = FLAME_EDIT_TASK_INBETWEEN; task <= FLAME_EDIT_TASK_PATH; task++) {
        CHECK_OK(flame_session_set_task_mask(s, task));
    }
    flame_session_free(s);
}

/* Every task, run to the end with the default settings (paste on): the kept values are the
 * reference's, bit for bit, and the rest is generated. */
static void test_task_masks_paste(const FlameModel *m, const float *r) {
    const uint32_t F = ref_frames;
    for (int32_t task = FLAME_EDIT_TASK_INBETWEEN; task <= FLAME_EDIT_TASK_PATH; task++) {
        FlameSession *s = ref_session(m);
        CHECK_OK(flame_session_keep_frames(s, 0, F)); /* replaced by the task's mask */
        CHECK_OK(flame_session_set_task_mask(s, task));
        CHECK_OK(flame_session_set_reference(s, r, F, FLAME_TINY_DIM));
        float *x = finish_features(s);
        if (x) {
            struct keep_count k = compare_kept(x, r, F, task, F);
            char what[96];
            snprintf(what, sizeof what, "task %d: %zu kept values, %zu differ from the reference",
                     task, k.kept, k.kept_diff);
            check_record(k.kept > 0 && k.kept_diff == 0, __FILE__, __LINE__, what, "");
            snprintf(what, sizeof what, "task %d: the generated values are not the reference's",
                     task);
            check_record(k.free_diff > 0, __FILE__, __LINE__, what, "");
        }
        free(x);
        flame_session_free(s);
    }
}

/* A task mask equals the same mask built from parts and frames, and replaces what was there. */
static float *edited_by(const FlameModel *m, const float *r, int task, int part, uint32_t lo,
                        uint32_t hi) {
    FlameSession *s = ref_session(m);
    CHECK_OK(flame_session_set_reference(s, r, ref_frames, FLAME_TINY_DIM));
    if (task >= 0) {
        CHECK_OK(flame_session_set_task_mask(s, task));
    }
    if (part >= 0) {
        CHECK_OK(flame_session_keep_part(s, part, 0, ref_frames));
    } else if (hi > lo) {
        CHECK_OK(flame_session_keep_frames(s, lo, hi));
    }
    float *x = finish_features(s);
    flame_session_free(s);
    return x;
}

static void test_parts_match_tasks(const FlameModel *m, const float *r) {
    const uint32_t F = ref_frames;
    float *a = edited_by(m, r, FLAME_EDIT_TASK_PATH, -1, 0, 0);
    float *b = edited_by(m, r, -1, FLAME_BODY_PART_ROOT_PATH, 0, 0);
    CHECK(same_bits(a, REF_VALUES, b, REF_VALUES));
    free(a);
    free(b);
    a = edited_by(m, r, FLAME_EDIT_TASK_UPPER_BODY, -1, 0, 0);
    b = edited_by(m, r, -1, FLAME_BODY_PART_LOWER_BODY, 0, 0);
    CHECK(same_bits(a, REF_VALUES, b, REF_VALUES));
    free(a);
    free(b);
    a = edited_by(m, r, FLAME_EDIT_TASK_PREDICT, -1, 0, 0);
    b = edited_by(m, r, -1, -1, 0, F / 4);
    CHECK(same_bits(a, REF_VALUES, b, REF_VALUES));
    free(b);
    /* keep_part adds to the task's mask: PREDICT + arms keeps more than PREDICT alone. */
    b = edited_by(m, r, FLAME_EDIT_TASK_PREDICT, FLAME_BODY_PART_ARMS, 0, 0);
    CHECK(!same_bits(a, REF_VALUES, b, REF_VALUES));
    free(a);

    /* ARMS over the second half: exactly the arm joints' channels of those frames are kept. */
    FlameSession *s = ref_session(m);
    CHECK_OK(flame_session_set_reference(s, r, F, FLAME_TINY_DIM));
    CHECK_OK(flame_session_keep_part(s, FLAME_BODY_PART_ARMS, F / 2, F));
    float *x = finish_features(s);
    static const int arms[] = {13, 14, 16, 17, 18, 19, 20, 21, 22, 23};
    size_t kept_diff = 0, other_same = 0;
    for (uint32_t f = 0; x && f < F; f++) {
        for (int c = 0; c < FLAME_TINY_DIM; c++) {
            int j = smpl_joint_of(c), arm = 0;
            for (size_t a_ = 0; a_ < sizeof arms / sizeof arms[0]; a_++) {
                arm |= arms[a_] == j;
            }
            size_t i = (size_t)f * FLAME_TINY_DIM + (size_t)c;
            int same = memcmp(&x[i], &r[i], sizeof(float)) == 0;
            if (arm && f >= F / 2) {
                kept_diff += !same;
            } else {
                other_same += same;
            }
        }
    }
    CHECK(x != NULL && kept_diff == 0);
    CHECK(other_same == 0);
    free(x);
    free(b);
    flame_session_free(s);
}

/* paste 0: the official behaviour, the kept values are only close; methods and seams matter. */
static void test_paste_off_and_methods(const FlameModel *m, const float *r) {
    const uint32_t F = ref_frames;
    float *out[4] = {NULL, NULL, NULL, NULL};
    /* 0: noised reference, paste off; 1: replace x0, paste off; 2: replace x0, paste on;
     * 3: noised reference, paste on, no seam blending. */
    const int32_t method[4] = {FLAME_EDIT_METHOD_NOISED_REFERENCE, FLAME_EDIT_METHOD_REPLACE_X0,
                               FLAME_EDIT_METHOD_REPLACE_X0, FLAME_EDIT_METHOD_NOISED_REFERENCE};
    const uint32_t paste[4] = {0, 0, 1, 1}, seams[4] = {4, 4, 4, 0};
    for (int i = 0; i < 4; i++) {
        FlameSession *s = ref_session(m);
        CHECK_OK(set_params(s, method[i], 0.2f, paste[i], seams[i]));
        CHECK_OK(flame_session_set_reference(s, r, F, FLAME_TINY_DIM));
        CHECK_OK(flame_session_set_task_mask(s, FLAME_EDIT_TASK_INBETWEEN));
        out[i] = finish_features(s);
        flame_session_free(s);
    }
    struct keep_count k[4];
    for (int i = 0; i < 4; i++) {
        k[i] = out[i] ? compare_kept(out[i], r, F, FLAME_EDIT_TASK_INBETWEEN, F)
                      : (struct keep_count){0, 1, 0};
    }
    /* Paste off: the noised reference leaves the kept values only close to the reference.
     * (x0 replacement needs no paste with DDIM: its last step returns the replaced x0.) */
    CHECK(k[0].kept_diff > 0);
    CHECK(k[2].kept_diff == 0 && k[3].kept_diff == 0);
    CHECK(!same_bits(out[0], REF_VALUES, out[1], REF_VALUES)); /* the methods differ */

    /* Seam blending changes only generated frames near the seams: with and without it the
     * kept values are the same and the generated ones are not. */
    FlameSession *s = ref_session(m);
    CHECK_OK(flame_session_set_reference(s, r, F, FLAME_TINY_DIM));
    CHECK_OK(flame_session_set_task_mask(s, FLAME_EDIT_TASK_INBETWEEN));
    float *blended = finish_features(s);
    flame_session_free(s);
    CHECK(!same_bits(blended, REF_VALUES, out[3], REF_VALUES));
    free(blended);
    for (int i = 0; i < 4; i++) {
        free(out[i]);
    }
}

static float max_abs_diff(const float *a, const float *b, size_t n) {
    float d = 0.0f;
    for (size_t i = 0; i < n; i++) {
        float e = fabsf(a[i] - b[i]);
        d = e > d || e != e ? e : d;
    }
    return d;
}

/* A reference shorter than the session: its frames can be kept, later frames cannot. */
static void test_short_reference(const FlameModel *m, const float *r) {
    const int INV = FLAME_STATUS_INVALID_ARGUMENT;
    const uint32_t F = ref_frames, R = ref_frames / 4;
    FlameSession *s = ref_session(m);
    CHECK_OK(flame_session_set_reference(s, r, R, FLAME_TINY_DIM));
    /* A mask keeping frame R, set after the reference. */
    CHECK_ERROR_MENTIONS(flame_session_keep_frames(s, 0, R + 1), INV, num(R));
    CHECK_ERROR_MENTIONS(flame_session_set_task_mask(s, FLAME_EDIT_TASK_INBETWEEN), INV,
                         "keeps frame");
    CHECK_ERROR_MENTIONS(flame_session_keep_part(s, FLAME_BODY_PART_ROOT_PATH, 0, F), INV,
                         "keeps frame");
    /* PREDICT keeps [0, F/4): the reference's frames exactly. */
    CHECK_OK(flame_session_set_task_mask(s, FLAME_EDIT_TASK_PREDICT));
    CHECK_OK(flame_session_keep_part(s, FLAME_BODY_PART_ARMS, 0, R));
    float *x = finish_features(s);
    flame_session_free(s);
    if (x) {
        size_t head = (size_t)R * FLAME_TINY_DIM;
        CHECK(memcmp(x, r, head * sizeof(float)) == 0);
        CHECK(max_abs_diff(x + head, r + head, REF_VALUES - head) > 0.0f); /* generated */
    }
    free(x);

    /* The other order: a mask keeping every frame, then a short reference. */
    s = ref_session(m);
    CHECK_OK(flame_session_keep_frames(s, 0, F));
    char frame[32];
    snprintf(frame, sizeof frame, "keeps frame %u", R);
    CHECK_ERROR_MENTIONS(flame_session_set_reference(s, r, R, FLAME_TINY_DIM), INV, frame);
    CHECK_OK(flame_session_set_reference(s, r, F, FLAME_TINY_DIM));
    /* One frame is the shortest reference. */
    CHECK_OK(flame_session_clear_edit(s));
    CHECK_OK(flame_session_set_reference(s, r, 1, FLAME_TINY_DIM));
    CHECK_OK(flame_session_keep_frames(s, 0, 1));
    CHECK_ERROR_MENTIONS(flame_session_keep_frames(s, 1, 2), INV, "keeps frame 1");
    flame_session_free(s);
}

struct poses {
    float *root, *rot;
    size_t root_n, rot_n;
};

static struct poses read_poses(const FlameSession *s, int32_t layout, int32_t conv) {
    struct poses p;
    p.root = read_layout(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION, conv, 0, &p.root_n);
    p.rot = read_layout(s, FLAME_WHICH_SAMPLE, layout, conv, 0, &p.rot_n);
    return p;
}

static void free_poses(struct poses *p) {
    free(p->root);
    free(p->rot);
}

static void test_reference_pose_errors(const FlameModel *m, const struct poses *p) {
    const int INV = FLAME_STATUS_INVALID_ARGUMENT;
    const uint32_t F = ref_frames;
    const int32_t L6 = FLAME_LAYOUT_LOCAL6D;
    FlameSession *s = ref_session(m);
    size_t rn = p->root_n, qn = p->rot_n;
    CHECK_ERROR_MENTIONS(flame_session_set_reference_poses(s, p->root, rn, p->rot, qn, 0, L6, 0),
                         INV, "frames");
    CHECK_ERROR_MENTIONS(
        flame_session_set_reference_poses(s, p->root, rn, p->rot, qn, F + 1, L6, 0), INV, "frames");
    CHECK_ERROR_MENTIONS(
        flame_session_set_reference_poses(s, p->root, rn - 1, p->rot, qn, F, L6, 0), INV, "root");
    CHECK_STATUS(flame_session_set_reference_poses(s, p->root, rn, p->rot, qn - 1, F, L6, 0), INV);
    CHECK_STATUS(flame_session_set_reference_poses(s, p->root, 0, p->rot, qn, F, L6, 0), INV);
    /* 6D values passed as quaternions: a length mismatch. */
    CHECK_STATUS(flame_session_set_reference_poses(s, p->root, rn, p->rot, qn, F,
                                                   FLAME_LAYOUT_LOCAL_QUAT_XYZW, 0),
                 INV);
    const int32_t bad_layouts[] = {FLAME_LAYOUT_FEATURES,         FLAME_LAYOUT_ROOT_TRANSLATION,
                                   FLAME_LAYOUT_GLOBAL_POSITIONS, FLAME_LAYOUT_GLOBAL_QUAT_XYZW,
                                   FLAME_LAYOUT_GLOBAL_QUAT_WXYZ, FLAME_LAYOUT_FOOT_CONTACTS,
                                   99,                            -1};
    for (size_t i = 0; i < sizeof bad_layouts / sizeof bad_layouts[0]; i++) {
        CHECK_ERROR_MENTIONS(flame_session_set_reference_poses(s, p->root, rn, p->rot, qn, F,
                                                               bad_layouts[i], 0),
                             INV, "layout");
    }
    CHECK_ERROR_MENTIONS(flame_session_set_reference_poses(s, p->root, rn, p->rot, qn, F, L6,
                                                           FLAME_CONVENTION_GLTF + 1),
                         INV, "convention");
    CHECK_STATUS(flame_session_set_reference_poses(s, p->root, rn, p->rot, qn, F, L6, -1), INV);

    /* Values: NaN and infinity; zero matrices and quaternions are no rotations. */
    float *root = (float *)malloc(rn * sizeof(float));
    float *rot = (float *)calloc((size_t)F * 24 * 9, sizeof(float));
    memcpy(root, p->root, rn * sizeof(float));
    root[4] = NAN;
    CHECK_ERROR_MENTIONS(flame_session_set_reference_poses(s, root, rn, p->rot, qn, F, L6, 0), INV,
                         "finite");
    root[4] = 0.0f;
    memcpy(rot, p->rot, qn * sizeof(float));
    rot[7] = INFINITY;
    CHECK_STATUS(flame_session_set_reference_poses(s, root, rn, rot, qn, F, L6, 0), INV);
    memset(rot, 0, (size_t)F * 24 * 9 * sizeof(float));
    CHECK_STATUS(flame_session_set_reference_poses(s, root, rn, rot, (size_t)F * 24 * 9, F,
                                                   FLAME_LAYOUT_LOCAL_MATRIX, 0),
                 INV);
    CHECK_STATUS(flame_session_set_reference_poses(s, root, rn, rot, (size_t)F * 24 * 4, F,
                                                   FLAME_LAYOUT_LOCAL_QUAT_WXYZ, 0),
                 INV);
    /* Identity rotations (unit quaternions w = 1) and a shorter pose reference are fine. */
    for (size_t i = 0; i < (size_t)F * 24; i++) {
        rot[4 * i] = 1.0f;
    }
    CHECK_OK(flame_session_set_reference_poses(s, root, rn, rot, (size_t)F * 24 * 4, F,
                                               FLAME_LAYOUT_LOCAL_QUAT_WXYZ, 0));
    CHECK_OK(flame_session_set_reference_poses(s, root, 3, rot, 24 * 4, 1,
                                               FLAME_LAYOUT_LOCAL_QUAT_WXYZ, 0));
    free(root);
    free(rot);
    flame_session_free(s);
}

/* A session keeping every frame of a pose reference: returns its final features. */
static float *from_poses(const FlameModel *m, const struct poses *p, int32_t layout,
                         int32_t conv) {
    FlameSession *s = ref_session(m);
    CHECK_OK(flame_session_set_reference_poses(s, p->root, p->root_n, p->rot, p->rot_n, ref_frames,
                                               layout, conv));
    CHECK_OK(flame_session_keep_frames(s, 0, ref_frames));
    float *x = finish_features(s);
    flame_session_free(s);
    return x;
}

/* flame_session_set_reference_poses is flame_session_read's inverse. The poses come from the
 * sample after one step (generic; the tiny model's final motions hold degenerate 6D
 * rotations). */
static void test_reference_poses(const FlameModel *m) {
    const uint32_t F = ref_frames;
    const int32_t U = FLAME_CONVENTION_UNITY;
    FlameSession *g = ref_session(m);
    CHECK_OK(flame_session_set_prompt(g, REF_PROMPT));
    CHECK_OK(flame_session_step(g, NULL));
    struct poses p1 = read_poses(g, FLAME_LAYOUT_LOCAL6D, U);
    CHECK(p1.root && p1.rot && p1.root_n == F * 3 && p1.rot_n == F * 24 * 6);
    if (!p1.root || !p1.rot) {
        flame_session_free(g);
        free_poses(&p1);
        return;
    }
    /* poses -> features (kept, pasted) -> poses: the same poses. */
    float *b = from_poses(m, &p1, FLAME_LAYOUT_LOCAL6D, U);
    FlameSession *s = ref_session(m);
    CHECK_OK(flame_session_set_reference_poses(s, p1.root, p1.root_n, p1.rot, p1.rot_n, F,
                                               FLAME_LAYOUT_LOCAL6D, U));
    CHECK_OK(flame_session_keep_frames(s, 0, F));
    CHECK_OK(run_to_end(s, REF_PROMPT));
    struct poses p2 = read_poses(s, FLAME_LAYOUT_LOCAL6D, U);
    flame_session_free(s);
    CHECK(p2.root && p2.rot && p2.root_n == p1.root_n && p2.rot_n == p1.rot_n);
    if (p2.root && p2.rot) {
        CHECK(max_abs_diff(p2.root, p1.root, p1.root_n) < 1e-4f);
        CHECK(max_abs_diff(p2.rot, p1.rot, p1.rot_n) < 1e-4f);
        /* features -> poses -> features: the same features (the brief's round trip). */
        float *c = from_poses(m, &p2, FLAME_LAYOUT_LOCAL6D, U);
        CHECK(b && c && max_abs_diff(b, c, REF_VALUES) < 1e-4f);
        free(c);
    }
    free_poses(&p2);

    /* Every rotation layout and another convention give the same features. */
    const int32_t layouts[] = {FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_LAYOUT_LOCAL_QUAT_WXYZ,
                               FLAME_LAYOUT_LOCAL_MATRIX};
    for (int i = 0; i < 4 && b; i++) {
        int32_t layout = i < 3 ? layouts[i] : FLAME_LAYOUT_LOCAL6D;
        int32_t conv = i < 3 ? U : FLAME_CONVENTION_UNREAL;
        struct poses q = read_poses(g, layout, conv);
        float *x = q.root && q.rot ? from_poses(m, &q, layout, conv) : NULL;
        char what[64];
        snprintf(what, sizeof what, "layout %d convention %d gives the same features", layout,
                 conv);
        check_record(x && max_abs_diff(x, b, REF_VALUES) < 1e-4f, __FILE__, __LINE__, what, "");
        free(x);
        free_poses(&q);
    }
    free(b);

    test_reference_pose_errors(m, &p1);
    free_poses(&p1);
    flame_session_free(g);
}

/* A fixture next to the FLAME model (tests/fixtures/NAME). */
static FlameModel *load_fixture(const char *name) {
    char path[4096];
    const char *slash = strrchr(g_model_path, '/');
    int dir = slash ? (int)(slash - g_model_path) : 1;
    snprintf(path, sizeof path, "%.*s/%s", dir, slash ? g_model_path : ".", name);
    return load_or_die(path);
}

/* MotionLCM's consistency latent tuning (tests/fixtures/motionlcm_v2_control_tiny): a pelvis path
 * followed through the ControlNet; the report says the hint is followed closer; the same bits
 * with and without a report; the wrong states, a short report and NULLs refused. (Python and C#
 * compare the tuned motion with the CLI's `generate --optimize`.) */
static FlameSession *tuning_session(const FlameModel *m) {
    FlameSessionParams p;
    CHECK_OK(flame_session_params_default(&p));
    p.frames = 24;
    p.steps = 1;
    p.seed = 5;
    p.threads = 1;
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(m, &p, &s));
    CHECK_OK(flame_session_set_prompt(s, "a person walks forward"));
    return s;
}

static void test_latent_tuning(void) {
    FlameModel *m = load_fixture("motionlcm_v2_control_tiny.safetensors");
    float hint[24 * 22 * 3];
    for (size_t i = 0; i < 24 * 22 * 3; i++) {
        hint[i] = NAN;
    }
    for (int f = 0; f < 24; f++) {
        hint[f * 66] = 0.05f * (float)f;
        hint[f * 66 + 1] = 0.9f;
        hint[f * 66 + 2] = 0.02f * (float)f;
    }
    FlameSession *a = tuning_session(m), *b = tuning_session(m);
    FlameTuningReport r;
    memset(&r, 0, sizeof r);
    r.struct_size = sizeof r;
    CHECK_ERROR_MENTIONS(flame_session_tune_latent(a, 5, &r), FLAME_STATUS_WRONG_STATE,
                         "set one first");
    CHECK_OK(flame_session_set_control(a, hint, 24 * 22 * 3, NULL, 0, FLAME_CONVENTION_NATIVE));
    CHECK_OK(flame_session_set_control(b, hint, 24 * 22 * 3, NULL, 0, FLAME_CONVENTION_NATIVE));
    CHECK_ERROR_MENTIONS(flame_session_tune_latent(NULL, 5, &r), FLAME_STATUS_INVALID_ARGUMENT,
                         "session");
    r.struct_size = 8;
    CHECK_ERROR_MENTIONS(flame_session_tune_latent(a, 5, &r), FLAME_STATUS_INVALID_ARGUMENT,
                         "struct_size");
    CHECK_ERROR_MENTIONS(flame_session_tune_latent(a, 0, NULL), FLAME_STATUS_INVALID_ARGUMENT,
                         "iterations");
    r.struct_size = sizeof r;
    CHECK_OK(flame_session_tune_latent(a, 20, &r));
    CHECK(r.iterations == 20 && r.struct_size == sizeof r);
    CHECK(r.control_error_after < r.control_error_before);
    CHECK(r.hint_loss_after < r.hint_loss_before);
    CHECK_OK(flame_session_tune_latent(b, 20, NULL));
    FlameStatus st = FLAME_STATUS_OK;
    CHECK_OK(flame_session_step(a, NULL));
    CHECK_OK(flame_session_step(b, NULL));
    size_t na = 0, nb = 0;
    float *xa = read_features(a, FLAME_WHICH_SAMPLE, &na, &st);
    float *xb = read_features(b, FLAME_WHICH_SAMPLE, &nb, &st);
    CHECK(xa && xb && same_bits(xa, na, xb, nb));
    free(xa);
    free(xb);
    CHECK_ERROR_MENTIONS(flame_session_tune_latent(a, 5, NULL), FLAME_STATUS_WRONG_STATE,
                         "before the first step");
    flame_session_free(a);
    flame_session_free(b);
    flame_model_free(m);
}

/* ---- read frames and sample shape ------------------------------------------------------- */

/* flame_session_read_frames and flame_session_sample_shape on a non-latent model of
 * `dim` features (`joints` joints): the frames of a read are the session's, the sampled space
 * is frames × feature_dim, and both agree with what flame_session_read and
 * flame_session_set_noise take. */
static void check_frames_and_shape(const FlameModel *m, uint32_t dim, uint32_t joints,
                                   uint32_t frames, int32_t sampler) {
    const int INV = FLAME_STATUS_INVALID_ARGUMENT, WS = FLAME_STATUS_WRONG_STATE;
    FlameModelInfo info;
    memset(&info, 0, sizeof info);
    info.struct_size = sizeof info;
    CHECK_OK(flame_model_info(m, &info));
    CHECK(info.latent == 0);
    CHECK(info.feature_dim == dim && info.sample_dim == dim && info.joint_count == joints);

    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = frames;
    p.steps = 2;
    p.sampler = sampler;
    p.seed = 1;
    p.threads = 1;
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(m, &p, &s));
    if (!s) {
        return;
    }

    /* The shape is known from the start (it sizes the initial noise); either pointer may be
     * NULL. */
    uint32_t rows = 0, cols = 0;
    CHECK_OK(flame_session_sample_shape(s, &rows, &cols));
    CHECK(rows == frames && cols == dim);
    rows = cols = 7;
    CHECK_OK(flame_session_sample_shape(s, &rows, NULL));
    CHECK(rows == frames && cols == 7);
    CHECK_OK(flame_session_sample_shape(s, NULL, &cols));
    CHECK(cols == dim);
    CHECK_OK(flame_session_sample_shape(s, NULL, NULL));
    CHECK_ERROR_MENTIONS(flame_session_sample_shape(NULL, &rows, &cols), INV, "session");

    /* Nothing to read before the first step; a wrong `which` is an argument error first. */
    uint32_t got = 12345;
    CHECK_ERROR_MENTIONS(flame_session_read_frames(s, FLAME_WHICH_SAMPLE, &got), WS, "no sample");
    CHECK_ERROR_MENTIONS(flame_session_read_frames(s, FLAME_WHICH_ESTIMATE, &got), WS, "estimate");
    CHECK_ERROR_MENTIONS(flame_session_read_frames(s, 2, &got), INV, "which");
    CHECK(got == 12345); /* outputs only on success */
    CHECK_ERROR_MENTIONS(flame_session_read_frames(s, FLAME_WHICH_SAMPLE, NULL), INV,
                         "out_frames");
    CHECK_ERROR_MENTIONS(flame_session_read_frames(NULL, FLAME_WHICH_SAMPLE, &got), INV,
                         "session");

    /* set_noise takes exactly rows × dim values. */
    size_t len = (size_t)frames * dim;
    float *noise = (float *)calloc(len + 1, sizeof(float));
    for (size_t i = 0; i < len + 1; i++) {
        noise[i] = 0.5f * sinf(0.1f * (float)i);
    }
    CHECK_STATUS(flame_session_set_noise(s, noise, len - 1), INV);
    CHECK_STATUS(flame_session_set_noise(s, noise, len + 1), INV);
    CHECK_OK(flame_session_set_noise(s, noise, len));
    free(noise);

    CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
    CHECK_OK(flame_session_step(s, NULL));
    for (int32_t which = FLAME_WHICH_SAMPLE; which <= FLAME_WHICH_ESTIMATE; which++) {
        got = 0;
        CHECK_OK(flame_session_read_frames(s, which, &got));
        CHECK(got == frames);
        /* The frames of a read: its length over the layout's per-frame size. */
        size_t n = 0;
        CHECK_OK(flame_session_read(s, which, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n));
        CHECK(n == (size_t)got * dim);
        CHECK_OK(flame_session_read(s, which, FLAME_LAYOUT_GLOBAL_POSITIONS, 0, 0, NULL, 0, &n));
        CHECK(n == (size_t)got * joints * 3);
    }
    got = 12345;
    CHECK_ERROR_MENTIONS(flame_session_read_frames(s, -1, &got), INV, "which");
    CHECK_ERROR_MENTIONS(flame_session_read_frames(s, 2, &got), INV, "which");
    CHECK(got == 12345);
    CHECK_OK(flame_session_sample_shape(s, &rows, &cols));
    CHECK(rows == frames && cols == dim);

    /* After a reset there is nothing to read again; the shape stays. */
    CHECK_OK(flame_session_reset(s));
    CHECK_STATUS(flame_session_read_frames(s, FLAME_WHICH_SAMPLE, &got), WS);
    CHECK_STATUS(flame_session_read_frames(s, FLAME_WHICH_ESTIMATE, &got), WS);
    CHECK(got == 12345);
    CHECK_OK(flame_session_sample_shape(s, &rows, &cols));
    CHECK(rows == frames && cols == dim);
    flame_session_free(s);

    /* frames = 0 takes the model's default frame count. */
    p.frames = 0;
    CHECK_OK(flame_session_new(m, &p, &s));
    CHECK_OK(flame_session_sample_shape(s, &rows, &cols));
    CHECK(rows == info.default_frames && cols == dim);
    flame_session_free(s);
}

/* A latent model (tests/fixtures/mola_tiny.safetensors, MoLA): 60 frames are a latent of
 * 60 / 4 + 1 = 16 rows of 16 channels (tests/fixtures/mola_expected.json), and its decoder
 * cuts the 64 frames it writes to a valid length of 10..63 frames, which every read has. */
static void test_latent_frames_and_shape(void) {
    const int INV = FLAME_STATUS_INVALID_ARGUMENT, WS = FLAME_STATUS_WRONG_STATE;
    FlameModel *m = load_fixture("mola_tiny.safetensors");
    FlameModelInfo info;
    memset(&info, 0, sizeof info);
    info.struct_size = sizeof info;
    CHECK_OK(flame_model_info(m, &info));
    CHECK(info.latent != 0 && info.sample_dim == 16);
    CHECK(info.feature_dim == 263 && info.joint_count == 22);
    CHECK(strcmp(info.architecture, "mola") == 0);

    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = 60;
    p.steps = 3;
    p.seed = 3;
    p.threads = 1;
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(m, &p, &s));
    uint32_t rows = 0, dim = 0, got = 12345;
    CHECK_OK(flame_session_sample_shape(s, &rows, &dim));
    CHECK(rows == 16 && dim == 16);
    CHECK_STATUS(flame_session_read_frames(s, FLAME_WHICH_SAMPLE, &got), WS);
    CHECK(got == 12345);
    /* The noise is the latent, not the motion. */
    float *noise = (float *)calloc((size_t)60 * 263, sizeof(float));
    CHECK_ERROR_MENTIONS(flame_session_set_noise(s, noise, (size_t)60 * 263), INV, "16 rows");
    for (size_t i = 0; i < (size_t)rows * dim; i++) {
        noise[i] = 1.5f * sinf(0.37f * (float)i);
    }
    CHECK_OK(flame_session_set_noise(s, noise, (size_t)rows * dim));
    /* Masks and references do not apply to a latent. */
    CHECK_ERROR_MENTIONS(flame_session_set_reference(s, noise, 60, 263), INV, "samples a latent");
    CHECK_OK(run_to_end(s, REF_PROMPT));
    for (int32_t which = FLAME_WHICH_SAMPLE; which <= FLAME_WHICH_ESTIMATE; which++) {
        got = 0;
        CHECK_OK(flame_session_read_frames(s, which, &got));
        CHECK(got >= 10 && got <= 4 * rows - 1);
        size_t n = 0;
        CHECK_OK(flame_session_read(s, which, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n));
        CHECK(n == (size_t)got * 263);
        CHECK_OK(flame_session_read(s, which, FLAME_LAYOUT_GLOBAL_POSITIONS, 0, 0, NULL, 0, &n));
        CHECK(n == (size_t)got * 22 * 3);
    }
    CHECK_ERROR_MENTIONS(flame_session_read_frames(s, 7, &got), INV, "which");

    /* After a reset, a generation from another noise reads as a fresh session's. */
    for (size_t i = 0; i < (size_t)rows * dim; i++) {
        noise[i] = 2.0f * cosf(0.11f * (float)i);
    }
    CHECK_OK(flame_session_reset(s));
    CHECK_STATUS(flame_session_read_frames(s, FLAME_WHICH_SAMPLE, &got), WS);
    CHECK_OK(flame_session_set_noise(s, noise, (size_t)rows * dim));
    FlameStatus st = run_to_end(s, REF_PROMPT);
    CHECK_OK(st);
    FlameSession *fresh = NULL;
    CHECK_OK(flame_session_new(m, &p, &fresh));
    CHECK_OK(flame_session_set_noise(fresh, noise, (size_t)rows * dim));
    CHECK_OK(run_to_end(fresh, REF_PROMPT));
    size_t na = 0, nb = 0;
    float *a = read_features(s, FLAME_WHICH_SAMPLE, &na, &st);
    float *b = read_features(fresh, FLAME_WHICH_SAMPLE, &nb, &st);
    CHECK(a != NULL && b != NULL);
    /* A reset and new noise: the read decodes the new generation, not a cached one. */
    CHECK(a && b && na == nb && memcmp(a, b, na * sizeof(float)) == 0);
    free(a);
    free(b);
    free(noise);
    flame_session_free(fresh);
    flame_session_free(s);
    flame_model_free(m);
}

static void test_read_frames_and_sample_shape(const FlameModel *m) {
    check_frames_and_shape(m, FLAME_TINY_DIM, 24, 12, FLAME_SAMPLER_DDIM);
    FlameModel *mdm = load_fixture("mdm_tiny.safetensors");
    check_frames_and_shape(mdm, 263, 22, 16, FLAME_SAMPLER_DDIM);
    flame_model_free(mdm);
    test_latent_frames_and_shape();
}

/* A small session on another model family, with a reference of `dim` smooth values. */
static FlameSession *family_session(const FlameModel *m, uint32_t frames, int32_t sampler) {
    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = frames;
    p.steps = 3;
    p.sampler = sampler;
    p.seed = 1;
    p.threads = 1;
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(m, &p, &s));
    return s;
}

static float *family_run(FlameSession *s, size_t expect) {
    FlameStatus st = run_to_end(s, REF_PROMPT);
    CHECK_OK(st);
    size_t n = 0;
    float *x = st == FLAME_STATUS_OK ? read_features(s, FLAME_WHICH_SAMPLE, &n, &st) : NULL;
    CHECK(x != NULL && n == expect);
    return x;
}

/* Whether channels [c0, c1) of frames [f0, f1) of x equal r's bit for bit. */
static int same_block(const float *x, const float *r, int dim, uint32_t f0, uint32_t f1, int c0,
                      int c1) {
    for (uint32_t f = f0; x && f < f1; f++) {
        size_t i = (size_t)f * (size_t)dim + (size_t)c0;
        if (memcmp(x + i, r + i, (size_t)(c1 - c0) * sizeof(float)) != 0) {
            return 0;
        }
    }
    return x != NULL;
}

/* MDM (humanml263, a diffusion model with x0 replacement): joints, parts and tasks keep its
 * channels; pose references are smpl24_6d only. The fixture's text tower is a placeholder:
 * prompts encode, meaninglessly. */
static void test_edit_mdm(void) {
    const int INV = FLAME_STATUS_INVALID_ARGUMENT;
    const uint32_t F = 16;
    const int D = 263;
    FlameModel *m = load_fixture("mdm_tiny.safetensors");
    FlameModelInfo info;
    memset(&info, 0, sizeof info);
    info.struct_size = sizeof info;
    CHECK_OK(flame_model_info(m, &info));
    CHECK(info.feature_dim == (uint32_t)D && strcmp(info.motion_format, "humanml263") == 0);
    CHECK(info.joint_count == 22);
    float *r = (float *)malloc((size_t)F * D * sizeof(float));
    for (size_t i = 0; i < (size_t)F * D; i++) {
        r[i] = 0.4f * sinf(0.03f * (float)i) - 0.1f;
    }

    FlameSession *s = family_session(m, F, FLAME_SAMPLER_DDIM);
    CHECK_ERROR_MENTIONS(set_params(s, FLAME_EDIT_METHOD_REWRITE_TRAJECTORY, 0.2f, 1, 4), INV,
                         "does not apply");
    CHECK_OK(set_params(s, FLAME_EDIT_METHOD_NOISED_REFERENCE, 0.2f, 1, 4));
    CHECK_OK(set_params(s, FLAME_EDIT_METHOD_REPLACE_X0, 0.2f, 1, 4));
    int32_t bad[] = {22}, good[] = {FLAME_ROOT_TRANSLATION, 0, 7, 21};
    CHECK_ERROR_MENTIONS(flame_session_keep_joints(s, bad, 1), INV, "22");
    CHECK_OK(flame_session_keep_joints(s, good, 4));
    for (int32_t part = FLAME_BODY_PART_ROOT_PATH; part <= FLAME_BODY_PART_LEGS; part++) {
        CHECK_OK(flame_session_keep_part(s, part, 0, F));
    }
    for (int32_t task = FLAME_EDIT_TASK_INBETWEEN; task <= FLAME_EDIT_TASK_PATH; task++) {
        CHECK_OK(flame_session_set_task_mask(s, task));
    }
    float q[24 * 4] = {0}, root[3] = {0};
    for (int j = 0; j < 24; j++) {
        q[4 * j] = 1.0f;
    }
    CHECK_ERROR_MENTIONS(flame_session_set_reference_poses(s, root, 3, q, 24 * 4, 1,
                                                           FLAME_LAYOUT_LOCAL_QUAT_WXYZ, 0),
                         INV, "smpl24_6d");
    flame_session_free(s);

    /* keep_joints({ROOT}) keeps the root path (channels 0..4) exactly, as keep_part does. */
    float *x[3];
    for (int k = 0; k < 3; k++) {
        s = family_session(m, F, FLAME_SAMPLER_DDIM);
        CHECK_OK(flame_session_set_reference(s, r, F, (uint32_t)D));
        int32_t joint = k == 2 ? 0 : FLAME_ROOT_TRANSLATION;
        if (k == 1) {
            CHECK_OK(flame_session_keep_part(s, FLAME_BODY_PART_ROOT_PATH, 0, F));
        } else {
            CHECK_OK(flame_session_keep_joints(s, &joint, 1));
        }
        x[k] = family_run(s, (size_t)F * D);
        flame_session_free(s);
    }
    CHECK(same_block(x[0], r, D, 0, F, 0, 4));
    CHECK(!same_block(x[0], r, D, 0, F, 4, D));
    CHECK(same_bits(x[0], (size_t)F * D, x[1], (size_t)F * D));
    CHECK(same_block(x[2], r, D, 0, F, 0, 4)); /* joint 0 holds the root's channels too */
    CHECK(!same_bits(x[0], (size_t)F * D, x[2], (size_t)F * D));
    for (int k = 0; k < 3; k++) {
        free(x[k]);
    }

    /* PREDICT with a reference of just its frames. */
    s = family_session(m, F, FLAME_SAMPLER_DDIM);
    CHECK_OK(flame_session_set_reference(s, r, F / 4, (uint32_t)D));
    CHECK_OK(flame_session_set_task_mask(s, FLAME_EDIT_TASK_PREDICT));
    float *p = family_run(s, (size_t)F * D);
    CHECK(same_block(p, r, D, 0, F / 4, 0, D));
    CHECK(!same_block(p, r, D, F / 4, F, 0, D));
    free(p);
    flame_session_free(s);
    free(r);
    flame_model_free(m);
}

/* Motion Flow Matching (a flow model): trajectory rewriting only; with paste on the kept
 * values are the reference's whatever edit_till is. */
static void test_edit_flow(void) {
    const int INV = FLAME_STATUS_INVALID_ARGUMENT;
    const uint32_t F = 16;
    const int D = 263;
    FlameModel *m = load_fixture("motionfm_tiny.safetensors");
    float *r = (float *)malloc((size_t)F * D * sizeof(float));
    for (size_t i = 0; i < (size_t)F * D; i++) {
        r[i] = 0.3f * cosf(0.02f * (float)i);
    }
    FlameSession *s = family_session(m, F, FLAME_SAMPLER_EULER);
    CHECK_ERROR_MENTIONS(set_params(s, FLAME_EDIT_METHOD_NOISED_REFERENCE, 0.2f, 1, 4), INV,
                         "does not apply");
    CHECK_ERROR_MENTIONS(set_params(s, FLAME_EDIT_METHOD_REPLACE_X0, 0.2f, 1, 4), INV,
                         "does not apply");
    CHECK_ERROR_MENTIONS(set_params(s, FLAME_EDIT_METHOD_REWRITE_TRAJECTORY, NAN, 1, 4), INV,
                         "edit_till");
    CHECK_OK(set_params(s, FLAME_EDIT_METHOD_REWRITE_TRAJECTORY, 0.5f, 1, 4));
    CHECK_OK(flame_session_set_reference(s, r, F, (uint32_t)D));
    CHECK_OK(flame_session_set_task_mask(s, FLAME_EDIT_TASK_INBETWEEN));
    float *x = family_run(s, (size_t)F * D);
    CHECK(same_block(x, r, D, 0, F / 4, 0, D) && same_block(x, r, D, 3 * F / 4, F, 0, D));
    CHECK(!same_block(x, r, D, F / 4, 3 * F / 4, 0, D));
    /* edit_till changes the generation; paste off leaves the kept frames only close. */
    CHECK_OK(set_params(s, FLAME_EDIT_METHOD_AUTO, 1.0f, 1, 4));
    CHECK_OK(flame_session_reset(s));
    float *y = family_run(s, (size_t)F * D);
    CHECK(!same_bits(x, (size_t)F * D, y, (size_t)F * D));
    CHECK_OK(set_params(s, FLAME_EDIT_METHOD_AUTO, 0.2f, 0, 4));
    CHECK_OK(flame_session_reset(s));
    float *z = family_run(s, (size_t)F * D);
    CHECK(!same_block(z, r, D, 0, F / 4, 0, D));
    free(x);
    free(y);
    free(z);
    free(r);
    flame_session_free(s);
    flame_model_free(m);
}

static void test_edit_api(const FlameModel *m) {
    float *r = (float *)malloc(REF_VALUES * sizeof(float));
    make_reference(r);
    test_edit_params(m);
    test_task_mask_errors(m);
    test_task_masks_paste(m, r);
    test_parts_match_tasks(m, r);
    test_paste_off_and_methods(m, r);
    test_short_reference(m, r);
    test_reference_poses(m);
    free(r);
}

/* ---- explicit noise, thread counts ------------------------------------------------------- */

static void test_noise(const FlameModel *m) {
    float *noise = (float *)malloc(REF_VALUES * sizeof(float));
    for (size_t i = 0; i < REF_VALUES; i++) {
        noise[i] = cosf(0.37f * (float)i);
    }
    /* DDIM with eta 0 draws no noise after x_T: with x_T given, the seed does not matter. */
    float *a = NULL, *b = NULL;
    for (int seed = 1; seed <= 2; seed++) {
        FlameSessionParams p;
        ref_params(&p);
        p.seed = (uint64_t)seed;
        FlameSession *s = NULL;
        CHECK_OK(flame_session_new(m, &p, &s));
        CHECK_OK(flame_session_set_noise(s, noise, REF_VALUES));
        FlameStatus st = run_to_end(s, REF_PROMPT);
        CHECK_OK(st);
        size_t n = 0;
        float *x = read_features(s, FLAME_WHICH_SAMPLE, &n, &st);
        if (seed == 1) {
            a = x;
        } else {
            b = x;
        }
        flame_session_free(s);
    }
    CHECK(same_bits(a, REF_VALUES, b, REF_VALUES));
    CHECK(!same_bits(a, REF_VALUES, g_ref, g_ref_n));
    free(a);
    free(b);
    free(noise);
}

/* Two worker threads give the same bits as one (the promise of docs/cli.md). */
static void test_thread_count_invariance(const FlameModel *m) {
    FlameSessionParams p;
    ref_params(&p);
    p.threads = 2;
    FlameStatus st;
    size_t n = 0;
    float *x = generate(m, &p, REF_PROMPT, &n, &st);
    CHECK_OK(st);
    CHECK(same_bits(x, n, g_ref, g_ref_n));
    free(x);
}

/* ---- progress ---------------------------------------------------------------------------- */

struct progress_log {
    int calls;
    uint32_t last_done, last_total;
    int bad_order;      /* done did not go up by one */
    int wrong_thread;   /* not called on the stepping thread */
    pthread_t stepping; /* the thread that steps */
};

static void on_progress(void *user_data, uint32_t done, uint32_t total) {
    struct progress_log *log = (struct progress_log *)user_data;
    if (done != log->last_done + 1) {
        log->bad_order++;
    }
    if (!pthread_equal(pthread_self(), log->stepping)) {
        log->wrong_thread++;
    }
    log->calls++;
    log->last_done = done;
    log->last_total = total;
}

static void test_progress(const FlameModel *m) {
    enum { N = 6 };
    struct progress_log log;
    memset(&log, 0, sizeof log);
    log.stepping = pthread_self();
    FlameSessionParams p;
    ref_params(&p);
    p.frames = 4;
    p.steps = N;
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(m, &p, &s));
    CHECK_OK(flame_session_set_progress_callback(s, on_progress, &log));
    CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
    CHECK(log.calls == 0);
    uint32_t left = 0, done = 0, total = 0;
    for (int k = 1; k <= 3; k++) {
        CHECK_OK(flame_session_step(s, &left));
        CHECK(log.calls == k && log.last_done == (uint32_t)k && log.last_total == N);
        CHECK_OK(flame_session_progress(s, &done, &total));
        CHECK(done == (uint32_t)k && total == N && left == N - (uint32_t)k);
    }
    /* Removed: no more calls. */
    CHECK_OK(flame_session_set_progress_callback(s, NULL, &log));
    CHECK_OK(flame_session_step(s, &left));
    CHECK(log.calls == 3);
    /* Back again, to the end; a failing step does not call it. */
    CHECK_OK(flame_session_set_progress_callback(s, on_progress, &log));
    log.last_done = 4;
    while (left > 0) {
        CHECK_OK(flame_session_step(s, &left));
    }
    CHECK(log.calls == N - 1 && log.last_done == N && log.last_total == N);
    CHECK_STATUS(flame_session_step(s, &left), FLAME_STATUS_WRONG_STATE);
    CHECK(log.calls == N - 1);
    CHECK(log.bad_order == 0 && log.wrong_thread == 0);
    flame_session_free(s);
}

/* The callback may use its session: read the preview, ask the progress. */
struct reentry_log {
    FlameSession *session;
    int calls;
    int read_status, progress_status;
    size_t read_len;
};

static void reenter(void *user_data, uint32_t done, uint32_t total) {
    struct reentry_log *log = (struct reentry_log *)user_data;
    (void)done, (void)total;
    log->calls++;
    log->read_status = flame_session_read(log->session, FLAME_WHICH_ESTIMATE, FLAME_LAYOUT_FEATURES,
                                          0, 0, NULL, 0, &log->read_len);
    log->progress_status = flame_session_progress(log->session, NULL, NULL);
}

static void test_progress_reentry(const FlameModel *m) {
    struct reentry_log log;
    memset(&log, 0, sizeof log);
    log.read_status = log.progress_status = -1;
    log.session = ref_session(m);
    CHECK_OK(flame_session_set_progress_callback(log.session, reenter, &log));
    CHECK_OK(flame_session_set_prompt(log.session, REF_PROMPT));
    CHECK_OK(flame_session_step(log.session, NULL));
    CHECK(log.calls == 1);
    /* The callback runs after the session's lock is released (it used to be WRONG_STATE,
     * "the session is in use by another thread"). */
    CHECK(log.read_status == FLAME_STATUS_OK && log.read_len == REF_VALUES);
    CHECK(log.progress_status == FLAME_STATUS_OK);
    flame_session_free(log.session);
}

/* ---- cancel ------------------------------------------------------------------------------ */

struct cancel_job {
    FlameSession *session;
    volatile int steps_done; /* written by the progress callback on the main thread */
    pthread_mutex_t lock;
    pthread_cond_t cond;
    int cancel_status;
};

static void cancel_progress(void *user_data, uint32_t done, uint32_t total) {
    struct cancel_job *job = (struct cancel_job *)user_data;
    (void)total;
    pthread_mutex_lock(&job->lock);
    job->steps_done = (int)done;
    pthread_cond_broadcast(&job->cond);
    pthread_mutex_unlock(&job->lock);
}

static void *canceller(void *arg) {
    struct cancel_job *job = (struct cancel_job *)arg;
    pthread_mutex_lock(&job->lock);
    while (job->steps_done < 2) {
        pthread_cond_wait(&job->cond, &job->lock);
    }
    pthread_mutex_unlock(&job->lock);
    job->cancel_status = flame_session_cancel(job->session);
    return NULL;
}

static void test_cancel_from_thread(const FlameModel *m) {
    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = quick_mode() ? 40 : 300;
    p.steps = quick_mode() ? 20 : 200;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.threads = 1;
    struct cancel_job job;
    memset(&job, 0, sizeof job);
    pthread_mutex_init(&job.lock, NULL);
    pthread_cond_init(&job.cond, NULL);
    job.cancel_status = -1;
    CHECK_OK(flame_session_new(m, &p, &job.session));
    CHECK_OK(flame_session_set_progress_callback(job.session, cancel_progress, &job));
    CHECK_OK(flame_session_set_prompt(job.session, REF_PROMPT));

    pthread_t t;
    pthread_create(&t, NULL, canceller, &job);
    double t0 = now_seconds();
    uint32_t left = p.steps, left_before = 0;
    FlameStatus st = FLAME_STATUS_OK;
    while (left > 0) {
        left_before = left;
        st = flame_session_step(job.session, &left);
        if (st != FLAME_STATUS_OK) {
            break;
        }
    }
    double t_cancel = now_seconds() - t0;
    pthread_join(t, NULL);
    CHECK(job.cancel_status == FLAME_STATUS_OK);
    CHECK_STATUS(st, FLAME_STATUS_CANCELLED);
    CHECK(left == left_before); /* a cancelled step writes no steps_left and is not counted */
    uint32_t done = 0;
    CHECK_OK(flame_session_progress(job.session, &done, NULL));
    CHECK(done == p.steps - left_before);
    /* The step may be retried: the next one succeeds and counts. */
    CHECK_OK(flame_session_step(job.session, &left));
    CHECK(left == left_before - 1);
    printf("cancel: landed after %.2f s, at step %u of %u (%u frames)\n", t_cancel,
           p.steps - left_before + 1, p.steps, p.frames);
    flame_session_free(job.session);
    pthread_mutex_destroy(&job.lock);
    pthread_cond_destroy(&job.cond);
}

/* An edited, stochastic (DDPM) generation cancelled from another thread a few milliseconds
 * into a step, then retried, gives the same bits as one never cancelled: the abandoned step
 * leaves no trace (neither in x_t nor in the noise stream the edit and the sampler draw from).
 * Wherever the cancel lands (mid-step or at the next step's start) the result must match. */
struct edit_cancel {
    FlameSession *session;
    pthread_mutex_t lock;
    pthread_cond_t cond;
    int steps_done;
};

static void edit_cancel_progress(void *user_data, uint32_t done, uint32_t total) {
    struct edit_cancel *job = (struct edit_cancel *)user_data;
    (void)total;
    pthread_mutex_lock(&job->lock);
    job->steps_done = (int)done;
    pthread_cond_broadcast(&job->cond);
    pthread_mutex_unlock(&job->lock);
}

static void *edit_canceller(void *arg) {
    struct edit_cancel *job = (struct edit_cancel *)arg;
    pthread_mutex_lock(&job->lock);
    while (job->steps_done < 2) {
        pthread_cond_wait(&job->cond, &job->lock);
    }
    pthread_mutex_unlock(&job->lock);
    sleep_ms(3); /* into step 3's forward pass */
    flame_session_cancel(job->session);
    return NULL;
}

static float *edited_ddpm(const FlameModel *m, const float *r, int cancel, int *cancels,
                          size_t *n) {
    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = quick_mode() ? 24 : 96;
    p.steps = quick_mode() ? 5 : 12;
    p.sampler = FLAME_SAMPLER_DDPM;
    p.seed = 5;
    p.threads = 1;
    struct edit_cancel job;
    memset(&job, 0, sizeof job);
    pthread_mutex_init(&job.lock, NULL);
    pthread_cond_init(&job.cond, NULL);
    CHECK_OK(flame_session_new(m, &p, &job.session));
    int32_t root = FLAME_ROOT_TRANSLATION;
    CHECK_OK(flame_session_set_reference(job.session, r, p.frames, FLAME_TINY_DIM));
    CHECK_OK(flame_session_keep_joints(job.session, &root, 1));
    CHECK_OK(flame_session_keep_frames(job.session, 0, 4));
    CHECK_OK(flame_session_set_progress_callback(job.session, edit_cancel_progress, &job));
    CHECK_OK(flame_session_set_prompt(job.session, REF_PROMPT));
    pthread_t t;
    if (cancel) {
        pthread_create(&t, NULL, edit_canceller, &job);
    }
    uint32_t left = 1;
    *cancels = 0;
    while (left > 0) {
        FlameStatus st = flame_session_step(job.session, &left);
        if (st == FLAME_STATUS_CANCELLED) {
            ++*cancels;
        } else if (st != FLAME_STATUS_OK) {
            CHECK_OK(st);
            break;
        }
    }
    if (cancel) {
        pthread_join(t, NULL);
    }
    FlameStatus st;
    float *x = read_features(job.session, FLAME_WHICH_SAMPLE, n, &st);
    flame_session_free(job.session);
    pthread_mutex_destroy(&job.lock);
    pthread_cond_destroy(&job.cond);
    return x;
}

static void test_cancel_edit_retry(const FlameModel *m) {
    size_t values = (size_t)96 * FLAME_TINY_DIM;
    float *r = (float *)malloc(values * sizeof(float));
    for (size_t i = 0; i < values; i++) {
        r[i] = 0.3f * sinf(0.05f * (float)i);
    }
    int cancels_a = 0, cancels_b = 0;
    size_t na = 0, nb = 0;
    float *a = edited_ddpm(m, r, 0, &cancels_a, &na);
    /* The cancel comes from another thread a few milliseconds into step 3; on a loaded machine
     * it can arrive after the last step, which proves nothing: run again until it lands. */
    float *b = NULL;
    for (int attempt = 0; attempt < 10 && cancels_b == 0; attempt++) {
        free(b);
        b = edited_ddpm(m, r, 1, &cancels_b, &nb);
    }
    CHECK(cancels_a == 0 && cancels_b == 1);
    CHECK(same_bits(a, na, b, nb));
    free(a);
    free(b);
    free(r);
}

/* A cancel with no step running applies to the next step only; the generation then ends with
 * the same bits as one never cancelled. */
static void test_cancel_idle(const FlameModel *m) {
    FlameSession *s = ref_session(m);
    CHECK_OK(flame_session_cancel(s));
    CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
    uint32_t left = 99;
    CHECK_STATUS(flame_session_step(s, &left), FLAME_STATUS_CANCELLED);
    CHECK(left == 99);
    CHECK_OK(flame_session_step(s, &left));
    CHECK(left == ref_steps - 1);
    CHECK_OK(flame_session_cancel(s));
    CHECK_STATUS(flame_session_step(s, &left), FLAME_STATUS_CANCELLED);
    while (left > 0) {
        CHECK_OK(flame_session_step(s, &left));
    }
    FlameStatus st;
    size_t n = 0;
    float *x = read_features(s, FLAME_WHICH_SAMPLE, &n, &st);
    CHECK(same_bits(x, n, g_ref, g_ref_n));
    free(x);
    /* reset forgets a pending cancel. */
    CHECK_OK(flame_session_cancel(s));
    CHECK_OK(flame_session_reset(s));
    CHECK_OK(flame_session_step(s, &left));
    flame_session_free(s);
}

/* ---- ownership ---------------------------------------------------------------------------- */

/* The session keeps the model alive: free the model first, then generate. */
static void test_model_freed_first(void) {
    FlameModel *m = load_or_die(g_model_path);
    FlameSession *s = ref_session(m);
    flame_model_free(m);
    CHECK(matches_reference(s));
    flame_session_free(s);
}

/* The CLI's reference, bit for bit, through flame_model_load. */
static void test_cli_parity(const FlameModel *m) {
    FlameSession *s = ref_session(m);
    CHECK(matches_reference(s));
    /* The estimate after the last step is readable and finite. */
    size_t n = 0;
    FlameStatus st;
    float *e = read_features(s, FLAME_WHICH_ESTIMATE, &n, &st);
    CHECK(e != NULL && n == REF_VALUES);
    free(e);
    flame_session_free(s);
}

/* Waits (up to 2 s) until only `n` threads are left. */
static int wait_for_threads(int n) {
    for (int i = 0; i < 100 && count_threads("") > n; i++) {
        sleep_ms(20);
    }
    return count_threads("");
}

/* flame_session_free joins the session's worker threads (and a load joins its temporary
 * pool): nothing of libflame is left running once a call returns. pthread_join returns when
 * the kernel clears the thread id, slightly before the exited task leaves /proc/self/task (on
 * a loaded machine the gap reached a few ms; an immediate count failed about 1 run in 10), so
 * a call counts as leaving threads behind when the count is still above base 5 ms after it
 * returned. That the pool runs its workers' thread-exit destructors before the free returns
 * is checked exactly in src/pool.rs (workers_are_gone_when_the_pool_is_dropped). */
static int left_behind(int base) {
    for (int i = 0; i < 5 && count_threads("") != base; i++) {
        sleep_ms(1);
    }
    return count_threads("") != base;
}

static void test_threads_joined(void) {
    if (count_threads("") < 0) {
        return; /* no /proc */
    }
    int base = wait_for_threads(1);
    int loads = quick_mode() ? 1 : 3, sessions = quick_mode() ? 3 : 10;
    int left_by_load = 0, left_by_free = 0;
    FlameModelParams mp;
    flame_model_params_default(&mp);
    mp.threads = 4;
    FlameModel *m = NULL;
    for (int i = 0; i < loads; i++) {
        if (m) {
            flame_model_free(m);
            m = NULL;
        }
        wait_for_threads(base);
        CHECK_OK(flame_model_load(g_model_path, &mp, &m));
        left_by_load += left_behind(base);
    }
    FlameSessionParams p;
    ref_params(&p);
    p.threads = 4;
    for (int i = 0; i < sessions && m; i++) {
        wait_for_threads(base);
        FlameSession *s = NULL;
        CHECK_OK(flame_session_new(m, &p, &s));
        CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
        CHECK_OK(flame_session_step(s, NULL));
        if (i == 0) {
            /* A thread names itself once it runs, so give idle workers a moment. */
            int workers = count_threads("flame-worker");
            for (int tries = 0; tries < 50 && workers != 4; tries++) {
                sleep_ms(20);
                workers = count_threads("flame-worker");
            }
            CHECK(workers == 4);
        }
        flame_session_free(s);
        left_by_free += left_behind(base);
    }
    flame_model_free(m);
    CHECK(wait_for_threads(base) == base); /* they do go, eventually */
    CHECK(left_by_load == 0); /* flame_model_load's temporary pool is joined before it returns */
    CHECK(left_by_free == 0); /* flame_session_free joins the session's workers */
}

/* Runs one test; FLAME_TEST_TIMES=1 prints how long it took. */
#define TIMED(call)                                                 \
    do {                                                            \
        double t_ = now_seconds();                                  \
        call;                                                       \
        if (getenv("FLAME_TEST_TIMES")) {                           \
            printf("  %-45s %7.2f s\n", #call, now_seconds() - t_); \
        }                                                           \
    } while (0)

int main(int argc, char **argv) {
    if (argc != 4 && argc != 5) {
        fprintf(stderr, "usage: %s MODEL REFERENCE_NPY TMPDIR [STEPS]\n", argv[0]);
        return 2;
    }
    ref_steps = argc == 5 ? (uint32_t)strtoul(argv[4], NULL, 10) : 10;
    g_model_path = argv[1];
    g_tmp_dir = argv[3];
    size_t rows = 0, cols = 0;
    g_ref = read_npy_f32(argv[2], &rows, &cols);
    if (!g_ref || rows < 2 || cols != FLAME_TINY_DIM || ref_steps < 2) {
        fprintf(stderr, "cannot read a frames x 147 float32 array from %s (or STEPS < 2)\n",
                argv[2]);
        return 2;
    }
    ref_frames = (uint32_t)rows;
    g_ref_n = rows * cols;
    size_t file_len = 0;
    unsigned char *file = read_file(g_model_path, &file_len);
    if (!file) {
        fprintf(stderr, "cannot read %s\n", g_model_path);
        return 2;
    }

    double t0 = now_seconds();
    TIMED(test_versions());
    TIMED(test_status_strings());
    TIMED(test_param_defaults());
    TIMED(test_last_error());
    TIMED(test_free_null());
    TIMED(test_load_errors(file, file_len));
    TIMED(test_load_from_memory(file, file_len));

    FlameModel *m = load_or_die(g_model_path);
    TIMED(test_model_info(m));
    TIMED(test_session_new(m));
    TIMED(test_null_arguments(m));
    TIMED(test_wrong_state(m));
    TIMED(test_read_frames_and_sample_shape(m));
    TIMED(test_reset(m));
    TIMED(test_prompt_info(m));
    TIMED(test_prompt_from(m));
    TIMED(test_latent_tuning());
    TIMED(test_read(m));
    TIMED(test_gltf(m));
    TIMED(test_layouts(m));
    TIMED(test_lengths(m));
    TIMED(test_edit(m));
    TIMED(test_edit_api(m));
    TIMED(test_noise(m));
    TIMED(test_thread_count_invariance(m));
    TIMED(test_progress(m));
    TIMED(test_progress_reentry(m));
    TIMED(test_cancel_idle(m));
    TIMED(test_cancel_from_thread(m));
    TIMED(test_cancel_edit_retry(m));
    TIMED(test_cli_parity(m));
    flame_model_free(m);

    TIMED(test_edit_mdm());
    TIMED(test_edit_flow());
    TIMED(test_model_freed_first());
    TIMED(test_threads_joined());

    free(file);
    free(g_ref);
    printf("test_api: %.2f s\n", now_seconds() - t0);
    return check_summary();
}
