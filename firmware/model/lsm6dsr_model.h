/* A register-level model of the ST LSM6DSR for the host board, the unit tests and the emulator build: SPI
 * transactions in, register contents and a tagged FIFO out, driven by a physical signal. It models what the
 * driver relies on (identity, reset, ODR, full scales, self-test response, FIFO continuous mode with
 * watermark, tags and overrun, burst reads that roll back at the FIFO's last register) and nothing more.
 * Its register addresses and bits are its own, written again from the datasheet, not the driver's: a wrong
 * constant in the driver then fails a test instead of agreeing with itself. */
#ifndef LSM6DSR_MODEL_H
#define LSM6DSR_MODEL_H

#include <stddef.h>
#include <stdint.h>

#define LSM_MODEL_FIFO_WORDS 512u

/* The physical signal at time t_ns: angular rate in dps and specific force in g, sensor frame. */
typedef void (*lsm_model_signal_fn)(void *ctx, int64_t t_ns, double gyro_dps[3], double accel_g[3]);

typedef struct {
    uint8_t reg[128];
    uint8_t fifo[LSM_MODEL_FIFO_WORDS][7];
    uint16_t fifo_head, fifo_count;
    uint8_t ovr_latched, ovr_ia;
    uint8_t tag_cnt;
    uint8_t word[7];                 /* the FIFO word being read out */
    /* the chip as built */
    uint8_t who_am_i;                /* 0x6B LSM6DSR; 0x6C an LSM6DSO (CTRL2_G bit 0 reserved: no 4000 dps);
                                      * anything else models the wrong part */
    uint8_t absent;                  /* no chip: MISO reads miso_idle */
    uint8_t miso_idle;
    double st_xl_mg, st_g_dps;       /* self-test deflection (datasheet window 40-1700 mg, 150-700 dps) */
    double odr_ppm;                  /* the chip's oscillator error */
    int8_t freq_fine;                /* INTERNAL_FREQ_FINE as the factory trimmed it */
    /* time and signal */
    int64_t t_ns;
    int64_t next_xl_ns, next_g_ns;
    lsm_model_signal_fn signal;
    void *signal_ctx;
    double gyro_dps[3], accel_g[3];  /* the signal now (push mode) */
    /* counters */
    uint64_t samples_made;           /* time slots with at least one sensor sampled */
    uint64_t words_batched;
    uint64_t words_overwritten;      /* lost to overruns */
    uint64_t overruns;
    int64_t first_fifo_ns;           /* the time slot of the first word the FIFO took (-1: none yet) */
} lsm_model;

void lsm_model_init(lsm_model *m);
/* Time passes: every sensor that is on samples at its ODR up to t_ns (signal from the callback). */
void lsm_model_advance(lsm_model *m, int64_t t_ns);
/* Push mode (a signal that comes in real time from elsewhere): one sample of both sensors now. */
void lsm_model_emit(lsm_model *m, const double gyro_dps[3], const double accel_g[3]);
/* The SPI transaction, with the signature of tfw_bus.transfer: ctx is the lsm_model. */
int lsm_model_transfer(void *ctx, const uint8_t *tx, uint8_t *rx, size_t n);
/* The model's output data rate of a CTRL1_XL/CTRL2_G code, Hz (0 when powered down). */
double lsm_model_odr_hz(uint8_t code);
/* Its sample period at that code with the chip's oscillator error, ns (0 when powered down). */
int64_t lsm_model_period_ns(const lsm_model *m, uint8_t code);

#endif
