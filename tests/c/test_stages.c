/*
 * Prompts per time stage through the C ABI: flame_session_set_prompt_stages and FlameStage.
 *
 * usage: test_stages FIXTURES_DIR [FINEMOGEN_REFERENCE_NPY]
 *   FIXTURES_DIR             tests/fixtures: mdm_tiny, flame_tiny, motionfm_tiny, mola_tiny, and
 *                            finemogen_tiny when present (its checks are skipped otherwise)
 *   FINEMOGEN_REFERENCE_NPY  `flame generate` on finemogen_tiny with the stages of
 *                            FMG_STAGE_A@24 and FMG_STAGE_B@31 (tests/c/run.sh writes it)
 *
 * - a family that takes one prompt (MDM): one stage is the plain prompt, bit for bit (NULL or
 *   empty part texts alike, a newer caller's larger struct too); two stages or a part text are
 *   INVALID_ARGUMENT naming what it takes, and so on every such fixture;
 * - every malformed call is INVALID_ARGUMENT naming the field, and changes nothing;
 * - FineMoGen: 24 + 31 frames on a 55-frame session sample 2 x 31 rows, read back as 55
 *   finite frames equal to the CLI's; stage frame counts are fixed once stepping started
 *   (WRONG_STATE) and free again after a reset.
 */
#define _POSIX_C_SOURCE 200809L

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "flame.h"

#include "check.h"
#include "util.h"

#define INV FLAME_STATUS_INVALID_ARGUMENT
#define COUNT(a) (sizeof(a) / sizeof((a)[0]))

#define MDM_PROMPT "a person walks forward and waves."
#define MDM_FRAMES 16
#define MDM_STEPS 3
#define FMG_STAGE_A "a person walks forward"
#define FMG_STAGE_B "a person jumps"
#define FMG_FRAMES 55
#define FMG_STEPS 4

static char g_dir[4096];

static FlameModel *load(const char *file) {
    char path[4200];
    snprintf(path, sizeof path, "%s/%s", g_dir, file);
    FlameModel *m = NULL;
    if (flame_model_load(path, NULL, &m) != FLAME_STATUS_OK) {
        fprintf(stderr, "cannot load %s: %s\n", path, flame_last_error());
        return NULL;
    }
    return m;
}

static FlameSession *new_session_with(const FlameModel *m, uint32_t frames, uint32_t steps,
                                      uint64_t seed, int32_t sampler) {
    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = frames;
    p.steps = steps;
    p.sampler = sampler;
    p.seed = seed;
    p.threads = 1;
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(m, &p, &s));
    return s;
}

/* DDIM: every fixture here but the flow model's sampler. */
static FlameSession *new_session(const FlameModel *m, uint32_t frames, uint32_t steps,
                                 uint64_t seed) {
    return new_session_with(m, frames, steps, seed, FLAME_SAMPLER_DDIM);
}

/* A stage of `frames` frames doing `text`, no part texts. */
static FlameStage stage(const char *text, uint32_t frames) {
    FlameStage st;
    memset(&st, 0, sizeof st);
    st.struct_size = sizeof st;
    st.frames = frames;
    st.text = text;
    return st;
}

/* Every remaining step, then the final features (malloc'd; NULL on error). */
static float *finish(FlameSession *s, size_t *n) {
    uint32_t left = 1;
    FlameStatus st = FLAME_STATUS_OK;
    while (st == FLAME_STATUS_OK && left > 0) {
        st = flame_session_step(s, &left);
    }
    CHECK_OK(st);
    if (st != FLAME_STATUS_OK) {
        return NULL;
    }
    return read_features(s, FLAME_WHICH_SAMPLE, n, &st);
}

/* The MDM generation with a plain prompt: what one stage must reproduce. */
static float *mdm_plain(const FlameModel *m, size_t *n) {
    FlameSession *s = new_session(m, MDM_FRAMES, MDM_STEPS, 5);
    CHECK_OK(flame_session_set_prompt(s, MDM_PROMPT));
    float *x = finish(s, n);
    flame_session_free(s);
    return x;
}

/* The same generation with `count` stages given as they are (malloc'd result; NULL if
 * refused). */
static float *mdm_staged(const FlameModel *m, const FlameStage *stages, size_t count,
                         size_t *n) {
    FlameSession *s = new_session(m, MDM_FRAMES, MDM_STEPS, 5);
    float *x = NULL;
    if (CHECK_OK(flame_session_set_prompt_stages(s, stages, count))) {
        uint32_t rows = 0, dim = 0;
        CHECK_OK(flame_session_sample_shape(s, &rows, &dim));
        CHECK(rows == MDM_FRAMES && dim == 263);
        x = finish(s, n);
    }
    flame_session_free(s);
    return x;
}

/* ---- one stage = the plain prompt --------------------------------------------------------- */

static void test_one_stage_is_the_prompt(const FlameModel *m) {
    size_t n_plain = 0, n = 0;
    float *plain = mdm_plain(m, &n_plain);
    CHECK(plain && n_plain == (size_t)MDM_FRAMES * 263);

    FlameStage one = stage(MDM_PROMPT, MDM_FRAMES);
    float *x = mdm_staged(m, &one, 1, &n);
    CHECK(same_bits(x, n, plain, n_plain));
    free(x);

    /* Empty part texts (and blank ones) mean "the part follows the stage text": no parts. */
    FlameStage empty = one;
    empty.head = "";
    empty.stem = "";
    empty.left_arm = "";
    empty.right_arm = " ";
    empty.left_leg = "";
    empty.right_leg = "";
    empty.pelvis = "\t";
    x = mdm_staged(m, &empty, 1, &n);
    CHECK(same_bits(x, n, plain, n_plain));
    free(x);

    /* A caller built against a newer header: a larger struct, its extra fields unknown here. */
    struct {
        FlameStage stage;
        const char *future_text;
        uint64_t future_count;
    } newer[1];
    memset(newer, 0xA5, sizeof newer);
    newer[0].stage = one;
    newer[0].stage.struct_size = sizeof newer[0];
    CHECK(sizeof newer[0] > sizeof(FlameStage));
    x = mdm_staged(m, &newer[0].stage, 1, &n);
    CHECK(same_bits(x, n, plain, n_plain));
    free(x);

    /* Between steps, as a prompt may change: the same as set_prompt with that text. */
    FlameSession *a = new_session(m, MDM_FRAMES, MDM_STEPS, 5);
    FlameSession *b = new_session(m, MDM_FRAMES, MDM_STEPS, 5);
    CHECK_OK(flame_session_set_prompt(a, MDM_PROMPT));
    CHECK_OK(flame_session_set_prompt(b, MDM_PROMPT));
    CHECK_OK(flame_session_step(a, NULL));
    CHECK_OK(flame_session_step(b, NULL));
    FlameStage other = stage("a person jumps", MDM_FRAMES);
    CHECK_OK(flame_session_set_prompt(a, "a person jumps"));
    CHECK_OK(flame_session_set_prompt_stages(b, &other, 1));
    size_t na = 0, nb = 0;
    float *xa = finish(a, &na), *xb = finish(b, &nb);
    CHECK(same_bits(xa, na, xb, nb));
    CHECK(!same_bits(xa, na, plain, n_plain));
    free(xa);
    free(xb);
    flame_session_free(a);
    flame_session_free(b);
    free(plain);
}

/* ---- families that take one prompt refuse more -------------------------------------------- */

static void test_refusals(const FlameModel *m, const char *name, uint32_t frames) {
    FlameSession *s = new_session_with(m, frames, 2, 1, FLAME_SAMPLER_DEFAULT);
    FlameStage two[2] = {stage("a person walks", frames / 2),
                         stage("a person jumps", frames - frames / 2)};
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, two, 2), INV,
                         "a single stage without part texts");
    char arch[64];
    snprintf(arch, sizeof arch, "this %s model", name);
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, two, 2), INV, arch);
    FlameStage part = stage("a person walks", frames);
    part.left_arm = "waves";
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, &part, 1), INV,
                         "a single stage without part texts");
    /* Refused: still no prompt. */
    CHECK_STATUS(flame_session_step(s, NULL), FLAME_STATUS_WRONG_STATE);
    flame_session_free(s);
}

/* ---- malformed calls ---------------------------------------------------------------------- */

static void test_errors(const FlameModel *m) {
    FlameStage one = stage(MDM_PROMPT, MDM_FRAMES);
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(NULL, &one, 1), INV, "session");

    FlameSession *s = new_session(m, MDM_FRAMES, MDM_STEPS, 5);
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, &one, 0), INV, "0 stages");
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, NULL, 1), INV, "`stages[0]` is NULL");
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, NULL, 0), INV, "0 stages");
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, &one, 1025), INV, "1025 stages");

    /* struct_size: smaller than the struct, or a size no array of it can have. */
    uint32_t sizes[] = {0, 8, (uint32_t)sizeof one - 1, (uint32_t)sizeof one + 1,
                        (uint32_t)sizeof one + 4, UINT32_MAX};
    for (size_t i = 0; i < COUNT(sizes); i++) {
        FlameStage bad = one;
        bad.struct_size = sizes[i];
        CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, &bad, 1), INV, "struct_size");
    }
    FlameStage mixed[2] = {stage("a", 8), stage("b", 8)};
    mixed[1].struct_size = 0;
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, mixed, 2), INV,
                         "stages[1].struct_size is 0");

    /* Texts: NULL, empty or blank, not UTF-8; a part text not UTF-8. */
    FlameStage text = one;
    text.text = NULL;
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, &text, 1), INV,
                         "`stages[0].text` is NULL");
    text.text = "";
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, &text, 1), INV, "stage 0 has no text");
    text.text = "  ";
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, &text, 1), INV, "stage 0 has no text");
    text.text = "caf\xC3";
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, &text, 1), INV,
                         "`stages[0].text` is not valid UTF-8");
    FlameStage bad_part = one;
    bad_part.pelvis = "\xFF";
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, &bad_part, 1), INV,
                         "`stages[0].pelvis` is not valid UTF-8");

    /* Frames: a stage of none, a sum other than the session's (either way), an overflow. */
    FlameStage frames[2] = {stage("a person walks", 0), stage("a person jumps", MDM_FRAMES)};
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, frames, 2), INV, "stage 0 has 0 frames");
    FlameStage short_one = stage(MDM_PROMPT, MDM_FRAMES - 1);
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, &short_one, 1), INV,
                         "the stages cover 15 frames, the session has 16");
    FlameStage long_one = stage(MDM_PROMPT, MDM_FRAMES + 1);
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, &long_one, 1), INV, "add up");
    FlameStage huge[2] = {stage("a", UINT32_MAX), stage("b", UINT32_MAX)};
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, huge, 2), INV, "add up");

    /* None of that changed the session: no prompt yet. Then a failed call keeps the prompt. */
    CHECK_STATUS(flame_session_step(s, NULL), FLAME_STATUS_WRONG_STATE);
    CHECK_OK(flame_session_set_prompt(s, MDM_PROMPT));
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, &short_one, 1), INV, "add up");
    size_t n = 0, n_plain = 0;
    float *x = finish(s, &n);
    float *plain = mdm_plain(m, &n_plain);
    CHECK(same_bits(x, n, plain, n_plain));
    free(x);
    free(plain);
    flame_session_free(s);
}

/* ---- FineMoGen: composed stages ----------------------------------------------------------- */

static int all_finite(const float *x, size_t n) {
    for (size_t i = 0; i < n; i++) {
        if (!isfinite(x[i])) {
            return 0;
        }
    }
    return 1;
}

static void test_finemogen(const FlameModel *m, const char *reference_npy) {
    FlameSession *s = new_session(m, FMG_FRAMES, FMG_STEPS, 1);
    uint32_t rows = 0, dim = 0;
    CHECK_OK(flame_session_sample_shape(s, &rows, &dim));
    CHECK(rows == FMG_FRAMES && dim == 263);
    FlameStage stages[2] = {stage(FMG_STAGE_A, 24), stage(FMG_STAGE_B, 31)};
    CHECK_OK(flame_session_set_prompt_stages(s, stages, 2));
    /* The sample is laid out per stage, each padded to the longest. */
    CHECK_OK(flame_session_sample_shape(s, &rows, &dim));
    CHECK(rows == 2 * 31 && dim == 263);
    size_t n = 0;
    float *x = finish(s, &n);
    uint32_t frames = 0;
    CHECK_OK(flame_session_read_frames(s, FLAME_WHICH_SAMPLE, &frames));
    CHECK(frames == FMG_FRAMES);
    CHECK(x && n == (size_t)FMG_FRAMES * 263 && all_finite(x, n));
    size_t pos_len = 0;
    CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_POSITIONS, 0, 0, NULL,
                                0, &pos_len));
    CHECK(pos_len == (size_t)FMG_FRAMES * 22 * 3);

    /* The CLI's --stage output for the same stages and settings, bit for bit. */
    if (reference_npy) {
        size_t r = 0, c = 0;
        float *ref = read_npy_f32(reference_npy, &r, &c);
        CHECK(ref && r == FMG_FRAMES && c == 263);
        CHECK(same_bits(x, n, ref, r * c));
        free(ref);
    } else {
        printf("no FineMoGen CLI reference given: not compared\n");
    }

    /* Part texts change the motion; empty ones are no part texts. */
    FlameStage parts[2] = {stages[0], stages[1]};
    parts[0].head = "";
    parts[1].left_arm = "";
    parts[1].pelvis = "";
    CHECK_OK(flame_session_set_prompt_stages(s, parts, 2));
    CHECK_OK(flame_session_reset(s));
    size_t ne = 0;
    float *empty = finish(s, &ne);
    CHECK(same_bits(empty, ne, x, n));
    free(empty);
    parts[1].left_arm = "raises the left arm";
    parts[0].head = "looks to the right";
    CHECK_OK(flame_session_set_prompt_stages(s, parts, 2));
    CHECK_OK(flame_session_reset(s));
    size_t np = 0;
    float *with_parts = finish(s, &np);
    CHECK(with_parts && np == n && all_finite(with_parts, np) && !same_bits(with_parts, np, x, n));
    free(with_parts);

    /* Once stepping started: the same frame counts may take new texts, other counts may not. */
    CHECK_OK(flame_session_reset(s));
    CHECK_OK(flame_session_set_prompt_stages(s, stages, 2));
    CHECK_OK(flame_session_step(s, NULL));
    FlameStage swapped[2] = {stage(FMG_STAGE_B, 31), stage(FMG_STAGE_A, 24)};
    FlameStage three[3] = {stage(FMG_STAGE_A, 20), stage(FMG_STAGE_B, 20), stage(FMG_STAGE_A, 15)};
    /* The same count and longest stage (so the same sample rows), in another order. */
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, swapped, 2), FLAME_STATUS_WRONG_STATE,
                         "before the first step");
    FlameStage moved[2] = {stage(FMG_STAGE_A, 25), stage(FMG_STAGE_B, 30)};
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, moved, 2), FLAME_STATUS_WRONG_STATE,
                         "before the first step");
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, three, 3), FLAME_STATUS_WRONG_STATE,
                         "before the first step");
    FlameStage retexted[2] = {stage(FMG_STAGE_B, 24), stage(FMG_STAGE_A, 31)};
    CHECK_OK(flame_session_set_prompt_stages(s, retexted, 2));
    CHECK_OK(flame_session_sample_shape(s, &rows, &dim));
    CHECK(rows == 2 * 31);
    /* After a reset the layout is free again. */
    CHECK_OK(flame_session_reset(s));
    CHECK_OK(flame_session_set_prompt_stages(s, three, 3));
    CHECK_OK(flame_session_sample_shape(s, &rows, &dim));
    CHECK(rows == 3 * 20);
    /* The noise follows the layout: sample_shape's rows after the stages. */
    float *noise = (float *)calloc((size_t)rows * dim, sizeof(float));
    CHECK_ERROR_MENTIONS(flame_session_set_noise(s, noise, (size_t)FMG_FRAMES * 263), INV,
                         "3 stages × 20 frames");
    CHECK_OK(flame_session_set_noise(s, noise, (size_t)rows * dim));
    free(noise);
    size_t n3 = 0;
    float *x3 = finish(s, &n3);
    CHECK(x3 && n3 == (size_t)FMG_FRAMES * 263 && all_finite(x3, n3));
    free(x3);
    /* The errors as for any family. */
    CHECK_ERROR_MENTIONS(flame_session_set_prompt_stages(s, stages, 1), INV,
                         "the stages cover 24 frames, the session has 55");
    free(x);
    flame_session_free(s);
}

int main(int argc, char **argv) {
    if (argc != 2 && argc != 3) {
        fprintf(stderr, "usage: %s FIXTURES_DIR [FINEMOGEN_REFERENCE_NPY]\n", argv[0]);
        return 2;
    }
    snprintf(g_dir, sizeof g_dir, "%s", argv[1]);
    double t0 = now_seconds();
    FlameModel *mdm = load("mdm_tiny.safetensors");
    if (!mdm) {
        return 2;
    }
    test_one_stage_is_the_prompt(mdm);
    test_errors(mdm);
    test_refusals(mdm, "mdm", MDM_FRAMES);
    flame_model_free(mdm);
    const char *others[][2] = {{"flame_tiny.safetensors", "flame"},
                               {"motionfm_tiny.safetensors", "motionfm"},
                               {"mola_tiny.safetensors", "mola"}};
    for (size_t i = 0; i < COUNT(others); i++) {
        FlameModel *m = load(others[i][0]);
        CHECK(m != NULL);
        if (m) {
            test_refusals(m, others[i][1], 40);
            flame_model_free(m);
        }
    }

    char path[4200];
    snprintf(path, sizeof path, "%s/finemogen_tiny.safetensors", g_dir);
    FILE *f = fopen(path, "rb");
    if (f) {
        fclose(f);
        FlameModel *fmg = load("finemogen_tiny.safetensors");
        CHECK(fmg != NULL);
        if (fmg) {
            test_finemogen(fmg, argc == 3 ? argv[2] : NULL);
            flame_model_free(fmg);
        }
    } else {
        printf("skip FineMoGen: no %s\n", path);
    }
    printf("test_stages: %.2f s\n", now_seconds() - t0);
    return check_summary();
}
