/* Sample batching: up to 64 samples a packet, and a flush deadline that bounds latency at low rates. */
#ifndef TFW_BATCH_H
#define TFW_BATCH_H

#include <stddef.h>
#include <stdint.h>

#include "tfw_wire.h"

typedef struct {
    tfw_sample s[TFW_MAX_SAMPLES];
    uint8_t n;
    uint8_t max_n;             /* samples per packet, 1..64 */
    uint32_t deadline_us;      /* the longest the first sample of a batch waits for its packet */
    uint32_t t0_us;            /* MCU time of the batch's first sample */
    uint32_t first_in_us;      /* MCU time it was added (read from the FIFO) */
    uint16_t seq;              /* of the next packet; wraps at 65536 */
} tfw_batch;

void tfw_batch_init(tfw_batch *b, uint8_t max_n, uint32_t deadline_us, uint16_t seq0);
/* Adds a sample stamped t_us, read at now_us. When that fills the batch, its packet is written to out and
 * its length returned (the batch is then empty); otherwise 0. */
size_t tfw_batch_add(tfw_batch *b, const tfw_sample *s, uint32_t t_us, uint32_t now_us, uint8_t *out, size_t cap);
/* The packet of a batch whose first sample has waited deadline_us or more by now_us; 0 otherwise. */
size_t tfw_batch_due(tfw_batch *b, uint32_t now_us, uint8_t *out, size_t cap);
/* The packet of whatever the batch holds (0 when empty). */
size_t tfw_batch_flush(tfw_batch *b, uint8_t *out, size_t cap);

#endif
