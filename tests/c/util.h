/*
 * Helpers shared by the ABI tests: whole-file I/O, a float32 .npy reader (the CLI's output), the
 * reference generation settings, a generate-and-read loop over the C API, and a count of this
 * process's threads (Linux /proc). Header-only, C11 and C++17; include after check.h.
 */
#ifndef FLAME_TESTS_UTIL_H
#define FLAME_TESTS_UTIL_H

#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "flame.h"

#define FLAME_TINY_DIM 147
#define FLAME_TINY_MAX_FRAMES 470
#define REF_PROMPT "a person walks forward and waves."

/* The frames and steps of the CLI reference run (tests/c/run.sh): 24 and 10, or fewer for the
 * valgrind runs; the tests set them from the reference file and their arguments. */
static uint32_t ref_frames = 24;
static uint32_t ref_steps = 10;

/* The settings of the CLI reference run: ref_frames, ref_steps, DDIM, seed 3, one thread. */
static inline void ref_params(FlameSessionParams *p) {
    flame_session_params_default(p);
    p->frames = ref_frames;
    p->steps = ref_steps;
    p->sampler = FLAME_SAMPLER_DDIM;
    p->seed = 3;
    p->threads = 1;
}

/* The whole file in a malloc'd buffer (NULL on error). */
static inline unsigned char *read_file(const char *path, size_t *len) {
    FILE *f = fopen(path, "rb");
    if (!f) {
        return NULL;
    }
    unsigned char *buf = NULL;
    if (fseek(f, 0, SEEK_END) == 0) {
        long n = ftell(f);
        if (n >= 0 && fseek(f, 0, SEEK_SET) == 0) {
            buf = (unsigned char *)malloc((size_t)n + 1);
            if (buf && fread(buf, 1, (size_t)n, f) != (size_t)n) {
                free(buf);
                buf = NULL;
            }
            *len = (size_t)n;
        }
    }
    fclose(f);
    return buf;
}

static inline int write_file(const char *path, const void *bytes, size_t len) {
    FILE *f = fopen(path, "wb");
    if (!f) {
        return 0;
    }
    int ok = fwrite(bytes, 1, len, f) == len;
    return fclose(f) == 0 && ok;
}

/* A C-order little-endian float32 .npy (format 1.0 or 2.0), 2-D or 3-D (rows of the last two
 * dimensions' values), as a malloc'd array. */
static inline float *read_npy_f32(const char *path, size_t *rows, size_t *cols) {
    size_t len = 0;
    unsigned char *b = read_file(path, &len);
    float *out = NULL;
    if (!b || len < 12 || memcmp(b, "\x93NUMPY", 6) != 0) {
        free(b);
        return NULL;
    }
    size_t hlen, start;
    if (b[6] == 1) {
        hlen = (size_t)b[8] | (size_t)b[9] << 8;
        start = 10;
    } else {
        hlen = (size_t)b[8] | (size_t)b[9] << 8 | (size_t)b[10] << 16 | (size_t)b[11] << 24;
        start = 12;
    }
    if (start + hlen > len) {
        free(b);
        return NULL;
    }
    char header[1024] = {0};
    memcpy(header, b + start, hlen < sizeof header - 1 ? hlen : sizeof header - 1);
    unsigned long r = 0, c = 0, d = 1;
    const char *shape = strstr(header, "'shape': (");
    /* 2-D, or 3-D read as rows of c * d values. */
    int dims = shape ? sscanf(shape, "'shape': (%lu, %lu, %lu)", &r, &c, &d) : 0;
    if (dims == 3) {
        c *= d;
    }
    if (strstr(header, "'descr': '<f4'") && strstr(header, "'fortran_order': False") && shape &&
        dims >= 2 &&
        len - start - hlen == (size_t)r * c * sizeof(float)) {
        out = (float *)malloc((size_t)r * c * sizeof(float));
        if (out) {
            memcpy(out, b + start + hlen, (size_t)r * c * sizeof(float));
            *rows = r;
            *cols = c;
        }
    }
    free(b);
    return out;
}

/* Reads `which` in the raw-feature layout into a malloc'd array (NULL on error; the status is
 * in *status). */
static inline float *read_features(const FlameSession *s, int32_t which, size_t *n,
                                   FlameStatus *status) {
    size_t need = 0;
    *status = flame_session_read(s, which, FLAME_LAYOUT_FEATURES, 0, 0, NULL, 0, &need);
    if (*status != FLAME_STATUS_OK) {
        return NULL;
    }
    float *out = (float *)malloc(need * sizeof(float) + 1);
    *status = flame_session_read(s, which, FLAME_LAYOUT_FEATURES, 0, 0, out, need, n);
    if (*status != FLAME_STATUS_OK) {
        free(out);
        return NULL;
    }
    return out;
}

/* Sets the prompt and steps to the end. */
static inline FlameStatus run_to_end(FlameSession *s, const char *prompt) {
    FlameStatus st = flame_session_set_prompt(s, prompt);
    uint32_t left = 1;
    while (st == FLAME_STATUS_OK && left > 0) {
        st = flame_session_step(s, &left);
    }
    return st;
}

/* One whole generation on `model`: a new session, the prompt, every step, the final sample.
 * Returns the malloc'd features (NULL on error, the failing status in *status). */
static inline float *generate(const FlameModel *model, const FlameSessionParams *params,
                              const char *prompt, size_t *n, FlameStatus *status) {
    FlameSession *s = NULL;
    *status = flame_session_new(model, params, &s);
    if (*status != FLAME_STATUS_OK) {
        return NULL;
    }
    float *out = NULL;
    *status = run_to_end(s, prompt);
    if (*status == FLAME_STATUS_OK) {
        out = read_features(s, FLAME_WHICH_SAMPLE, n, status);
    }
    flame_session_free(s);
    return out;
}

/* Equal length and equal bytes: the bit-for-bit comparison every parity check uses. */
static inline int same_bits(const float *a, size_t na, const float *b, size_t nb) {
    return a && b && na == nb && memcmp(a, b, na * sizeof(float)) == 0;
}

/* Seconds since an arbitrary start (for the timings the tests print). */
#include <time.h>
static inline double now_seconds(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

/* This process's threads whose name starts with `prefix` (all threads for ""); -1 if /proc is
 * not there. */
#include <dirent.h>
static inline int count_threads(const char *prefix) {
    DIR *d = opendir("/proc/self/task");
    if (!d) {
        return -1;
    }
    int n = 0;
    struct dirent *e;
    while ((e = readdir(d)) != NULL) {
        if (e->d_name[0] == '.') {
            continue;
        }
        char path[64 + sizeof e->d_name], name[64] = {0};
        snprintf(path, sizeof path, "/proc/self/task/%s/comm", e->d_name);
        FILE *f = fopen(path, "r");
        if (!f) {
            continue;
        }
        if (fgets(name, sizeof name, f) && strncmp(name, prefix, strlen(prefix)) == 0) {
            n++;
        }
        fclose(f);
    }
    closedir(d);
    return n;
}

static inline void sleep_ms(long ms) {
    struct timespec ts;
    ts.tv_sec = ms / 1000;
    ts.tv_nsec = (ms % 1000) * 1000000L;
    nanosleep(&ts, NULL);
}

/* Short runs for valgrind (FLAME_TEST_QUICK=1): fewer frames and steps where a test only
 * needs "long enough". */
static inline int quick_mode(void) {
    const char *q = getenv("FLAME_TEST_QUICK");
    return q && strcmp(q, "1") == 0;
}

#endif /* FLAME_TESTS_UTIL_H */
