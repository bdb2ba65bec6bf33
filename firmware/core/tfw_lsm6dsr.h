/* ST LSM6DSR, and the LSM6DSO/LSM6DSOX beside it, over SPI, written from the datasheets (DS12544; DS12140,
 * DS13158): identity, reset, self-test, ODR and full scales, and the tagged FIFO in continuous mode. The two
 * share the register map, the rate codes, the FIFO's tags and the self-test; the LSM6DSO has no 4000 dps. The bus is two functions the board supplies; nothing here allocates, and
 * every call is bounded in time (waits poll a bounded number of times). */
#ifndef TFW_LSM6DSR_H
#define TFW_LSM6DSR_H

#include <stddef.h>
#include <stdint.h>

#include "tfw_wire.h"

/* registers (datasheet, "Register mapping") */
#define LSM_FIFO_CTRL1 0x07u
#define LSM_FIFO_CTRL2 0x08u
#define LSM_FIFO_CTRL3 0x09u
#define LSM_FIFO_CTRL4 0x0Au
#define LSM_WHO_AM_I 0x0Fu
#define LSM_CTRL1_XL 0x10u
#define LSM_CTRL2_G 0x11u
#define LSM_CTRL3_C 0x12u
#define LSM_CTRL4_C 0x13u
#define LSM_CTRL5_C 0x14u
#define LSM_CTRL6_C 0x15u
#define LSM_CTRL7_G 0x16u
#define LSM_CTRL8_XL 0x17u
#define LSM_CTRL9_XL 0x18u
#define LSM_CTRL10_C 0x19u
#define LSM_STATUS_REG 0x1Eu
#define LSM_OUTX_L_G 0x22u
#define LSM_OUTX_L_A 0x28u
#define LSM_FIFO_STATUS1 0x3Au
#define LSM_FIFO_STATUS2 0x3Bu
#define LSM_INTERNAL_FREQ_FINE 0x63u
#define LSM_FIFO_DATA_OUT_TAG 0x78u
#define LSM_FIFO_DATA_OUT_Z_H 0x7Eu

#define LSM_WHO_AM_I_VALUE 0x6Bu         /* LSM6DSR */
#define LSM_WHO_AM_I_LSM6DSO 0x6Cu       /* LSM6DSO and LSM6DSOX (and the LSM6DSO32, whose accel scales differ) */
#define LSM_SPI_READ 0x80u
#define LSM_CTRL3_SW_RESET 0x01u
#define LSM_CTRL3_IF_INC 0x04u
#define LSM_CTRL3_BDU 0x40u
#define LSM_CTRL9_I3C_DISABLE 0x02u
#define LSM_STATUS_XLDA 0x01u
#define LSM_STATUS_GDA 0x02u
#define LSM_FIFO_MODE_CONTINUOUS 0x06u
#define LSM_FIFO_STATUS2_OVR_IA 0x40u
#define LSM_FIFO_STATUS2_OVR_LATCHED 0x08u
#define LSM_FIFO_WORDS 512u             /* 3 kB of 6-byte words */
#define LSM_TAG_GYRO 0x01u              /* TAG_SENSOR: gyroscope, not compressed */
#define LSM_TAG_ACCEL 0x02u             /* accelerometer, not compressed */
#define LSM_FIFO_WORD_BYTES 7u          /* tag + X, Y, Z */
#define TFW_LSM_BURST_WORDS 16u         /* words per SPI read: 113 bytes, 11 us at 10 MHz */

/* The board's SPI: one full-duplex transaction of n bytes with chip select held for its length (tx and rx
 * may be the same buffer); 0 on success. delay_us waits at least us microseconds. */
typedef struct {
    int (*transfer)(void *ctx, const uint8_t *tx, uint8_t *rx, size_t n);
    void (*delay_us)(void *ctx, uint32_t us);
    void *ctx;
} tfw_bus;

typedef enum {
    TFW_PART_NONE = 0,
    TFW_PART_LSM6DSR = 1,
    TFW_PART_LSM6DSO = 2         /* LSM6DSO or LSM6DSOX: one WHO_AM_I */
} tfw_lsm_part;

typedef struct {
    uint16_t odr_hz;          /* one of the chip's rates, rounded: 12, 26, ... 3333, 6667 */
    uint16_t gyro_fs_dps;     /* 125, 250, 500, 1000, 2000, and 4000 on the LSM6DSR only */
    uint8_t accel_fs_g;       /* 2, 4, 8 or 16 */
    uint16_t watermark_words; /* FIFO threshold, 1..511 words */
} tfw_lsm_config;

typedef enum {
    TFW_LSM_OK = 0,
    TFW_LSM_ERR_BUS = -1,        /* the bus reported a failed transfer */
    TFW_LSM_ERR_WHO_AM_I = -2,   /* no LSM6DSR or LSM6DSO answers (wrong id, or the line floats at 0x00/0xFF) */
    TFW_LSM_ERR_TIMEOUT = -3,    /* reset or data-ready never came */
    TFW_LSM_ERR_CONFIG = -4,     /* a rate or full scale the chip does not have */
    TFW_LSM_ERR_READBACK = -5    /* a control register did not keep what was written */
} tfw_lsm_err;

typedef struct {
    int32_t accel_delta_mg[3];   /* |self-test on - off| per axis */
    int32_t gyro_delta_dps[3];
    uint8_t passed;
} tfw_lsm_self_test;

typedef struct {
    tfw_bus bus;
    tfw_lsm_config cfg;
    uint8_t who_am_i;            /* as last read */
    uint8_t part;                /* tfw_lsm_part of that WHO_AM_I */
    int8_t freq_fine;            /* INTERNAL_FREQ_FINE: the ODR's deviation, 0.15 % per LSB */
    /* FIFO pairing: a gyro and an accel word of the same time slot (TAG_CNT) make a sample */
    uint8_t have_g, have_xl, cnt_g, cnt_xl;
    int16_t g[3], xl[3];
    uint32_t words_read;
    uint32_t words_unpaired;     /* words whose partner was overwritten in an overrun */
    uint32_t words_other;        /* tags this driver does not batch (timestamp, temperature, ...) */
    uint8_t buf[1u + LSM_FIFO_WORD_BYTES * TFW_LSM_BURST_WORDS];
} tfw_lsm6dsr;

void tfw_lsm_init(tfw_lsm6dsr *dev, const tfw_bus *bus);
int tfw_lsm_read(tfw_lsm6dsr *dev, uint8_t reg, uint8_t *data, size_t n);
int tfw_lsm_write(tfw_lsm6dsr *dev, uint8_t reg, uint8_t value);
/* WHO_AM_I (an LSM6DSR or an LSM6DSO), then a software reset (CTRL3_C.SW_RESET, polled until it clears). */
int tfw_lsm_probe_and_reset(tfw_lsm6dsr *dev);
/* The datasheet's self-test, accelerometer (52 Hz, 4 g) then gyroscope (208 Hz, 2000 dps); leaves the
 * chip powered down. Returns TFW_LSM_OK with result->passed set, or an error. */
int tfw_lsm_self_test_run(tfw_lsm6dsr *dev, tfw_lsm_self_test *result);
/* ODR and full scales, block data update, then both sensors batched at the ODR into the FIFO in
 * continuous mode with the watermark; each register is read back. */
int tfw_lsm_configure(tfw_lsm6dsr *dev, const tfw_lsm_config *cfg);
/* Unread FIFO words, and whether the FIFO overran since the last call (the latched flag). */
int tfw_lsm_fifo_status(tfw_lsm6dsr *dev, uint16_t *words, uint8_t *overrun);
/* Reads min(words, TFW_LSM_BURST_WORDS) words in one burst and pairs them: up to cap samples to out. */
int tfw_lsm_fifo_read(tfw_lsm6dsr *dev, uint16_t words, tfw_sample *out, size_t cap, size_t *n_out);
/* The chip's actual output rate, Hz x 1000, from the nominal rate and INTERNAL_FREQ_FINE. */
uint32_t tfw_lsm_actual_odr_mhz(const tfw_lsm6dsr *dev);
/* The widest gyro full scale of the part found: 4000 dps on the LSM6DSR, 2000 on the LSM6DSO. */
uint16_t tfw_lsm_max_gyro_fs(const tfw_lsm6dsr *dev);
/* The rate's register code, or 0 for a rate the chip does not have. */
uint8_t tfw_lsm_odr_code(uint16_t odr_hz);

#endif
