/* Sample times on the MCU's microsecond clock, steered from the FIFO reads (see tfw_stamp.h). */
#include "tfw_stamp.h"

#include <string.h>

#define Q 16
#define MAX_SLEW_PPM 50            /* phase corrections move a step by at most this: within the spec's 100 ppm */
#define CATCH_UP_SLEW_PPM 500      /* ... unless the phase is this far off (a start on a chip whose rate is off) */
#define CATCH_UP_US 300
#define MAX_RATE_ERROR_PPM 30000   /* the period estimate stays within 3 % of the chip's stated rate */
#define REANCHOR_US 2000           /* a phase error beyond this is not slewed away but re-anchored */
#define POINT_EVERY_WINDOWS 4u     /* a baseline point every 4 windows (1 s at 250 ms) */
#define MIN_BASELINE_S 1

void tfw_stamp_init(tfw_stamp *s, uint32_t odr_mhz, uint32_t window_us) {
    memset(s, 0, sizeof *s);
    s->nominal_q = ((int64_t)1000000000 << Q) / (int64_t)(odr_mhz ? odr_mhz : 1u);
    s->period_q = s->nominal_q;
    s->window_us = window_us;
}

void tfw_stamp_reanchor(tfw_stamp *s) {
    s->started = 0;
    s->n_points = 0;
    s->slew_q = 0;
}

static int64_t clamp64(int64_t v, int64_t lo, int64_t hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* the end of a window: steer the phase (slew) and the period (baseline) */
static void steer(tfw_stamp *s) {
    int64_t samples = (s->window_us << Q) / s->period_q;
    int64_t err_q = -s->best_lat_q;            /* the best read saw the newest sample at lat 0: shift by it */
    int64_t far = err_q > ((int64_t)CATCH_UP_US << Q) || err_q < -((int64_t)CATCH_UP_US << Q);
    int64_t max_slew = s->period_q * (far ? CATCH_UP_SLEW_PPM : MAX_SLEW_PPM) / 1000000;
    if (err_q > ((int64_t)REANCHOR_US << Q) || err_q < -((int64_t)REANCHOR_US << Q)) {
        tfw_stamp_reanchor(s);
        return;
    }
    s->slew_q = clamp64(-err_q / (samples > 0 ? samples : 1), -max_slew, max_slew);
    if (s->windows % POINT_EVERY_WINDOWS == 0u) {
        uint32_t i = s->n_points % TFW_STAMP_POINTS;
        uint32_t oldest = s->n_points >= TFW_STAMP_POINTS ? i : 0u;
        s->pt_t[i] = s->best_t_us;
        s->pt_k[i] = s->best_k;
        s->n_points++;
        int64_t dt = s->best_t_us - s->pt_t[oldest];
        uint64_t dk = s->best_k - s->pt_k[oldest];
        if (dk > 0 && dt >= (int64_t)MIN_BASELINE_S * 1000000) {
            int64_t p = (dt << Q) / (int64_t)dk;
            int64_t lim = s->nominal_q * MAX_RATE_ERROR_PPM / 1000000;
            s->period_q = clamp64(p, s->nominal_q - lim, s->nominal_q + lim);
        }
    }
}

void tfw_stamp_observe(tfw_stamp *s, int64_t now_us, uint32_t unread) {
    if (!s->started) {
        /* the newest sample is taken as read the moment it was made */
        s->t_next_q = (now_us << Q) - (int64_t)(unread ? unread - 1u : 0u) * s->period_q;
        s->k_next = 0;
        s->window_end_us = now_us + s->window_us;
        s->best_lat_q = INT64_MAX;
        s->started = 1;
        s->anchors++;
        return;
    }
    if (!unread) {
        return;
    }
    uint64_t k_newest = s->k_next + unread - 1u;
    int64_t pred_q = s->t_next_q + (int64_t)(unread - 1u) * (s->period_q + s->slew_q);
    int64_t lat_q = (now_us << Q) - pred_q;
    if (lat_q < s->best_lat_q) {
        s->best_lat_q = lat_q;
        s->best_t_us = now_us;
        s->best_k = k_newest;
    }
    if (now_us >= s->window_end_us) {
        s->windows++;
        steer(s);
        s->window_end_us = now_us + s->window_us;
        s->best_lat_q = INT64_MAX;
    }
}

uint32_t tfw_stamp_next(tfw_stamp *s) {
    int64_t t = (s->t_next_q + (1 << (Q - 1))) >> Q;
    s->t_next_q += s->period_q + s->slew_q;
    s->k_next++;
    return (uint32_t)t;
}
