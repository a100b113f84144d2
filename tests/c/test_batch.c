/*
 * The batch runner through the C ABI (flame_batch_*): a JSONL file of jobs run into a folder,
 * with a bad job reported and counted while the others are written; a resumed run skipping the
 * finished jobs; a cancel raised before a run stopping that run only; NULL handles, NULL paths,
 * a short params struct and a missing jobs file refused with a status and a message.
 * Bit-identity with `flame generate` is checked by tests/batch.rs and the Python tests.
 *
 * usage: test_batch MODEL SCRATCH_DIR (the tiny FLAME fixture, an empty writable folder)
 */
#define _POSIX_C_SOURCE 200809L

#include <stdio.h>
#include <string.h>
#include <sys/stat.h>

#include "flame.h"

#include "check.h"
#include "util.h"

static int exists(const char *path) {
    struct stat st;
    return stat(path, &st) == 0;
}

static int count_lines(const char *path) {
    size_t len = 0;
    unsigned char *text = read_file(path, &len);
    int n = 0;
    for (size_t i = 0; text && i < len; i++) {
        n += text[i] == '\n';
    }
    free(text);
    return n;
}

int main(int argc, char **argv) {
    if (argc != 3) {
        fprintf(stderr, "usage: %s MODEL SCRATCH_DIR\n", argv[0]);
        return 2;
    }
    const char *dir = argv[2];
    char jobs[1024], manifest[1024], out_a[1024], out_b[1024];
    snprintf(jobs, sizeof jobs, "%s/jobs.jsonl", dir);
    snprintf(manifest, sizeof manifest, "%s/manifest.jsonl", dir);
    snprintf(out_a, sizeof out_a, "%s/a.bvh", dir);
    snprintf(out_b, sizeof out_b, "%s/b.npy", dir);
    const char *text =
        "{\"prompt\": \"a person walks\", \"frames\": 8, \"steps\": 2, \"out\": \"a.bvh\"}\n"
        "{\"prompt\": \"a person waves\", \"frames\": 8, \"steps\": 2, \"seed\": 3, \"out\": "
        "\"b.npy\"}\n"
        "{\"prompt\": \"a person runs\", \"out\": \"c.bvh\", \"stpes\": 2}\n";
    CHECK(write_file(jobs, text, strlen(text)));

    FlameModel *model = NULL;
    CHECK_OK(flame_model_load(argv[1], NULL, &model));
    FlameBatch *batch = NULL;
    CHECK_STATUS(flame_batch_new(NULL, &batch), FLAME_STATUS_INVALID_ARGUMENT);
    CHECK_STATUS(flame_batch_new(model, NULL), FLAME_STATUS_INVALID_ARGUMENT);
    CHECK_OK(flame_batch_new(model, &batch));

    FlameBatchParams p;
    CHECK_OK(flame_batch_params_default(&p));
    CHECK(p.workers == 0 && p.threads == 0 && p.resume == 0 && p.base_dir == NULL);
    p.base_dir = dir;
    p.workers = 2;
    FlameBatchSummary s;
    memset(&s, 0, sizeof s);
    s.struct_size = sizeof s;
    CHECK_OK(flame_batch_run(batch, jobs, manifest, &p, &s));
    CHECK(s.total == 3 && s.ok == 2 && s.failed == 1 && s.skipped == 0);
    CHECK(exists(out_a) && exists(out_b));
    CHECK(count_lines(manifest) == 3);

    /* Resumed: the two written jobs are skipped, the bad one fails again. */
    p.resume = 1;
    CHECK_OK(flame_batch_run(batch, jobs, manifest, &p, &s));
    CHECK(s.total == 3 && s.ok == 0 && s.failed == 1 && s.skipped == 2);
    CHECK(count_lines(manifest) == 4);

    /* A cancel raised with no run going stops the next run, and only that one. */
    p.resume = 0;
    CHECK_OK(flame_batch_cancel(batch));
    CHECK_STATUS(flame_batch_run(batch, jobs, manifest, &p, &s), FLAME_STATUS_CANCELLED);
    CHECK_OK(flame_batch_run(batch, jobs, manifest, &p, &s));
    CHECK(s.ok == 2 && s.failed == 1);

    /* Refusals. */
    CHECK_STATUS(flame_batch_run(NULL, jobs, manifest, &p, &s), FLAME_STATUS_INVALID_ARGUMENT);
    CHECK_STATUS(flame_batch_run(batch, NULL, manifest, &p, &s), FLAME_STATUS_INVALID_ARGUMENT);
    CHECK_STATUS(flame_batch_run(batch, jobs, NULL, &p, &s), FLAME_STATUS_INVALID_ARGUMENT);
    FlameBatchParams short_params = p;
    short_params.struct_size = 4;
    CHECK_STATUS(flame_batch_run(batch, jobs, manifest, &short_params, &s),
                 FLAME_STATUS_INVALID_ARGUMENT);
    FlameBatchSummary short_summary = s;
    short_summary.struct_size = 4;
    CHECK_STATUS(flame_batch_run(batch, jobs, manifest, &p, &short_summary),
                 FLAME_STATUS_INVALID_ARGUMENT);
    char missing[1024];
    snprintf(missing, sizeof missing, "%s/no_such_jobs.jsonl", dir);
    FlameStatus st = flame_batch_run(batch, missing, manifest, &p, &s);
    CHECK(st == FLAME_STATUS_IO && strstr(flame_last_error(), "no_such_jobs.jsonl") != NULL);
    CHECK_STATUS(flame_batch_cancel(NULL), FLAME_STATUS_INVALID_ARGUMENT);

    flame_batch_free(batch);
    flame_batch_free(NULL);
    flame_model_free(model);
    return check_summary();
}
