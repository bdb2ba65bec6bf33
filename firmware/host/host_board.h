/* The host board's parts (host/): its options (options.c), the signal sources that feed the chip model
 * (signals.c) and the board itself, which runs the firmware's core against them (host_board.c). */
#ifndef HOST_BOARD_H
#define HOST_BOARD_H

#include <stdint.h>
#include <stdio.h>

#include "lsm6dsr_model.h"
#include "tfw_app.h"

#define TIMING_QUEUE 4096
#define STDIN_RECORD_BYTES 12

typedef struct {
    const char *pty_link, *out_path, *signal_path, *gen, *counters_path, *timing_path;
    double seconds, mcu_ppm, mcu_wander_ppm, chip_ppm, stall_every_s, stall_ms, linger_s, wait_open_s;
    long uart_baud, poll_us, timing_every;
    uint32_t t0_us;
    int realtime, absent, st_fail, freq_fine;
    int whoami;
    int signal_gfs, signal_afs;
    tfw_app_config cfg;
} options;

typedef struct {
    int64_t end_offset;              /* the stream offset of the packet's last byte */
    uint16_t seq;
    uint8_t n;
    uint32_t t0_us, first_in_us;
    uint64_t first_sample;           /* its first sample's index in the stream */
} pending_packet;

typedef struct {
    options o;
    lsm_model chip;
    tfw_app app;
    int out_fd;
    FILE *signal_file, *timing;
    int64_t t_ns;                    /* true time since start */
    int64_t start_mono_ns;
    int64_t bytes_out;
    double uart_credit;
    uint64_t rng;
    pending_packet q[TIMING_QUEUE];
    unsigned q_head, q_len;
    uint64_t stdin_records;
    int stdin_eof;
    uint8_t stdin_buf[STDIN_RECORD_BYTES * 256];
    size_t stdin_fill;
    int64_t max_latency_us;
    double latency_sum_us;
    uint64_t latency_n;
} board;

/* options.c: the command line into `o` (0), or a one-line error on stderr (-1); --help exits */
int host_options_parse(int argc, char **argv, options *o);

/* signals.c: what the chip model senses. A generator (--gen rest|sine), a file of raw records looping
 * (--signal PATH), or stdin in push mode (--signal -), each record one chip sample as it arrives. */
void host_signal_generator(void *ctx, int64_t t_ns, double g[3], double a[3]);
void host_signal_from_file(void *ctx, int64_t t_ns, double g[3], double a[3]);
void host_pump_stdin(board *b);

#endif
