/* The host board's signal sources: what the LSM6DSR register model senses (host_board.h). */
#define _GNU_SOURCE
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <unistd.h>

#include "host_board.h"

static double noise(board *b) {
    b->rng = b->rng * 6364136223846793005ULL + 1442695040888963407ULL;
    return ((double)(b->rng >> 11) / 9007199254740992.0) - 0.5;
}

void host_signal_generator(void *ctx, int64_t t_ns, double g[3], double a[3]) {
    board *b = ctx;
    double t = (double)t_ns * 1e-9;
    if (b->o.gen && strcmp(b->o.gen, "sine") == 0) {
        g[0] = 100.0 * sin(2 * M_PI * 5.0 * t);
        g[1] = 50.0 * cos(2 * M_PI * 3.0 * t);
        g[2] = 10.0 * sin(2 * M_PI * 1.0 * t);
        a[0] = 0.5 * sin(2 * M_PI * 7.0 * t);
        a[1] = 0.25 * cos(2 * M_PI * 2.0 * t);
        a[2] = 1.0 + 0.1 * sin(2 * M_PI * 11.0 * t);
    } else {                         /* rest: gravity along +z and the noise of a chip at rest */
        for (int k = 0; k < 3; k++) {
            g[k] = 0.2 * noise(b);
            a[k] = 0.004 * noise(b);
        }
        a[2] += 1.0;
    }
}

static void raw_to_physical(const options *o, const uint8_t *p, double g[3], double a[3]) {
    static const struct { int fs; double s; } GS[] = {{125, 4.375}, {250, 8.75}, {500, 17.5}, {1000, 35},
                                                    {2000, 70}, {4000, 140}};
    static const struct { int fs; double s; } AS[] = {{2, 0.061}, {4, 0.122}, {8, 0.244}, {16, 0.488}};
    double gs = 140, as = 0.488;
    for (size_t i = 0; i < 6; i++) {
        if (GS[i].fs == o->signal_gfs) {
            gs = GS[i].s;
        }
    }
    for (size_t i = 0; i < 4; i++) {
        if (AS[i].fs == o->signal_afs) {
            as = AS[i].s;
        }
    }
    for (int k = 0; k < 3; k++) {
        g[k] = (int16_t)(p[2 * k] | (p[2 * k + 1] << 8)) * gs * 1e-3;
        a[k] = (int16_t)(p[6 + 2 * k] | (p[7 + 2 * k] << 8)) * as * 1e-3;
    }
}

void host_signal_from_file(void *ctx, int64_t t_ns, double g[3], double a[3]) {
    board *b = ctx;
    uint8_t rec[STDIN_RECORD_BYTES];
    (void)t_ns;
    if (fread(rec, 1, sizeof rec, b->signal_file) != sizeof rec) {
        rewind(b->signal_file);      /* a signal file loops */
        if (fread(rec, 1, sizeof rec, b->signal_file) != sizeof rec) {
            memset(rec, 0, sizeof rec);
        }
    }
    raw_to_physical(&b->o, rec, g, a);
}

/* push mode: every whole record on stdin is one sample of the chip, now */
void host_pump_stdin(board *b) {
    for (;;) {
        ssize_t r = read(STDIN_FILENO, b->stdin_buf + b->stdin_fill, sizeof b->stdin_buf - b->stdin_fill);
        if (r == 0) {
            b->stdin_eof = 1;
            return;
        }
        if (r < 0) {
            return;                  /* EAGAIN: nothing more now */
        }
        b->stdin_fill += (size_t)r;
        size_t whole = b->stdin_fill / STDIN_RECORD_BYTES * STDIN_RECORD_BYTES;
        for (size_t off = 0; off < whole; off += STDIN_RECORD_BYTES) {
            double g[3], a[3];
            raw_to_physical(&b->o, b->stdin_buf + off, g, a);
            lsm_model_emit(&b->chip, g, a);
            b->stdin_records++;
        }
        memmove(b->stdin_buf, b->stdin_buf + whole, b->stdin_fill - whole);
        b->stdin_fill -= whole;
    }
}
