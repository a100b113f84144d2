/*
 * Cancelling a running step and catching non-finite values, through the C ABI:
 *  - a step cancelled from another thread soon after it starts returns CANCELLED (or, when
 *    the step won the race, OK and then CANCELLED at the next step) and leaves the step count
 *    alone; the latency is printed, not asserted (measuring it belongs to `flame-bench
 *    cancel`; that the flag is seen between layers is tested deterministically in
 *    src/session.rs);
 *  - a generation cancelled in the middle of a stochastic (DDPM) step and retried gives the
 *    bits of one never cancelled;
 *  - initial noise so large that the network overflows makes the first step return
 *    NOT_FINITE, naming the step; further steps are WRONG_STATE until a reset, after which a
 *    valid generation gives the bits of a fresh session.
 *
 * usage: test_cancel MODEL (the tiny FLAME fixture)
 */
#define _POSIX_C_SOURCE 200809L

#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "flame.h"

#include "check.h"
#include "util.h"

static void sleep_seconds(double s) {
    struct timespec ts;
    ts.tv_sec = (time_t)s;
    ts.tv_nsec = (long)((s - (double)ts.tv_sec) * 1e9);
    nanosleep(&ts, NULL);
}

static FlameSession *new_session(const FlameModel *m, uint32_t frames, uint32_t steps,
                                 int32_t sampler, uint64_t seed) {
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

/* One step run on a worker thread; the main thread cancels it `delay` seconds after it
 * starts. */
struct stepper {
    FlameSession *session;
    pthread_mutex_t lock;
    pthread_cond_t cond;
    int started;
    double t_start, t_end;
    FlameStatus status;
};

static void *step_worker(void *arg) {
    struct stepper *w = (struct stepper *)arg;
    pthread_mutex_lock(&w->lock);
    w->t_start = now_seconds();
    w->started = 1;
    pthread_cond_broadcast(&w->cond);
    pthread_mutex_unlock(&w->lock);
    w->status = flame_session_step(w->session, NULL);
    w->t_end = now_seconds();
    return NULL;
}

/* Steps `s` once on a worker and cancels after `delay` s; returns the status and, in
 * *latency, the seconds from the cancel to the step's return. */
static FlameStatus step_and_cancel(FlameSession *s, double delay, double *latency) {
    struct stepper w;
    memset(&w, 0, sizeof w);
    w.session = s;
    pthread_mutex_init(&w.lock, NULL);
    pthread_cond_init(&w.cond, NULL);
    pthread_t t;
    pthread_create(&t, NULL, step_worker, &w);
    pthread_mutex_lock(&w.lock);
    while (!w.started) {
        pthread_cond_wait(&w.cond, &w.lock);
    }
    double start = w.t_start;
    pthread_mutex_unlock(&w.lock);
    double wait = start + delay - now_seconds();
    if (wait > 0) {
        sleep_seconds(wait);
    }
    double t_cancel = now_seconds();
    CHECK_OK(flame_session_cancel(s));
    pthread_join(t, NULL);
    *latency = w.t_end - t_cancel;
    pthread_mutex_destroy(&w.lock);
    pthread_cond_destroy(&w.cond);
    return w.status;
}

/* The full step's time at the fixture's largest frame count, then steps cancelled a fifth of
 * the way in: each returns CANCELLED (or, when the step won the race, OK and then CANCELLED at
 * the next step) and leaves the step count alone; the latency is printed. */
static void test_cancel_latency(const FlameModel *m) {
    uint32_t frames = quick_mode() ? 64 : FLAME_TINY_MAX_FRAMES;
    FlameSession *s = new_session(m, frames, 50, FLAME_SAMPLER_DDIM, 1);
    CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
    double full[3];
    CHECK_OK(flame_session_step(s, NULL)); /* warm-up: buffers sized */
    for (int i = 0; i < 3; i++) {
        double t0 = now_seconds();
        CHECK_OK(flame_session_step(s, NULL));
        full[i] = now_seconds() - t0;
    }
    double step = full[0];
    for (int i = 1; i < 3; i++) {
        step = full[i] < step ? full[i] : step;
    }
    uint32_t done_before = 0, done_after = 0;
    CHECK_OK(flame_session_progress(s, &done_before, NULL));
    /* The best of three trials: one descheduled thread on a busy machine proves nothing. */
    double best = 1e9;
    int cancelled = 0;
    for (int trial = 0; trial < 3; trial++) {
        double latency = 0;
        FlameStatus st = step_and_cancel(s, step / 5, &latency);
        if (st == FLAME_STATUS_CANCELLED) {
            cancelled++;
            best = latency < best ? latency : best;
        } else {
            /* Finished before the flag (a very slow cancelling thread): the flag now waits
             * for the next step, which returns CANCELLED at once. */
            CHECK_OK(st);
            CHECK_STATUS(flame_session_step(s, NULL), FLAME_STATUS_CANCELLED);
            done_before++;
        }
    }
    /* How fast a cancel lands is a timing, measured by `flame-bench cancel`, not asserted
     * here (under valgrind on a busy machine every trial may finish first); that the flag is
     * checked between layers is tested deterministically in src/session.rs. */
    CHECK_OK(flame_session_progress(s, &done_after, NULL));
    CHECK(done_after == done_before);
    if (cancelled > 0) {
        printf("cancel: full step %.1f ms, cancel latency %.1f ms (best of %d cancelled, %u "
               "frames, 1 thread)\n",
               step * 1e3, best * 1e3, cancelled, frames);
    } else {
        printf("cancel: full step %.1f ms, every step finished before its cancel (%u frames)\n",
               step * 1e3, frames);
    }
    flame_session_free(s);
}

/* DDPM (a noise draw per step) cancelled mid-step at step 3, retried: same bits. Where the
 * cancel lands depends on the scheduler, so the step may also finish first and the next
 * step be cancelled at its start; either way the result must match. */
static float *ddpm_run(const FlameModel *m, int cancel, size_t *n) {
    uint32_t frames = quick_mode() ? 32 : 200;
    FlameSession *s = new_session(m, frames, 6, FLAME_SAMPLER_DDPM, 9);
    CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
    uint32_t left = 6;
    double step = 0;
    int cancels = 0;
    while (left > 0) {
        if (cancel && left == 4 && cancels == 0) {
            double latency = 0;
            FlameStatus st = step_and_cancel(s, step / 3, &latency);
            cancels += st == FLAME_STATUS_CANCELLED;
            CHECK(st == FLAME_STATUS_CANCELLED || st == FLAME_STATUS_OK);
            CHECK_OK(flame_session_progress(s, &left, NULL));
            left = 6 - left;
            if (st == FLAME_STATUS_OK) {
                CHECK_STATUS(flame_session_step(s, NULL), FLAME_STATUS_CANCELLED);
                cancels++;
            }
            continue;
        }
        double t0 = now_seconds();
        CHECK_OK(flame_session_step(s, &left));
        step = now_seconds() - t0;
    }
    CHECK(cancels == (cancel ? 1 : 0));
    FlameStatus st;
    float *x = read_features(s, FLAME_WHICH_SAMPLE, n, &st);
    CHECK_OK(st);
    flame_session_free(s);
    return x;
}

static void test_cancel_retry_same_bits(const FlameModel *m) {
    size_t na = 0, nb = 0;
    float *a = ddpm_run(m, 0, &na);
    float *b = ddpm_run(m, 1, &nb);
    CHECK(same_bits(a, na, b, nb));
    free(a);
    free(b);
}

/* Initial noise of 1e30 is finite but overflows inside the network (layer norm squares it):
 * the first step returns NOT_FINITE and names itself; the session refuses steps until reset;
 * after a reset with ordinary noise the generation equals a fresh session's. */
static void test_not_finite(const FlameModel *m) {
    const uint32_t frames = 16, steps = 4;
    size_t n = (size_t)frames * FLAME_TINY_DIM;
    float *huge = (float *)malloc(n * sizeof(float));
    float *calm = (float *)malloc(n * sizeof(float));
    for (size_t i = 0; i < n; i++) {
        huge[i] = (i % 2 ? -1e30f : 1e30f);
        calm[i] = 0.5f * (float)((int)(i % 7) - 3);
    }
    FlameSession *s = new_session(m, frames, steps, FLAME_SAMPLER_DDIM, 4);
    CHECK_OK(flame_session_set_prompt(s, REF_PROMPT));
    CHECK_OK(flame_session_set_noise(s, huge, n));
    CHECK_ERROR_MENTIONS(flame_session_step(s, NULL), FLAME_STATUS_NOT_FINITE, "step 1 of 4");
    CHECK(strcmp(flame_status_string(FLAME_STATUS_NOT_FINITE), "FLAME_STATUS_NOT_FINITE") == 0);
    CHECK_ERROR_MENTIONS(flame_session_step(s, NULL), FLAME_STATUS_WRONG_STATE, "reset");
    uint32_t done = 99;
    CHECK_OK(flame_session_progress(s, &done, NULL));
    CHECK(done == 0); /* the failed step is not counted */
    CHECK_OK(flame_session_reset(s));
    CHECK_OK(flame_session_set_noise(s, calm, n));
    uint32_t left = 1;
    while (left > 0) {
        CHECK_OK(flame_session_step(s, &left));
    }
    FlameStatus st;
    size_t na = 0, nb = 0;
    float *a = read_features(s, FLAME_WHICH_SAMPLE, &na, &st);
    flame_session_free(s);

    FlameSession *fresh = new_session(m, frames, steps, FLAME_SAMPLER_DDIM, 4);
    CHECK_OK(flame_session_set_noise(fresh, calm, n));
    CHECK_OK(run_to_end(fresh, REF_PROMPT));
    float *b = read_features(fresh, FLAME_WHICH_SAMPLE, &nb, &st);
    CHECK(same_bits(a, na, b, nb));
    flame_session_free(fresh);
    free(a);
    free(b);
    free(huge);
    free(calm);
}

int main(int argc, char **argv) {
    if (argc < 2) {
        fprintf(stderr, "usage: %s MODEL\n", argv[0]);
        return 2;
    }
    FlameModel *m = NULL;
    if (flame_model_load(argv[1], NULL, &m) != FLAME_STATUS_OK) {
        fprintf(stderr, "cannot load %s: %s\n", argv[1], flame_last_error());
        return 2;
    }
    test_cancel_latency(m);
    test_cancel_retry_same_bits(m);
    test_not_finite(m);
    flame_model_free(m);
    return check_summary();
}
