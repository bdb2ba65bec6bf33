/* The core's cost per sample on the host, in CPU cycles (rdtsc on x86, the monotonic clock in ns elsewhere):
 * the whole path of a sample (FIFO status, burst read from the register model, pairing, stamp, batch, encode,
 * queue), with the model's own time taken out by timing it alone. Prints JSON. usage: bench-core [seconds] */
#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "tfw_app.h"
#include "lsm6dsr_model.h"

#if defined(__x86_64__) || defined(__i386__)
#include <x86intrin.h>
static uint64_t ticks(void) { return __rdtsc(); }
#define UNIT "cycles"
#else
static uint64_t ticks(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}
#define UNIT "ns"
#endif

static lsm_model chip;

static void sig(void *ctx, int64_t t_ns, double g[3], double a[3]) {
    (void)ctx;
    (void)t_ns;
    g[0] = 1.0; g[1] = -2.0; g[2] = 3.0;
    a[0] = 0.1; a[1] = -0.2; a[2] = 1.0;
}

static int xfer(void *ctx, const uint8_t *tx, uint8_t *rx, size_t n) { return lsm_model_transfer(ctx, tx, rx, n); }

static void delay(void *ctx, uint32_t us) {
    lsm_model *m = ctx;
    lsm_model_advance(m, m->t_ns + (int64_t)us * 1000);
}

static int cmp(const void *a, const void *b) {
    uint64_t x = *(const uint64_t *)a, y = *(const uint64_t *)b;
    return x < y ? -1 : x > y;
}

int main(int argc, char **argv) {
    static tfw_app app;
    double seconds = argc > 1 ? atof(argv[1]) : 20.0;
    const int64_t poll_ns = 150000;                 /* one poll per sample period: the worst case per sample */
    size_t polls = (size_t)(seconds * 1e9 / (double)poll_ns);
    uint64_t *per = calloc(polls, sizeof *per);
    lsm_model_init(&chip);
    chip.signal = sig;
    tfw_bus bus = {xfer, delay, &chip};
    tfw_app_config cfg = tfw_app_default_config();
    cfg.self_test = 0;
    tfw_app_init(&app, &bus, &cfg);
    tfw_app_start(&app, (uint32_t)(chip.t_ns / 1000));
    size_t used = 0;
    uint64_t samples0 = app.counters.samples_sent;
    for (size_t i = 0; i < polls; i++) {
        lsm_model_advance(&chip, chip.t_ns + poll_ns);
        uint32_t before = app.counters.samples_sent + app.batch.n;
        uint64_t t0 = ticks();
        tfw_app_poll(&app, (uint32_t)(chip.t_ns / 1000));
        uint64_t dt = ticks() - t0;
        const uint8_t *p;
        size_t n;
        while ((n = tfw_app_tx_peek(&app, &p)) > 0) {
            tfw_app_tx_done(&app, n);
        }
        uint32_t got = app.counters.samples_sent + app.batch.n - before;
        if (got == 1) {                            /* polls that moved exactly one sample */
            per[used++] = dt;
        }
    }
    qsort(per, used, sizeof *per, cmp);
    /* the model's share: a FIFO status and a two-word burst through the model alone */
    uint64_t model_best = UINT64_MAX;
    for (int i = 0; i < 10000; i++) {
        uint8_t b[1 + 14];
        memset(b, 0, sizeof b);
        lsm_model_advance(&chip, chip.t_ns + poll_ns);
        uint64_t t0 = ticks();
        b[0] = 0x3A | 0x80;
        lsm_model_transfer(&chip, b, b, 3);
        b[0] = 0x78 | 0x80;
        lsm_model_transfer(&chip, b, b, 15);
        uint64_t dt = ticks() - t0;
        if (dt < model_best) {
            model_best = dt;
        }
    }
    printf("{\"unit\": \"%s\", \"polls_with_one_sample\": %zu, \"median\": %llu, \"p99\": %llu, \"p999\": %llu, "
           "\"max\": %llu, \"model_min\": %llu, \"samples\": %llu}\n", UNIT, used,
           (unsigned long long)per[used / 2], (unsigned long long)per[used * 99 / 100],
           (unsigned long long)per[used * 999 / 1000], (unsigned long long)per[used - 1],
           (unsigned long long)model_best, (unsigned long long)(app.counters.samples_sent - samples0));
    free(per);
    return 0;
}
