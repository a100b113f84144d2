/*
 * Streams through the C ABI (flame_stream_*): continuous motion from a timeline of prompts.
 *
 * usage: test_stream FIXTURES_DIR   (tests/fixtures: flame_tiny, mdm_tiny, mld_tiny, mola_tiny,
 *                                    finemogen_tiny)
 *
 * - every entry point with NULL handles, NULL out-pointers and NULL strings: INVALID_ARGUMENT
 *   (flame_stream_free(NULL) is a no-op), a short struct_size: INVALID_ARGUMENT;
 * - flame_stream_params_default's values, a stream from NULL params, the status of a new stream;
 * - push / pump / read on the FLAME (smpl24_6d) and MDM (humanml263) fixtures: the chunk and
 *   step counts, every layout's length, a sub-range read equal to the same frames of a whole
 *   read, and the features' bytes equal between a stream pumped one step per call on one thread
 *   and one pumped with UINT32_MAX on two threads;
 * - the length protocol of flame_session_read (NULL out, too small, exact, larger);
 * - frames not generated yet: WRONG_STATE; dropped behind the playhead: INVALID_ARGUMENT naming
 *   the window; a playhead past the frames ready: INVALID_ARGUMENT;
 * - interrupt (between chunks and with a chunk in flight), a zero-frame segment;
 * - a latent model (MLD), chunk above the model's maximum, overlap >= chunk, threads above
 *   FLAME_MAX_THREADS, an unknown sampler, a NaN guidance: INVALID_ARGUMENT at creation;
 * - read flags, unknown layouts and conventions, foot contacts of a format without them;
 * - a call while another thread pumps: WRONG_STATE "in use by another thread";
 * - flame_stream_cancel: raised between pumps (the next pump is CANCELLED, nothing kept) and by
 *   another thread during pumps; pumping on gives the bytes of a stream never cancelled;
 * - flame_stream_push_stage / interrupt_stage: NULL and short structs, empty part texts follow
 *   the whole-body text, part texts refused by FLAME when the chunk starts, and on FineMoGen
 *   (finemogen_tiny) every part given the segment's text equals the plain push bit for bit;
 * - a MoLA stream (mola_tiny; continues through position targets): deterministic, finite;
 * - flame_stream_close_looped (the settings of tests/cycle.rs: chunks of 60 keeping 20, 3 steps,
 *   seed 9; "a person walks" 70 + "a person jumps" 30, a 20-frame bridge): 120 frames, six
 *   steps (two chunks) more than the plain close, frames 0..100 the plain close's bit for bit,
 *   cleaned reads (feet locked) of all 120 settled; a bridge too short (12) or too long for the
 *   model (the overlap + the bridge + 0.5 s past max_frames): INVALID_ARGUMENT naming it, the
 *   stream still open; no segment, a second close: WRONG_STATE; NULL: INVALID_ARGUMENT; a
 *   latent model (mola_tiny): INVALID_ARGUMENT "samples a latent".
 */
#define _POSIX_C_SOURCE 200809L

#include <math.h>
#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "flame.h"

#include "check.h"
#include "util.h"

static char fixtures[4096];

static FlameModel *load(const char *name) {
    char path[4200];
    snprintf(path, sizeof path, "%s/%s.safetensors", fixtures, name);
    FlameModelParams mp;
    flame_model_params_default(&mp);
    mp.threads = 1;
    FlameModel *m = NULL;
    CHECK_OK(flame_model_load(path, &mp, &m));
    return m;
}

/* The settings of tests/stream.rs: chunks of 40 frames keeping 10, 3 DDIM steps, seed 5. */
static void small_params(FlameStreamParams *p, uint32_t threads) {
    flame_stream_params_default(p);
    p->chunk = 40;
    p->overlap = 10;
    p->lookahead = 1000;
    p->window = 10000;
    p->steps = 3;
    p->sampler = FLAME_SAMPLER_DDIM;
    p->seed = 5;
    p->threads = threads;
}

static FlameStream *new_stream(const FlameModel *m, const FlameStreamParams *p) {
    FlameStream *s = NULL;
    CHECK_OK(flame_stream_new(m, p, &s));
    return s;
}

/* 50 + 25 + 40 = 115 frames: chunks of 40 + 10, 25, 30 + 10 new frames (five of 3 steps). */
#define TIMELINE_FRAMES 115
static void timeline(FlameStream *s) {
    CHECK_OK(flame_stream_push(s, "a person walks forward.", 50));
    CHECK_OK(flame_stream_push(s, "a person waves.", 25));
    CHECK_OK(flame_stream_push(s, "a person sits down.", 40));
}

static FlameStreamStatus status_of(const FlameStream *s) {
    FlameStreamStatus st;
    memset(&st, 0xab, sizeof st);
    st.struct_size = sizeof st;
    CHECK_OK(flame_stream_status(s, &st));
    return st;
}

/* Pumps `per_call` steps at a time until a call runs none; returns the calls. */
static int run(FlameStream *s, uint32_t per_call) {
    int calls = 0;
    for (;;) {
        FlameStreamStatus st;
        st.struct_size = sizeof st;
        if (!CHECK_OK(flame_stream_pump(s, per_call, &st))) {
            return calls;
        }
        calls++;
        if (st.steps == 0 || calls > 10000) {
            return calls;
        }
    }
}

/* Frames first..first+count in `layout` (convention `conv`) as a malloc'd array. */
static float *read_range(const FlameStream *s, uint64_t first, uint32_t count, int32_t layout,
                         int32_t conv, size_t *n) {
    size_t need = 0;
    *n = 0;
    if (!CHECK_OK(flame_stream_read(s, first, count, layout, conv, 0, NULL, 0, &need))) {
        return NULL;
    }
    float *out = (float *)malloc(need * sizeof(float) + 1);
    if (!CHECK_OK(flame_stream_read(s, first, count, layout, conv, 0, out, need, n))) {
        free(out);
        return NULL;
    }
    CHECK(*n == need);
    return out;
}

static int all_finite(const float *v, size_t n) {
    for (size_t i = 0; i < n; i++) {
        if (!isfinite(v[i])) {
            return 0;
        }
    }
    return 1;
}

/* ---- NULL checks ------------------------------------------------------------------------- */

static void test_null_checks(const FlameModel *m) {
    const int32_t INV = FLAME_STATUS_INVALID_ARGUMENT;
    FlameStreamParams p;
    CHECK_ERROR_MENTIONS(flame_stream_params_default(NULL), INV, "params");
    small_params(&p, 1);

    FlameStream *s = NULL;
    CHECK_ERROR_MENTIONS(flame_stream_new(NULL, &p, &s), INV, "model");
    CHECK(s == NULL);
    CHECK_ERROR_MENTIONS(flame_stream_new(m, &p, NULL), INV, "stream");
    FlameStreamParams shortp = p;
    shortp.struct_size = 8;
    CHECK_ERROR_MENTIONS(flame_stream_new(m, &shortp, &s), INV, "struct_size");
    shortp.struct_size = 0;
    CHECK_ERROR_MENTIONS(flame_stream_new(m, &shortp, &s), INV, "struct_size");
    CHECK(s == NULL);
    flame_stream_free(NULL);

    s = new_stream(m, &p);
    CHECK(s != NULL);
    CHECK_ERROR_MENTIONS(flame_stream_push(NULL, "a person walks.", 10), INV, "stream");
    CHECK_ERROR_MENTIONS(flame_stream_push(s, NULL, 10), INV, "prompt");
    CHECK_ERROR_MENTIONS(flame_stream_push(s, "\xff\xfe", 10), INV, "UTF-8");
    CHECK_ERROR_MENTIONS(flame_stream_interrupt(NULL, "a person walks.", 10), INV, "stream");
    CHECK_ERROR_MENTIONS(flame_stream_interrupt(s, NULL, 10), INV, "prompt");
    CHECK_ERROR_MENTIONS(flame_stream_set_playhead(NULL, 0), INV, "stream");
    CHECK_ERROR_MENTIONS(flame_stream_pump(NULL, 1, NULL), INV, "stream");

    FlameStreamStatus st;
    memset(&st, 0, sizeof st);
    CHECK_ERROR_MENTIONS(flame_stream_status(NULL, &st), INV, "stream");
    CHECK_ERROR_MENTIONS(flame_stream_status(s, NULL), INV, "status");
    st.struct_size = 4;
    CHECK_ERROR_MENTIONS(flame_stream_status(s, &st), INV, "struct_size");
    CHECK_ERROR_MENTIONS(flame_stream_pump(s, 1, &st), INV, "struct_size");
    CHECK(st.struct_size == 4 && st.steps == 0); /* not written on failure */

    size_t n = 12345;
    float buf[4];
    CHECK_ERROR_MENTIONS(flame_stream_read(NULL, 0, 1, 0, 0, 0, buf, 4, &n), INV, "stream");
    CHECK_ERROR_MENTIONS(flame_stream_read(s, 0, 1, 0, 0, 0, buf, 4, NULL), INV, "out_len");
    CHECK(n == 12345);

    /* Nothing pushed by the failed calls: the stream has nothing to pump. */
    CHECK_OK(flame_stream_pump(s, 1, NULL));
    FlameStreamStatus now = status_of(s);
    CHECK(now.ready == 0 && now.starving == 1);
    flame_stream_free(s);
}

/* ---- defaults ---------------------------------------------------------------------------- */

static void test_defaults(const FlameModel *m) {
    FlameStreamParams p;
    memset(&p, 0xab, sizeof p);
    CHECK_OK(flame_stream_params_default(&p));
    CHECK(p.struct_size == sizeof(FlameStreamParams));
    CHECK(p.chunk == 0 && p.overlap == 20 && p.lookahead == 60 && p.window == 1200);
    CHECK(p.steps == 0 && p.sampler == FLAME_SAMPLER_DEFAULT && p.guidance < 0);
    CHECK(p.seed == 0 && p.threads == 0);

    /* NULL params = the defaults; a new stream stands at 0 and starves (nothing pushed). */
    FlameStream *s = NULL;
    CHECK_OK(flame_stream_new(m, NULL, &s));
    CHECK(s != NULL);
    FlameStreamStatus st = status_of(s);
    CHECK(st.struct_size == sizeof st && st.steps == 0);
    CHECK(st.ready == 0 && st.first_frame == 0 && st.playhead == 0 && st.starving == 1);
    /* Nothing to read yet: frame 0 is not generated. */
    size_t n = 0;
    CHECK_ERROR_MENTIONS(flame_stream_read(s, 0, 1, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n),
                         FLAME_STATUS_WRONG_STATE, "not generated yet");
    flame_stream_free(s);

    /* Zero in overlap, lookahead and window is the default too. */
    p.overlap = p.lookahead = p.window = 0;
    p.chunk = 40;
    p.threads = 1;
    s = new_stream(m, &p);
    flame_stream_free(s);
}

/* ---- push, pump, read -------------------------------------------------------------------- */

static void test_round_trip(const FlameModel *m, const char *name) {
    FlameModelInfo info;
    info.struct_size = sizeof info;
    CHECK_OK(flame_model_info(m, &info));
    const uint32_t dim = info.feature_dim, joints = info.joint_count;

    FlameStreamParams p;
    small_params(&p, 1);
    FlameStream *a = new_stream(m, &p);
    timeline(a);
    int calls = run(a, 1);
    CHECK(calls == 16); /* 15 steps, then one call that runs none */
    FlameStreamStatus st = status_of(a);
    CHECK(st.ready == TIMELINE_FRAMES && st.first_frame == 0 && st.playhead == 0);
    CHECK(st.starving == 1); /* fewer than 1000 frames ahead and nothing left to push */

    small_params(&p, 2);
    FlameStream *b = new_stream(m, &p);
    timeline(b);
    FlameStreamStatus sb;
    sb.struct_size = sizeof sb;
    CHECK_OK(flame_stream_pump(b, UINT32_MAX, &sb));
    CHECK(sb.steps == 15 && sb.ready == TIMELINE_FRAMES && sb.starving == 1);

    /* Determinism: the same timeline gives the same bytes whatever the pump pattern and the
     * threads. */
    size_t na = 0, nb = 0;
    float *fa = read_range(a, 0, TIMELINE_FRAMES, FLAME_LAYOUT_FEATURES, 0, &na);
    float *fb = read_range(b, 0, TIMELINE_FRAMES, FLAME_LAYOUT_FEATURES, 0, &nb);
    CHECK(na == (size_t)TIMELINE_FRAMES * dim);
    CHECK(same_bits(fa, na, fb, nb));
    CHECK(fa && all_finite(fa, na));
    if (!same_bits(fa, na, fb, nb)) {
        fprintf(stderr, "     (%s)\n", name);
    }

    /* A sub-range is the same frames of the whole (features, and decoded poses). */
    size_t nsub = 0;
    float *sub = read_range(a, 30, 20, FLAME_LAYOUT_FEATURES, 0, &nsub);
    CHECK(sub && fa && nsub == 20u * dim &&
          memcmp(sub, fa + (size_t)30 * dim, nsub * sizeof(float)) == 0);
    free(sub);
    size_t nroot = 0;
    float *root = read_range(a, 0, TIMELINE_FRAMES, FLAME_LAYOUT_ROOT_TRANSLATION,
                             FLAME_CONVENTION_GLTF, &nroot);
    CHECK(nroot == TIMELINE_FRAMES * 3u && root && all_finite(root, nroot));
    sub = read_range(a, 70, 45, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_GLTF, &nsub);
    CHECK(sub && root && nsub == 45u * 3 && memcmp(sub, root + 70 * 3, nsub * sizeof(float)) == 0);
    free(sub);
    free(root);

    /* Every layout's length. */
    const struct {
        int32_t layout;
        size_t per_frame;
    } layouts[] = {
        {FLAME_LAYOUT_FEATURES, dim},
        {FLAME_LAYOUT_ROOT_TRANSLATION, 3},
        {FLAME_LAYOUT_LOCAL_QUAT_XYZW, joints * 4u},
        {FLAME_LAYOUT_LOCAL_QUAT_WXYZ, joints * 4u},
        {FLAME_LAYOUT_LOCAL_MATRIX, joints * 9u},
        {FLAME_LAYOUT_LOCAL6D, joints * 6u},
        {FLAME_LAYOUT_GLOBAL_POSITIONS, joints * 3u},
        {FLAME_LAYOUT_GLOBAL_QUAT_XYZW, joints * 4u},
        {FLAME_LAYOUT_GLOBAL_QUAT_WXYZ, joints * 4u},
    };
    for (size_t i = 0; i < sizeof layouts / sizeof layouts[0]; i++) {
        size_t need = 0;
        CHECK_OK(flame_stream_read(b, 5, 7, layouts[i].layout, FLAME_CONVENTION_UNITY, 0, NULL, 0,
                                   &need));
        CHECK(need == 7 * layouts[i].per_frame);
    }
    /* Foot contacts: humanml263's own, smpl24_6d's detected; 4 per frame either way. */
    size_t need = 0;
    CHECK_OK(flame_stream_read(b, 0, 3, FLAME_LAYOUT_FOOT_CONTACTS, 0, 0, NULL, 0, &need));
    CHECK(need == 12);
    /* Zero frames: an empty read, inside the range. */
    need = 99;
    CHECK_OK(flame_stream_read(b, 10, 0, FLAME_LAYOUT_GLOBAL_POSITIONS, 0, 0, NULL, 0, &need));
    CHECK(need == 0);

    /* Flags, layouts and conventions the stream does not know. */
    const int32_t INV = FLAME_STATUS_INVALID_ARGUMENT;
    CHECK_ERROR_MENTIONS(flame_stream_read(b, 0, 1, 1, 0, FLAME_READ_SMOOTH, NULL, 0, &need), INV,
                         "flags");
    CHECK_ERROR_MENTIONS(flame_stream_read(b, 0, 1, 0, 0, FLAME_READ_RAW_SIGNS, NULL, 0, &need),
                         INV, "flags");
    CHECK_ERROR_MENTIONS(flame_stream_read(b, 0, 1, 0, 0, 0x80, NULL, 0, &need), INV, "flags");
    CHECK_ERROR_MENTIONS(flame_stream_read(b, 0, 1, 10, 0, 0, NULL, 0, &need), INV, "layout");
    CHECK_ERROR_MENTIONS(flame_stream_read(b, 0, 1, -1, 0, 0, NULL, 0, &need), INV, "layout");
    CHECK_ERROR_MENTIONS(flame_stream_read(b, 0, 1, INT32_MIN, 0, 0, NULL, 0, &need), INV,
                         "layout");
    CHECK_ERROR_MENTIONS(flame_stream_read(b, 0, 1, 1, 6, 0, NULL, 0, &need), INV, "convention");

    /* Not generated yet, also past the end by one frame and far beyond. */
    const int32_t WS = FLAME_STATUS_WRONG_STATE;
    CHECK_ERROR_MENTIONS(flame_stream_read(b, 0, TIMELINE_FRAMES + 1, 0, 0, 0, NULL, 0, &need), WS,
                         "not generated yet");
    CHECK_ERROR_MENTIONS(flame_stream_read(b, TIMELINE_FRAMES, 1, 6, 0, 0, NULL, 0, &need), WS,
                         "not generated yet");
    CHECK_ERROR_MENTIONS(flame_stream_read(b, UINT64_MAX - 1, UINT32_MAX, 0, 0, 0, NULL, 0, &need),
                         INV, "overflow");
    CHECK_STATUS(flame_stream_read(b, (uint64_t)1 << 40, 1, 0, 0, 0, NULL, 0, &need), WS);

    free(fa);
    free(fb);
    flame_stream_free(a);
    flame_stream_free(b);
}

/* One chunk at a time: its frames become readable when its last step has run. */
static void test_pump_budget(const FlameModel *m) {
    FlameStreamParams p;
    small_params(&p, 1);
    FlameStream *s = new_stream(m, &p);
    CHECK_OK(flame_stream_push(s, "a person walks forward.", 100));
    FlameStreamStatus st;
    st.struct_size = sizeof st;
    CHECK_OK(flame_stream_pump(s, 2, &st));
    CHECK(st.steps == 2 && st.ready == 0 && st.starving == 0);
    size_t n = 0;
    CHECK_ERROR_MENTIONS(flame_stream_read(s, 0, 1, 0, 0, 0, NULL, 0, &n),
                         FLAME_STATUS_WRONG_STATE, "not generated yet");
    CHECK_OK(flame_stream_pump(s, 1, &st));
    CHECK(st.steps == 1 && st.ready == 40);
    CHECK_OK(flame_stream_pump(s, 3, NULL));
    st = status_of(s);
    CHECK(st.ready == 70 && st.steps == 0 && st.starving == 0);
    CHECK_ERROR_MENTIONS(flame_stream_read(s, 60, 11, 0, 0, 0, NULL, 0, &n),
                         FLAME_STATUS_WRONG_STATE, "not generated yet");
    /* pump(0) runs nothing. */
    CHECK_OK(flame_stream_pump(s, 0, &st));
    CHECK(st.steps == 0 && st.ready == 70);

    /* The lookahead: with 20 frames wanted ahead of the playhead, pumping stops once they are
     * ready and goes on when the playhead moves. */
    flame_stream_free(s);
    p.lookahead = 20;
    s = new_stream(m, &p);
    CHECK_OK(flame_stream_push(s, "a person walks forward.", 200));
    CHECK_OK(flame_stream_pump(s, UINT32_MAX, &st));
    CHECK(st.steps == 3 && st.ready == 40 && st.starving == 0);
    CHECK_OK(flame_stream_pump(s, UINT32_MAX, &st));
    CHECK(st.steps == 0 && st.ready == 40);
    CHECK_OK(flame_stream_set_playhead(s, 30));
    CHECK_OK(flame_stream_pump(s, UINT32_MAX, &st));
    CHECK(st.steps == 3 && st.ready == 70 && st.playhead == 30);
    CHECK_ERROR_MENTIONS(flame_stream_set_playhead(s, 71), FLAME_STATUS_INVALID_ARGUMENT,
                         "past the 70 frames");
    CHECK_OK(flame_stream_set_playhead(s, 70));
    flame_stream_free(s);
}

/* ---- the length protocol ----------------------------------------------------------------- */

static void test_length_protocol(const FlameModel *m) {
    FlameStreamParams p;
    small_params(&p, 1);
    FlameStream *s = new_stream(m, &p);
    CHECK_OK(flame_stream_push(s, "a person walks forward.", 40));
    CHECK_OK(flame_stream_pump(s, UINT32_MAX, NULL));

    const uint32_t frames = 6;
    size_t need = 0;
    CHECK_OK(flame_stream_read(s, 2, frames, FLAME_LAYOUT_GLOBAL_POSITIONS, 0, 0, NULL, 0, &need));
    CHECK(need == frames * 24u * 3);
    /* NULL out with any len: still just the length. */
    size_t need2 = 0;
    CHECK_OK(flame_stream_read(s, 2, frames, FLAME_LAYOUT_GLOBAL_POSITIONS, 0, 0, NULL, 1000,
                               &need2));
    CHECK(need2 == need);

    float *buf = (float *)malloc((need + 8) * sizeof(float));
    for (size_t i = 0; i < need + 8; i++) {
        buf[i] = -7.0f;
    }
    size_t got = 0;
    CHECK_ERROR_MENTIONS(flame_stream_read(s, 2, frames, FLAME_LAYOUT_GLOBAL_POSITIONS, 0, 0, buf,
                                           need - 1, &got),
                         FLAME_STATUS_BUFFER_TOO_SMALL, "floats");
    CHECK(got == need);
    int untouched = 1;
    for (size_t i = 0; i < need + 8; i++) {
        untouched &= buf[i] == -7.0f;
    }
    CHECK(untouched);
    got = 0;
    CHECK_STATUS(flame_stream_read(s, 2, frames, FLAME_LAYOUT_GLOBAL_POSITIONS, 0, 0, buf, 0, &got),
                 FLAME_STATUS_BUFFER_TOO_SMALL);
    CHECK(got == need);

    got = 0;
    CHECK_OK(flame_stream_read(s, 2, frames, FLAME_LAYOUT_GLOBAL_POSITIONS, 0, 0, buf, need, &got));
    CHECK(got == need && all_finite(buf, need));
    float *exact = (float *)malloc(need * sizeof(float));
    memcpy(exact, buf, need * sizeof(float));
    for (size_t i = 0; i < need + 8; i++) {
        buf[i] = -7.0f;
    }
    got = 0;
    CHECK_OK(flame_stream_read(s, 2, frames, FLAME_LAYOUT_GLOBAL_POSITIONS, 0, 0, buf, need + 8,
                               &got));
    CHECK(got == need && memcmp(buf, exact, need * sizeof(float)) == 0);
    CHECK(buf[need] == -7.0f && buf[need + 7] == -7.0f);
    free(exact);
    free(buf);
    flame_stream_free(s);
}

/* ---- the window -------------------------------------------------------------------------- */

static void test_window(const FlameModel *m) {
    FlameStreamParams p;
    small_params(&p, 1);
    p.window = 20;
    FlameStream *s = new_stream(m, &p);
    timeline(s);
    CHECK_OK(flame_stream_pump(s, UINT32_MAX, NULL));
    size_t n_before = 0;
    float *before = read_range(s, 70, 45, FLAME_LAYOUT_FEATURES, 0, &n_before);
    CHECK_OK(flame_stream_set_playhead(s, 90));
    FlameStreamStatus st = status_of(s);
    CHECK(st.first_frame == 70 && st.playhead == 90 && st.ready == TIMELINE_FRAMES);
    size_t n = 0;
    CHECK_ERROR_MENTIONS(flame_stream_read(s, 60, 10, FLAME_LAYOUT_ROOT_TRANSLATION, 0, 0, NULL, 0,
                                           &n),
                         FLAME_STATUS_INVALID_ARGUMENT, "were dropped");
    CHECK_ERROR_MENTIONS(flame_stream_read(s, 69, 2, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n),
                         FLAME_STATUS_INVALID_ARGUMENT, "keeps 20 frames behind the playhead 90");
    CHECK_ERROR_MENTIONS(flame_stream_read(s, 0, 0, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n),
                         FLAME_STATUS_INVALID_ARGUMENT, "were dropped");
    /* What is held is as it was. */
    size_t n_after = 0;
    float *after = read_range(s, 70, 45, FLAME_LAYOUT_FEATURES, 0, &n_after);
    CHECK(same_bits(before, n_before, after, n_after));
    free(before);
    free(after);
    flame_stream_free(s);
}

/* ---- interrupt and bad segments ---------------------------------------------------------- */

static void test_interrupt(const FlameModel *m) {
    FlameStreamParams p;
    small_params(&p, 1);
    /* Between chunks: the current segment ends at the 40 frames ready. */
    FlameStream *s = new_stream(m, &p);
    CHECK_OK(flame_stream_push(s, "a person walks forward.", 100));
    CHECK_OK(flame_stream_push(s, "a person sits down.", 100));
    CHECK_OK(flame_stream_pump(s, 3, NULL));
    CHECK(status_of(s).ready == 40);
    CHECK_OK(flame_stream_interrupt(s, "a person waves.", 20));
    CHECK_OK(flame_stream_pump(s, UINT32_MAX, NULL));
    FlameStreamStatus st = status_of(s);
    CHECK(st.ready == 60 && st.starving == 1);
    flame_stream_free(s);

    /* With a chunk in flight: it finishes, then the new segment starts. */
    s = new_stream(m, &p);
    CHECK_OK(flame_stream_push(s, "a person walks forward.", 100));
    CHECK_OK(flame_stream_pump(s, 1, NULL));
    CHECK_OK(flame_stream_interrupt(s, "a person waves.", 20));
    CHECK_OK(flame_stream_pump(s, UINT32_MAX, NULL));
    st = status_of(s);
    CHECK(st.ready == 60 && st.starving == 1);

    /* Zero frames. */
    CHECK_ERROR_MENTIONS(flame_stream_push(s, "a person jumps.", 0), FLAME_STATUS_INVALID_ARGUMENT,
                         "at least one frame");
    CHECK_ERROR_MENTIONS(flame_stream_interrupt(s, "a person jumps.", 0),
                         FLAME_STATUS_INVALID_ARGUMENT, "at least one frame");
    /* Nothing was queued by them. */
    CHECK_OK(flame_stream_pump(s, UINT32_MAX, &st));
    CHECK(st.steps == 0 && st.ready == 60);
    /* An interrupt on an empty timeline is a push. */
    flame_stream_free(s);
    s = new_stream(m, &p);
    CHECK_OK(flame_stream_interrupt(s, "a person waves.", 15));
    CHECK_OK(flame_stream_pump(s, UINT32_MAX, &st));
    CHECK(st.steps == 3 && st.ready == 15);
    flame_stream_free(s);
}

/* ---- creation errors --------------------------------------------------------------------- */

static void test_bad_params(const FlameModel *m, const FlameModel *latent) {
    const int32_t INV = FLAME_STATUS_INVALID_ARGUMENT;
    FlameModelInfo info;
    info.struct_size = sizeof info;
    CHECK_OK(flame_model_info(m, &info));
    FlameStreamParams p;
    FlameStream *s = NULL;

    small_params(&p, 1);
    CHECK_ERROR_MENTIONS(flame_stream_new(latent, &p, &s), INV, "gradient");
    CHECK(s == NULL);

    small_params(&p, 1);
    p.chunk = info.max_frames + 1;
    CHECK_ERROR_MENTIONS(flame_stream_new(m, &p, &s), INV, "exceeds");
    p.chunk = UINT32_MAX;
    CHECK_ERROR_MENTIONS(flame_stream_new(m, &p, &s), INV, "exceeds");
    p.chunk = info.max_frames; /* the largest is fine */
    s = new_stream(m, &p);
    flame_stream_free(s);
    s = NULL;

    small_params(&p, 1);
    p.overlap = 40;
    CHECK_ERROR_MENTIONS(flame_stream_new(m, &p, &s), INV, "overlap");
    p.overlap = 41;
    CHECK_ERROR_MENTIONS(flame_stream_new(m, &p, &s), INV, "overlap");
    p.overlap = UINT32_MAX;
    CHECK_ERROR_MENTIONS(flame_stream_new(m, &p, &s), INV, "overlap");
    p.overlap = 39; /* the largest is fine */
    s = new_stream(m, &p);
    flame_stream_free(s);
    s = NULL;

    small_params(&p, FLAME_MAX_THREADS + 1);
    CHECK_ERROR_MENTIONS(flame_stream_new(m, &p, &s), INV, "threads");
    small_params(&p, UINT32_MAX);
    CHECK_ERROR_MENTIONS(flame_stream_new(m, &p, &s), INV, "threads");

    small_params(&p, 1);
    p.sampler = 99;
    CHECK_ERROR_MENTIONS(flame_stream_new(m, &p, &s), INV, "sampler");
    small_params(&p, 1);
    p.guidance = NAN;
    CHECK_ERROR_MENTIONS(flame_stream_new(m, &p, &s), INV, "guidance");
    small_params(&p, 1);
    p.steps = UINT32_MAX;
    CHECK_STATUS(flame_stream_new(m, &p, &s), INV);
    CHECK(s == NULL);
}

/* ---- one thread at a time ---------------------------------------------------------------- */

struct pumper {
    FlameStream *stream;
    atomic_int stop;
    atomic_int calls;
    int failures; /* statuses other than OK and WRONG_STATE "in use by another thread" */
};

static void *pump_worker(void *arg) {
    struct pumper *w = (struct pumper *)arg;
    while (!atomic_load(&w->stop)) {
        /* The main thread's status calls may hold the stream when a pump starts: that pump
         * is WRONG_STATE too (flame_last_error is per thread). */
        FlameStatus r = flame_stream_pump(w->stream, 1, NULL);
        if (r != FLAME_STATUS_OK && !(r == FLAME_STATUS_WRONG_STATE &&
                                      strstr(flame_last_error(), "in use by another thread"))) {
            w->failures++;
        }
        atomic_fetch_add(&w->calls, 1);
    }
    return NULL;
}

static void test_busy(const FlameModel *m) {
    FlameStreamParams p;
    small_params(&p, 1);
    p.chunk = 160;
    p.lookahead = 1000000;
    p.window = 1000000;
    struct pumper w;
    w.stream = new_stream(m, &p);
    atomic_init(&w.stop, 0);
    atomic_init(&w.calls, 0);
    w.failures = 0;
    CHECK_OK(flame_stream_push(w.stream, "a person walks forward.", 1000000));
    pthread_t t;
    pthread_create(&t, NULL, pump_worker, &w);
    int busy = 0, other = 0;
    char msg[512] = "";
    double t0 = now_seconds();
    while (!busy && now_seconds() - t0 < 60.0) {
        FlameStreamStatus st;
        st.struct_size = sizeof st;
        FlameStatus r = flame_stream_status(w.stream, &st);
        if (r == FLAME_STATUS_WRONG_STATE) {
            busy = 1;
            check_copy_last_error(msg, sizeof msg);
        } else if (r != FLAME_STATUS_OK) {
            other++;
        }
        /* Let the worker run: under valgrind, whose threads take turns on one lock, a thread
         * that polls without yielding can keep the worker from ever starting a pump. */
        sched_yield();
    }
    atomic_store(&w.stop, 1);
    pthread_join(t, NULL);
    CHECK(busy);
    CHECK(strstr(msg, "in use by another thread") != NULL);
    CHECK(other == 0);
    CHECK(w.failures == 0);
    CHECK(atomic_load(&w.calls) > 0);
    flame_stream_free(w.stream);
}

/* ---- cancel ------------------------------------------------------------------------------ */

struct canceller {
    const FlameStream *stream;
    atomic_int stop;
};

static void *cancel_worker(void *arg) {
    struct canceller *c = (struct canceller *)arg;
    for (int i = 0; i < 30 && !atomic_load(&c->stop); i++) {
        struct timespec ts = {0, 200000};
        nanosleep(&ts, NULL);
        flame_stream_cancel(c->stream);
    }
    return NULL;
}

static void test_cancel(const FlameModel *m, const char *name) {
    FlameStreamParams p;
    small_params(&p, 1);
    FlameStream *want = new_stream(m, &p);
    timeline(want);
    run(want, UINT32_MAX);

    FlameStream *s = new_stream(m, &p);
    timeline(s);
    CHECK_STATUS(flame_stream_cancel(NULL), FLAME_STATUS_INVALID_ARGUMENT);
    FlameStreamStatus st;
    st.struct_size = sizeof st;
    CHECK_OK(flame_stream_pump(s, 4, &st));
    CHECK(st.ready == 40);
    CHECK_OK(flame_stream_cancel(s));
    CHECK_STATUS(flame_stream_pump(s, UINT32_MAX, &st), FLAME_STATUS_CANCELLED);
    CHECK(status_of(s).ready == 40);

    struct canceller c;
    c.stream = s;
    atomic_init(&c.stop, 0);
    pthread_t t;
    pthread_create(&t, NULL, cancel_worker, &c);
    int cancelled = 0, calls = 0, other = 0;
    for (;;) {
        st.struct_size = sizeof st;
        FlameStatus r = flame_stream_pump(s, 1, &st);
        calls++;
        if (r == FLAME_STATUS_CANCELLED) {
            cancelled++;
        } else if (r != FLAME_STATUS_OK) {
            other++;
            break;
        } else if (st.steps == 0 || calls > 10000) {
            break;
        }
    }
    atomic_store(&c.stop, 1);
    pthread_join(t, NULL);
    CHECK(other == 0);
    /* A cancel raised after the last pump would cancel the next one: drain it. */
    while (flame_stream_pump(s, 1, &st) == FLAME_STATUS_CANCELLED) {
    }
    size_t na = 0, nb = 0;
    float *a = read_range(s, 0, TIMELINE_FRAMES, FLAME_LAYOUT_FEATURES, 0, &na);
    float *b = read_range(want, 0, TIMELINE_FRAMES, FLAME_LAYOUT_FEATURES, 0, &nb);
    int same = a && b && same_bits(a, na, b, nb);
    if (!same) {
        fprintf(stderr, "  %s: %d cancels changed the frames\n", name, cancelled);
    }
    CHECK(same);
    free(a);
    free(b);
    flame_stream_free(s);
    flame_stream_free(want);
}

/* ---- segments with part texts ------------------------------------------------------------ */

static FlameStage stage_of(const char *text, uint32_t frames) {
    FlameStage st;
    memset(&st, 0, sizeof st);
    st.struct_size = sizeof st;
    st.text = text;
    st.frames = frames;
    return st;
}

static void test_stages(const FlameModel *flame, const FlameModel *fmg) {
    const int32_t INV = FLAME_STATUS_INVALID_ARGUMENT;
    FlameStreamParams p;
    small_params(&p, 1);
    FlameStream *s = new_stream(flame, &p);
    FlameStage st = stage_of("a person walks.", 30);
    CHECK_STATUS(flame_stream_push_stage(NULL, &st), INV);
    CHECK_STATUS(flame_stream_push_stage(s, NULL), INV);
    CHECK_STATUS(flame_stream_interrupt_stage(NULL, &st), INV);
    CHECK_STATUS(flame_stream_interrupt_stage(s, NULL), INV);
    st.struct_size = 4;
    CHECK_ERROR_MENTIONS(flame_stream_push_stage(s, &st), INV, "struct_size");
    st = stage_of(NULL, 30);
    CHECK_ERROR_MENTIONS(flame_stream_push_stage(s, &st), INV, "stage.text");
    st = stage_of("a person walks.", 0);
    CHECK_ERROR_MENTIONS(flame_stream_push_stage(s, &st), INV, "frame");
    /* An empty part text follows the whole-body text: a plain segment for FLAME. */
    st = stage_of("a person walks.", 30);
    st.head = "";
    CHECK_OK(flame_stream_push_stage(s, &st));
    FlameStreamStatus ss;
    ss.struct_size = sizeof ss;
    CHECK_OK(flame_stream_pump(s, UINT32_MAX, &ss));
    CHECK(ss.ready == 30);
    st.left_arm = "the left arm waves.";
    CHECK_OK(flame_stream_interrupt_stage(s, &st));
    CHECK_ERROR_MENTIONS(flame_stream_pump(s, UINT32_MAX, &ss), INV, "part");
    flame_stream_free(s);

    /* FineMoGen: every part given the segment's own text = the plain segment, bit for bit;
     * another right-arm text changes the second segment only. */
    p.chunk = 30;
    p.overlap = 8;
    const char *walk = "a person walks forward.", *wave = "a person waves.";
    float *got[3] = {NULL, NULL, NULL};
    size_t n[3] = {0, 0, 0};
    for (int k = 0; k < 3; k++) {
        s = new_stream(fmg, &p);
        CHECK_OK(flame_stream_push(s, walk, 20));
        FlameStage w = stage_of(wave, 30);
        if (k == 1) {
            w.head = w.stem = w.left_arm = w.right_arm = w.left_leg = w.right_leg = w.pelvis =
                wave;
        } else if (k == 2) {
            w.right_arm = "the right arm swings up and down.";
        }
        CHECK_OK(flame_stream_push_stage(s, &w));
        run(s, UINT32_MAX);
        got[k] = read_range(s, 0, 50, FLAME_LAYOUT_FEATURES, 0, &n[k]);
        flame_stream_free(s);
    }
    CHECK(got[0] && got[1] && same_bits(got[0], n[0], got[1], n[1]));
    CHECK(got[0] && got[2] && n[0] == n[2] && n[0] % 50 == 0);
    if (got[0] && got[2] && n[0] == n[2]) {
        size_t first = n[0] / 50 * 20;
        CHECK(memcmp(got[0], got[2], first * sizeof(float)) == 0);
        CHECK(memcmp(got[0] + first, got[2] + first, (n[0] - first) * sizeof(float)) != 0);
    }
    for (int k = 0; k < 3; k++) {
        free(got[k]);
    }
}

/* ---- a latent model ---------------------------------------------------------------------- */

static void test_mola(const FlameModel *mola) {
    FlameStreamParams p;
    small_params(&p, 1);
    p.chunk = 32;
    p.overlap = 8;
    float *got[2] = {NULL, NULL};
    size_t n[2] = {0, 0};
    for (int k = 0; k < 2; k++) {
        p.threads = (uint32_t)k + 1;
        FlameStream *s = new_stream(mola, &p);
        timeline(s);
        run(s, k == 0 ? 1 : UINT32_MAX);
        CHECK(status_of(s).ready == TIMELINE_FRAMES);
        got[k] = read_range(s, 0, TIMELINE_FRAMES, FLAME_LAYOUT_GLOBAL_POSITIONS,
                            FLAME_CONVENTION_NATIVE, &n[k]);
        flame_stream_free(s);
    }
    CHECK(got[0] && got[1] && same_bits(got[0], n[0], got[1], n[1]));
    CHECK(got[0] && all_finite(got[0], n[0]));
    free(got[0]);
    free(got[1]);
}

/* ---- closing into a loop ----------------------------------------------------------------- */

/* tests/cycle.rs's looped streams: chunks of 60 frames keeping 20, 3 steps, seed 9, one thread;
 * "a person walks" for 70 frames, then "a person jumps" for 30. */
#define LOOP_TIMELINE 100
#define LOOP_BRIDGE 20
static FlameStream *loop_stream(const FlameModel *m) {
    FlameStreamParams p;
    flame_stream_params_default(&p);
    p.chunk = 60;
    p.overlap = 20;
    p.lookahead = 1000;
    p.window = 1000;
    p.steps = 3;
    p.seed = 9;
    p.threads = 1;
    FlameStream *s = new_stream(m, &p);
    CHECK_OK(flame_stream_push(s, "a person walks", 70));
    CHECK_OK(flame_stream_push(s, "a person jumps", 30));
    return s;
}

/* Pumps to the end; returns the steps run. */
static uint32_t pump_all(FlameStream *s) {
    uint32_t steps = 0;
    for (int calls = 0; calls < 10000; calls++) {
        FlameStreamStatus st;
        st.struct_size = sizeof st;
        if (!CHECK_OK(flame_stream_pump(s, 1, &st)) || st.steps == 0) {
            break;
        }
        steps += st.steps;
    }
    return steps;
}

static void test_close_looped(const FlameModel *m, const FlameModel *mola) {
    const int32_t INV = FLAME_STATUS_INVALID_ARGUMENT, WS = FLAME_STATUS_WRONG_STATE;
    FlameModelInfo info;
    info.struct_size = sizeof info;
    CHECK_OK(flame_model_info(m, &info));
    const uint32_t dim = info.feature_dim, joints = info.joint_count;

    FlameStream *plain = loop_stream(m), *looped = loop_stream(m);
    CHECK_OK(flame_stream_close(plain));
    CHECK_OK(flame_stream_close_looped(looped, LOOP_BRIDGE));
    const uint32_t plain_steps = pump_all(plain), looped_steps = pump_all(looped);
    FlameStreamStatus ps = status_of(plain), ls = status_of(looped);
    CHECK(ps.ready == LOOP_TIMELINE && ps.starving == 1);
    CHECK(ls.ready == LOOP_TIMELINE + LOOP_BRIDGE && ls.starving == 1 && ls.first_frame == 0);
    /* The bridge is two chunks' steps: a probe and the edit that keeps both ends. */
    CHECK(looped_steps == plain_steps + 2 * 3);
    if (looped_steps != plain_steps + 2 * 3) {
        fprintf(stderr, "     (plain %u steps, looped %u)\n", plain_steps, looped_steps);
    }
    size_t n = 0;
    CHECK_ERROR_MENTIONS(flame_stream_read(looped, LOOP_TIMELINE + LOOP_BRIDGE, 1,
                                           FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &n),
                         WS, "not generated yet");

    /* The bridge only appends: the timeline's frames are the plain close's, bit for bit. */
    size_t np = 0, nl = 0;
    float *fp = read_range(plain, 0, LOOP_TIMELINE, FLAME_LAYOUT_FEATURES, 0, &np);
    float *fl = read_range(looped, 0, LOOP_TIMELINE + LOOP_BRIDGE, FLAME_LAYOUT_FEATURES, 0, &nl);
    CHECK(np == (size_t)LOOP_TIMELINE * dim && nl == (size_t)(LOOP_TIMELINE + LOOP_BRIDGE) * dim);
    CHECK(fp && fl && nl >= np && memcmp(fp, fl, np * sizeof(float)) == 0);
    CHECK(fl && all_finite(fl, nl));
    free(fp);
    free(fl);

    /* Cleaned reads (the default cleanup: feet locked, on the ground) settle every frame of
     * the completed loop, the bridge's too. */
    FlameCleanupParams c;
    CHECK_OK(flame_cleanup_params_default(&c));
    CHECK(c.feet == FLAME_FEET_LOCK && c.fps == 0.0f);
    size_t need = 0;
    CHECK_OK(flame_stream_read_cleaned(looped, 0, LOOP_TIMELINE + LOOP_BRIDGE,
                                       FLAME_LAYOUT_GLOBAL_POSITIONS, FLAME_CONVENTION_GLTF, &c,
                                       NULL, 0, &need));
    CHECK(need == (size_t)(LOOP_TIMELINE + LOOP_BRIDGE) * joints * 3);
    float *clean = (float *)malloc(need * sizeof(float) + 1);
    CHECK_OK(flame_stream_read_cleaned(looped, 0, LOOP_TIMELINE + LOOP_BRIDGE,
                                       FLAME_LAYOUT_GLOBAL_POSITIONS, FLAME_CONVENTION_GLTF, &c,
                                       clean, need, &n));
    CHECK(n == need && all_finite(clean, n));
    /* The last frame alone: settled, the same values. */
    float last[24 * 3];
    CHECK(joints <= 24);
    CHECK_OK(flame_stream_read_cleaned(looped, LOOP_TIMELINE + LOOP_BRIDGE - 1, 1,
                                       FLAME_LAYOUT_GLOBAL_POSITIONS, FLAME_CONVENTION_GLTF, &c,
                                       last, sizeof last / sizeof last[0], &n));
    CHECK(n == joints * 3u && memcmp(last, clean + need - n, n * sizeof(float)) == 0);
    free(clean);
    flame_stream_free(plain);
    flame_stream_free(looped);

    /* Refusals. No segment yet: nothing to loop. */
    FlameStreamParams p;
    flame_stream_params_default(&p);
    p.chunk = 60;
    p.overlap = 20;
    p.steps = 3;
    p.threads = 1;
    FlameStream *s = new_stream(m, &p);
    CHECK_ERROR_MENTIONS(flame_stream_close_looped(s, LOOP_BRIDGE), WS, "push a segment");
    CHECK_ERROR_MENTIONS(flame_stream_close_looped(NULL, LOOP_BRIDGE), INV, "stream");
    CHECK_OK(flame_stream_push(s, "a person walks", 40));
    /* Shorter than 1 s (two leads of 0.5 s), longer than the model's frames allow: named,
     * and the stream stays open. */
    CHECK_ERROR_MENTIONS(flame_stream_close_looped(s, 12), INV, "bridge of 12 frames");
    CHECK_ERROR_MENTIONS(flame_stream_close_looped(s, 0), INV, "bridge of 0 frames");
    const uint32_t longest = info.max_frames - 20 - 10; /* overlap + bridge + lead <= max */
    char name[64];
    snprintf(name, sizeof name, "bridge of %u frames", longest + 1);
    CHECK_ERROR_MENTIONS(flame_stream_close_looped(s, longest + 1), INV, name);
    snprintf(name, sizeof name, "at most the model's %u", info.max_frames);
    CHECK_ERROR_MENTIONS(flame_stream_close_looped(s, longest + 1), INV, name);
    CHECK_ERROR_MENTIONS(flame_stream_close_looped(s, UINT32_MAX), INV, "bridge of");
    CHECK_OK(flame_stream_push(s, "a person jumps", 20));
    CHECK_OK(flame_stream_close_looped(s, longest)); /* the longest is fine */
    /* Closed: a second close, a push. */
    CHECK_ERROR_MENTIONS(flame_stream_close_looped(s, LOOP_BRIDGE), WS, "closed");
    CHECK_ERROR_MENTIONS(flame_stream_push(s, "a person waves", 20), WS, "closed");
    flame_stream_free(s);
    /* A plain close, then a looped one. */
    s = new_stream(m, &p);
    CHECK_OK(flame_stream_push(s, "a person walks", 40));
    CHECK_OK(flame_stream_close(s));
    CHECK_ERROR_MENTIONS(flame_stream_close_looped(s, LOOP_BRIDGE), WS, "closed");
    flame_stream_free(s);

    /* A latent model (MoLA streams through position targets): a bridge keeps frames at both
     * ends, which a sampled latent cannot. */
    p.chunk = 32;
    p.overlap = 8;
    s = new_stream(mola, &p);
    CHECK_OK(flame_stream_push(s, "a person walks", 40));
    CHECK_ERROR_MENTIONS(flame_stream_close_looped(s, LOOP_BRIDGE), INV, "samples a latent");
    flame_stream_free(s);
}

int main(int argc, char **argv) {
    if (argc < 2) {
        fprintf(stderr, "usage: %s FIXTURES_DIR\n", argv[0]);
        return 2;
    }
    snprintf(fixtures, sizeof fixtures, "%s", argv[1]);
    FlameModel *flame = load("flame_tiny");
    FlameModel *mdm = load("mdm_tiny");
    FlameModel *mld = load("mld_tiny");
    FlameModel *mola = load("mola_tiny");
    FlameModel *fmg = load("finemogen_tiny");
    if (!flame || !mdm || !mld || !mola || !fmg) {
        check_summary();
        return 1;
    }
    test_null_checks(flame);
    test_defaults(flame);
    test_round_trip(flame, "flame_tiny");
    test_round_trip(mdm, "mdm_tiny");
    test_pump_budget(flame);
    test_length_protocol(flame);
    test_window(flame);
    test_window(mdm);
    test_interrupt(flame);
    test_bad_params(flame, mld);
    test_bad_params(mdm, mld);
    test_busy(flame);
    test_cancel(flame, "flame_tiny");
    test_cancel(mdm, "mdm_tiny");
    test_stages(flame, fmg);
    test_mola(mola);
    test_close_looped(flame, mola);
    flame_model_free(mola);
    flame_model_free(fmg);
    flame_model_free(flame);
    flame_model_free(mdm);
    flame_model_free(mld);
    return check_summary();
}
