/*
 * Position targets through the C ABI: flame_target_params_default,
 * flame_session_set_target_params, flame_session_set_position_targets,
 * flame_session_clear_position_targets and flame_session_target_loss, their error paths, and
 * what they do to a generation (scale 0 and cleared targets change nothing, bit for bit; targets
 * pull the pelvis toward them).
 *
 * usage: test_targets FIXTURES_DIR   (tests/fixtures: flame_tiny.safetensors)
 *
 * The generations are short (16 frames, 20 steps of the tiny model) and stay so under valgrind:
 * fewer steps would not pull the pelvis far enough to tell guidance from chance.
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
#define JOINTS 24 /* smpl24_6d */
#define PER_FRAME (JOINTS * 3)

static const uint32_t g_frames = 16;
static const uint32_t g_steps = 20;

static FlameSession *new_session(const FlameModel *m) {
    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = g_frames;
    p.steps = g_steps;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.guidance = 2.5f;
    p.seed = 7;
    p.threads = 1;
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(m, &p, &s));
    return s;
}

/* Every step, then the final features (malloc'd; NULL on error). */
static float *run(FlameSession *s, size_t *n) {
    FlameStatus st = run_to_end(s, "a person walks forward.");
    CHECK_OK(st);
    if (st != FLAME_STATUS_OK) {
        return NULL;
    }
    return read_features(s, FLAME_WHICH_SAMPLE, n, &st);
}

/* Joint positions of the final sample in `conv`, frames × 24 × 3 (malloc'd). */
static float *positions(const FlameSession *s, int32_t conv) {
    size_t need = 0, n = 0;
    if (flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_POSITIONS, conv, 0, NULL, 0,
                           &need) != FLAME_STATUS_OK) {
        return NULL;
    }
    float *out = (float *)malloc(need * sizeof(float) + 1);
    if (flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_POSITIONS, conv, 0, out,
                           need, &n) != FLAME_STATUS_OK) {
        free(out);
        return NULL;
    }
    return out;
}

/* A pelvis path in the Unreal convention (Z up, centimetres): from where the unguided pelvis
 * starts, a straight line across the ground (+5 cm in X and -4 cm in Y per frame) at the
 * unguided height, every other joint NaN (free). frames × 24 × 3 values. */
static float *pelvis_path(const float *unguided, uint32_t frames) {
    float *t = (float *)malloc((size_t)frames * PER_FRAME * sizeof(float));
    for (size_t i = 0; i < (size_t)frames * PER_FRAME; i++) {
        t[i] = NAN;
    }
    for (uint32_t f = 0; f < frames; f++) {
        float *q = t + (size_t)f * PER_FRAME;
        q[0] = unguided[0] + 5.0f * (float)f;
        q[1] = unguided[1] - 4.0f * (float)f;
        q[2] = unguided[(size_t)f * PER_FRAME + 2];
    }
    return t;
}

/* The median over frames of the pelvis's distance to the path. */
static double pelvis_error(const float *pos, const float *target, uint32_t frames) {
    double e[512];
    for (uint32_t f = 0; f < frames; f++) {
        double d = 0;
        for (int k = 0; k < 3; k++) {
            double x = pos[(size_t)f * PER_FRAME + k] - target[(size_t)f * PER_FRAME + k];
            d += x * x;
        }
        e[f] = sqrt(d);
    }
    for (uint32_t i = 1; i < frames; i++) { /* insertion sort: a handful of frames */
        for (uint32_t j = i; j > 0 && e[j - 1] > e[j]; j--) {
            double x = e[j];
            e[j] = e[j - 1];
            e[j - 1] = x;
        }
    }
    return e[frames / 2];
}

/* ---- flame_target_params_default ---------------------------------------------------------- */

static void test_params_default(void) {
    CHECK_ERROR_MENTIONS(flame_target_params_default(NULL), INV, "params");
    FlameTargetParams p;
    memset(&p, 0xAB, sizeof p);
    CHECK_OK(flame_target_params_default(&p));
    CHECK(p.struct_size == sizeof(FlameTargetParams));
    CHECK(p.scale == 0.6f);
    CHECK(p.schedule == FLAME_TARGET_SCHEDULE_MPGD);
    CHECK(FLAME_TARGET_SCHEDULE_MPGD == 0 && FLAME_TARGET_SCHEDULE_CONSTANT == 1);
}

/* ---- flame_session_set_target_params ------------------------------------------------------ */

static FlameStatus set_params(FlameSession *s, float scale, int32_t schedule) {
    FlameTargetParams p;
    flame_target_params_default(&p);
    p.scale = scale;
    p.schedule = schedule;
    return flame_session_set_target_params(s, &p);
}

static void test_set_target_params(const FlameModel *m) {
    FlameTargetParams p;
    flame_target_params_default(&p);
    CHECK_ERROR_MENTIONS(flame_session_set_target_params(NULL, &p), INV, "session");
    FlameSession *s = new_session(m);
    CHECK_ERROR_MENTIONS(flame_session_set_target_params(s, NULL), INV, "params");
    /* A session starts with its family's defaults: FLAME takes the constant schedule. */
    FlameTargetParams got;
    CHECK_ERROR_MENTIONS(flame_session_target_params(NULL, &got), INV, "session");
    CHECK_ERROR_MENTIONS(flame_session_target_params(s, NULL), INV, "params");
    CHECK_OK(flame_session_target_params(s, &got));
    CHECK(got.struct_size == sizeof got && got.scale == 0.6f &&
          got.schedule == FLAME_TARGET_SCHEDULE_CONSTANT);
    CHECK_OK(flame_session_set_target_params(s, &p));
    /* struct_size: less than the struct is refused; a larger (newer) caller is accepted. */
    uint32_t sizes[] = {0, 4, (uint32_t)sizeof p - 1};
    for (size_t i = 0; i < sizeof sizes / sizeof sizes[0]; i++) {
        p.struct_size = sizes[i];
        CHECK_ERROR_MENTIONS(flame_session_set_target_params(s, &p), INV, "struct_size");
    }
    flame_target_params_default(&p);
    CHECK_OK(set_params(s, 0.0f, FLAME_TARGET_SCHEDULE_MPGD));
    CHECK_OK(flame_session_target_params(s, &got));
    CHECK(got.scale == 0.0f && got.schedule == FLAME_TARGET_SCHEDULE_MPGD);
    CHECK_OK(set_params(s, 100.0f, FLAME_TARGET_SCHEDULE_CONSTANT));
    CHECK_ERROR_MENTIONS(set_params(s, 0.6f, 2), INV, "unknown target schedule 2");
    CHECK_ERROR_MENTIONS(set_params(s, 0.6f, -1), INV, "unknown target schedule -1");
    CHECK_ERROR_MENTIONS(set_params(s, 0.6f, INT32_MAX), INV, "unknown target schedule");
    CHECK_ERROR_MENTIONS(set_params(s, -0.1f, 0), INV, "target scale");
    CHECK_ERROR_MENTIONS(set_params(s, NAN, 0), INV, "target scale");
    CHECK_ERROR_MENTIONS(set_params(s, 100.5f, 0), INV, "target scale");
    CHECK_ERROR_MENTIONS(set_params(s, INFINITY, 0), INV, "target scale");
    CHECK_ERROR_MENTIONS(set_params(s, -INFINITY, 0), INV, "target scale");
    flame_session_free(s);
}

/* ---- flame_session_set_position_targets: errors ------------------------------------------- */

static void test_set_position_targets_errors(const FlameModel *m) {
    const size_t n = (size_t)2 * PER_FRAME;
    float t[2 * PER_FRAME];
    uint8_t mask[2 * PER_FRAME];
    for (size_t i = 0; i < n; i++) {
        t[i] = 0.01f * (float)(i % 7) + 0.1f;
        mask[i] = 1;
    }
    const int32_t NAT = FLAME_CONVENTION_NATIVE;
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(NULL, t, n, NULL, 0, NAT), INV,
                         "session");
    CHECK_ERROR_MENTIONS(flame_session_clear_position_targets(NULL), INV, "session");
    double loss = -7.0;
    CHECK_ERROR_MENTIONS(flame_session_target_loss(NULL, &loss), INV, "session");

    FlameSession *s = new_session(m);
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, NULL, n, NULL, 0, NAT), INV,
                         "`targets` is NULL");
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, NULL, 0, NULL, 0, NAT), INV,
                         "hold 0 values");
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, t, 0, NULL, 0, NAT), INV,
                         "hold 0 values");
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, t, n, NULL, n, NAT), INV,
                         "`mask` is NULL");
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, t, n - 1, NULL, 0, NAT), INV,
                         "multiple of 72");
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, t, 3, NULL, 0, NAT), INV,
                         "hold 3 values");
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, t, n, mask, n - 1, NAT), INV,
                         "the target mask has 143 flags");
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, t, n, mask, 0, NAT), INV,
                         "the target mask has 0 flags");
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, t, n, NULL, 0, 6), INV,
                         "convention");
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, t, n, NULL, 0, -1), INV,
                         "convention");

    /* A NaN or an infinity where constrained: the mask constrains it, or (no mask) ∞ is not
     * NaN, so it is constrained. */
    float bad[2 * PER_FRAME];
    memcpy(bad, t, sizeof bad);
    bad[PER_FRAME + 5 * 3 + 1] = NAN; /* frame 1, joint 5, axis 1 */
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, bad, n, mask, n, NAT), INV,
                         "frame 1, joint 5, axis 1 is NaN but constrained");
    mask[PER_FRAME + 5 * 3 + 1] = 0; /* masked out: its value does not matter */
    CHECK_OK(flame_session_set_position_targets(s, bad, n, mask, n, NAT));
    mask[PER_FRAME + 5 * 3 + 1] = 1;
    memcpy(bad, t, sizeof bad);
    bad[7] = INFINITY;
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, bad, n, NULL, 0, NAT), INV,
                         "frame 0, joint 2, axis 1 is inf but constrained");
    bad[7] = -INFINITY;
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, bad, n, mask, n, NAT), INV,
                         "is -inf but constrained");

    /* Nothing constrained: every value NaN, or a mask of zeros. */
    float free_all[2 * PER_FRAME];
    uint8_t none[2 * PER_FRAME];
    for (size_t i = 0; i < n; i++) {
        free_all[i] = NAN;
        none[i] = 0;
    }
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, free_all, n, NULL, 0, NAT), INV,
                         "constrain nothing");
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, t, n, none, n, NAT), INV,
                         "constrain nothing");

    /* More frames than the session's. */
    size_t over = (size_t)(g_frames + 1) * PER_FRAME;
    float *many = (float *)calloc(over, sizeof(float));
    CHECK_ERROR_MENTIONS(flame_session_set_position_targets(s, many, over, NULL, 0, NAT), INV,
                         "cover");
    CHECK_OK(flame_session_set_position_targets(s, many, over - PER_FRAME, NULL, 0, NAT));
    free(many);

    /* Every convention is accepted. */
    for (int32_t c = FLAME_CONVENTION_NATIVE; c <= FLAME_CONVENTION_GLTF; c++) {
        CHECK_OK(flame_session_set_position_targets(s, t, n, NULL, 0, c));
    }
    CHECK_OK(flame_session_clear_position_targets(s));
    CHECK_OK(flame_session_clear_position_targets(s)); /* twice: nothing to clear is fine */
    flame_session_free(s);
}

/* ---- flame_session_target_loss ------------------------------------------------------------ */

static void test_target_loss(const FlameModel *m) {
    FlameSession *s = new_session(m);
    double loss = -7.0;
    CHECK_ERROR_MENTIONS(flame_session_target_loss(s, &loss), FLAME_STATUS_WRONG_STATE,
                         "no step has been guided");
    CHECK(loss == -7.0); /* outputs are written only on success */
    float t[PER_FRAME];
    for (int i = 0; i < PER_FRAME; i++) {
        t[i] = i < 3 ? 0.1f * (float)(i + 1) : NAN; /* the pelvis only */
    }
    CHECK_OK(flame_session_set_position_targets(s, t, PER_FRAME, NULL, 0, FLAME_CONVENTION_NATIVE));
    CHECK_STATUS(flame_session_target_loss(s, &loss), FLAME_STATUS_WRONG_STATE);
    CHECK_OK(flame_session_set_prompt(s, "a person walks forward."));
    uint32_t left = 0;
    CHECK_OK(flame_session_step(s, &left));
    loss = -7.0;
    CHECK_OK(flame_session_target_loss(s, &loss));
    CHECK(isfinite(loss) && loss > 0.0);
    CHECK_ERROR_MENTIONS(flame_session_target_loss(s, NULL), INV, "loss");
    /* Each guided step records its own loss, which the pull brings down: the last is a small
     * fraction of the first. */
    double first = loss;
    while (left > 0 && flame_session_step(s, &left) == FLAME_STATUS_OK) {
    }
    CHECK(left == 0);
    CHECK_OK(flame_session_target_loss(s, &loss));
    printf("target loss: %.4f m after the first step, %.4f m after the last\n", first, loss);
    CHECK(isfinite(loss) && loss > 0.0 && loss < 0.1 * first);
    /* reset and clear forget it. */
    CHECK_OK(flame_session_reset(s));
    CHECK_STATUS(flame_session_target_loss(s, &loss), FLAME_STATUS_WRONG_STATE);
    CHECK_OK(flame_session_step(s, &left));
    CHECK_OK(flame_session_target_loss(s, &loss));
    CHECK(loss == first); /* the same first step again */
    CHECK_OK(flame_session_clear_position_targets(s));
    CHECK_STATUS(flame_session_target_loss(s, &loss), FLAME_STATUS_WRONG_STATE);
    CHECK_OK(flame_session_step(s, &left));
    CHECK_STATUS(flame_session_target_loss(s, &loss), FLAME_STATUS_WRONG_STATE);
    /* Scale 0 guides nothing, so it records no loss either. */
    CHECK_OK(flame_session_reset(s));
    CHECK_OK(flame_session_set_position_targets(s, t, PER_FRAME, NULL, 0, FLAME_CONVENTION_NATIVE));
    CHECK_OK(set_params(s, 0.0f, FLAME_TARGET_SCHEDULE_CONSTANT));
    CHECK_OK(flame_session_step(s, &left));
    CHECK_STATUS(flame_session_target_loss(s, &loss), FLAME_STATUS_WRONG_STATE);
    flame_session_free(s);
}

/* ---- what targets do to a generation ------------------------------------------------------ */

static void test_generation(const FlameModel *m) {
    const uint32_t F = g_frames;
    size_t n_plain = 0, n = 0;
    FlameSession *plain = new_session(m);
    float *unguided = run(plain, &n_plain);
    float *p_unguided = positions(plain, FLAME_CONVENTION_UNREAL); /* centimetres */
    float *target = p_unguided ? pelvis_path(p_unguided, F) : NULL;
    CHECK(unguided && p_unguided && target);
    if (!unguided || !p_unguided || !target) {
        flame_session_free(plain);
        return;
    }
    const size_t tn = (size_t)F * PER_FRAME;

    /* Scale 0: the unguided run, bit for bit. */
    FlameSession *s = new_session(m);
    CHECK_OK(flame_session_set_position_targets(s, target, tn, NULL, 0, FLAME_CONVENTION_UNREAL));
    CHECK_OK(set_params(s, 0.0f, FLAME_TARGET_SCHEDULE_CONSTANT));
    float *x = run(s, &n);
    CHECK(same_bits(x, n, unguided, n_plain));
    free(x);
    flame_session_free(s);

    /* The session's defaults (0.6, the constant schedule for this family) pull the pelvis to
     * the path. */
    s = new_session(m);
    CHECK_OK(flame_session_set_position_targets(s, target, tn, NULL, 0, FLAME_CONVENTION_UNREAL));
    float *guided = run(s, &n);
    float *p_guided = positions(s, FLAME_CONVENTION_UNREAL);
    CHECK(guided && p_guided && !same_bits(guided, n, unguided, n_plain));
    if (p_guided) {
        double before = pelvis_error(p_unguided, target, F);
        double after = pelvis_error(p_guided, target, F);
        printf("median pelvis error: %.2f cm unguided, %.2f cm guided\n", before, after);
        CHECK(before > 5.0);        /* the path is off the unguided motion */
        CHECK(after < 0.5 * before); /* and the guidance pulls the pelvis to it */
    }
    double loss = 0;
    CHECK_OK(flame_session_target_loss(s, &loss));
    CHECK(isfinite(loss) && loss > 0.0);

    /* reset replays the guided run; cleared targets then reset: the unguided run. */
    CHECK_OK(flame_session_reset(s));
    x = run(s, &n);
    CHECK(same_bits(x, n, guided, n_plain));
    free(x);
    CHECK_OK(flame_session_clear_position_targets(s));
    CHECK_OK(flame_session_reset(s));
    x = run(s, &n);
    CHECK(same_bits(x, n, unguided, n_plain));
    free(x);
    flame_session_free(s);

    /* The same constraint as a mask (values where free arbitrary but finite) is the same
     * targets: the NaN form's result, bit for bit. A failed call changes nothing. */
    float *values = (float *)malloc(tn * sizeof(float));
    uint8_t *mask = (uint8_t *)malloc(tn);
    for (size_t i = 0; i < tn; i++) {
        mask[i] = !isnan(target[i]);
        values[i] = mask[i] ? target[i] : 123.0f;
    }
    s = new_session(m);
    CHECK_OK(flame_session_set_position_targets(s, values, tn, mask, tn, FLAME_CONVENTION_UNREAL));
    CHECK_STATUS(flame_session_set_position_targets(s, values, tn, mask, tn - 1,
                                                    FLAME_CONVENTION_UNREAL),
                 INV);
    CHECK_STATUS(set_params(s, 0.6f, 2), INV);
    x = run(s, &n);
    CHECK(same_bits(x, n, guided, n_plain));
    free(x);

    /* The MPGD schedule is another, also guided, result. */
    CHECK_OK(set_params(s, 0.6f, FLAME_TARGET_SCHEDULE_MPGD));
    CHECK_OK(flame_session_reset(s));
    x = run(s, &n);
    CHECK(x && !same_bits(x, n, guided, n_plain) && !same_bits(x, n, unguided, n_plain));
    free(x);
    flame_session_free(s);

    free(values);
    free(mask);
    free(guided);
    free(p_guided);
    free(target);
    free(p_unguided);
    free(unguided);
    flame_session_free(plain);
}

/* ---- flame_session_set_task_targets ------------------------------------------------------- */

static void test_task_targets(const FlameModel *m) {
    FlameSession *plain = new_session(m);
    size_t n = 0;
    float *reference = run(plain, &n);
    flame_session_free(plain);
    if (!reference) {
        return;
    }
    uint32_t dim = 147, frames = (uint32_t)(n / dim);
    CHECK(frames == (uint32_t)g_frames);
    CHECK_ERROR_MENTIONS(flame_session_set_task_targets(NULL, reference, frames, dim, 3), INV, "session");
    FlameSession *s = new_session(m);
    CHECK_ERROR_MENTIONS(flame_session_set_task_targets(s, NULL, frames, dim, 3), INV, "features");
    CHECK_ERROR_MENTIONS(flame_session_set_task_targets(s, reference, frames, dim, -1), INV, "unknown editing task -1");
    CHECK_ERROR_MENTIONS(flame_session_set_task_targets(s, reference, frames, dim, 4), INV, "unknown editing task 4");
    CHECK_ERROR_MENTIONS(flame_session_set_task_targets(s, reference, frames, dim - 1, 3), INV, "reference shape");
    CHECK_ERROR_MENTIONS(flame_session_set_task_targets(s, reference, 0, dim, 3), INV, "reference shape");
    CHECK_ERROR_MENTIONS(flame_session_set_task_targets(s, reference, frames + 1, dim, 3), INV, "reference shape");
    double loss = -1;
    CHECK_STATUS(flame_session_target_loss(s, &loss), FLAME_STATUS_WRONG_STATE);
    /* Every task from the reference: a guided generation with a finite loss. */
    for (int32_t task = 0; task < 4; task++) {
        CHECK_OK(flame_session_set_task_targets(s, reference, frames, dim, task));
        CHECK_OK(flame_session_reset(s));
        float *x = run(s, &n);
        free(x);
        CHECK_OK(flame_session_target_loss(s, &loss));
        CHECK(isfinite(loss) && loss >= 0.0);
    }
    float bad = reference[5];
    reference[5] = NAN;
    CHECK_ERROR_MENTIONS(flame_session_set_task_targets(s, reference, frames, dim, 3), INV, "not finite");
    reference[5] = bad;
    flame_session_free(s);
    free(reference);
}

int main(int argc, char **argv) {
    if (argc != 2) {
        fprintf(stderr, "usage: %s FIXTURES_DIR\n", argv[0]);
        return 2;
    }
    char path[4096];
    snprintf(path, sizeof path, "%s/flame_tiny.safetensors", argv[1]);
    FlameModel *m = NULL;
    if (flame_model_load(path, NULL, &m) != FLAME_STATUS_OK) {
        fprintf(stderr, "cannot load %s: %s\n", path, flame_last_error());
        return 2;
    }
    double t0 = now_seconds();
    test_params_default();
    test_set_target_params(m);
    test_set_position_targets_errors(m);
    test_target_loss(m);
    test_generation(m);
    test_task_targets(m);
    flame_model_free(m);
    printf("test_targets: %.2f s\n", now_seconds() - t0);
    return check_summary();
}
