/* Sample times on the MCU's microsecond clock. The chip samples on its own oscillator; the FIFO says only
 * how many samples came. Each sample is stamped one period after the one before (so a packet's t0_us steps
 * by n periods, without the jitter of the reads), and the period and phase are steered to the MCU clock
 * from the reads: the phase by the smallest delay between a sample's predicted time and a read that found
 * it, the period by a baseline of such points. */
#ifndef TFW_STAMP_H
#define TFW_STAMP_H

#include <stdint.h>

#define TFW_STAMP_POINTS 16u

typedef struct {
    int64_t t_next_q;          /* MCU time of the next sample, us << 16 */
    uint64_t k_next;           /* its index since the last anchor */
    int64_t period_q;          /* estimated period, us << 16 */
    int64_t nominal_q;
    int64_t slew_q;            /* per-sample phase correction in force, us << 16 */
    int64_t window_us;         /* phase window */
    int64_t window_end_us;
    int64_t best_lat_q;        /* the window's smallest (read time - predicted time of the newest sample) */
    int64_t best_t_us;
    uint64_t best_k;
    int64_t pt_t[TFW_STAMP_POINTS];   /* baseline points: (time, index) of each window's best read */
    uint64_t pt_k[TFW_STAMP_POINTS];
    uint32_t n_points;
    uint32_t windows;
    uint32_t anchors;          /* re-anchored (start, overrun, a phase error beyond repair) */
    uint8_t started;
} tfw_stamp;

/* odr_mhz: the chip's rate in mHz (e.g. 6667000); window_us: how often phase and period are steered. */
void tfw_stamp_init(tfw_stamp *s, uint32_t odr_mhz, uint32_t window_us);
/* Drop the phase (after samples were lost in the sensor); the period estimate is kept. */
void tfw_stamp_reanchor(tfw_stamp *s);
/* A read at now_us found `unread` samples in the FIFO, of which the oldest is the next to be stamped. */
void tfw_stamp_observe(tfw_stamp *s, int64_t now_us, uint32_t unread);
/* The next sample's time, us, wrapping at 2^32. */
uint32_t tfw_stamp_next(tfw_stamp *s);

#endif
