/* A register-level model of the ST LSM6DSR (see lsm6dsr_model.h). */
#include "lsm6dsr_model.h"

#include <math.h>
#include <string.h>

#define R_FIFO_CTRL1 0x07
#define R_FIFO_CTRL2 0x08
#define R_FIFO_CTRL3 0x09
#define R_FIFO_CTRL4 0x0A
#define R_WHO_AM_I 0x0F
#define R_CTRL1_XL 0x10
#define R_CTRL2_G 0x11
#define R_CTRL3_C 0x12
#define R_CTRL5_C 0x14
#define R_CTRL9_XL 0x18
#define R_STATUS 0x1E
#define R_OUTX_L_G 0x22
#define R_OUTX_L_A 0x28
#define R_OUTZ_H_A 0x2D
#define R_FIFO_STATUS1 0x3A
#define R_FIFO_STATUS2 0x3B
#define R_FREQ_FINE 0x63
#define R_TAG 0x78
#define R_Z_H 0x7E

static const double ODR_HZ[] = {0, 12.5, 26, 52, 104, 208, 416, 833, 1666, 3332, 6667};

double lsm_model_odr_hz(uint8_t code) { return code <= 10 ? ODR_HZ[code] : 0.0; }

static void reset_registers(lsm_model *m) {
    memset(m->reg, 0, sizeof m->reg);
    m->reg[R_WHO_AM_I] = m->who_am_i;
    m->reg[R_CTRL3_C] = 0x04;                /* IF_INC */
    m->reg[R_CTRL9_XL] = 0xE0;
    m->reg[R_FREQ_FINE] = (uint8_t)m->freq_fine;
    m->fifo_head = m->fifo_count = 0;
    m->ovr_latched = m->ovr_ia = 0;
    m->tag_cnt = 0;
    m->next_xl_ns = m->next_g_ns = -1;
}

void lsm_model_init(lsm_model *m) {
    memset(m, 0, sizeof *m);
    m->who_am_i = 0x6B;
    m->miso_idle = 0xFF;
    m->st_xl_mg = 500.0;
    m->st_g_dps = 300.0;
    reset_registers(m);
    m->accel_g[2] = 1.0;
    m->first_fifo_ns = -1;
}

static double gyro_mdps_per_lsb(uint8_t ctrl2) {
    static const double fs[4] = {8.75, 17.5, 35.0, 70.0};
    if (ctrl2 & 0x01) {
        return 140.0;
    }
    if (ctrl2 & 0x02) {
        return 4.375;
    }
    return fs[(ctrl2 >> 2) & 3];
}

static double accel_mg_per_lsb(uint8_t ctrl1) {
    static const double fs[4] = {0.061, 0.488, 0.122, 0.244};   /* FS_XL 00 2 g, 01 16 g, 10 4 g, 11 8 g */
    return fs[(ctrl1 >> 2) & 3];
}

static int16_t to_lsb(double v) {
    double r = floor(v + 0.5);
    return (int16_t)(r > 32767.0 ? 32767 : (r < -32768.0 ? -32768 : r));
}

static void put_xyz(uint8_t *p, const int16_t xyz[3]) {
    for (int a = 0; a < 3; a++) {
        p[2 * a] = (uint8_t)((uint16_t)xyz[a] & 0xFF);
        p[2 * a + 1] = (uint8_t)((uint16_t)xyz[a] >> 8);
    }
}

static void fifo_push(lsm_model *m, uint8_t tag_sensor, const int16_t xyz[3]) {
    uint8_t *w;
    if (m->fifo_count == LSM_MODEL_FIFO_WORDS) {       /* continuous mode: the oldest word is overwritten */
        m->fifo_head = (uint16_t)((m->fifo_head + 1) % LSM_MODEL_FIFO_WORDS);
        m->fifo_count--;
        m->words_overwritten++;
        if (!m->ovr_ia) {
            m->overruns++;
        }
        m->ovr_ia = m->ovr_latched = 1;
    }
    w = m->fifo[(m->fifo_head + m->fifo_count) % LSM_MODEL_FIFO_WORDS];
    uint8_t tag = (uint8_t)((tag_sensor << 3) | ((m->tag_cnt & 3) << 1));
    uint8_t parity = 0;
    for (int b = 1; b < 8; b++) {
        parity ^= (uint8_t)((tag >> b) & 1);
    }
    w[0] = (uint8_t)(tag | parity);
    put_xyz(w + 1, xyz);
    m->fifo_count++;
    if (!m->words_batched) {
        m->first_fifo_ns = m->t_ns;
    }
    m->words_batched++;
}

static int fifo_continuous(const lsm_model *m) { return (m->reg[R_FIFO_CTRL4] & 0x07) == 0x06; }

/* one time slot: the sensors named sample the signal; output registers, STATUS_REG and the FIFO */
static void sample(lsm_model *m, int do_xl, int do_g, const double g_dps[3], const double a_g[3]) {
    int16_t g[3], a[3];
    uint8_t st = m->reg[R_CTRL5_C];
    double st_g = (st & 0x0C) == 0x04 ? m->st_g_dps : ((st & 0x0C) == 0x0C ? -m->st_g_dps : 0.0);
    double st_xl = (st & 0x03) == 0x01 ? m->st_xl_mg : ((st & 0x03) == 0x02 ? -m->st_xl_mg : 0.0);
    for (int k = 0; k < 3; k++) {
        g[k] = to_lsb((g_dps[k] * 1000.0 + st_g * 1000.0) / gyro_mdps_per_lsb(m->reg[R_CTRL2_G]));
        a[k] = to_lsb((a_g[k] * 1000.0 + st_xl) / accel_mg_per_lsb(m->reg[R_CTRL1_XL]));
    }
    m->tag_cnt = (uint8_t)((m->tag_cnt + 1) & 3);
    m->samples_made++;
    if (do_g) {
        put_xyz(m->reg + R_OUTX_L_G, g);
        m->reg[R_STATUS] |= 0x02;
        if ((m->reg[R_FIFO_CTRL3] >> 4) && fifo_continuous(m)) {
            fifo_push(m, 0x01, g);
        }
    }
    if (do_xl) {
        put_xyz(m->reg + R_OUTX_L_A, a);
        m->reg[R_STATUS] |= 0x01;
        if ((m->reg[R_FIFO_CTRL3] & 0x0F) && fifo_continuous(m)) {
            fifo_push(m, 0x02, a);
        }
    }
}

int64_t lsm_model_period_ns(const lsm_model *m, uint8_t code) {
    double hz = lsm_model_odr_hz(code) * (1.0 + m->odr_ppm * 1e-6);
    return hz > 0 ? (int64_t)(1e9 / hz + 0.5) : 0;
}

void lsm_model_advance(lsm_model *m, int64_t t_ns) {
    for (;;) {
        int64_t pxl = lsm_model_period_ns(m, (uint8_t)(m->reg[R_CTRL1_XL] >> 4));
        int64_t pg = lsm_model_period_ns(m, (uint8_t)(m->reg[R_CTRL2_G] >> 4));
        /* a sensor switched on samples on the other's grid when their rates match, as the chip does */
        if (pxl && m->next_xl_ns < 0) {
            m->next_xl_ns = (pg == pxl && m->next_g_ns >= 0) ? m->next_g_ns : m->t_ns + pxl;
        }
        if (pg && m->next_g_ns < 0) {
            m->next_g_ns = (pg == pxl && m->next_xl_ns >= 0) ? m->next_xl_ns : m->t_ns + pg;
        }
        if (!pxl) {
            m->next_xl_ns = -1;
        }
        if (!pg) {
            m->next_g_ns = -1;
        }
        int64_t next = -1;
        if (m->next_xl_ns >= 0) {
            next = m->next_xl_ns;
        }
        if (m->next_g_ns >= 0 && (next < 0 || m->next_g_ns < next)) {
            next = m->next_g_ns;
        }
        if (next < 0 || next > t_ns) {
            break;
        }
        int do_xl = m->next_xl_ns == next, do_g = m->next_g_ns == next;
        m->t_ns = next;
        if (m->signal) {
            m->signal(m->signal_ctx, next, m->gyro_dps, m->accel_g);
        }
        sample(m, do_xl, do_g, m->gyro_dps, m->accel_g);
        if (do_xl) {
            m->next_xl_ns += pxl;
        }
        if (do_g) {
            m->next_g_ns += pg;
        }
    }
    if (t_ns > m->t_ns) {
        m->t_ns = t_ns;
    }
}

void lsm_model_emit(lsm_model *m, const double gyro_dps[3], const double accel_g[3]) {
    int on_xl = (m->reg[R_CTRL1_XL] >> 4) != 0, on_g = (m->reg[R_CTRL2_G] >> 4) != 0;
    memcpy(m->gyro_dps, gyro_dps, sizeof m->gyro_dps);
    memcpy(m->accel_g, accel_g, sizeof m->accel_g);
    if (on_xl || on_g) {
        sample(m, on_xl, on_g, gyro_dps, accel_g);
    }
}

static uint8_t read_reg(lsm_model *m, uint8_t a) {
    if (a >= R_TAG && a <= R_Z_H) {
        if (a == R_TAG) {            /* each word is popped as its tag is read */
            if (m->fifo_count) {
                memcpy(m->word, m->fifo[m->fifo_head], 7);
                m->fifo_head = (uint16_t)((m->fifo_head + 1) % LSM_MODEL_FIFO_WORDS);
                m->fifo_count--;
                if (m->fifo_count < LSM_MODEL_FIFO_WORDS) {
                    m->ovr_ia = 0;
                }
            } else {
                memset(m->word, 0, 7);
            }
        }
        return m->word[a - R_TAG];
    }
    if (a == R_FIFO_STATUS1) {
        return (uint8_t)(m->fifo_count & 0xFF);
    }
    if (a == R_FIFO_STATUS2) {
        uint16_t wtm = (uint16_t)(m->reg[R_FIFO_CTRL1] | ((m->reg[R_FIFO_CTRL2] & 1) << 8));
        uint8_t v = (uint8_t)((m->fifo_count >> 8) & 0x03);
        v |= (uint8_t)((wtm && m->fifo_count >= wtm) ? 0x80 : 0);
        v |= (uint8_t)(m->ovr_ia ? 0x40 : 0);
        v |= (uint8_t)(m->fifo_count == LSM_MODEL_FIFO_WORDS ? 0x20 : 0);
        v |= (uint8_t)(m->ovr_latched ? 0x08 : 0);
        m->ovr_latched = 0;          /* reset when this register is read */
        return v;
    }
    if (a >= R_OUTX_L_G && a < R_OUTX_L_A) {
        m->reg[R_STATUS] &= (uint8_t)~0x02;
    } else if (a >= R_OUTX_L_A && a <= R_OUTZ_H_A) {
        m->reg[R_STATUS] &= (uint8_t)~0x01;
    }
    return m->reg[a & 0x7F];
}

static void write_reg(lsm_model *m, uint8_t a, uint8_t v) {
    if (a == R_WHO_AM_I || a == R_STATUS || a == R_FIFO_STATUS1 || a == R_FIFO_STATUS2 || a >= R_TAG) {
        return;                      /* read-only */
    }
    if (a == R_CTRL3_C && (v & 0x01)) {
        reset_registers(m);          /* SW_RESET: registers to their defaults, the bit clears itself */
        return;
    }
    if (a == R_CTRL1_XL && (v >> 4) != (m->reg[a] >> 4)) {
        m->next_xl_ns = -1;          /* a new rate: a new schedule */
    }
    if (a == R_CTRL2_G && m->who_am_i == 0x6C) {
        v &= (uint8_t)~0x01;         /* the LSM6DSO: bit 0 is reserved (no 4000 dps) and reads 0 */
    }
    if (a == R_CTRL2_G && (v >> 4) != (m->reg[a] >> 4)) {
        m->next_g_ns = -1;
    }
    if (a == R_FIFO_CTRL4 && (v & 0x07) == 0) {
        m->fifo_head = m->fifo_count = 0;          /* bypass mode empties the FIFO */
        m->ovr_ia = m->ovr_latched = 0;
    }
    m->reg[a] = v;
}

int lsm_model_transfer(void *ctx, const uint8_t *tx, uint8_t *rx, size_t n) {
    lsm_model *m = ctx;
    if (!n) {
        return 0;
    }
    uint8_t cmd = tx[0];
    uint8_t addr = (uint8_t)(cmd & 0x7F);
    int read = (cmd & 0x80) != 0;
    int inc = (m->reg[R_CTRL3_C] & 0x04) != 0;
    uint8_t data[1024];
    if (n - 1 > sizeof data) {
        return -1;
    }
    memcpy(data, tx + 1, n - 1);     /* tx and rx may be one buffer */
    rx[0] = m->absent ? m->miso_idle : 0x00;
    for (size_t i = 1; i < n; i++) {
        if (m->absent) {
            rx[i] = m->miso_idle;
            continue;
        }
        if (read) {
            rx[i] = read_reg(m, addr);
        } else {
            write_reg(m, addr, data[i - 1]);
            rx[i] = 0;
        }
        if (inc) {
            addr = addr == R_Z_H ? R_TAG : (uint8_t)((addr + 1) & 0x7F);   /* the FIFO output rolls back */
        }
    }
    return 0;
}
