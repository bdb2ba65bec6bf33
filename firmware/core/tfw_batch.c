/* Sample batching: up to 64 samples a packet, and a flush deadline that bounds latency at low rates. */
#include "tfw_batch.h"

void tfw_batch_init(tfw_batch *b, uint8_t max_n, uint32_t deadline_us, uint16_t seq0) {
    b->n = 0;
    b->max_n = (uint8_t)(max_n < 1u ? 1u : (max_n > TFW_MAX_SAMPLES ? TFW_MAX_SAMPLES : max_n));
    b->deadline_us = deadline_us;
    b->t0_us = b->first_in_us = 0;
    b->seq = seq0;
}

size_t tfw_batch_flush(tfw_batch *b, uint8_t *out, size_t cap) {
    if (!b->n) {
        return 0;
    }
    size_t len = tfw_encode_samples(b->seq, b->t0_us, b->s, b->n, out, cap);
    /* seq counts packets made, sent or not: a packet the board cannot send shows as a gap */
    b->seq = (uint16_t)(b->seq + 1u);
    b->n = 0;
    return len;
}

size_t tfw_batch_add(tfw_batch *b, const tfw_sample *s, uint32_t t_us, uint32_t now_us, uint8_t *out, size_t cap) {
    if (!b->n) {
        b->t0_us = t_us;
        b->first_in_us = now_us;
    }
    b->s[b->n++] = *s;
    return b->n >= b->max_n ? tfw_batch_flush(b, out, cap) : 0;
}

size_t tfw_batch_due(tfw_batch *b, uint32_t now_us, uint8_t *out, size_t cap) {
    if (b->n && (uint32_t)(now_us - b->first_in_us) >= b->deadline_us) {
        return tfw_batch_flush(b, out, cap);
    }
    return 0;
}
