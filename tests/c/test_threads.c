/*
 * One model shared by 8 threads, each with its own session (different prompts, seeds, frame
 * counts, samplers, some editing): every thread's features equal, bit for bit, those of the
 * same job run alone. The main thread frees the model while the sessions still run (they keep
 * it alive).
 *
 * usage: test_threads MODEL
 */
#define _POSIX_C_SOURCE 200809L

#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "flame.h"

#include "check.h"
#include "util.h"

#define JOBS 8

static const char *const PROMPTS[JOBS] = {
    "a person walks forward and waves.", "a person jumps twice.",
    "someone turns around slowly.",      "a man kicks with his right leg.",
    "a person sits down on a chair.",    "a woman raises both arms.",
    "a person runs in a circle.",        "somebody crouches and stands up.",
};

struct job {
    int index;
    FlameSessionParams params;
    const char *prompt;
    int edit; /* keep the root translation of a reference */
    /* results */
    FlameStatus status;
    float *features;
    size_t n;
    char error[256];
};

static void job_init(struct job *j, int i) {
    memset(j, 0, sizeof *j);
    j->index = i;
    flame_session_params_default(&j->params);
    j->params.frames = (uint32_t)(quick_mode() ? 4 + i : 16 + 4 * i);
    j->params.steps = (uint32_t)(quick_mode() ? 2 + i % 2 : 6 + i % 5);
    j->params.sampler = i % 2 ? FLAME_SAMPLER_DDPM : FLAME_SAMPLER_DDIM;
    j->params.eta = i % 4 == 2 ? 0.5f : -1.0f;
    j->params.seed = 1000u + (uint64_t)i * 7919u;
    j->params.threads = i == 3 ? 2 : 1;
    j->params.guidance = i == 5 ? 2.5f : -1.0f;
    j->prompt = PROMPTS[i];
    j->edit = i % 3 == 0;
}

/* Runs `j` on session `s` (already created) and stores its result. */
static void job_run(struct job *j, FlameSession *s) {
    FlameStatus st = FLAME_STATUS_OK;
    if (j->edit) {
        size_t n = (size_t)j->params.frames * FLAME_TINY_DIM;
        float *r = (float *)malloc(n * sizeof(float));
        for (size_t k = 0; k < n; k++) {
            r[k] = 0.3f * sinf(0.02f * (float)k + (float)j->index);
        }
        int32_t root = FLAME_ROOT_TRANSLATION;
        st = flame_session_set_reference(s, r, j->params.frames, FLAME_TINY_DIM);
        if (st == FLAME_STATUS_OK) {
            st = flame_session_keep_joints(s, &root, 1);
        }
        free(r);
    }
    if (st == FLAME_STATUS_OK) {
        st = run_to_end(s, j->prompt);
    }
    if (st == FLAME_STATUS_OK) {
        j->features = read_features(s, FLAME_WHICH_SAMPLE, &j->n, &st);
    }
    j->status = st;
    if (st != FLAME_STATUS_OK) {
        snprintf(j->error, sizeof j->error, "%s", flame_last_error());
    }
}

struct shared {
    const FlameModel *model;
    pthread_barrier_t sessions_made;
};

struct worker {
    struct shared *shared;
    struct job *job;
};

static void *worker_main(void *arg) {
    struct worker *w = (struct worker *)arg;
    FlameSession *s = NULL;
    w->job->status = flame_session_new(w->shared->model, &w->job->params, &s);
    /* Everyone waits here, so the main thread can free the model under running sessions. */
    pthread_barrier_wait(&w->shared->sessions_made);
    if (w->job->status == FLAME_STATUS_OK) {
        job_run(w->job, s);
    } else {
        snprintf(w->job->error, sizeof w->job->error, "%s", flame_last_error());
    }
    flame_session_free(s);
    return NULL;
}

int main(int argc, char **argv) {
    if (argc != 2) {
        fprintf(stderr, "usage: %s MODEL\n", argv[0]);
        return 2;
    }
    struct job alone[JOBS], together[JOBS];

    /* One after another. */
    FlameModel *model = NULL;
    CHECK_OK(flame_model_load(argv[1], NULL, &model));
    if (!model) {
        return check_summary();
    }
    double t0 = now_seconds();
    for (int i = 0; i < JOBS; i++) {
        job_init(&alone[i], i);
        FlameSession *s = NULL;
        CHECK_OK(flame_session_new(model, &alone[i].params, &s));
        job_run(&alone[i], s);
        flame_session_free(s);
        CHECK_OK(alone[i].status);
        CHECK(alone[i].n == (size_t)alone[i].params.frames * FLAME_TINY_DIM);
    }
    double t_alone = now_seconds() - t0;

    /* All at once; the model is freed as soon as every session exists. */
    struct shared sh;
    sh.model = model;
    pthread_barrier_init(&sh.sessions_made, NULL, JOBS + 1);
    pthread_t threads[JOBS];
    struct worker workers[JOBS];
    t0 = now_seconds();
    for (int i = 0; i < JOBS; i++) {
        job_init(&together[i], i);
        workers[i].shared = &sh;
        workers[i].job = &together[i];
        CHECK(pthread_create(&threads[i], NULL, worker_main, &workers[i]) == 0);
    }
    pthread_barrier_wait(&sh.sessions_made);
    flame_model_free(model);
    for (int i = 0; i < JOBS; i++) {
        pthread_join(threads[i], NULL);
    }
    double t_together = now_seconds() - t0;
    pthread_barrier_destroy(&sh.sessions_made);

    for (int i = 0; i < JOBS; i++) {
        if (together[i].status != FLAME_STATUS_OK) {
            fprintf(stderr, "job %d: %s: %s\n", i, flame_status_string(together[i].status),
                    together[i].error);
        }
        CHECK(together[i].status == FLAME_STATUS_OK);
        CHECK(same_bits(together[i].features, together[i].n, alone[i].features, alone[i].n));
    }
    /* The jobs really differ (different seeds and prompts give different motions). */
    CHECK(alone[0].n != alone[1].n ||
          memcmp(alone[0].features, alone[1].features, alone[0].n * sizeof(float)) != 0);

    for (int i = 0; i < JOBS; i++) {
        free(alone[i].features);
        free(together[i].features);
    }
    printf("test_threads: %d jobs alone %.2f s, on %d threads %.2f s\n", JOBS, t_alone, JOBS,
           t_together);
    return check_summary();
}
