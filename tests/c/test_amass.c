/*
 * The AMASS export through the C ABI: flame_session_write_amass in both layouts. The size query
 * (out NULL), BUFFER_TOO_SMALL with the size reported, the same bytes on a second call; the
 * archive read here (ZIP end record, central directory, local headers: PKWARE APPNOTE 4.3) with
 * the keys AMASS uses and their .npy shapes; `trans` + the rest pelvis equal to the root
 * translation flame_session_read gives (smpl24_6d's native frame is AMASS's world); the
 * cleanup's frame rate in `mocap_framerate` and in the frame count; every bad argument refused
 * with INVALID_ARGUMENT (NULL session or out_len, unknown layout or flags, a bad cleanup) and a
 * read before the first step with WRONG_STATE.
 *
 * usage: test_amass FIXTURES_DIR   (tests/fixtures: flame_tiny.safetensors, 20 fps)
 *
 * The motion is read after two of ten steps: the tiny model's final motion saturates.
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
#define FRAMES 24
/* The neutral SMPL template's rest pelvis (Stanford-TML/EDGE vis.py; docs/official/smpl.md#rest-offsets):
 * trans = pelvis - it. */
static const double REST_PELVIS[3] = {-0.00179506, -0.22333345, 0.02821913};

static uint32_t u16_at(const unsigned char *b, size_t i) {
    return (uint32_t)b[i] | (uint32_t)b[i + 1] << 8;
}

static uint32_t u32_at(const unsigned char *b, size_t i) {
    return u16_at(b, i) | u16_at(b, i + 2) << 16;
}

/* The .npy member `name` of the archive `b` (stored): its bytes and length, NULL if absent. */
static const unsigned char *member(const unsigned char *b, size_t len, const char *name,
                                   size_t *size) {
    if (len < 22) {
        return NULL;
    }
    size_t end = len - 22;
    if (u32_at(b, end) != 0x06054b50u) {
        return NULL;
    }
    size_t count = u16_at(b, end + 10), at = u32_at(b, end + 16);
    for (size_t k = 0; k < count && at + 46 <= end; k++) {
        size_t name_len = u16_at(b, at + 28);
        size_t local = u32_at(b, at + 42);
        if (name_len == strlen(name) && memcmp(b + at + 46, name, name_len) == 0) {
            *size = u32_at(b, at + 20);
            return b + local + 30 + u16_at(b, local + 26) + u16_at(b, local + 28);
        }
        at += 46 + name_len + u16_at(b, at + 30) + u16_at(b, at + 32);
    }
    return NULL;
}

/* Whether a .npy's header holds `text` (e.g. "'shape': (24, 156)"). */
static int npy_header_has(const unsigned char *npy, const char *text) {
    size_t hlen = u16_at(npy, 8);
    char header[512];
    if (hlen >= sizeof header) {
        return 0;
    }
    memcpy(header, npy + 10, hlen);
    header[hlen] = '\0';
    return strstr(header, text) != NULL;
}

/* The float64 values of a .npy (C order), after its header. */
static double npy_f64(const unsigned char *npy, size_t i) {
    double v;
    memcpy(&v, npy + 10 + u16_at(npy, 8) + 8 * i, sizeof v);
    return v;
}

/* The archive of `layout` (cleanup may be NULL), malloc'd, its length in *n. */
static unsigned char *write_amass(const FlameSession *s, int32_t layout,
                                  const FlameCleanupParams *c, size_t *n) {
    size_t need = 0;
    *n = 0;
    if (!CHECK_OK(flame_session_write_amass(s, FLAME_WHICH_SAMPLE, layout, 0, c, NULL, 0, &need))) {
        return NULL;
    }
    unsigned char *b = malloc(need);
    if (!b) {
        return NULL;
    }
    CHECK_OK(flame_session_write_amass(s, FLAME_WHICH_SAMPLE, layout, 0, c, b, need, n));
    CHECK(*n == need);
    return b;
}

int main(int argc, char **argv) {
    if (argc < 2) {
        fprintf(stderr, "usage: %s FIXTURES_DIR\n", argv[0]);
        return 2;
    }
    char path[1024];
    snprintf(path, sizeof path, "%s/flame_tiny.safetensors", argv[1]);
    FlameModel *m = NULL;
    CHECK_OK(flame_model_load(path, NULL, &m));
    if (!m) {
        return check_summary();
    }
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
        flame_model_free(m);
        return check_summary();
    }
    size_t n = 0;
    CHECK_OK(flame_session_set_prompt(s, "a person walks forward and waves."));
    CHECK_STATUS(flame_session_write_amass(s, FLAME_WHICH_SAMPLE, FLAME_AMASS_SMPLH, 0, NULL,
                                           NULL, 0, &n),
                 FLAME_STATUS_WRONG_STATE);
    CHECK_OK(flame_session_step(s, NULL));
    CHECK_OK(flame_session_step(s, NULL));

    /* SMPL-H: size query, too small, full; the same bytes twice. */
    size_t need = 0, got = 0;
    CHECK_OK(flame_session_write_amass(s, FLAME_WHICH_SAMPLE, FLAME_AMASS_SMPLH, 0, NULL, NULL, 0,
                                       &need));
    CHECK(need > 1000);
    unsigned char small[16];
    CHECK_STATUS(flame_session_write_amass(s, FLAME_WHICH_SAMPLE, FLAME_AMASS_SMPLH, 0, NULL,
                                           small, sizeof small, &got),
                 FLAME_STATUS_BUFFER_TOO_SMALL);
    CHECK(got == need);
    unsigned char *h = write_amass(s, FLAME_AMASS_SMPLH, NULL, &n);
    size_t n2 = 0;
    unsigned char *h2 = write_amass(s, FLAME_AMASS_SMPLH, NULL, &n2);
    CHECK(h && h2 && n == n2 && memcmp(h, h2, n) == 0);
    free(h2);
    if (h) {
        CHECK(memcmp(h, "PK\x03\x04", 4) == 0);
        CHECK(u16_at(h, n - 22 + 10) == 6);
        size_t size = 0;
        const unsigned char *poses = member(h, n, "poses.npy", &size);
        CHECK(poses && npy_header_has(poses, "'descr': '<f8'") &&
              npy_header_has(poses, "'shape': (24, 156)"));
        const unsigned char *g = member(h, n, "gender.npy", &size);
        CHECK(g && npy_header_has(g, "'descr': '<U7'") && npy_header_has(g, "'shape': ()"));
        const unsigned char *rate = member(h, n, "mocap_framerate.npy", &size);
        CHECK(rate && npy_f64(rate, 0) == 20.0);
        const unsigned char *dmpls = member(h, n, "dmpls.npy", &size);
        CHECK(dmpls && npy_header_has(dmpls, "'shape': (24, 8)"));
        /* trans + the rest pelvis = the root translation of the raw poses. */
        const unsigned char *trans = member(h, n, "trans.npy", &size);
        size_t len = 0;
        float root[FRAMES * 3];
        CHECK_OK(flame_session_read(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION,
                                    FLAME_CONVENTION_NATIVE, 0, root, FRAMES * 3, &len));
        double worst = 0.0;
        for (size_t i = 0; trans && i < FRAMES * 3; i++) {
            double d = fabs(npy_f64(trans, i) + REST_PELVIS[i % 3] - root[i]);
            worst = d > worst ? d : worst;
        }
        CHECK(trans && len == FRAMES * 3 && worst < 1e-5);
    }
    free(h);

    /* SMPL-X at 30 fps through a cleanup: the frames a cleaned read has. */
    FlameCleanupParams c;
    flame_cleanup_params_default(&c);
    c.fps = 30.0f;
    size_t cleaned = 0;
    CHECK_OK(flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION,
                                        FLAME_CONVENTION_NATIVE, 0, &c, NULL, 0, &cleaned));
    unsigned char *x = write_amass(s, FLAME_AMASS_SMPLX, &c, &n);
    if (x) {
        CHECK(u16_at(x, n - 22 + 10) == 13);
        char shape[64];
        snprintf(shape, sizeof shape, "'shape': (%zu, 63)", cleaned / 3);
        size_t size = 0;
        const unsigned char *body = member(x, n, "pose_body.npy", &size);
        CHECK(body && npy_header_has(body, shape));
        const unsigned char *rate = member(x, n, "mocap_frame_rate.npy", &size);
        CHECK(rate && npy_f64(rate, 0) == 30.0);
        const unsigned char *len = member(x, n, "mocap_time_length.npy", &size);
        CHECK(len && fabs(npy_f64(len, 0) - (double)(cleaned / 3) / 30.0) < 1e-12);
        const unsigned char *nb = member(x, n, "num_betas.npy", &size);
        CHECK(nb && npy_header_has(nb, "'descr': '<i8'"));
        CHECK(member(x, n, "surface_model_type.npy", &size) != NULL);
        CHECK(member(x, n, "poses.npy", &size) != NULL);
    }
    free(x);
    /* The clean-motion estimate after a step. */
    CHECK_OK(flame_session_write_amass(s, FLAME_WHICH_ESTIMATE, FLAME_AMASS_SMPLX, 0, NULL, NULL,
                                       0, &n));

    /* Refusals. */
    CHECK_ERROR_MENTIONS(flame_session_write_amass(NULL, 0, 0, 0, NULL, NULL, 0, &n), INV,
                         "session");
    CHECK_ERROR_MENTIONS(flame_session_write_amass(s, 0, 0, 0, NULL, NULL, 0, NULL), INV,
                         "out_len");
    CHECK_ERROR_MENTIONS(flame_session_write_amass(s, 0, 2, 0, NULL, NULL, 0, &n), INV,
                         "AMASS layout 2");
    CHECK_ERROR_MENTIONS(flame_session_write_amass(s, 0, -1, 0, NULL, NULL, 0, &n), INV,
                         "AMASS layout -1");
    CHECK_ERROR_MENTIONS(flame_session_write_amass(s, 0, 0, 0x80, NULL, NULL, 0, &n), INV,
                         "flags");
    CHECK_STATUS(flame_session_write_amass(s, 7, 0, 0, NULL, NULL, 0, &n), INV);
    FlameCleanupParams bad = c;
    bad.fps = -3.0f;
    CHECK_STATUS(flame_session_write_amass(s, 0, 0, 0, &bad, NULL, 0, &n), INV);
    bad = c;
    bad.struct_size = 4;
    CHECK_STATUS(flame_session_write_amass(s, 0, 0, 0, &bad, NULL, 0, &n), INV);

    flame_session_free(s);
    flame_model_free(m);
    return check_summary();
}
