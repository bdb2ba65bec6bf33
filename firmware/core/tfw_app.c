/* The firmware's logic on any board: sensor bring-up, FIFO to stamped packets, status once a second. */
#include "tfw_app.h"

#include <string.h>

#define DEFAULT_SAMPLES_PER_PACKET 8u    /* 1.2 ms of samples a packet: 110 bytes, 91.7 kB/s at 6667 Hz */
#define DEFAULT_DEADLINE_US 2000u
#define STATUS_PERIOD_US 1000000u
#define WATERMARK_WORDS 32u

tfw_app_config tfw_app_default_config(void) {
    tfw_app_config c;
    memset(&c, 0, sizeof c);
    c.sensor.odr_hz = 6667;
    c.sensor.gyro_fs_dps = 4000;
    c.sensor.accel_fs_g = 16;
    c.sensor.watermark_words = WATERMARK_WORDS;
    c.samples_per_packet = DEFAULT_SAMPLES_PER_PACKET;
    c.flush_deadline_us = DEFAULT_DEADLINE_US;
    c.status_period_us = STATUS_PERIOD_US;
    c.self_test = 1;
    return c;
}

static size_t ring_free(const tfw_ring *r) { return r->size - (r->head - r->tail); }

/* a whole frame or nothing: a frame cut in two would cost the host a resync and the next packet */
static int ring_put(tfw_ring *r, const uint8_t *data, size_t n) {
    if (n > ring_free(r)) {
        return 0;
    }
    for (size_t i = 0; i < n; i++) {
        r->mem[(r->head + i) & (r->size - 1u)] = data[i];
    }
    r->head += (uint32_t)n;
    return 1;
}

size_t tfw_app_tx_pending(const tfw_app *app) { return app->tx.head - app->tx.tail; }

size_t tfw_app_tx_peek(const tfw_app *app, const uint8_t **data) {
    const tfw_ring *r = &app->tx;
    uint32_t off = r->tail & (r->size - 1u);
    size_t n = r->head - r->tail, to_end = r->size - off;
    *data = r->mem + off;
    return n < to_end ? n : to_end;
}

void tfw_app_tx_done(tfw_app *app, size_t n) { app->tx.tail += (uint32_t)n; }

void tfw_app_init(tfw_app *app, const tfw_bus *bus, const tfw_app_config *cfg) {
    memset(app, 0, sizeof *app);
    app->cfg = *cfg;
    app->active = cfg->sensor;
    tfw_lsm_init(&app->dev, bus);
    app->tx.mem = app->tx_mem;
    app->tx.size = TFW_TX_BYTES;
    tfw_batch_init(&app->batch, cfg->samples_per_packet, cfg->flush_deadline_us, 0);
}

static void send_samples(tfw_app *app, size_t len) {
    uint8_t n = app->frame[TFW_HEADER_BYTES + 6];
    int queued = ring_put(&app->tx, app->frame, len);
    if (app->on_frame) {
        app->on_frame(app->on_frame_ctx, app->frame, len, app->batch.first_in_us, queued);
    }
    if (queued) {
        app->counters.packets_sent++;
        app->counters.samples_sent += n;
    } else {
        app->counters.packets_dropped++;
        app->counters.samples_dropped += n;
    }
}

static void send_status(tfw_app *app) {
    tfw_status st = {app->active.odr_hz, app->active.gyro_fs_dps, app->active.accel_fs_g,
                     (uint8_t)(app->flags | (app->overrun_since_status ? TFW_FLAG_FIFO_OVERRUN : 0u))};
    uint8_t buf[TFW_STATUS_FRAME_BYTES];
    size_t len = tfw_encode_status(&st, buf, sizeof buf);
    if (ring_put(&app->tx, buf, len)) {
        app->counters.status_sent++;
        app->counters.overrun_statuses += app->overrun_since_status;
        app->overrun_since_status = 0;      /* reported: the next status covers the next second */
    } else {
        app->counters.status_dropped++;
    }
    /* the part the board found (or what answered in its place), after every status: a reader that opens the
     * port late learns it within a second */
    len = tfw_encode_identity(app->dev.who_am_i, buf, sizeof buf);
    if (ring_put(&app->tx, buf, len)) {
        app->counters.identity_sent++;
    }
}

static int bring_up(tfw_app *app) {
    int rc = tfw_lsm_probe_and_reset(&app->dev);
    if (rc == TFW_LSM_OK && app->cfg.self_test) {
        rc = tfw_lsm_self_test_run(&app->dev, &app->self_test);
        if (rc == TFW_LSM_OK && !app->self_test.passed) {
            app->flags |= TFW_FLAG_SELF_TEST_FAILED;      /* reported in every status; samples still flow */
        }
    }
    app->active = app->cfg.sensor;
    if (rc == TFW_LSM_OK && app->active.gyro_fs_dps > tfw_lsm_max_gyro_fs(&app->dev)) {
        app->active.gyro_fs_dps = tfw_lsm_max_gyro_fs(&app->dev);   /* 4000 dps asked of an LSM6DSO: 2000 */
    }
    if (rc == TFW_LSM_OK) {
        rc = tfw_lsm_configure(&app->dev, &app->active);
    }
    app->last_error = rc;
    app->streaming = rc == TFW_LSM_OK;
    if (app->streaming) {
        app->flags &= (uint8_t)~TFW_FLAG_SENSOR_ABSENT;
        tfw_stamp_init(&app->stamp, tfw_lsm_actual_odr_mhz(&app->dev), TFW_STAMP_WINDOW_US);
    } else if (rc != TFW_LSM_ERR_CONFIG) {
        app->flags |= TFW_FLAG_SENSOR_ABSENT;
    }
    return rc;
}

int tfw_app_start(tfw_app *app, uint32_t now_us) {
    int rc = bring_up(app);
    app->last_now_us = now_us;
    app->now64_us = now_us;
    app->next_status_us = now_us + app->cfg.status_period_us;
    send_status(app);
    return rc;
}

/* the 32-bit clock extended by its forward steps: a clock read that goes back (a timer glitch) is held,
 * never taken for a wrap of 71 minutes */
static int64_t now64(tfw_app *app, uint32_t now_us) {
    int32_t step = (int32_t)(now_us - app->last_now_us);
    if (step > 0) {
        app->now64_us += step;
        app->last_now_us = now_us;
    }
    return app->now64_us;
}

static void read_fifo(tfw_app *app, uint32_t now_us, int64_t t64) {
    uint16_t words = 0, done = 0;
    uint8_t overrun = 0;
    if (tfw_lsm_fifo_status(&app->dev, &words, &overrun) != TFW_LSM_OK) {
        return;
    }
    if (overrun) {
        /* samples were lost inside the sensor: the overrun flag says so, and the times start afresh so
         * that the next packet's t0_us is its own and not that of the samples lost */
        app->counters.fifo_overruns++;
        app->overrun_since_status = 1;
        tfw_stamp_reanchor(&app->stamp);
    }
    if (words > TFW_POLL_MAX_WORDS) {
        words = TFW_POLL_MAX_WORDS;
    }
    if (words > app->counters.max_poll_words) {
        app->counters.max_poll_words = words;
    }
    /* the newest of the unread samples is as late as the read; half-read pairs count as a sample */
    tfw_stamp_observe(&app->stamp, t64, (uint32_t)(words + app->dev.have_g + app->dev.have_xl) / 2u);
    while (done < words) {
        size_t n = 0;
        uint16_t burst = (uint16_t)(words - done);
        if (tfw_lsm_fifo_read(&app->dev, burst, app->read, TFW_LSM_BURST_WORDS, &n) != TFW_LSM_OK) {
            return;
        }
        done = (uint16_t)(done + (burst > TFW_LSM_BURST_WORDS ? TFW_LSM_BURST_WORDS : burst));
        for (size_t i = 0; i < n; i++) {
            size_t len = tfw_batch_add(&app->batch, &app->read[i], tfw_stamp_next(&app->stamp), now_us,
                                       app->frame, sizeof app->frame);
            if (len) {
                send_samples(app, len);
            }
        }
    }
}

void tfw_app_poll(tfw_app *app, uint32_t now_us) {
    int64_t t64 = now64(app, now_us);
    if ((int32_t)(now_us - app->next_status_us) >= 0) {
        app->next_status_us += app->cfg.status_period_us;         /* an absolute schedule: no drift */
        if ((int32_t)(now_us - app->next_status_us) >= 0) {
            app->next_status_us = now_us + app->cfg.status_period_us;    /* stalled: start again from now */
        }
        if (!app->streaming && app->last_error != TFW_LSM_ERR_CONFIG) {
            app->counters.sensor_retries++;
            bring_up(app);               /* a sensor that did not answer: try again each second */
        }
        send_status(app);
    }
    if (!app->streaming) {
        return;
    }
    read_fifo(app, now_us, t64);
    size_t len = tfw_batch_due(&app->batch, now_us, app->frame, sizeof app->frame);
    if (len) {
        send_samples(app, len);
    }
}
