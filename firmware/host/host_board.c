/* The host board: the firmware's core, built natively against the LSM6DSR register model, streaming
 * tecdar-imu/1 to a pseudo-terminal (or a file) as a board streams to its USB-serial bridge. The MCU clock,
 * the chip's oscillator and the UART are modelled; the signal comes from a generator, a file, or stdin in
 * real time (the simulator's fingertip). This is how the tests put the real firmware code in the loop.
 * Its options are options.c's, its signal sources signals.c's. */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "host_board.h"

#define WANDER_PERIOD_S 300.0

static volatile sig_atomic_t stop_requested;

static void on_signal(int sig) {
    (void)sig;
    stop_requested = 1;
}

static int64_t mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

/* the MCU's free-running microsecond counter at true time t: an offset, a rate error and a slow wander */
static uint32_t mcu_us(const board *b, int64_t t_ns) {
    double t = (double)t_ns * 1e-9;
    double wander = b->o.mcu_wander_ppm * WANDER_PERIOD_S / (2 * M_PI) * (1 - cos(2 * M_PI * t / WANDER_PERIOD_S));
    double us = t * 1e6 * (1 + b->o.mcu_ppm * 1e-6) + wander;
    return b->o.t0_us + (uint32_t)(int64_t)floor(us);
}

static int bus_transfer(void *ctx, const uint8_t *tx, uint8_t *rx, size_t n) {
    return lsm_model_transfer(&((board *)ctx)->chip, tx, rx, n);
}

/* the firmware's busy-wait: time passes for the chip (and the wall clock in real time) */
static void bus_delay(void *ctx, uint32_t us) {
    board *b = ctx;
    b->t_ns += (int64_t)us * 1000;
    if (b->o.realtime) {
        struct timespec ts = {(time_t)((b->start_mono_ns + b->t_ns) / 1000000000),
                              (long)((b->start_mono_ns + b->t_ns) % 1000000000)};
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL);
    }
    if (b->o.signal_path && strcmp(b->o.signal_path, "-") == 0) {
        host_pump_stdin(b);               /* push mode: the signal keeps coming while the firmware waits */
    } else {
        lsm_model_advance(&b->chip, b->t_ns);
    }
}

static void drain_uart(board *b, double dt_s) {
    double per_step = (double)b->o.uart_baud / 10.0 * dt_s;
    b->uart_credit += per_step;
    if (b->uart_credit > per_step + 1.0) {
        b->uart_credit = per_step + 1.0;   /* an idle line saves no time for later (one holding register) */
    }
    while (b->uart_credit >= 1.0 && tfw_app_tx_pending(&b->app)) {
        const uint8_t *p;
        size_t n = tfw_app_tx_peek(&b->app, &p);
        if (n > (size_t)b->uart_credit) {
            n = (size_t)b->uart_credit;
        }
        ssize_t w = write(b->out_fd, p, n);
        if (w <= 0) {
            return;                  /* the reader is not reading: the bytes wait in the UART queue */
        }
        tfw_app_tx_done(&b->app, (size_t)w);
        b->bytes_out += w;
        b->uart_credit -= (double)w;
    }
    uint32_t now = mcu_us(b, b->t_ns);
    while (b->q_len && b->q[b->q_head].end_offset <= b->bytes_out) {
        pending_packet *pp = &b->q[b->q_head];
        int64_t lat = (int64_t)(uint32_t)(now - pp->first_in_us);
        if (lat > b->max_latency_us) {
            b->max_latency_us = lat;
        }
        b->latency_sum_us += (double)lat;
        b->latency_n++;
        if (b->timing && b->latency_n % (uint64_t)b->o.timing_every == 0) {
            fprintf(b->timing, "%llu,%u,%u,%lld\n", (unsigned long long)pp->first_sample, pp->n, pp->t0_us,
                    (long long)b->t_ns);
        }
        b->q_head = (b->q_head + 1) % TIMING_QUEUE;
        b->q_len--;
    }
}

/* each samples frame the firmware makes: when queued, its last byte's place in the stream */
static void on_frame(void *ctx, const uint8_t *f, size_t len, uint32_t first_in_us, int queued) {
    board *b = ctx;
    if (!queued || b->q_len >= TIMING_QUEUE) {
        return;
    }
    pending_packet *pp = &b->q[(b->q_head + b->q_len) % TIMING_QUEUE];
    pp->end_offset = b->bytes_out + (int64_t)tfw_app_tx_pending(&b->app);
    pp->seq = (uint16_t)(f[5] | (f[6] << 8));
    pp->t0_us = (uint32_t)f[7] | ((uint32_t)f[8] << 8) | ((uint32_t)f[9] << 16) | ((uint32_t)f[10] << 24);
    pp->n = f[11];
    pp->first_in_us = first_in_us;
    pp->first_sample = b->app.counters.samples_sent;      /* the counters count it after this call */
    b->q_len++;
    (void)len;
}

static int open_pty(const char *link) {
    int fd = posix_openpt(O_RDWR | O_NOCTTY);
    if (fd < 0 || grantpt(fd) || unlockpt(fd)) {
        return -1;
    }
    const char *name = ptsname(fd);
    int s = open(name, O_RDWR | O_NOCTTY);
    if (s >= 0) {                    /* raw, as a USB-CDC or UART bridge delivers bytes */
        struct termios tio;
        tcgetattr(s, &tio);
        cfmakeraw(&tio);
        tcsetattr(s, TCSANOW, &tio);
        close(s);
    }
    char tmp[4096];
    snprintf(tmp, sizeof tmp, "%s.tmp", link);
    unlink(tmp);
    if (symlink(name, tmp) || rename(tmp, link)) {
        return -1;
    }
    fcntl(fd, F_SETFL, fcntl(fd, F_GETFL) | O_NONBLOCK);
    return fd;
}

/* a pty master reports POLLHUP while no one holds the other end open */
static int wait_reader(int fd, double seconds) {
    int64_t end = mono_ns() + (int64_t)(seconds * 1e9);
    while (mono_ns() < end && !stop_requested) {
        struct pollfd p = {fd, POLLOUT, 0};
        poll(&p, 1, 0);
        if (!(p.revents & POLLHUP)) {
            return 1;
        }
        usleep(2000);
    }
    return 0;
}

static void write_counters(const board *b) {
    if (!b->o.counters_path) {
        return;
    }
    FILE *f = fopen(b->o.counters_path, "w");
    if (!f) {
        fprintf(stderr, "host-board: cannot write %s: %s\n", b->o.counters_path, strerror(errno));
        return;
    }
    const tfw_app_counters *c = &b->app.counters;
    fprintf(f,
            "{\"samples_sent\": %u, \"packets_sent\": %u, \"status_sent\": %u, \"packets_dropped\": %u, "
            "\"samples_dropped\": %u, \"status_dropped\": %u, \"identity_sent\": %u, \"fifo_overruns\": %u, \"overrun_statuses\": %u, "
            "\"sensor_retries\": %u, \"max_poll_words\": %u, \"words_unpaired\": %u, \"words_read\": %u, "
            "\"chip_samples\": %llu, \"chip_words_overwritten\": %llu, \"chip_overruns\": %llu, "
            "\"bytes_out\": %lld, \"bytes_unsent\": %zu, \"stdin_records\": %llu, \"flags\": %u, "
            "\"last_error\": %d, \"who_am_i\": %u, \"self_test_passed\": %u, \"stamp_anchors\": %u, "
            "\"first_fifo_ns\": %lld, \"chip_period_ns\": %lld, \"true_ns\": %lld, "
            "\"latency_max_us\": %lld, \"latency_mean_us\": %.1f, \"packets_timed\": %llu}\n",
            c->samples_sent, c->packets_sent, c->status_sent, c->packets_dropped, c->samples_dropped,
            c->status_dropped, c->identity_sent, c->fifo_overruns, c->overrun_statuses, c->sensor_retries, c->max_poll_words,
            b->app.dev.words_unpaired, b->app.dev.words_read, (unsigned long long)b->chip.samples_made,
            (unsigned long long)b->chip.words_overwritten, (unsigned long long)b->chip.overruns,
            (long long)b->bytes_out, tfw_app_tx_pending(&b->app), (unsigned long long)b->stdin_records,
            b->app.flags, b->app.last_error, b->app.dev.who_am_i, b->app.self_test.passed, b->app.stamp.anchors,
            (long long)b->chip.first_fifo_ns,
            (long long)lsm_model_period_ns(&b->chip, (uint8_t)(b->chip.reg[0x10] >> 4)),
            (long long)b->t_ns, (long long)b->max_latency_us,
            b->latency_n ? b->latency_sum_us / (double)b->latency_n : 0.0, (unsigned long long)b->latency_n);
    fclose(f);
}

int main(int argc, char **argv) {
    static board b;                  /* static: the model's FIFO and the app are a few tens of kB */
    if (host_options_parse(argc, argv, &b.o)) {
        return 2;
    }
    signal(SIGINT, on_signal);
    signal(SIGTERM, on_signal);
    signal(SIGPIPE, SIG_IGN);
    b.rng = 0x2545F4914F6CDD1DULL;
    lsm_model_init(&b.chip);
    b.chip.who_am_i = (uint8_t)b.o.whoami;
    b.chip.reg[0x0F] = (uint8_t)b.o.whoami;
    b.chip.absent = (uint8_t)b.o.absent;
    b.chip.odr_ppm = b.o.chip_ppm;
    b.chip.freq_fine = (int8_t)b.o.freq_fine;
    b.chip.reg[0x63] = (uint8_t)b.o.freq_fine;
    if (b.o.st_fail) {
        b.chip.st_xl_mg = 10.0;      /* a deflection below the datasheet's window */
        b.chip.st_g_dps = 0.0;
    }
    int push = b.o.signal_path && strcmp(b.o.signal_path, "-") == 0;
    if (push) {
        fcntl(STDIN_FILENO, F_SETFL, fcntl(STDIN_FILENO, F_GETFL) | O_NONBLOCK);
    } else if (b.o.signal_path) {
        b.signal_file = fopen(b.o.signal_path, "rb");
        if (!b.signal_file) {
            fprintf(stderr, "host-board: cannot read --signal %s: %s\n", b.o.signal_path, strerror(errno));
            return 2;
        }
        b.chip.signal = host_signal_from_file;
        b.chip.signal_ctx = &b;
    } else {
        b.chip.signal = host_signal_generator;
        b.chip.signal_ctx = &b;
    }
    if (b.o.pty_link) {
        b.out_fd = open_pty(b.o.pty_link);
        if (b.out_fd < 0) {
            fprintf(stderr, "host-board: cannot make a pseudo-terminal at %s: %s\n", b.o.pty_link, strerror(errno));
            return 2;
        }
        if (b.o.wait_open_s > 0 && !wait_reader(b.out_fd, b.o.wait_open_s)) {
            fprintf(stderr, "host-board: no reader opened %s within %.1f s\n", b.o.pty_link, b.o.wait_open_s);
            return 3;
        }
    } else if (strcmp(b.o.out_path, "-") == 0) {
        b.out_fd = STDOUT_FILENO;
    } else {
        b.out_fd = open(b.o.out_path, O_WRONLY | O_CREAT | O_TRUNC, 0644);
        if (b.out_fd < 0) {
            fprintf(stderr, "host-board: cannot write --out %s: %s\n", b.o.out_path, strerror(errno));
            return 2;
        }
    }
    if (b.o.timing_path) {
        b.timing = fopen(b.o.timing_path, "w");
        if (!b.timing) {
            fprintf(stderr, "host-board: cannot write --timing %s: %s\n", b.o.timing_path, strerror(errno));
            return 2;
        }
    }
    tfw_bus bus = {bus_transfer, bus_delay, &b};
    tfw_app_init(&b.app, &bus, &b.o.cfg);
    b.app.on_frame = on_frame;
    b.app.on_frame_ctx = &b;
    b.start_mono_ns = mono_ns();
    int rc = tfw_app_start(&b.app, mcu_us(&b, b.t_ns));
    if (rc != TFW_LSM_OK) {
        fprintf(stderr, "host-board: the sensor did not come up (error %d, WHO_AM_I 0x%02X); status only\n", rc,
                b.app.dev.who_am_i);
    }
    const int64_t poll_ns = b.o.poll_us * 1000;
    const int64_t end_ns = b.o.seconds > 0 ? b.t_ns + (int64_t)(b.o.seconds * 1e9) : INT64_MAX;
    while (!stop_requested && b.t_ns < end_ns && !(push && b.stdin_eof)) {
        b.t_ns += poll_ns;
        if (b.o.realtime) {
            int64_t due = b.start_mono_ns + b.t_ns;
            struct timespec ts = {(time_t)(due / 1000000000), (long)(due % 1000000000)};
            clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL);
        }
        if (push) {
            host_pump_stdin(&b);
        } else {
            lsm_model_advance(&b.chip, b.t_ns);
        }
        double t_s = (double)b.t_ns * 1e-9;
        int stalled = b.o.stall_every_s > 0 && fmod(t_s, b.o.stall_every_s) >= b.o.stall_every_s - b.o.stall_ms * 1e-3;
        if (!stalled) {
            tfw_app_poll(&b.app, mcu_us(&b, b.t_ns));
        }
        drain_uart(&b, (double)poll_ns * 1e-9);
    }
    /* the stream has ended: what the UART still holds goes out, then the port stays open for the reader */
    for (int i = 0; i < 1000 && tfw_app_tx_pending(&b.app) && !stop_requested; i++) {
        b.t_ns += poll_ns;
        drain_uart(&b, (double)poll_ns * 1e-9);
        if (b.o.realtime) {
            usleep((useconds_t)b.o.poll_us);
        }
    }
    write_counters(&b);
    if (b.timing) {
        fclose(b.timing);
    }
    if (b.o.pty_link && b.o.linger_s > 0) {
        int64_t end = mono_ns() + (int64_t)(b.o.linger_s * 1e9);
        while (!stop_requested && mono_ns() < end) {
            usleep(10000);
        }
    }
    if (b.o.pty_link) {
        unlink(b.o.pty_link);
    }
    return 0;
}
