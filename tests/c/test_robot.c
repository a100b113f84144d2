/*
 * Robots through the C ABI: flame_robot_load and its queries, flame_robot_retarget_new, the
 * whole clip of a session as each FLAME_ROBOT_* file (size query, BUFFER_TOO_SMALL, the CSV's
 * rows and header, the .npz and .npy records), the per-frame reads through a FlameRobotState
 * (deterministic: a reset state gives the same frames again, frame by frame or in chunks; unit
 * root quaternions x, y, z, w), a stream read, and every refusal (malformed URDF, a cycle, a
 * configuration naming a missing body, unknown files and options, a state of another retarget,
 * short buffers, frames past the read).
 *
 * usage: test_robot FIXTURES_DIR GR1T2.urdf GR1T2.json
 *   (tests/fixtures: flame_tiny.safetensors; the URDF fetched by tools/fetch_robots.sh; the
 *   configuration libflame ships as robots/gr1t2.json)
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
#define DOFS 32

static const char CYCLE[] =
    "<robot name=\"c\"><link name=\"a\"/><link name=\"b\"/>"
    "<joint name=\"ab\" type=\"fixed\"><parent link=\"a\"/><child link=\"b\"/></joint>"
    "<joint name=\"ba\" type=\"fixed\"><parent link=\"b\"/><child link=\"a\"/></joint></robot>";

/* The file `file` of the session's sample (options as given), malloc'd; its size in *n. */
static unsigned char *write_robot(const FlameRobotRetarget *r, const FlameSession *s,
                                  uint32_t file, uint32_t options, size_t *n) {
    size_t need = 0;
    *n = 0;
    if (!CHECK_OK(flame_robot_retarget_write(r, s, FLAME_WHICH_SAMPLE, 0, NULL, file, options,
                                             NULL, 0, &need))) {
        return NULL;
    }
    unsigned char *b = malloc(need + 1);
    if (!b) {
        return NULL;
    }
    CHECK_OK(flame_robot_retarget_write(r, s, FLAME_WHICH_SAMPLE, 0, NULL, file, options, b, need,
                                        n));
    CHECK(*n == need);
    b[need] = '\0';
    return b;
}

static size_t count_char(const unsigned char *b, size_t n, char c) {
    size_t k = 0;
    for (size_t i = 0; i < n; i++) {
        k += b[i] == (unsigned char)c;
    }
    return k;
}

/* Frames first..first+count through `state`, into the four buffers (all FRAMES long). */
static int read_frames(const FlameRobotRetarget *r, const FlameRobotState *st,
                       const FlameSession *s, size_t first, size_t count, double *pos,
                       double *rot, double *q, double *res) {
    return CHECK_OK(flame_robot_retarget_read(r, st, s, FLAME_WHICH_SAMPLE, 0, NULL, first, count,
                                              pos + 3 * first, 3 * count, rot + 4 * first,
                                              4 * count, q + DOFS * first, DOFS * count,
                                              res + first, count, NULL));
}

int main(int argc, char **argv) {
    if (argc < 4) {
        fprintf(stderr, "usage: %s FIXTURES_DIR ROBOT.urdf CONFIG.json\n", argv[0]);
        return 2;
    }
    size_t urdf_len = 0, config_len = 0;
    unsigned char *urdf = read_file(argv[2], &urdf_len);
    unsigned char *config = read_file(argv[3], &config_len);
    if (!urdf || !config) {
        fprintf(stderr, "cannot read %s or %s (bash tools/fetch_robots.sh)\n", argv[2], argv[3]);
        free(urdf);
        free(config);
        return 2;
    }

    /* The robot and its queries. */
    FlameRobot *robot = NULL;
    CHECK_OK(flame_robot_load(urdf, urdf_len, &robot));
    size_t dofs = 0;
    const char *name = NULL;
    CHECK_OK(flame_robot_dof_count(robot, &dofs));
    CHECK(dofs == DOFS);
    CHECK_OK(flame_robot_dof_name(robot, 0, &name));
    CHECK(name && strcmp(name, "left_hip_roll_joint") == 0);
    CHECK_OK(flame_robot_name(robot, &name));
    CHECK(name && strcmp(name, "gr1t2") == 0);
    CHECK_ERROR_MENTIONS(flame_robot_dof_name(robot, DOFS, &name), INV, "past");
    FlameRobot *bad = NULL;
    CHECK_STATUS(flame_robot_load((const uint8_t *)CYCLE, strlen(CYCLE), &bad), INV);
    CHECK_STATUS(flame_robot_load(urdf, urdf_len / 2, &bad), INV);
    CHECK_ERROR_MENTIONS(flame_robot_load(NULL, 10, &bad), INV, "urdf");
    CHECK_ERROR_MENTIONS(flame_robot_load(urdf, urdf_len, NULL), INV, "out");
    CHECK(bad == NULL);
    flame_robot_free(NULL);

    /* The retarget: the robot may go once it is made. */
    FlameRobotRetarget *r = NULL, *r2 = NULL;
    CHECK_OK(flame_robot_retarget_new(robot, config, config_len, &r));
    CHECK_OK(flame_robot_retarget_new(robot, config, config_len, &r2));
    const char *missing = "{\"robot_root_name\": \"no_such_body\"}";
    FlameRobotRetarget *rbad = NULL;
    CHECK_ERROR_MENTIONS(flame_robot_retarget_new(robot, (const uint8_t *)missing,
                                                  strlen(missing), &rbad),
                         INV, "no_such_body");
    CHECK_STATUS(flame_robot_retarget_new(robot, (const uint8_t *)"{", 1, &rbad), INV);
    CHECK_ERROR_MENTIONS(flame_robot_retarget_new(NULL, config, config_len, &rbad), INV, "robot");
    flame_robot_free(robot);
    CHECK_OK(flame_robot_retarget_dof_count(r, &dofs));
    CHECK(dofs == DOFS);

    /* A session, read after two of ten steps (the tiny model's final motion saturates). */
    char path[1024];
    snprintf(path, sizeof path, "%s/flame_tiny.safetensors", argv[1]);
    FlameModel *m = NULL;
    CHECK_OK(flame_model_load(path, NULL, &m));
    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = FRAMES;
    p.steps = 10;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.seed = 5;
    p.threads = 1;
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(m, &p, &s));
    CHECK_OK(flame_session_set_prompt(s, "a person walks forward and waves."));
    size_t n = 0;
    CHECK_STATUS(flame_robot_retarget_write(r, s, FLAME_WHICH_SAMPLE, 0, NULL,
                                            FLAME_ROBOT_BEYONDMIMIC_CSV_XYZW, 0, NULL, 0, &n),
                 FLAME_STATUS_WRONG_STATE);
    CHECK_OK(flame_session_step(s, NULL));
    CHECK_OK(flame_session_step(s, NULL));

    /* Whole clips. */
    unsigned char small[8];
    size_t got = 0;
    CHECK_STATUS(flame_robot_retarget_write(r, s, FLAME_WHICH_SAMPLE, 0, NULL,
                                            FLAME_ROBOT_BEYONDMIMIC_CSV_XYZW, 0, small,
                                            sizeof small, &got),
                 FLAME_STATUS_BUFFER_TOO_SMALL);
    CHECK(got > 1000);
    unsigned char *csv = write_robot(r, s, FLAME_ROBOT_BEYONDMIMIC_CSV_XYZW, 0, &n);
    if (csv) {
        CHECK(count_char(csv, n, '\n') == FRAMES);
        CHECK(count_char(csv, n, ',') == FRAMES * (7 + DOFS - 1));
        CHECK(csv[0] != '#');
    }
    size_t nh = 0;
    unsigned char *csvh = write_robot(r, s, FLAME_ROBOT_BEYONDMIMIC_CSV_XYZW,
                                      FLAME_ROBOT_CSV_HEADER, &nh);
    if (csv && csvh) {
        CHECK(strncmp((const char *)csvh, "# x,y,z,qx,qy,qz,qw,left_hip_roll_joint,", 40) == 0);
        const char *rows = strchr((const char *)csvh, '\n');
        CHECK(rows && strcmp(rows + 1, (const char *)csv) == 0);
    }
    free(csvh);
    unsigned char *npz = write_robot(r, s, FLAME_ROBOT_GMR_NPZ_XYZW, 0, &n);
    CHECK(npz && memcmp(npz, "PK\x03\x04", 4) == 0);
    CHECK(npz && strstr((const char *)npz + 30, "fps.npy") != NULL);
    free(npz);
    unsigned char *npy = write_robot(r, s, FLAME_ROBOT_QPOS_NPY_WXYZ, 0, &n);
    CHECK(npy && memcmp(npy, "\x93NUMPY", 6) == 0);
    CHECK(npy && strstr((const char *)npy + 10, "'shape': (24, 39)") != NULL);
    free(npy);
    unsigned char *qcsv = write_robot(r, s, FLAME_ROBOT_QPOS_CSV_WXYZ, FLAME_ROBOT_CSV_HEADER, &n);
    CHECK(qcsv && strncmp((const char *)qcsv, "# x,y,z,qw,qx,qy,qz,", 20) == 0);
    free(qcsv);
    CHECK_STATUS(flame_robot_retarget_write(r, s, 0, 0, NULL, FLAME_ROBOT_GMR_NPZ_XYZW,
                                            FLAME_ROBOT_CSV_HEADER, NULL, 0, &n),
                 INV);
    CHECK_ERROR_MENTIONS(flame_robot_retarget_write(r, s, 0, 0, NULL, 4, 0, NULL, 0, &n), INV,
                         "robot trajectory file 4");
    CHECK_ERROR_MENTIONS(flame_robot_retarget_write(r, s, 0, 0, NULL, 0, 2, NULL, 0, &n), INV,
                         "options");
    CHECK_ERROR_MENTIONS(flame_robot_retarget_write(r, s, 0, 0, NULL, 0, 0, NULL, 0, NULL), INV,
                         "out_len");
    CHECK_ERROR_MENTIONS(flame_robot_retarget_write(NULL, s, 0, 0, NULL, 0, 0, NULL, 0, &n), INV,
                         "retarget");

    /* Per-frame reads: in chunks, then frame by frame from a reset state: the same bits. */
    FlameRobotState *st = NULL, *other = NULL;
    CHECK_OK(flame_robot_state_new(r, &st));
    CHECK_OK(flame_robot_state_new(r2, &other));
    size_t frames = 0;
    CHECK_OK(flame_robot_retarget_read(r, st, s, 0, 0, NULL, 0, 0, NULL, 0, NULL, 0, NULL, 0,
                                       NULL, 0, &frames));
    CHECK(frames == FRAMES);
    static double pos[2][FRAMES * 3], rot[2][FRAMES * 4], q[2][FRAMES * DOFS], res[2][FRAMES];
    for (size_t f = 0; f < FRAMES; f += 6) {
        read_frames(r, st, s, f, 6, pos[0], rot[0], q[0], res[0]);
    }
    CHECK_OK(flame_robot_state_reset(st));
    for (size_t f = 0; f < FRAMES; f++) {
        read_frames(r, st, s, f, 1, pos[1], rot[1], q[1], res[1]);
    }
    CHECK(memcmp(pos[0], pos[1], sizeof pos[0]) == 0 && memcmp(rot[0], rot[1], sizeof rot[0]) == 0 &&
          memcmp(q[0], q[1], sizeof q[0]) == 0 && memcmp(res[0], res[1], sizeof res[0]) == 0);
    double worst = 0.0;
    int finite = 1;
    for (size_t f = 0; f < FRAMES; f++) {
        double nq = 0.0;
        for (int k = 0; k < 4; k++) {
            nq += rot[0][4 * f + k] * rot[0][4 * f + k];
        }
        worst = fmax(worst, fabs(sqrt(nq) - 1.0));
        finite &= isfinite(res[0][f]) && res[0][f] >= 0.0 && isfinite(pos[0][3 * f + 2]);
    }
    CHECK(worst < 1e-9 && finite);
    double one[DOFS];
    CHECK_STATUS(flame_robot_retarget_read(r, st, s, 0, 0, NULL, 0, 1, NULL, 0, NULL, 0, one,
                                           DOFS - 1, NULL, 0, NULL),
                 FLAME_STATUS_BUFFER_TOO_SMALL);
    CHECK_ERROR_MENTIONS(flame_robot_retarget_read(r, st, s, 0, 0, NULL, FRAMES, 1, NULL, 0,
                                                   NULL, 0, one, DOFS, NULL, 0, NULL),
                         INV, "past");
    CHECK_ERROR_MENTIONS(flame_robot_retarget_read(r, other, s, 0, 0, NULL, 0, 1, NULL, 0, NULL,
                                                   0, one, DOFS, NULL, 0, NULL),
                         INV, "another retarget");
    CHECK_ERROR_MENTIONS(flame_robot_retarget_read(r, NULL, s, 0, 0, NULL, 0, 1, NULL, 0, NULL, 0,
                                                   one, DOFS, NULL, 0, NULL),
                         INV, "state");
    CHECK_STATUS(flame_robot_state_reset(NULL), INV);

    /* A stream: frames as they come, cleaned (game-ready feet, the floor at 0). */
    FlameStreamParams sp;
    flame_stream_params_default(&sp);
    sp.threads = 1;
    FlameStream *stream = NULL;
    CHECK_OK(flame_stream_new(m, &sp, &stream));
    CHECK_OK(flame_stream_push(stream, "a person walks forward.", 40));
    FlameCleanupParams c;
    flame_cleanup_params_default(&c);
    FlameRobotState *live = NULL;
    CHECK_OK(flame_robot_state_new(r, &live));
    double sq[4 * DOFS], srot[4 * 4];
    CHECK_STATUS(flame_robot_retarget_read_stream(r, live, stream, 0, 4, &c, NULL, 0, srot, 16, sq,
                                                  4 * DOFS, NULL, 0),
                 FLAME_STATUS_WRONG_STATE);
    FlameStreamStatus ss;
    ss.struct_size = sizeof ss;
    for (int k = 0; k < 200 && CHECK_OK(flame_stream_pump(stream, 10, &ss)) && ss.ready < 40;
         k++) {
    }
    CHECK(ss.ready >= 40);
    /* The timeline is complete: every frame's cleanup settles. */
    CHECK_OK(flame_stream_close(stream));
    CHECK_OK(flame_robot_retarget_read_stream(r, live, stream, 0, 4, &c, NULL, 0, srot, 16, sq,
                                              4 * DOFS, NULL, 0));
    CHECK(fabs(srot[0] * srot[0] + srot[1] * srot[1] + srot[2] * srot[2] + srot[3] * srot[3] - 1.0) <
          1e-9);
    CHECK_OK(flame_robot_retarget_read_stream(r, live, stream, 4, 4, &c, NULL, 0, NULL, 0, sq,
                                              4 * DOFS, NULL, 0));
    CHECK_ERROR_MENTIONS(flame_robot_retarget_read_stream(r, live, NULL, 0, 1, NULL, NULL, 0,
                                                          NULL, 0, NULL, 0, NULL, 0),
                         INV, "stream");

    flame_robot_state_free(live);
    flame_stream_free(stream);
    flame_robot_state_free(st);
    flame_robot_state_free(other);
    flame_robot_state_free(NULL);
    flame_robot_retarget_free(r);
    flame_robot_retarget_free(r2);
    flame_robot_retarget_free(NULL);
    flame_session_free(s);
    flame_model_free(m);
    free(csv);
    free(urdf);
    free(config);
    return check_summary();
}
