/* ST LSM6DSR (DS12544) and LSM6DSO/LSM6DSOX (DS12140, DS13158) over SPI: identity, reset, self-test, rates,
 * tagged FIFO. */
#include "tfw_lsm6dsr.h"

#include <string.h>

#define RESET_POLLS 50u               /* x 100 us: the reset takes tens of us */
#define SETTLE_US 100000u             /* the self-test's 100 ms settling, at each step */
#define DATA_READY_POLLS 100u         /* x 1 ms: a 52 Hz sample comes within 20 ms */
#define SELF_TEST_SAMPLES 5
/* datasheet self-test limits: accelerometer at 4 g, gyroscope at 2000 dps; the LSM6DSO's accelerometer
 * window starts at 50 mg (DS12140), the rest is the same on both parts */
#define ST_XL_MIN_MG 40
#define ST_XL_MIN_MG_LSM6DSO 50
#define ST_XL_MAX_MG 1700
#define ST_G_MIN_DPS 150
#define ST_G_MAX_DPS 700
#define ST_XL_CTRL1 0x38u             /* 52 Hz, 4 g */
#define ST_G_CTRL2 0x5Cu              /* 208 Hz, 2000 dps */
#define ST_XL_POSITIVE 0x01u          /* CTRL5_C.ST_XL */
#define ST_G_POSITIVE 0x04u           /* CTRL5_C.ST_G */
#define XL_MG_PER_LSB_4G_X1000 122    /* 0.122 mg/LSB */
#define G_MDPS_PER_LSB_2000 70

static const struct {
    uint16_t hz;
    uint8_t code;
} ODR_CODES[] = {{12, 1}, {13, 1}, {26, 2}, {52, 3}, {104, 4}, {208, 5}, {416, 6}, {417, 6},
                 {833, 7}, {1666, 8}, {1667, 8}, {3332, 9}, {3333, 9}, {6667, 10}};

uint8_t tfw_lsm_odr_code(uint16_t odr_hz) {
    for (size_t i = 0; i < sizeof ODR_CODES / sizeof ODR_CODES[0]; i++) {
        if (ODR_CODES[i].hz == odr_hz) {
            return ODR_CODES[i].code;
        }
    }
    return 0;
}

/* FS_XL bits 3:2 of CTRL1_XL; 0xFF for none */
static uint8_t accel_fs_bits(uint8_t g) {
    switch (g) {
    case 2: return 0x00u;
    case 16: return 0x04u;
    case 4: return 0x08u;
    case 8: return 0x0Cu;
    default: return 0xFFu;
    }
}

/* FS_G bits 3:2, FS_125 bit 1 and FS_4000 bit 0 of CTRL2_G (bit 0 is reserved on the LSM6DSO); 0xFF for none */
static uint8_t gyro_fs_bits(uint16_t dps, uint8_t part) {
    if (dps == 4000u && part != TFW_PART_LSM6DSR) {
        return 0xFFu;
    }
    switch (dps) {
    case 125: return 0x02u;
    case 250: return 0x00u;
    case 500: return 0x04u;
    case 1000: return 0x08u;
    case 2000: return 0x0Cu;
    case 4000: return 0x01u;
    default: return 0xFFu;
    }
}

void tfw_lsm_init(tfw_lsm6dsr *dev, const tfw_bus *bus) {
    memset(dev, 0, sizeof *dev);
    dev->bus = *bus;
}

int tfw_lsm_read(tfw_lsm6dsr *dev, uint8_t reg, uint8_t *data, size_t n) {
    uint8_t *b = dev->buf;
    if (n + 1u > sizeof dev->buf) {
        return TFW_LSM_ERR_CONFIG;
    }
    memset(b, 0, n + 1u);
    b[0] = (uint8_t)(reg | LSM_SPI_READ);
    if (dev->bus.transfer(dev->bus.ctx, b, b, n + 1u) != 0) {
        return TFW_LSM_ERR_BUS;
    }
    memcpy(data, b + 1, n);
    return TFW_LSM_OK;
}

int tfw_lsm_write(tfw_lsm6dsr *dev, uint8_t reg, uint8_t value) {
    uint8_t b[2] = {(uint8_t)(reg & 0x7Fu), value};
    return dev->bus.transfer(dev->bus.ctx, b, b, 2) == 0 ? TFW_LSM_OK : TFW_LSM_ERR_BUS;
}

static int write_checked(tfw_lsm6dsr *dev, uint8_t reg, uint8_t value) {
    uint8_t got = 0;
    int rc = tfw_lsm_write(dev, reg, value);
    if (rc == TFW_LSM_OK) {
        rc = tfw_lsm_read(dev, reg, &got, 1);
    }
    if (rc == TFW_LSM_OK && got != value) {
        rc = TFW_LSM_ERR_READBACK;
    }
    return rc;
}

int tfw_lsm_probe_and_reset(tfw_lsm6dsr *dev) {
    uint8_t v = 0;
    int rc = tfw_lsm_read(dev, LSM_WHO_AM_I, &v, 1);
    dev->who_am_i = v;
    if (rc != TFW_LSM_OK) {
        return rc;
    }
    dev->part = v == LSM_WHO_AM_I_VALUE ? TFW_PART_LSM6DSR : v == LSM_WHO_AM_I_LSM6DSO ? TFW_PART_LSM6DSO : TFW_PART_NONE;
    if (dev->part == TFW_PART_NONE) {
        return TFW_LSM_ERR_WHO_AM_I;
    }
    rc = tfw_lsm_write(dev, LSM_CTRL3_C, LSM_CTRL3_SW_RESET | LSM_CTRL3_IF_INC);
    for (uint32_t i = 0; rc == TFW_LSM_OK && i < RESET_POLLS; i++) {
        dev->bus.delay_us(dev->bus.ctx, 100u);
        rc = tfw_lsm_read(dev, LSM_CTRL3_C, &v, 1);
        if (rc == TFW_LSM_OK && !(v & LSM_CTRL3_SW_RESET)) {
            int8_t fine = 0;
            rc = tfw_lsm_read(dev, LSM_INTERNAL_FREQ_FINE, (uint8_t *)&fine, 1);
            dev->freq_fine = fine;
            return rc;
        }
    }
    return rc == TFW_LSM_OK ? TFW_LSM_ERR_TIMEOUT : rc;
}

/* the mean of SELF_TEST_SAMPLES fresh samples of the output registers at reg (after one discarded) */
static int mean_output(tfw_lsm6dsr *dev, uint8_t ready_bit, uint8_t reg, int32_t mean[3]) {
    int32_t sum[3] = {0, 0, 0};
    for (int k = 0; k <= SELF_TEST_SAMPLES; k++) {
        uint8_t st = 0, raw[6];
        uint32_t polls = 0;
        int rc;
        while ((rc = tfw_lsm_read(dev, LSM_STATUS_REG, &st, 1)) == TFW_LSM_OK && !(st & ready_bit)) {
            if (++polls > DATA_READY_POLLS) {
                return TFW_LSM_ERR_TIMEOUT;
            }
            dev->bus.delay_us(dev->bus.ctx, 1000u);
        }
        if (rc == TFW_LSM_OK) {
            rc = tfw_lsm_read(dev, reg, raw, 6);
        }
        if (rc != TFW_LSM_OK) {
            return rc;
        }
        for (int a = 0; k > 0 && a < 3; a++) {           /* the first sample after a change is discarded */
            sum[a] += (int16_t)(raw[2 * a] | (raw[2 * a + 1] << 8));
        }
    }
    for (int a = 0; a < 3; a++) {
        mean[a] = sum[a] / SELF_TEST_SAMPLES;
    }
    return TFW_LSM_OK;
}

/* one sensor's self-test: |mean(on) - mean(off)| per axis, in LSB */
static int self_test_one(tfw_lsm6dsr *dev, uint8_t ready_bit, uint8_t reg, uint8_t st_bits, int32_t delta[3]) {
    int32_t off[3], on[3];
    int rc = TFW_LSM_OK;
    dev->bus.delay_us(dev->bus.ctx, SETTLE_US);
    if ((rc = mean_output(dev, ready_bit, reg, off)) != TFW_LSM_OK ||
        (rc = tfw_lsm_write(dev, LSM_CTRL5_C, st_bits)) != TFW_LSM_OK) {
        return rc;
    }
    dev->bus.delay_us(dev->bus.ctx, SETTLE_US);
    rc = mean_output(dev, ready_bit, reg, on);
    int rc2 = tfw_lsm_write(dev, LSM_CTRL5_C, 0x00u);
    for (int a = 0; a < 3; a++) {
        int32_t d = on[a] - off[a];
        delta[a] = d < 0 ? -d : d;
    }
    return rc != TFW_LSM_OK ? rc : rc2;
}

/* the datasheet's two self-tests, in order: the sensor's control register and setting, its data-ready bit and
 * output registers, its self-test bits, its sensitivity (thousandths of mg or dps per LSB) and pass window */
static const struct {
    uint8_t ctrl_reg, ctrl_value, ready_bit, out_reg, st_bits;
    int32_t milli_per_lsb, min, max;
} SELF_TESTS[2] = {
    {LSM_CTRL1_XL, ST_XL_CTRL1, LSM_STATUS_XLDA, LSM_OUTX_L_A, ST_XL_POSITIVE, XL_MG_PER_LSB_4G_X1000,
     ST_XL_MIN_MG, ST_XL_MAX_MG},
    {LSM_CTRL2_G, ST_G_CTRL2, LSM_STATUS_GDA, LSM_OUTX_L_G, ST_G_POSITIVE, G_MDPS_PER_LSB_2000,
     ST_G_MIN_DPS, ST_G_MAX_DPS},
};

int tfw_lsm_self_test_run(tfw_lsm6dsr *dev, tfw_lsm_self_test *result) {
    static const uint8_t zero_regs[] = {LSM_CTRL2_G, LSM_CTRL4_C, LSM_CTRL5_C, LSM_CTRL6_C,
                                        LSM_CTRL7_G, LSM_CTRL8_XL, LSM_CTRL10_C};
    int32_t *deltas[2] = {result->accel_delta_mg, result->gyro_delta_dps};
    int rc = TFW_LSM_OK, rc_off = TFW_LSM_OK;
    memset(result, 0, sizeof *result);
    for (size_t i = 0; rc == TFW_LSM_OK && i < sizeof zero_regs; i++) {
        rc = tfw_lsm_write(dev, zero_regs[i], 0x00u);
    }
    if (rc == TFW_LSM_OK) {
        rc = tfw_lsm_write(dev, LSM_CTRL3_C, LSM_CTRL3_BDU | LSM_CTRL3_IF_INC);
    }
    result->passed = 1;
    for (size_t k = 0; k < 2 && rc == TFW_LSM_OK; k++) {
        int32_t d[3];
        rc = tfw_lsm_write(dev, SELF_TESTS[k].ctrl_reg, SELF_TESTS[k].ctrl_value);
        if (rc == TFW_LSM_OK) {
            rc = self_test_one(dev, SELF_TESTS[k].ready_bit, SELF_TESTS[k].out_reg, SELF_TESTS[k].st_bits, d);
        }
        for (int a = 0; rc == TFW_LSM_OK && a < 3; a++) {
            int32_t lo = k == 0 && dev->part == TFW_PART_LSM6DSO ? ST_XL_MIN_MG_LSM6DSO : SELF_TESTS[k].min;
            deltas[k][a] = d[a] * SELF_TESTS[k].milli_per_lsb / 1000;
            if (deltas[k][a] < lo || deltas[k][a] > SELF_TESTS[k].max) {
                result->passed = 0;
            }
        }
        rc_off = tfw_lsm_write(dev, SELF_TESTS[k].ctrl_reg, 0x00u);     /* the sensor off again, whatever came */
    }
    if (rc != TFW_LSM_OK) {
        result->passed = 0;
        return rc;
    }
    return rc_off;
}

int tfw_lsm_configure(tfw_lsm6dsr *dev, const tfw_lsm_config *cfg) {
    uint8_t odr = tfw_lsm_odr_code(cfg->odr_hz), afs = accel_fs_bits(cfg->accel_fs_g);
    uint8_t gfs = gyro_fs_bits(cfg->gyro_fs_dps, dev->part);
    if (!odr || afs == 0xFFu || gfs == 0xFFu || cfg->watermark_words < 1u || cfg->watermark_words >= 512u) {
        return TFW_LSM_ERR_CONFIG;
    }
    const uint8_t writes[][2] = {
        {LSM_FIFO_CTRL4, 0x00u},                                  /* bypass: empties the FIFO */
        {LSM_CTRL3_C, LSM_CTRL3_BDU | LSM_CTRL3_IF_INC},
        {LSM_CTRL9_XL, 0xE0u | LSM_CTRL9_I3C_DISABLE},            /* SPI only: the I3C pads off */
        {LSM_CTRL5_C, 0x00u},
        {LSM_CTRL1_XL, (uint8_t)((odr << 4) | afs)},
        {LSM_CTRL2_G, (uint8_t)((odr << 4) | gfs)},
        {LSM_FIFO_CTRL1, (uint8_t)(cfg->watermark_words & 0xFFu)},
        {LSM_FIFO_CTRL2, (uint8_t)((cfg->watermark_words >> 8) & 0x01u)},
        {LSM_FIFO_CTRL3, (uint8_t)((odr << 4) | odr)},            /* BDR_GY, BDR_XL at the ODR */
        {LSM_FIFO_CTRL4, LSM_FIFO_MODE_CONTINUOUS},
    };
    for (size_t i = 0; i < sizeof writes / sizeof writes[0]; i++) {
        int rc = write_checked(dev, writes[i][0], writes[i][1]);
        if (rc != TFW_LSM_OK) {
            return rc;
        }
    }
    dev->cfg = *cfg;
    dev->have_g = dev->have_xl = 0;
    return TFW_LSM_OK;
}

int tfw_lsm_fifo_status(tfw_lsm6dsr *dev, uint16_t *words, uint8_t *overrun) {
    uint8_t s[2];
    int rc = tfw_lsm_read(dev, LSM_FIFO_STATUS1, s, 2);
    if (rc != TFW_LSM_OK) {
        return rc;
    }
    *words = (uint16_t)(s[0] | ((s[1] & 0x03u) << 8));
    *overrun = (s[1] & (LSM_FIFO_STATUS2_OVR_LATCHED | LSM_FIFO_STATUS2_OVR_IA)) ? 1u : 0u;
    return TFW_LSM_OK;
}

/* one tagged word into the pairing state; 1 when it completed a sample */
static int pair_word(tfw_lsm6dsr *dev, const uint8_t *w, tfw_sample *out) {
    uint8_t sensor = (uint8_t)(w[0] >> 3), cnt = (uint8_t)((w[0] >> 1) & 0x03u);
    int16_t xyz[3];
    for (int a = 0; a < 3; a++) {
        xyz[a] = (int16_t)(w[1 + 2 * a] | (w[2 + 2 * a] << 8));
    }
    if (sensor == LSM_TAG_GYRO) {
        dev->words_unpaired += dev->have_g;                 /* a gyro word whose accel never came */
        if (dev->have_xl && dev->cnt_xl != cnt) {
            dev->words_unpaired++;
            dev->have_xl = 0;
        }
        memcpy(dev->g, xyz, sizeof xyz);
        dev->have_g = 1;
        dev->cnt_g = cnt;
    } else if (sensor == LSM_TAG_ACCEL) {
        dev->words_unpaired += dev->have_xl;
        if (dev->have_g && dev->cnt_g != cnt) {
            dev->words_unpaired++;
            dev->have_g = 0;
        }
        memcpy(dev->xl, xyz, sizeof xyz);
        dev->have_xl = 1;
        dev->cnt_xl = cnt;
    } else {
        dev->words_other++;
        return 0;
    }
    if (!(dev->have_g && dev->have_xl)) {
        return 0;
    }
    memcpy(out->v, dev->g, sizeof dev->g);
    memcpy(out->v + 3, dev->xl, sizeof dev->xl);
    dev->have_g = dev->have_xl = 0;
    return 1;
}

int tfw_lsm_fifo_read(tfw_lsm6dsr *dev, uint16_t words, tfw_sample *out, size_t cap, size_t *n_out) {
    size_t n = 0;
    if (words > TFW_LSM_BURST_WORDS) {
        words = TFW_LSM_BURST_WORDS;
    }
    if (words > 2u * cap) {
        words = (uint16_t)(2u * cap);
    }
    *n_out = 0;
    if (!words) {
        return TFW_LSM_OK;
    }
    uint8_t *b = dev->buf;
    size_t len = 1u + LSM_FIFO_WORD_BYTES * words;
    memset(b, 0, len);
    b[0] = LSM_FIFO_DATA_OUT_TAG | LSM_SPI_READ;         /* the address rolls back to the tag after Z_H */
    if (dev->bus.transfer(dev->bus.ctx, b, b, len) != 0) {
        return TFW_LSM_ERR_BUS;
    }
    for (uint16_t i = 0; i < words; i++) {
        n += (size_t)pair_word(dev, b + 1 + LSM_FIFO_WORD_BYTES * i, out + n);
    }
    dev->words_read += words;
    *n_out = n;
    return TFW_LSM_OK;
}

uint32_t tfw_lsm_actual_odr_mhz(const tfw_lsm6dsr *dev) {
    /* 6.66 kHz nominal is 6667 Hz; INTERNAL_FREQ_FINE: (1 + 0.0015 x value) */
    int64_t nominal = (int64_t)dev->cfg.odr_hz * 1000;
    return (uint32_t)(nominal + nominal * 15 * dev->freq_fine / 10000);
}

uint16_t tfw_lsm_max_gyro_fs(const tfw_lsm6dsr *dev) { return dev->part == TFW_PART_LSM6DSR ? 4000u : 2000u; }
