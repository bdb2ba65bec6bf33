/* tecdar-imu/1 framing: CRC-16/CCITT-FALSE and the encoders of every packet type. */
#include "tfw_wire.h"

#include <string.h>

/* Byte-wise without a table (the well-known shift-and-xor form of poly 0x1021): constant time per byte,
 * no flash for a table, and no first-call initialisation. */
uint16_t tfw_crc16_update(uint16_t crc, const uint8_t *data, size_t len) {
    for (size_t i = 0; i < len; i++) {
        uint16_t x = (uint16_t)(((crc >> 8) ^ data[i]) & 0xFFu);
        x ^= (uint16_t)(x >> 4);
        crc = (uint16_t)((crc << 8) ^ (x << 12) ^ (x << 5) ^ x);
    }
    return crc;
}

uint16_t tfw_crc16(const uint8_t *data, size_t len) { return tfw_crc16_update(0xFFFFu, data, len); }

static void put_u16(uint8_t *p, uint16_t v) {
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

static void put_u32(uint8_t *p, uint32_t v) {
    for (int k = 0; k < 4; k++) {
        p[k] = (uint8_t)(v >> (8 * k));
    }
}

/* sync, type and len in front of a payload already at out + 5; the CRC after it */
static size_t seal(uint8_t type, size_t len, uint8_t *out) {
    out[0] = TFW_SYNC0;
    out[1] = TFW_SYNC1;
    out[2] = type;
    put_u16(out + 3, (uint16_t)len);
    put_u16(out + TFW_HEADER_BYTES + len, tfw_crc16(out + 2, 3u + len));
    return TFW_OVERHEAD_BYTES + len;
}

size_t tfw_encode_frame(uint8_t type, const uint8_t *payload, size_t len, uint8_t *out, size_t cap) {
    if (len > TFW_MAX_LEN || cap < TFW_OVERHEAD_BYTES + len) {
        return 0;
    }
    if (len) {
        memmove(out + TFW_HEADER_BYTES, payload, len);
    }
    return seal(type, len, out);
}

size_t tfw_encode_samples(uint16_t seq, uint32_t t0_us, const tfw_sample *samples, size_t n,
                          uint8_t *out, size_t cap) {
    if (n < 1 || n > TFW_MAX_SAMPLES || cap < TFW_SAMPLES_FRAME_BYTES(n)) {
        return 0;
    }
    uint8_t *p = out + TFW_HEADER_BYTES;
    put_u16(p, seq);
    put_u32(p + 2, t0_us);
    p[6] = (uint8_t)n;
    p += TFW_SAMPLES_HEADER_BYTES;
    for (size_t i = 0; i < n; i++) {
        for (int k = 0; k < 6; k++) {
            put_u16(p, (uint16_t)samples[i].v[k]);
            p += 2;
        }
    }
    return seal(TFW_TYPE_SAMPLES, TFW_SAMPLES_HEADER_BYTES + TFW_SAMPLE_BYTES * n, out);
}

size_t tfw_encode_status(const tfw_status *status, uint8_t *out, size_t cap) {
    if (cap < TFW_STATUS_FRAME_BYTES) {
        return 0;
    }
    uint8_t *p = out + TFW_HEADER_BYTES;
    put_u16(p, status->odr_hz);
    put_u16(p + 2, status->gyro_fs_dps);
    p[4] = status->accel_fs_g;
    p[5] = (uint8_t)(status->flags & 0x07u);
    return seal(TFW_TYPE_STATUS, TFW_STATUS_BYTES, out);
}

size_t tfw_encode_identity(uint8_t who_am_i, uint8_t *out, size_t cap) {
    if (cap < TFW_IDENTITY_FRAME_BYTES) {
        return 0;
    }
    out[TFW_HEADER_BYTES] = who_am_i;
    return seal(TFW_TYPE_IDENTITY, TFW_IDENTITY_BYTES, out);
}
