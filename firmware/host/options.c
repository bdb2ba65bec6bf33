/* The host board's command line (host_board.h). */
#define _GNU_SOURCE
#include <getopt.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "host_board.h"

static void usage(FILE *f) {
    fprintf(f,
            "usage: host-board (--pty LINK | --out PATH|-) [options]\n"
            "  --pty LINK          create a pseudo-terminal and link LINK to it\n"
            "  --out PATH|-        write the stream to a file or stdout (no real time unless --realtime)\n"
            "  --signal PATH|-     raw int16 gx gy gz ax ay az records (12 bytes, little-endian) at --signal-fs;\n"
            "                      '-': from stdin, each record one chip sample as it arrives\n"
            "  --signal-fs DPS,G   full scales of the signal's records (default 4000,16)\n"
            "  --gen rest|sine     a generated signal (default rest)\n"
            "  --seconds S         how long to stream, s (default: until stopped or stdin ends)\n"
            "  --realtime          pace to the wall clock (always with --pty)\n"
            "  --poll-us US        the firmware's poll period, us (default 250)\n"
            "  --odr HZ --gyro-fs DPS --accel-fs G --batch N --deadline-us US --no-self-test\n"
            "  --mcu-ppm PPM --mcu-wander-ppm PPM --chip-ppm PPM --freq-fine N --t0-us US\n"
            "  --uart-baud BAUD    the UART's rate, 10 bits a byte (default 2000000)\n"
            "  --stall-every S --stall-ms MS   the firmware stops polling MS ms every S s (forces FIFO overruns)\n"
            "  --whoami 0xNN --absent --self-test-fail   a wrong part, no part, a failing self-test\n"
            "  --counters PATH     the firmware's counters as JSON when it stops\n"
            "  --timing PATH       a line per samples packet: its first sample's index, n, t0_us, and the true\n"
            "                      time (ns) its last byte left the UART; --timing-every K: every Kth packet\n"
            "  --wait-open S       with --pty: wait up to S s for a reader before starting\n"
            "  --linger S          with --pty: keep the port open S s after the stream ends\n");
}

int host_options_parse(int argc, char **argv, options *o) {
    static const struct option opts[] = {
        {"pty", 1, 0, 'p'}, {"out", 1, 0, 'o'}, {"signal", 1, 0, 's'}, {"signal-fs", 1, 0, 'F'},
        {"gen", 1, 0, 'g'}, {"seconds", 1, 0, 'S'}, {"realtime", 0, 0, 'r'}, {"poll-us", 1, 0, 'P'},
        {"odr", 1, 0, 'O'}, {"gyro-fs", 1, 0, 'G'}, {"accel-fs", 1, 0, 'A'}, {"batch", 1, 0, 'b'},
        {"deadline-us", 1, 0, 'd'}, {"no-self-test", 0, 0, 'N'}, {"mcu-ppm", 1, 0, 'm'},
        {"mcu-wander-ppm", 1, 0, 'w'}, {"chip-ppm", 1, 0, 'c'}, {"freq-fine", 1, 0, 'f'}, {"t0-us", 1, 0, 't'},
        {"uart-baud", 1, 0, 'u'}, {"stall-every", 1, 0, 'E'}, {"stall-ms", 1, 0, 'M'}, {"whoami", 1, 0, 'W'},
        {"absent", 0, 0, 'a'}, {"self-test-fail", 0, 0, 'x'}, {"counters", 1, 0, 'C'}, {"timing", 1, 0, 'T'}, {"timing-every", 1, 0, 'K'},
        {"wait-open", 1, 0, 'L'}, {"linger", 1, 0, 'l'}, {"help", 0, 0, 'h'}, {0, 0, 0, 0}};
    int c;
    memset(o, 0, sizeof *o);
    o->cfg = tfw_app_default_config();
    o->uart_baud = 2000000;
    o->poll_us = 250;
    o->timing_every = 1;
    o->whoami = 0x6B;
    o->signal_gfs = 4000;
    o->signal_afs = 16;
    while ((c = getopt_long(argc, argv, "", opts, NULL)) != -1) {
        switch (c) {
        case 'p': o->pty_link = optarg; o->realtime = 1; break;
        case 'o': o->out_path = optarg; break;
        case 's': o->signal_path = optarg; break;
        case 'F':
            if (sscanf(optarg, "%d,%d", &o->signal_gfs, &o->signal_afs) != 2) {
                fprintf(stderr, "host-board: --signal-fs: expected DPS,G such as 4000,16, got %s\n", optarg);
                return -1;
            }
            break;
        case 'g': o->gen = optarg; break;
        case 'S': o->seconds = atof(optarg); break;
        case 'r': o->realtime = 1; break;
        case 'P': o->poll_us = atol(optarg); break;
        case 'O': o->cfg.sensor.odr_hz = (uint16_t)atoi(optarg); break;
        case 'G': o->cfg.sensor.gyro_fs_dps = (uint16_t)atoi(optarg); break;
        case 'A': o->cfg.sensor.accel_fs_g = (uint8_t)atoi(optarg); break;
        case 'b': o->cfg.samples_per_packet = (uint8_t)atoi(optarg); break;
        case 'd': o->cfg.flush_deadline_us = (uint32_t)atol(optarg); break;
        case 'N': o->cfg.self_test = 0; break;
        case 'm': o->mcu_ppm = atof(optarg); break;
        case 'w': o->mcu_wander_ppm = atof(optarg); break;
        case 'c': o->chip_ppm = atof(optarg); break;
        case 'f': o->freq_fine = atoi(optarg); break;
        case 't': o->t0_us = (uint32_t)strtoul(optarg, NULL, 0); break;
        case 'u': o->uart_baud = atol(optarg); break;
        case 'E': o->stall_every_s = atof(optarg); break;
        case 'M': o->stall_ms = atof(optarg); break;
        case 'W': o->whoami = (int)strtol(optarg, NULL, 0); break;
        case 'a': o->absent = 1; break;
        case 'x': o->st_fail = 1; break;
        case 'C': o->counters_path = optarg; break;
        case 'T': o->timing_path = optarg; break;
        case 'K': o->timing_every = atol(optarg) > 0 ? atol(optarg) : 1; break;
        case 'L': o->wait_open_s = atof(optarg); break;
        case 'l': o->linger_s = atof(optarg); break;
        case 'h': usage(stdout); exit(0);
        default: usage(stderr); return -1;
        }
    }
    if (!o->pty_link == !o->out_path) {
        fprintf(stderr, "host-board: give exactly one of --pty LINK and --out PATH\n");
        return -1;
    }
    if (o->cfg.samples_per_packet < 1 || o->cfg.samples_per_packet > 64 || o->poll_us < 10 || o->uart_baud < 1200) {
        fprintf(stderr, "host-board: --batch is 1..64, --poll-us at least 10, --uart-baud at least 1200\n");
        return -1;
    }
    return 0;
}
