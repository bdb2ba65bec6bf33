/* Unit tests of the firmware's core on the host: the encoder against the golden vectors, the CRC, the
 * batching deadline, the LSM6DSR driver against the register model, the app and its sample clock.
 * usage: test_core VECTOR_DIR */
#define _GNU_SOURCE
#include <dirent.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "tfw_app.h"
#include "lsm6dsr_model.h"
#include "unit.h"

static const char *vector_dir;

/* ---- CRC and encoder ---------------------------------------------------------------------------- */

static void test_crc_check_value(void) {
    CHECK_EQ(tfw_crc16((const uint8_t *)"123456789", 9), 0x29B1);
    CHECK_EQ(tfw_crc16(NULL, 0), 0xFFFF);
    uint16_t c = tfw_crc16_update(0xFFFF, (const uint8_t *)"1234", 4);
    CHECK_EQ(tfw_crc16_update(c, (const uint8_t *)"56789", 5), 0x29B1);
}

static int hexval(char c) { return c <= '9' ? c - '0' : (c | 0x20) - 'a' + 10; }

static size_t unhex(const char *s, uint8_t *out, size_t cap) {
    size_t n = 0;
    while (s[0] && s[1] && s[0] != '\n' && n < cap) {
        out[n++] = (uint8_t)(hexval(s[0]) << 4 | hexval(s[1]));
        s += 2;
    }
    return n;
}

/* every entry of one .vec file encoded by the core must give the file's bytes exactly */
static int check_vector_file(const char *path) {
    FILE *f = fopen(path, "r");
    static char line[8192];
    static uint8_t want[TFW_MAX_FRAME_BYTES], got[TFW_MAX_FRAME_BYTES], payload[TFW_MAX_LEN];
    tfw_sample rows[TFW_MAX_SAMPLES];
    unsigned seq = 0, n = 0, rows_n = 0, type = 0;
    unsigned long t0 = 0;
    size_t got_len = 0, payload_len = 0, entries = 0;
    char kind = 0;
    CHECK(f != NULL);
    if (!f) {
        return 0;
    }
    while (fgets(line, sizeof line, f)) {
        unsigned odr, gfs, afs, flags;
        int v[6];
        if (line[0] == '#') {
            continue;
        }
        if (sscanf(line, "samples seq=%u t0_us=%lu n=%u", &seq, &t0, &n) == 3) {
            kind = 's';
            rows_n = 0;
        } else if (sscanf(line, "sample %d %d %d %d %d %d", &v[0], &v[1], &v[2], &v[3], &v[4], &v[5]) == 6) {
            for (int k = 0; k < 6; k++) {
                rows[rows_n].v[k] = (int16_t)v[k];
            }
            rows_n++;
        } else if (sscanf(line, "status odr_hz=%u gyro_fs_dps=%u accel_fs_g=%u flags=%u", &odr, &gfs, &afs,
                          &flags) == 4) {
            tfw_status st = {(uint16_t)odr, (uint16_t)gfs, (uint8_t)afs, (uint8_t)flags};
            got_len = tfw_encode_status(&st, got, sizeof got);
            kind = 't';
        } else if (sscanf(line, "identity who_am_i=%u", &type) == 1) {
            got_len = tfw_encode_identity((uint8_t)type, got, sizeof got);
            kind = 'i';
        } else if (sscanf(line, "frame type=%u payload=", &type) == 1) {
            payload_len = unhex(strstr(line, "payload=") + 8, payload, sizeof payload);
            got_len = tfw_encode_frame((uint8_t)type, payload, payload_len, got, sizeof got);
            kind = 'f';
        } else if (strncmp(line, "bytes ", 6) == 0) {
            size_t want_len = unhex(line + 6, want, sizeof want);
            if (kind == 's') {
                CHECK_EQ(rows_n, n);
                got_len = tfw_encode_samples((uint16_t)seq, (uint32_t)t0, rows, rows_n, got, sizeof got);
            }
            CHECK_EQ(got_len, want_len);
            if (got_len != want_len || memcmp(got, want, want_len) != 0) {
                fprintf(stderr, "%s: entry %zu: the encoder's bytes differ from the vector's\n", path, entries);
                unit_failures++;
            }
            entries++;
            kind = 0;
        }
    }
    fclose(f);
    return (int)entries;
}

static void test_encoder_produces_the_golden_vectors(void) {
    DIR *d = opendir(vector_dir);
    struct dirent *e;
    int files = 0, entries = 0;
    CHECK(d != NULL);
    while (d && (e = readdir(d)) != NULL) {
        size_t len = strlen(e->d_name);
        if (len > 4 && strcmp(e->d_name + len - 4, ".vec") == 0) {
            char path[4096];
            snprintf(path, sizeof path, "%s/%s", vector_dir, e->d_name);
            entries += check_vector_file(path);
            files++;
        }
    }
    if (d) {
        closedir(d);
    }
    CHECK(files >= 4);
    CHECK(entries >= 20);
    printf("     %d vector files, %d packets\n", files, entries);
}

static void test_encoder_refuses_what_the_protocol_does_not_allow(void) {
    uint8_t out[TFW_MAX_FRAME_BYTES + 8];
    tfw_sample s[65];
    memset(s, 0, sizeof s);
    memset(out, 0xEE, sizeof out);
    CHECK_EQ(tfw_encode_samples(0, 0, s, 0, out, sizeof out), 0);
    CHECK_EQ(tfw_encode_samples(0, 0, s, 65, out, sizeof out), 0);
    CHECK_EQ(tfw_encode_samples(0, 0, s, 8, out, TFW_SAMPLES_FRAME_BYTES(8) - 1), 0);
    CHECK_EQ(out[0], 0xEE);                                   /* nothing written */
    CHECK_EQ(tfw_encode_samples(0, 0, s, 64, out, sizeof out), TFW_SAMPLES_FRAME_BYTES(64));
    CHECK_EQ(tfw_encode_frame(0x10, out, TFW_MAX_LEN + 1, out, sizeof out), 0);
    tfw_status st = {6667, 4000, 16, 0xFF};
    CHECK_EQ(tfw_encode_status(&st, out, sizeof out), TFW_STATUS_FRAME_BYTES);
    CHECK_EQ(out[TFW_HEADER_BYTES + 5], 0x07);               /* bits 3-7 are zero */
    CHECK_EQ(out[3] | (out[4] << 8), 6);                     /* a status is exactly 6 bytes */
}

/* ---- batching -------------------------------------------------------------------------------------- */

static void test_batch_fills_then_sends_and_seq_wraps(void) {
    tfw_batch b;
    uint8_t out[TFW_SAMPLES_FRAME_BYTES(64)];
    tfw_sample s = {{1, 2, 3, 4, 5, 6}};
    tfw_batch_init(&b, 8, 2000, 65535);
    for (int i = 0; i < 7; i++) {
        CHECK_EQ(tfw_batch_add(&b, &s, 1000u + 150u * (unsigned)i, 1000, out, sizeof out), 0);
    }
    CHECK_EQ(tfw_batch_add(&b, &s, 2050, 1100, out, sizeof out), TFW_SAMPLES_FRAME_BYTES(8));
    CHECK_EQ(out[5] | (out[6] << 8), 65535);
    CHECK_EQ(out[7] | (out[8] << 8), 1000);                  /* t0_us: the first sample's time */
    CHECK_EQ(b.seq, 0);                                      /* wrapped */
    CHECK_EQ(b.n, 0);
}

static void test_batch_deadline_bounds_latency_at_low_rates(void) {
    tfw_batch b;
    uint8_t out[TFW_SAMPLES_FRAME_BYTES(64)];
    tfw_sample s = {{0}};
    tfw_batch_init(&b, 64, 2000, 0);
    CHECK_EQ(tfw_batch_due(&b, 5000, out, sizeof out), 0);  /* empty: nothing due */
    tfw_batch_add(&b, &s, 4294967000u, 4294967000u, out, sizeof out);   /* across the clock's wrap */
    tfw_batch_add(&b, &s, 4294967100u, 4294967100u, out, sizeof out);
    CHECK_EQ(tfw_batch_due(&b, 4294967000u + 1999u, out, sizeof out), 0);
    CHECK_EQ(tfw_batch_due(&b, 4294967000u + 2000u, out, sizeof out), TFW_SAMPLES_FRAME_BYTES(2));
    CHECK_EQ(out[11], 2);
    CHECK_EQ(tfw_batch_due(&b, 4294967000u + 9000u, out, sizeof out), 0);
}

/* ---- the driver against the register model ---------------------------------------------------------- */

typedef struct {
    lsm_model chip;
    int fail_transfers;
} rig;

static int rig_transfer(void *ctx, const uint8_t *tx, uint8_t *rx, size_t n) {
    rig *r = ctx;
    if (r->fail_transfers) {
        return -1;
    }
    return lsm_model_transfer(&r->chip, tx, rx, n);
}

static void rig_delay(void *ctx, uint32_t us) {
    rig *r = ctx;
    lsm_model_advance(&r->chip, r->chip.t_ns + (int64_t)us * 1000);
}

static void sine_signal(void *ctx, int64_t t_ns, double g[3], double a[3]) {
    (void)ctx;
    double t = (double)t_ns * 1e-9;
    g[0] = 100.0 * sin(2 * M_PI * 5 * t);
    g[1] = -250.0;
    g[2] = 1500.0;                                              /* the self-test's 2000 dps leaves room */
    a[0] = 0.5;
    a[1] = -3.0;
    a[2] = 1.0;
}

static void rig_init(rig *r, tfw_lsm6dsr *dev) {
    memset(r, 0, sizeof *r);
    lsm_model_init(&r->chip);
    r->chip.signal = sine_signal;
    tfw_bus bus = {rig_transfer, rig_delay, r};
    tfw_lsm_init(dev, &bus);
}

static const tfw_lsm_config CFG = {6667, 4000, 16, 32};

static void test_driver_reset_and_configure(void) {
    rig r;
    tfw_lsm6dsr dev;
    rig_init(&r, &dev);
    r.chip.reg[LSM_CTRL1_XL] = 0x55;                            /* left over from an earlier run */
    CHECK_EQ(tfw_lsm_probe_and_reset(&dev), TFW_LSM_OK);
    CHECK_EQ(dev.who_am_i, 0x6B);
    CHECK_EQ(r.chip.reg[LSM_CTRL1_XL], 0x00);                   /* the reset cleared it */
    CHECK_EQ(tfw_lsm_configure(&dev, &CFG), TFW_LSM_OK);
    CHECK_EQ(r.chip.reg[LSM_CTRL1_XL], 0xA4);                   /* 6.66 kHz, 16 g */
    CHECK_EQ(r.chip.reg[LSM_CTRL2_G], 0xA1);                    /* 6.66 kHz, 4000 dps */
    CHECK_EQ(r.chip.reg[LSM_CTRL3_C], 0x44);                    /* BDU, IF_INC */
    CHECK_EQ(r.chip.reg[LSM_FIFO_CTRL1], 32);
    CHECK_EQ(r.chip.reg[LSM_FIFO_CTRL3], 0xAA);                 /* both batched at 6667 Hz */
    CHECK_EQ(r.chip.reg[LSM_FIFO_CTRL4], LSM_FIFO_MODE_CONTINUOUS);
    static const struct { uint16_t dps; uint8_t bits; } G[] = {{125, 0xA2}, {250, 0xA0}, {500, 0xA4},
                                                             {1000, 0xA8}, {2000, 0xAC}, {4000, 0xA1}};
    static const struct { uint8_t g; uint8_t bits; } A[] = {{2, 0xA0}, {4, 0xA8}, {8, 0xAC}, {16, 0xA4}};
    for (size_t i = 0; i < 6; i++) {
        tfw_lsm_config c = CFG;
        c.gyro_fs_dps = G[i].dps;
        c.accel_fs_g = A[i % 4].g;
        CHECK_EQ(tfw_lsm_configure(&dev, &c), TFW_LSM_OK);
        CHECK_EQ(r.chip.reg[LSM_CTRL2_G], G[i].bits);
        CHECK_EQ(r.chip.reg[LSM_CTRL1_XL], A[i % 4].bits);
    }
    tfw_lsm_config bad = CFG;
    bad.gyro_fs_dps = 3000;
    CHECK_EQ(tfw_lsm_configure(&dev, &bad), TFW_LSM_ERR_CONFIG);
    bad = CFG;
    bad.odr_hz = 5000;
    CHECK_EQ(tfw_lsm_configure(&dev, &bad), TFW_LSM_ERR_CONFIG);
    bad = CFG;
    bad.watermark_words = 512;
    CHECK_EQ(tfw_lsm_configure(&dev, &bad), TFW_LSM_ERR_CONFIG);
}

/* an LSM6DSO (DS12140): the same register map and rate codes, every range but 4000 dps, which it refuses; its
 * reserved CTRL2_G bit 0 reads 0 in the model, so a driver that wrote it would fail the read-back */
static void test_driver_lsm6dso(void) {
    rig r;
    tfw_lsm6dsr dev;
    rig_init(&r, &dev);
    r.chip.who_am_i = r.chip.reg[LSM_WHO_AM_I] = 0x6C;
    CHECK_EQ(tfw_lsm_probe_and_reset(&dev), TFW_LSM_OK);
    CHECK_EQ(dev.part, TFW_PART_LSM6DSO);
    CHECK_EQ(tfw_lsm_max_gyro_fs(&dev), 2000);
    static const struct { uint16_t dps; uint8_t bits; } G[] = {{125, 0xA2}, {250, 0xA0}, {500, 0xA4},
                                                             {1000, 0xA8}, {2000, 0xAC}};
    for (size_t i = 0; i < 5; i++) {
        tfw_lsm_config c = CFG;
        c.gyro_fs_dps = G[i].dps;
        CHECK_EQ(tfw_lsm_configure(&dev, &c), TFW_LSM_OK);
        CHECK_EQ(r.chip.reg[LSM_CTRL2_G], G[i].bits);
    }
    CHECK_EQ(tfw_lsm_configure(&dev, &CFG), TFW_LSM_ERR_CONFIG);     /* 4000 dps */
    tfw_lsm_self_test st;
    r.chip.st_xl_mg = 45.0;                                     /* in the LSM6DSR's window, not the LSM6DSO's */
    CHECK_EQ(tfw_lsm_self_test_run(&dev, &st), TFW_LSM_OK);
    CHECK_EQ(st.passed, 0);
    rig_init(&r, &dev);
    r.chip.st_xl_mg = 45.0;
    CHECK_EQ(tfw_lsm_probe_and_reset(&dev), TFW_LSM_OK);        /* the LSM6DSR passes it */
    CHECK_EQ(tfw_lsm_self_test_run(&dev, &st), TFW_LSM_OK);
    CHECK_EQ(st.passed, 1);
}

static void test_driver_wrong_who_am_i_and_no_chip(void) {
    rig r;
    tfw_lsm6dsr dev;
    rig_init(&r, &dev);
    r.chip.who_am_i = r.chip.reg[LSM_WHO_AM_I] = 0x69;          /* an LSM6DS3 on the board */
    CHECK_EQ(tfw_lsm_probe_and_reset(&dev), TFW_LSM_ERR_WHO_AM_I);
    CHECK_EQ(dev.who_am_i, 0x69);
    CHECK_EQ(dev.part, TFW_PART_NONE);
    rig_init(&r, &dev);
    r.chip.absent = 1;                                          /* MISO pulled up, nobody answers */
    CHECK_EQ(tfw_lsm_probe_and_reset(&dev), TFW_LSM_ERR_WHO_AM_I);
    CHECK_EQ(dev.who_am_i, 0xFF);
    rig_init(&r, &dev);
    r.fail_transfers = 1;
    CHECK_EQ(tfw_lsm_probe_and_reset(&dev), TFW_LSM_ERR_BUS);
}

static void test_driver_self_test_passes_and_fails(void) {
    rig r;
    tfw_lsm6dsr dev;
    tfw_lsm_self_test st;
    rig_init(&r, &dev);
    CHECK_EQ(tfw_lsm_probe_and_reset(&dev), TFW_LSM_OK);
    CHECK_EQ(tfw_lsm_self_test_run(&dev, &st), TFW_LSM_OK);
    CHECK_EQ(st.passed, 1);
    CHECK(abs(st.accel_delta_mg[0] - 500) <= 2);                /* the model's 500 mg deflection */
    CHECK(abs(st.gyro_delta_dps[2] - 300) <= 1);
    CHECK_EQ(r.chip.reg[LSM_CTRL5_C], 0);                       /* self-test off again */
    rig_init(&r, &dev);
    r.chip.st_xl_mg = 20.0;                                     /* below the datasheet's 40 mg */
    tfw_lsm_probe_and_reset(&dev);
    CHECK_EQ(tfw_lsm_self_test_run(&dev, &st), TFW_LSM_OK);
    CHECK_EQ(st.passed, 0);
    rig_init(&r, &dev);
    r.chip.st_g_dps = 800.0;                                    /* above 700 dps */
    tfw_lsm_probe_and_reset(&dev);
    tfw_lsm_self_test_run(&dev, &st);
    CHECK_EQ(st.passed, 0);
}

static void test_driver_fifo_tags_watermark_and_overrun(void) {
    rig r;
    tfw_lsm6dsr dev;
    tfw_sample out[TFW_LSM_BURST_WORDS];
    uint16_t words;
    uint8_t ovr;
    size_t n;
    rig_init(&r, &dev);
    tfw_lsm_probe_and_reset(&dev);
    CHECK_EQ(tfw_lsm_configure(&dev, &CFG), TFW_LSM_OK);
    lsm_model_advance(&r.chip, r.chip.t_ns + 15 * 149993);      /* 15 samples: 30 tagged words */
    CHECK_EQ(tfw_lsm_fifo_status(&dev, &words, &ovr), TFW_LSM_OK);
    CHECK_EQ(words, 30);
    CHECK_EQ(ovr, 0);
    uint8_t s2 = 0;
    tfw_lsm_read(&dev, LSM_FIFO_STATUS2, &s2, 1);
    CHECK_EQ(s2 & 0x80, 0);                                     /* under the watermark of 32 */
    lsm_model_advance(&r.chip, r.chip.t_ns + 149993);
    tfw_lsm_read(&dev, LSM_FIFO_STATUS2, &s2, 1);
    CHECK_EQ(s2 & 0x80, 0x80);                                  /* 32 words: at the watermark */
    CHECK_EQ(tfw_lsm_fifo_read(&dev, 16, out, TFW_LSM_BURST_WORDS, &n), TFW_LSM_OK);
    CHECK_EQ(n, 8);
    CHECK_EQ(out[0].v[1], (int16_t)lround(-250000.0 / 140.0)); /* gyro y, 140 mdps/LSB */
    CHECK_EQ(out[0].v[2], (int16_t)lround(1500000.0 / 140.0));
    CHECK_EQ(out[0].v[4], (int16_t)lround(-3000.0 / 0.488));   /* accel y, 0.488 mg/LSB */
    CHECK_EQ(out[0].v[5], (int16_t)lround(1000.0 / 0.488));
    CHECK_EQ(dev.words_unpaired, 0);
    /* nothing read for 300 samples: 600 words into a 512-word FIFO */
    lsm_model_advance(&r.chip, r.chip.t_ns + 300 * 149993);
    CHECK_EQ(tfw_lsm_fifo_status(&dev, &words, &ovr), TFW_LSM_OK);
    CHECK_EQ(words, 512);
    CHECK_EQ(ovr, 1);
    CHECK(r.chip.words_overwritten > 0);
    size_t total = 0;
    for (int i = 0; i < 32; i++) {
        tfw_lsm_fifo_read(&dev, 16, out, TFW_LSM_BURST_WORDS, &n);
        total += n;
    }
    CHECK_EQ(total, 256);                                       /* whole pairs: the overwrite took both words */
    CHECK_EQ(tfw_lsm_fifo_status(&dev, &words, &ovr), TFW_LSM_OK);
    CHECK_EQ(ovr, 0);                                           /* the latched flag was read: cleared */
    CHECK_EQ(words, 0);
}

static void test_driver_pairs_by_time_slot_after_a_lost_word(void) {
    rig r;
    tfw_lsm6dsr dev;
    tfw_sample out[TFW_LSM_BURST_WORDS];
    size_t n;
    rig_init(&r, &dev);
    tfw_lsm_probe_and_reset(&dev);
    tfw_lsm_configure(&dev, &CFG);
    lsm_model_advance(&r.chip, r.chip.t_ns + 4 * 149993);
    /* lose one gyro word as an overrun would: its accel partner must not pair with the next slot's gyro */
    r.chip.fifo_head = (uint16_t)((r.chip.fifo_head + 1) % LSM_MODEL_FIFO_WORDS);
    r.chip.fifo_count--;
    tfw_lsm_fifo_read(&dev, 7, out, TFW_LSM_BURST_WORDS, &n);
    CHECK_EQ(n, 3);
    CHECK_EQ(dev.words_unpaired, 1);
}

/* ---- the app: bring-up, status, streaming, the sample clock ----------------------------------------- */

typedef struct {
    rig r;
    tfw_app app;
    double mcu_ppm;
    uint32_t mcu0;
} app_rig;

static uint32_t rig_mcu(const app_rig *a) {
    return a->mcu0 + (uint32_t)(int64_t)floor((double)a->r.chip.t_ns * 1e-3 * (1 + a->mcu_ppm * 1e-6));
}

/* a zeroed rig whose chip sees the sine signal; a test sets what it needs, then app_rig_begin */
static app_rig *app_rig_new(void) {
    static app_rig a;
    memset(&a, 0, sizeof a);
    lsm_model_init(&a.r.chip);
    a.r.chip.signal = sine_signal;
    return &a;
}

static void app_rig_begin(app_rig *a, const tfw_app_config *cfg) {
    tfw_bus bus = {rig_transfer, rig_delay, &a->r};
    tfw_app_init(&a->app, &bus, cfg);
    tfw_app_start(&a->app, rig_mcu(a));
}

/* run for seconds with a poll every poll_us; parse what the app queues with a plain reader */
typedef struct {
    uint32_t samples, packets, statuses, flags_or, last_flags;
    uint32_t identities, last_who_am_i;
    uint32_t seq_gaps;
    int have_seq;
    uint16_t last_seq;
    uint32_t last_t0;
    uint8_t last_n;
    double max_step_err_us;
} stream_stats;

static void consume(app_rig *a, stream_stats *s) {
    static uint8_t buf[TFW_TX_BYTES];
    const uint8_t *p;
    size_t len = 0, k;
    while ((k = tfw_app_tx_peek(&a->app, &p)) > 0) {
        memcpy(buf + len, p, k);
        len += k;
        tfw_app_tx_done(&a->app, k);
    }
    for (size_t i = 0; i + 7 <= len;) {
        uint16_t plen = (uint16_t)(buf[i + 3] | (buf[i + 4] << 8));
        uint8_t type = buf[i + 2];
        CHECK(buf[i] == 0xA5 && buf[i + 1] == 0x5A);
        CHECK_EQ(tfw_crc16(buf + i + 2, 3u + plen), buf[i + 5 + plen] | (buf[i + 6 + plen] << 8));
        const uint8_t *q = buf + i + 5;
        if (type == TFW_TYPE_STATUS) {
            s->statuses++;
            s->flags_or |= q[5];
            s->last_flags = q[5];
        } else if (type == TFW_TYPE_IDENTITY) {
            CHECK_EQ(plen, TFW_IDENTITY_BYTES);
            CHECK_EQ(s->identities + 1u, s->statuses);              /* one after each status */
            s->identities++;
            s->last_who_am_i = q[0];
        } else {
            uint16_t seq = (uint16_t)(q[0] | (q[1] << 8));
            uint32_t t0 = (uint32_t)q[2] | ((uint32_t)q[3] << 8) | ((uint32_t)q[4] << 16) | ((uint32_t)q[5] << 24);
            if (s->have_seq && seq != (uint16_t)(s->last_seq + 1u)) {
                s->seq_gaps++;
            } else if (s->have_seq) {
                double step = (double)(uint32_t)(t0 - s->last_t0), want = s->last_n * 1e6 / 6667.0;
                double err = fabs(step - want) - 1.0;              /* 1 us: t0_us is whole microseconds */
                if (err > s->max_step_err_us) {
                    s->max_step_err_us = err;
                }
            }
            s->have_seq = 1;
            s->last_seq = seq;
            s->last_t0 = t0;
            s->last_n = q[6];
            s->samples += q[6];
            s->packets++;
        }
        i += 7u + plen;
    }
}

static void run(app_rig *a, double seconds, uint32_t poll_us, stream_stats *s) {
    int64_t end = a->r.chip.t_ns + (int64_t)(seconds * 1e9);
    while (a->r.chip.t_ns < end) {
        lsm_model_advance(&a->r.chip, a->r.chip.t_ns + poll_us * 1000);
        tfw_app_poll(&a->app, rig_mcu(a));
        consume(a, s);
    }
}

static void test_app_streams_with_a_status_each_second(void) {
    app_rig *a = app_rig_new();
    stream_stats s = {0};
    tfw_app_config cfg = tfw_app_default_config();
    app_rig_begin(a, &cfg);
    CHECK_EQ(a->app.last_error, TFW_LSM_OK);
    run(a, 3.0, 200, &s);
    CHECK_EQ(s.statuses, 4);                                    /* at start, then at 1, 2 and 3 s */
    CHECK_EQ(s.flags_or, 0);
    CHECK(abs((int)s.samples - 3 * 6667) < 20);
    CHECK_EQ(s.seq_gaps, 0);
    CHECK_EQ(a->app.counters.samples_sent, s.samples);
    CHECK(a->app.counters.max_poll_words <= TFW_POLL_MAX_WORDS);
    CHECK(s.max_step_err_us <= 100e-6 * 1200);                  /* within 100 ppm of a packet's 1.2 ms */
}

/* 4000 dps asked of an LSM6DSO: the app runs it at 2000 and says so in every status, with the part's
 * WHO_AM_I in the identity packet that follows each status */
static void test_app_lsm6dso_at_its_widest_gyro_range(void) {
    app_rig *a = app_rig_new();
    stream_stats s = {0};
    tfw_app_config cfg = tfw_app_default_config();
    a->r.chip.who_am_i = a->r.chip.reg[LSM_WHO_AM_I] = 0x6C;
    app_rig_begin(a, &cfg);
    CHECK_EQ(a->app.last_error, TFW_LSM_OK);
    CHECK_EQ(a->app.active.gyro_fs_dps, 2000);
    CHECK_EQ(a->r.chip.reg[LSM_CTRL2_G], 0xAC);
    run(a, 1.5, 200, &s);
    CHECK(s.statuses >= 2);
    CHECK_EQ(s.identities, s.statuses);
    CHECK_EQ(s.last_who_am_i, 0x6C);
    CHECK_EQ(a->app.counters.identity_sent, s.statuses);
    CHECK(abs((int)s.samples - 10000) < 20);
    CHECK_EQ(s.seq_gaps, 0);
    uint8_t buf[TFW_STATUS_FRAME_BYTES];
    tfw_status st = {a->app.active.odr_hz, a->app.active.gyro_fs_dps, a->app.active.accel_fs_g, 0};
    CHECK_EQ(tfw_encode_status(&st, buf, sizeof buf), TFW_STATUS_FRAME_BYTES);
    CHECK_EQ(buf[7] | (buf[8] << 8), 2000);
}

static void test_app_reports_an_overrun_in_the_next_status_only(void) {
    app_rig *a = app_rig_new();
    stream_stats s = {0};
    tfw_app_config cfg = tfw_app_default_config();
    app_rig_begin(a, &cfg);
    run(a, 1.2, 200, &s);
    lsm_model_advance(&a->r.chip, a->r.chip.t_ns + 60000000);   /* the firmware stalls 60 ms: 800 words */
    run(a, 0.9, 200, &s);                                       /* past the status at 2 s */
    CHECK_EQ(a->app.counters.fifo_overruns, 1);
    CHECK_EQ(a->app.counters.overrun_statuses, 1);
    CHECK(s.flags_or & TFW_FLAG_FIFO_OVERRUN);
    run(a, 1.0, 200, &s);
    CHECK_EQ(s.last_flags, 0);                                  /* the next second was clean */
    CHECK_EQ(s.seq_gaps, 0);                                    /* lost in the sensor: no gap in seq */
}

static void test_app_self_test_failure_is_reported_and_samples_flow(void) {
    app_rig *a = app_rig_new();
    stream_stats s = {0};
    tfw_app_config cfg = tfw_app_default_config();
    a->r.chip.st_xl_mg = 0.0;                                   /* the accelerometer's deflection is gone */
    app_rig_begin(a, &cfg);
    run(a, 1.1, 200, &s);
    CHECK_EQ(s.last_flags, TFW_FLAG_SELF_TEST_FAILED);
    CHECK(s.samples > 6000);
}

static void test_app_without_a_sensor_sends_status_only_and_retries(void) {
    app_rig *a = app_rig_new();
    stream_stats s = {0};
    tfw_app_config cfg = tfw_app_default_config();
    a->r.chip.absent = 1;
    app_rig_begin(a, &cfg);
    run(a, 2.5, 500, &s);
    CHECK_EQ(s.samples, 0);
    CHECK_EQ(s.statuses, 3);
    CHECK_EQ(s.last_flags, TFW_FLAG_SENSOR_ABSENT);
    CHECK_EQ(a->app.counters.sensor_retries, 2);
    a->r.chip.absent = 0;                                       /* the connector is reseated */
    run(a, 3.0, 500, &s);
    CHECK_EQ(s.last_flags, 0);
    CHECK(s.samples > 6000);
}

static void test_app_poll_work_is_bounded(void) {
    app_rig *a = app_rig_new();
    stream_stats s = {0};
    tfw_app_config cfg = tfw_app_default_config();
    app_rig_begin(a, &cfg);
    run(a, 0.2, 200, &s);
    lsm_model_advance(&a->r.chip, a->r.chip.t_ns + 30000000);   /* 400 words waiting */
    uint32_t before = a->app.dev.words_read;
    tfw_app_poll(&a->app, rig_mcu(a));
    CHECK_EQ(a->app.dev.words_read - before, TFW_POLL_MAX_WORDS);
}

static void test_app_sample_clock_follows_a_drifting_mcu(void) {
    app_rig *a = app_rig_new();
    stream_stats s = {0};
    tfw_app_config cfg = tfw_app_default_config();
    a->mcu_ppm = 95.0;                                          /* the crystal at the edge of its tolerance */
    a->mcu0 = 4294000000u;                                      /* the us counter wraps 1 s in */
    cfg.self_test = 0;
    app_rig_begin(a, &cfg);
    run(a, 30.0, 250, &s);
    CHECK_EQ(s.seq_gaps, 0);
    CHECK(s.max_step_err_us < 200e-6 * 1200);                   /* steps within 200 ppm (+1 us of rounding) */
    CHECK_EQ(a->app.stamp.anchors, 1);
    /* the newest sample's stamp against the MCU time it was made */
    int64_t true_mcu = (int64_t)rig_mcu(a);
    double lag_us = (double)(int32_t)((uint32_t)true_mcu - s.last_t0) - (s.last_n - 1) * 149.99;
    CHECK(lag_us >= 0 && lag_us < 2500);
    double period_ppm = ((double)a->app.stamp.period_q / 65536.0 / (1e6 / 6667.0) - 1.0) * 1e6;
    CHECK(fabs(period_ppm - 95.0) < 20.0);
    printf("     period %+.1f ppm (MCU +95 ppm), step error %.3f us, lag %.0f us\n", period_ppm,
           s.max_step_err_us, lag_us);
}

int main(int argc, char **argv) {
    vector_dir = argc > 1 ? argv[1] : "vectors";
    RUN(test_crc_check_value);
    RUN(test_encoder_produces_the_golden_vectors);
    RUN(test_encoder_refuses_what_the_protocol_does_not_allow);
    RUN(test_batch_fills_then_sends_and_seq_wraps);
    RUN(test_batch_deadline_bounds_latency_at_low_rates);
    RUN(test_driver_reset_and_configure);
    RUN(test_driver_lsm6dso);
    RUN(test_driver_wrong_who_am_i_and_no_chip);
    RUN(test_driver_self_test_passes_and_fails);
    RUN(test_driver_fifo_tags_watermark_and_overrun);
    RUN(test_driver_pairs_by_time_slot_after_a_lost_word);
    RUN(test_app_streams_with_a_status_each_second);
    RUN(test_app_lsm6dso_at_its_widest_gyro_range);
    RUN(test_app_reports_an_overrun_in_the_next_status_only);
    RUN(test_app_self_test_failure_is_reported_and_samples_flow);
    RUN(test_app_without_a_sensor_sends_status_only_and_retries);
    RUN(test_app_poll_work_is_bounded);
    RUN(test_app_sample_clock_follows_a_drifting_mcu);
    printf("%d checks, %d failed\n", unit_checks, unit_failures);
    return unit_failures ? 1 : 0;
}
