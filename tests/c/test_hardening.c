/*
 * Hostile inputs through the C ABI: none may abort, hang or crash the host; each gets its
 * documented status.
 *
 * usage: test_hardening FIXTURES_DIR   (tests/fixtures: flame_tiny, mdm_tiny, motionfm_tiny)
 *
 * - configuration bombs: every count of each fixture's `flame.config` set to 1e9, 1000000000,
 *   2^64 - 1, 0 and -1 (the model file rebuilt in memory: new header, same tensor data) must be
 *   BAD_MODEL_FILE from flame_model_load_from_memory, naming the field;
 * - layer counts and the CLIP MLP size that the tensors contradict; float fields out of range;
 *   unknown names (schedule, parameterization, variance, sampler, format, activation, uncond,
 *   hidden_act, text kind) at load;
 * - a tokenizer that is not JSON: BAD_MODEL_FILE;
 * - threads 0, FLAME_MAX_THREADS, FLAME_MAX_THREADS + 1 and UINT32_MAX for the model and the
 *   session;
 * - guidance 1e30: INVALID_ARGUMENT.
 * Rewriting a file with its own configuration, or a changed but valid one, loads (so the
 * rewriting itself is not what the bombs trip on).
 */
#define _POSIX_C_SOURCE 200809L

#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "flame.h"

#include "check.h"
#include "util.h"

typedef struct {
    unsigned char *bytes;
    size_t len;
} Buf;

static uint64_t le64(const unsigned char *p) {
    uint64_t n = 0;
    for (int i = 7; i >= 0; i--) {
        n = (n << 8) | p[i];
    }
    return n;
}

/* Where metadata `key`'s JSON string value starts and ends (after the opening quote, at the
 * closing quote) inside the header, or 0. */
static int find_value(const Buf *file, const char *key, size_t *start, size_t *end) {
    size_t n = (size_t)le64(file->bytes);
    const char *h = (const char *)file->bytes + 8;
    char pat[128];
    snprintf(pat, sizeof pat, "\"%s\":\"", key);
    size_t pl = strlen(pat);
    for (size_t i = 0; i + pl <= n; i++) {
        if (memcmp(h + i, pat, pl) == 0) {
            size_t j = i + pl;
            while (j < n && h[j] != '"') {
                j += h[j] == '\\' ? 2 : 1;
            }
            if (j >= n) {
                return 0;
            }
            *start = 8 + i + pl;
            *end = 8 + j;
            return 1;
        }
    }
    return 0;
}

/* Metadata `key`'s value, unescaped (the escapes JSON writers use for these texts). */
static char *metadata(const Buf *file, const char *key) {
    size_t s, e;
    if (!find_value(file, key, &s, &e)) {
        return NULL;
    }
    char *out = (char *)malloc(e - s + 1);
    size_t k = 0;
    for (size_t i = s; i < e; i++) {
        char c = (char)file->bytes[i];
        if (c == '\\' && i + 1 < e) {
            char d = (char)file->bytes[++i];
            c = d == 'n' ? '\n' : d == 't' ? '\t' : d == 'r' ? '\r' : d;
        }
        out[k++] = c;
    }
    out[k] = '\0';
    return out;
}

/* The file with metadata `key` set to `value` (escaped here), the header padded to 8 bytes and
 * its length rewritten; the tensor data is unchanged (offsets are relative to its start). */
static Buf with_metadata(const Buf *file, const char *key, const char *value) {
    size_t s, e;
    Buf out = {NULL, 0};
    if (!find_value(file, key, &s, &e)) {
        return out;
    }
    size_t n = (size_t)le64(file->bytes), vl = strlen(value);
    size_t data = 8 + n, tail = file->len - data;
    unsigned char *b = (unsigned char *)malloc(file->len + 2 * vl + 16);
    size_t k = 8;
    memcpy(b + k, file->bytes + 8, s - 8);
    k += s - 8;
    for (size_t i = 0; i < vl; i++) {
        char c = value[i];
        if (c == '"' || c == '\\') {
            b[k++] = '\\';
        } else if (c == '\n') {
            b[k++] = '\\';
            c = 'n';
        }
        b[k++] = (unsigned char)c;
    }
    memcpy(b + k, file->bytes + e, data - e);
    k += data - e;
    /* The original padding (trailing spaces) stays; pad again to a multiple of 8. */
    while ((k - 8) % 8) {
        b[k++] = ' ';
    }
    uint64_t hn = k - 8;
    for (int i = 0; i < 8; i++) {
        b[i] = (unsigned char)(hn >> (8 * i));
    }
    memcpy(b + k, file->bytes + data, tail);
    out.bytes = b;
    out.len = k + tail;
    return out;
}

/* `config` with `"key": <old>` inside section `"section": {` (NULL: the top level) set to
 * `value` (JSON text), or inserted first in the section when absent. */
static char *set_field(const char *config, const char *section, const char *key,
                       const char *value) {
    const char *from = config;
    if (section) {
        char sec[96];
        snprintf(sec, sizeof sec, "\"%s\": {", section);
        from = strstr(config, sec);
        if (!from) {
            return NULL;
        }
        from += strlen(sec);
    }
    const char *close = strchr(from, '}');
    char pat[96];
    snprintf(pat, sizeof pat, "\"%s\": ", key);
    const char *at = strstr(from, pat);
    size_t cl = strlen(config), vl = strlen(value);
    char *out = (char *)malloc(cl + vl + strlen(pat) + 8);
    if (at && (section == NULL || at < close)) {
        const char *v = at + strlen(pat);
        const char *ve = v;
        if (*ve == '"') {
            ve = strchr(ve + 1, '"') + 1;
        } else {
            while (*ve && *ve != ',' && *ve != '}') {
                ve++;
            }
        }
        size_t pre = (size_t)(v - config);
        memcpy(out, config, pre);
        memcpy(out + pre, value, vl);
        strcpy(out + pre + vl, ve);
    } else {
        size_t pre = (size_t)(from - config);
        memcpy(out, config, pre);
        sprintf(out + pre, "%s%s, %s", pat, value, from);
    }
    return out;
}

typedef struct {
    const char *name;
    Buf file;
    char *config;
} Fixture;

/* Loads `fx` with config field `section.key` set to `value`; returns the status and leaves the
 * message in `err`. A model that loads is freed. */
static int load_with(const Fixture *fx, const char *section, const char *key, const char *value,
                     char *err, size_t err_size) {
    char *cfg = set_field(fx->config, section, key, value);
    if (!cfg) {
        snprintf(err, err_size, "test bug: no field %s.%s in %s", section, key, fx->name);
        return -1;
    }
    Buf b = with_metadata(&fx->file, "flame.config", cfg);
    FlameModel *m = NULL;
    int st = (int)flame_model_load_from_memory(b.bytes, b.len, NULL, &m);
    check_copy_last_error(err, err_size);
    flame_model_free(m);
    free(b.bytes);
    free(cfg);
    return st;
}

/* `section.key = value` must be BAD_MODEL_FILE, the message mentioning `needle` (if any). */
static void expect_bad(const Fixture *fx, const char *section, const char *key,
                       const char *value, const char *needle) {
    char err[512], what[256];
    int st = load_with(fx, section, key, value, err, sizeof err);
    int ok = st == FLAME_STATUS_BAD_MODEL_FILE && err[0] && (!needle || strstr(err, needle));
    snprintf(what, sizeof what, "%s: %s.%s = %s is BAD_MODEL_FILE naming \"%s\" (got %s)",
             fx->name, section ? section : "", key, value, needle ? needle : "",
             flame_status_string(st));
    check_record(ok, __FILE__, __LINE__, what, err);
}

static void expect_loads(const Fixture *fx, const char *section, const char *key,
                         const char *value) {
    char err[512], what[256];
    int st = load_with(fx, section, key, value, err, sizeof err);
    snprintf(what, sizeof what, "%s: %s.%s = %s loads", fx->name, section ? section : "", key,
             value);
    check_record(st == FLAME_STATUS_OK, __FILE__, __LINE__, what, err);
}

typedef struct {
    const char *section;
    const char *key;
} Field;

/* Every count the configuration holds gets the bombs. */
static void bomb_counts(const Fixture *fx, const Field *fields, size_t n) {
    static const char *bombs[] = {"1e9", "1000000000", "18446744073709551615", "0", "-1"};
    for (size_t i = 0; i < n; i++) {
        for (size_t b = 0; b < sizeof bombs / sizeof bombs[0]; b++) {
            int pad = strcmp(fields[i].key, "pad_token_id") == 0;
            if (pad && strcmp(bombs[b], "0") == 0) {
                continue; /* pad id 0 is valid */
            }
            /* The bound checks name the field; a value that is not a non-negative integer
             * fails the schema (serde's message gives the position, not the name). */
            const char *needle = strcmp(bombs[b], "1000000000") == 0 ? fields[i].key : NULL;
            expect_bad(fx, fields[i].section, fields[i].key, bombs[b], needle);
        }
    }
}

static const Field FLAME_COUNTS[] = {
    {NULL, "format_version"},
    {"denoiser", "motion_dim"},
    {"denoiser", "model_channels"},
    {"denoiser", "num_layers"},
    {"denoiser", "num_heads"},
    {"denoiser", "dim_feedforward"},
    {"denoiser", "max_motion_length"},
    {"text_encoder", "vocab_size"},
    {"text_encoder", "hidden_size"},
    {"text_encoder", "num_layers"},
    {"text_encoder", "num_heads"},
    {"text_encoder", "intermediate_size"},
    {"text_encoder", "max_position_embeddings"},
    {"text_encoder", "type_vocab_size"},
    {"text_encoder", "pad_token_id"},
    {"text_encoder", "max_length"},
    {"diffusion", "num_timesteps"},
    {"defaults", "steps"},
    {"defaults", "frames"},
};

static const Field MDM_COUNTS[] = {
    {"denoiser", "njoints"},
    {"denoiser", "latent_dim"},
    {"denoiser", "layers"},
    {"denoiser", "heads"},
    {"denoiser", "ff_size"},
    {"denoiser", "clip_dim"},
    {"denoiser", "max_len"},
    {"text_encoder", "vocab_size"},
    {"text_encoder", "width"},
    {"text_encoder", "layers"},
    {"text_encoder", "heads"},
    {"text_encoder", "intermediate_size"},
    {"text_encoder", "context_length"},
    {"text_encoder", "projection_dim"},
    {"text_encoder", "max_length"},
    {"diffusion", "num_timesteps"},
    {"defaults", "steps"},
    {"defaults", "frames"},
};

#define COUNT(a) (sizeof(a) / sizeof((a)[0]))

static void test_rewrite_controls(const Fixture *fx) {
    /* The file rebuilt with its own configuration loads, and a valid change takes effect. */
    Buf same = with_metadata(&fx->file, "flame.config", fx->config);
    CHECK(same.bytes != NULL);
    FlameModel *m = NULL;
    CHECK_OK(flame_model_load_from_memory(same.bytes, same.len, NULL, &m));
    flame_model_free(m);
    free(same.bytes);

    char *cfg = set_field(fx->config, "defaults", "steps", "7");
    Buf b = with_metadata(&fx->file, "flame.config", cfg);
    m = NULL;
    if (CHECK_OK(flame_model_load_from_memory(b.bytes, b.len, NULL, &m))) {
        FlameModelInfo info;
        memset(&info, 0, sizeof info);
        info.struct_size = sizeof info;
        CHECK_OK(flame_model_info(m, &info));
        CHECK(info.default_steps == 7);
    }
    flame_model_free(m);
    free(b.bytes);
    free(cfg);
}

static void test_flame_config(const Fixture *fx) {
    test_rewrite_controls(fx);
    bomb_counts(fx, FLAME_COUNTS, COUNT(FLAME_COUNTS));
    /* Layer counts the tensors contradict: 3 (no layer 2 stored), 1 (layer 1 stored too). */
    expect_bad(fx, "denoiser", "num_layers", "3", "tf_decoder.layers.2.");
    expect_bad(fx, "denoiser", "num_layers", "1", "tf_decoder.layers.1.");
    expect_bad(fx, "text_encoder", "num_layers", "3", "text.encoder.layer.2.");
    expect_bad(fx, "denoiser", "max_motion_length", "472", "motion_length_emb.weight");
    expect_bad(fx, "denoiser", "dim_feedforward", "256", "linear1.weight");
    expect_bad(fx, "text_encoder", "vocab_size", "980", "word_embeddings");
    /* Floats. */
    expect_bad(fx, "denoiser", "layer_norm_eps", "0", "layer_norm_eps");
    expect_bad(fx, "denoiser", "layer_norm_eps", "-1e-5", "layer_norm_eps");
    expect_bad(fx, "text_encoder", "layer_norm_eps", "1e30", "layer_norm_eps");
    expect_bad(fx, "motion", "fps", "0", "fps");
    expect_bad(fx, "motion", "fps", "-20", "fps");
    expect_bad(fx, "motion", "fps", "1e30", "fps");
    expect_bad(fx, "defaults", "guidance", "1e30", "guidance");
    expect_bad(fx, "defaults", "guidance", "-1", "guidance");
    expect_bad(fx, "defaults", "eta", "1e30", "eta");
    expect_bad(fx, "defaults", "eta", "-0.5", "eta");
    expect_bad(fx, "defaults", "steps", "1001", "steps");
    expect_bad(fx, "defaults", "frames", "471", "frames");
    expect_loads(fx, "defaults", "frames", "470");
    /* Names: each rejected at load, naming the field. */
    expect_bad(fx, "diffusion", "schedule", "\"cosinus\"", "diffusion.schedule");
    expect_bad(fx, "diffusion", "parameterization", "\"noise\"", "diffusion.parameterization");
    expect_bad(fx, "diffusion", "parameterization", "\"velocity\"",
               "diffusion.parameterization");
    expect_bad(fx, "diffusion", "variance", "\"learned\"", "diffusion.variance");
    expect_bad(fx, "diffusion", "uncond", "\"none\"", "diffusion.uncond");
    expect_bad(fx, "diffusion", "uncond", "\"zeros\"", "diffusion.uncond");
    expect_bad(fx, "defaults", "sampler", "\"dpm++\"", "defaults.sampler");
    expect_bad(fx, "defaults", "sampler", "\"euler\"", "defaults.sampler");
    expect_bad(fx, "motion", "format", "\"bvh\"", "motion.format");
    expect_bad(fx, "motion", "format", "\"humanml263\"", "motion.format");
    expect_bad(fx, "denoiser", "activation", "\"swish\"", "denoiser.activation");
    expect_bad(fx, "text_encoder", "hidden_act", "\"relu\"", "hidden_act");
    expect_bad(fx, "text_encoder", "kind", "\"t6\"", "text_encoder.kind");
    expect_bad(fx, "text_encoder", "kind", "\"t5\"", "cannot use a `t5` text encoder");
    expect_bad(fx, "text_encoder", "kind", "\"clip\"", NULL);
    expect_bad(fx, NULL, "architecture", "\"unet\"", "architecture");
    /* The sampler's spellings (any case) are still accepted. */
    expect_loads(fx, "diffusion", "schedule", "\"squaredcos_cap_v2\"");
    expect_loads(fx, "diffusion", "parameterization", "\"EPS\"");
    expect_loads(fx, "defaults", "sampler", "\"ddim\"");
}

static void test_mdm_config(const Fixture *fx) {
    test_rewrite_controls(fx);
    bomb_counts(fx, MDM_COUNTS, COUNT(MDM_COUNTS));
    expect_bad(fx, "denoiser", "layers", "3", "seqTransEncoder.layers.2.");
    expect_bad(fx, "text_encoder", "layers", "1", "text.text_model.encoder.layers.1.");
    /* The CLIP MLP size comes from the configuration (4 x width = 128 when absent). */
    expect_loads(fx, "text_encoder", "intermediate_size", "128");
    expect_bad(fx, "text_encoder", "intermediate_size", "96", "mlp.fc1.weight");
    expect_bad(fx, "text_encoder", "max_length", "78", "max_length");
    expect_bad(fx, "denoiser", "max_len", "999", "max_len"); /* no row for t = 999 */
    expect_bad(fx, "diffusion", "variance", "\"learned_range\"", "learned_range");
    expect_bad(fx, "defaults", "frames", "5000", "frames");
    expect_bad(fx, "defaults", "sampler", "\"heun\"", "defaults.sampler");
    expect_bad(fx, "denoiser", "activation", "\"swish\"", "denoiser.activation");
}

static void test_motionfm_config(const Fixture *fx) {
    test_rewrite_controls(fx);
    bomb_counts(fx, MDM_COUNTS, COUNT(MDM_COUNTS));
    expect_bad(fx, "defaults", "steps", "10001", "steps");
    expect_loads(fx, "defaults", "steps", "10000");
    expect_bad(fx, "defaults", "sampler", "\"ddpm\"", "defaults.sampler");
    expect_bad(fx, "diffusion", "parameterization", "\"x0\"", "parameterization");
    expect_bad(fx, "denoiser", "max_len", "1000", "max_len"); /* row trunc(1000 t) at t = 1 */
    expect_loads(fx, "defaults", "sampler", "\"midpoint\"");
}

static void test_tokenizer(const Fixture *fx) {
    static const char *bad[] = {"not json", "{}", "", "{\"model\": {\"type\": \"Nonsense\"}}"};
    for (size_t i = 0; i < COUNT(bad); i++) {
        Buf b = with_metadata(&fx->file, "flame.tokenizer", bad[i]);
        FlameModel *m = NULL;
        CHECK_ERROR_MENTIONS(flame_model_load_from_memory(b.bytes, b.len, NULL, &m),
                             FLAME_STATUS_BAD_MODEL_FILE, "tokenizer");
        CHECK(m == NULL);
        free(b.bytes);
    }
    /* The real tokenizer rewritten through the same path loads. */
    char *tok = metadata(&fx->file, "flame.tokenizer");
    Buf b = with_metadata(&fx->file, "flame.tokenizer", tok);
    FlameModel *m = NULL;
    CHECK_OK(flame_model_load_from_memory(b.bytes, b.len, NULL, &m));
    flame_model_free(m);
    free(b.bytes);
    free(tok);
}

static void test_threads(const Fixture *fx) {
    CHECK(FLAME_MAX_THREADS == 256);
    const uint32_t fine[] = {0, 1, FLAME_MAX_THREADS};
    const uint32_t over[] = {FLAME_MAX_THREADS + 1, 100000, UINT32_MAX};
    FlameModelParams mp;
    flame_model_params_default(&mp);
    for (size_t i = 0; i < COUNT(fine); i++) {
        mp.threads = fine[i];
        FlameModel *m = NULL;
        CHECK_OK(flame_model_load_from_memory(fx->file.bytes, fx->file.len, &mp, &m));
        flame_model_free(m);
    }
    for (size_t i = 0; i < COUNT(over); i++) {
        mp.threads = over[i];
        FlameModel *m = NULL;
        CHECK_ERROR_MENTIONS(flame_model_load_from_memory(fx->file.bytes, fx->file.len, &mp, &m),
                             FLAME_STATUS_INVALID_ARGUMENT, "above the limit of 256");
        CHECK(m == NULL);
    }

    mp.threads = 1;
    FlameModel *m = NULL;
    if (!CHECK_OK(flame_model_load_from_memory(fx->file.bytes, fx->file.len, &mp, &m))) {
        return;
    }
    FlameSessionParams sp;
    for (size_t i = 0; i < COUNT(fine); i++) {
        flame_session_params_default(&sp);
        sp.threads = fine[i];
        FlameSession *s = NULL;
        CHECK_OK(flame_session_new(m, &sp, &s));
        flame_session_free(s);
    }
    for (size_t i = 0; i < COUNT(over); i++) {
        flame_session_params_default(&sp);
        sp.threads = over[i];
        FlameSession *s = NULL;
        char needle[64];
        snprintf(needle, sizeof needle, "threads %u is above the limit of 256", over[i]);
        CHECK_ERROR_MENTIONS(flame_session_new(m, &sp, &s), FLAME_STATUS_INVALID_ARGUMENT,
                             needle);
        CHECK(s == NULL);
    }

    /* Guidance: 100 is the bound; above it (or infinite) is refused at session start. */
    const float bad_guidance[] = {1e30f, 100.5f};
    for (size_t i = 0; i < COUNT(bad_guidance); i++) {
        flame_session_params_default(&sp);
        sp.guidance = bad_guidance[i];
        sp.threads = 1;
        FlameSession *s = NULL;
        CHECK_ERROR_MENTIONS(flame_session_new(m, &sp, &s), FLAME_STATUS_INVALID_ARGUMENT,
                             "guidance");
        CHECK(s == NULL);
    }
    flame_session_params_default(&sp);
    sp.guidance = 100.0f;
    sp.threads = 1;
    FlameSession *s = NULL;
    CHECK_OK(flame_session_new(m, &sp, &s));
    flame_session_free(s);
    flame_model_free(m);
}

static int open_fixture(Fixture *fx, const char *dir, const char *name) {
    char path[4096];
    snprintf(path, sizeof path, "%s/%s.safetensors", dir, name);
    fx->name = name;
    fx->file.bytes = read_file(path, &fx->file.len);
    fx->config = fx->file.bytes ? metadata(&fx->file, "flame.config") : NULL;
    if (!fx->config) {
        fprintf(stderr, "cannot read the configuration of %s\n", path);
        return 0;
    }
    return 1;
}

int main(int argc, char **argv) {
    if (argc != 2) {
        fprintf(stderr, "usage: %s FIXTURES_DIR\n", argv[0]);
        return 2;
    }
    Fixture flame, mdm, motionfm;
    if (!open_fixture(&flame, argv[1], "flame_tiny") || !open_fixture(&mdm, argv[1], "mdm_tiny") ||
        !open_fixture(&motionfm, argv[1], "motionfm_tiny")) {
        return 2;
    }
    test_flame_config(&flame);
    test_mdm_config(&mdm);
    test_motionfm_config(&motionfm);
    test_tokenizer(&flame);
    test_tokenizer(&mdm);
    test_threads(&flame);
    Fixture *all[] = {&flame, &mdm, &motionfm};
    for (size_t i = 0; i < COUNT(all); i++) {
        free(all[i]->file.bytes);
        free(all[i]->config);
    }
    return check_summary();
}
