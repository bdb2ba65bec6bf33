/* The firmware's logic on any board: bring the sensor up, then on each poll move FIFO samples into stamped
 * packets, send a status at start and once a second, and queue every frame for the board's UART. */
#ifndef TFW_APP_H
#define TFW_APP_H

#include <stddef.h>
#include <stdint.h>

#include "tfw_batch.h"
#include "tfw_lsm6dsr.h"
#include "tfw_stamp.h"
#include "tfw_wire.h"

#define TFW_TX_BYTES 4096u               /* the UART's queue: 37 packets of 8 samples, 2 ms at 2 Mbaud */
#define TFW_POLL_MAX_WORDS 64u           /* FIFO words one poll reads at most: bounded work per call */
#define TFW_STAMP_WINDOW_US 250000u

typedef struct {
    tfw_lsm_config sensor;
    uint8_t samples_per_packet;          /* 1..64 */
    uint32_t flush_deadline_us;          /* a batch's first sample waits at most this long */
    uint32_t status_period_us;           /* 1 s */
    uint8_t self_test;                   /* run the chip's self-test at start (adds ~0.5 s) */
} tfw_app_config;

typedef struct {
    uint32_t samples_sent;               /* samples in packets queued for the UART */
    uint32_t packets_sent;
    uint32_t status_sent;
    uint32_t packets_dropped;            /* made but not queued: the UART fell behind (the host sees a seq gap) */
    uint32_t samples_dropped;
    uint32_t status_dropped;
    uint32_t identity_sent;              /* identity packets (WHO_AM_I), one after each status */
    uint32_t fifo_overruns;              /* polls that found the sensor's FIFO overrun */
    uint32_t overrun_statuses;           /* status packets sent with flag bit 0 */
    uint32_t sensor_retries;             /* bring-up attempts after the first */
    uint32_t max_poll_words;
} tfw_app_counters;

typedef struct {
    uint8_t *mem;
    uint32_t head, tail;                 /* bytes in: head - tail (free-running, size a power of two) */
    uint32_t size;
} tfw_ring;

typedef struct {
    tfw_app_config cfg;
    tfw_lsm_config active;               /* what the sensor runs, which the status reports: cfg.sensor, with a
                                          * gyro range the part lacks (4000 dps on an LSM6DSO) at its widest */
    tfw_lsm6dsr dev;
    tfw_stamp stamp;
    tfw_batch batch;
    tfw_ring tx;
    uint8_t tx_mem[TFW_TX_BYTES];
    uint8_t frame[TFW_SAMPLES_FRAME_BYTES(TFW_MAX_SAMPLES)];
    tfw_sample read[TFW_LSM_BURST_WORDS];
    tfw_lsm_self_test self_test;
    uint8_t flags;                       /* self-test failed, sensor absent: stay set */
    uint8_t overrun_since_status;
    uint8_t streaming;
    uint32_t next_status_us;
    uint32_t last_now_us;
    int64_t now64_us;                    /* the 32-bit clock unwrapped: a 64-bit time for the stamp */
    int last_error;                      /* tfw_lsm_err of the last bring-up */
    tfw_app_counters counters;
    /* optional, for a host's measurements: each samples frame as made, with the MCU time its first sample
     * was read from the FIFO, and whether it was queued (NULL on a board) */
    void (*on_frame)(void *ctx, const uint8_t *frame, size_t len, uint32_t first_in_us, int queued);
    void *on_frame_ctx;
} tfw_app;

/* cfg is checked: a rate or full scale outside the spec makes tfw_app_start report TFW_LSM_ERR_CONFIG. */
void tfw_app_init(tfw_app *app, const tfw_bus *bus, const tfw_app_config *cfg);
/* Bring the sensor up (probe, reset, self-test, configure) and queue the first status and identity. Returns the bring-up's
 * tfw_lsm_err; on failure the status says so (flag bit 2) and tfw_app_poll retries once a second. */
int tfw_app_start(tfw_app *app, uint32_t now_us);
/* Bounded work: at most TFW_POLL_MAX_WORDS FIFO words, one status and identity, the batch's deadline. */
void tfw_app_poll(tfw_app *app, uint32_t now_us);
/* The UART side: up to max contiguous queued bytes at *data; then tfw_app_tx_done with how many went out. */
size_t tfw_app_tx_peek(const tfw_app *app, const uint8_t **data);
void tfw_app_tx_done(tfw_app *app, size_t n);
size_t tfw_app_tx_pending(const tfw_app *app);
/* A default configuration: 6667 Hz, 4000 dps, 16 g, 8 samples a packet, 2 ms deadline, status every 1 s. */
tfw_app_config tfw_app_default_config(void);

#endif
