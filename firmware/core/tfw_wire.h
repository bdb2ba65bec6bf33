/* tecdar-imu/1 framing: CRC-16/CCITT-FALSE and the encoders of every packet type. No allocation, no I/O. */
#ifndef TFW_WIRE_H
#define TFW_WIRE_H

#include <stddef.h>
#include <stdint.h>

#define TFW_SYNC0 0xA5u
#define TFW_SYNC1 0x5Au
#define TFW_TYPE_SAMPLES 0x01u
#define TFW_TYPE_STATUS 0x02u
#define TFW_TYPE_IDENTITY 0x03u      /* the sensor's WHO_AM_I as read: an extension readers of tecdar-imu/1 skip */
#define TFW_MAX_LEN 1024u
#define TFW_MAX_SAMPLES 64u
#define TFW_HEADER_BYTES 5u          /* sync (2), type (1), len (2) */
#define TFW_CRC_BYTES 2u
#define TFW_OVERHEAD_BYTES (TFW_HEADER_BYTES + TFW_CRC_BYTES)
#define TFW_SAMPLES_HEADER_BYTES 7u  /* seq (2), t0_us (4), n (1) */
#define TFW_SAMPLE_BYTES 12u
#define TFW_STATUS_BYTES 6u
#define TFW_IDENTITY_BYTES 1u
#define TFW_SAMPLES_FRAME_BYTES(n) (TFW_OVERHEAD_BYTES + TFW_SAMPLES_HEADER_BYTES + TFW_SAMPLE_BYTES * (n))
#define TFW_STATUS_FRAME_BYTES (TFW_OVERHEAD_BYTES + TFW_STATUS_BYTES)
#define TFW_IDENTITY_FRAME_BYTES (TFW_OVERHEAD_BYTES + TFW_IDENTITY_BYTES)
#define TFW_MAX_FRAME_BYTES (TFW_OVERHEAD_BYTES + TFW_MAX_LEN)

/* status flags (the spec's clarifications): bits 3-7 are always zero */
#define TFW_FLAG_FIFO_OVERRUN 0x01u    /* the sensor's FIFO overran since the last status */
#define TFW_FLAG_SELF_TEST_FAILED 0x02u
#define TFW_FLAG_SENSOR_ABSENT 0x04u   /* WHO_AM_I wrong or no reply: no samples are sent */

/* One sample in the LSM6DSR's output register order: gx, gy, gz, ax, ay, az (raw LSB). */
typedef struct {
    int16_t v[6];
} tfw_sample;

typedef struct {
    uint16_t odr_hz;
    uint16_t gyro_fs_dps;
    uint8_t accel_fs_g;
    uint8_t flags;
} tfw_status;

/* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0) continued from crc. */
uint16_t tfw_crc16_update(uint16_t crc, const uint8_t *data, size_t len);
uint16_t tfw_crc16(const uint8_t *data, size_t len);

/* Each encoder writes one whole frame to out and returns its length in bytes, or 0 (and writes
 * nothing) when the frame would not fit in cap or its contents are outside the protocol. */
size_t tfw_encode_frame(uint8_t type, const uint8_t *payload, size_t len, uint8_t *out, size_t cap);
size_t tfw_encode_samples(uint16_t seq, uint32_t t0_us, const tfw_sample *samples, size_t n,
                          uint8_t *out, size_t cap);
size_t tfw_encode_status(const tfw_status *status, uint8_t *out, size_t cap);
/* The identity packet: the WHO_AM_I byte the board last read (0x6B LSM6DSR, 0x6C LSM6DSO/DSOX; anything
 * else, 0x00 or 0xFF included, is what a wrong or missing part answered). */
size_t tfw_encode_identity(uint8_t who_am_i, uint8_t *out, size_t cap);

#endif
