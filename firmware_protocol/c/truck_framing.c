/* truck_framing.c: see truck_framing.h. */
#include "truck_framing.h"

#include <string.h>

uint8_t truck_crc8_j1850(const uint8_t *data, size_t len)
{
    uint8_t crc = 0xFFu;
    for (size_t i = 0; i < len; i++) {
        crc ^= data[i];
        for (int b = 0; b < 8; b++) {
            crc = (crc & 0x80u) ? (uint8_t)((crc << 1) ^ 0x1Du) : (uint8_t)(crc << 1);
        }
    }
    return (uint8_t)(crc ^ 0xFFu);
}

uint16_t truck_crc16_ccitt(const uint8_t *data, size_t len)
{
    uint16_t crc = 0xFFFFu;
    for (size_t i = 0; i < len; i++) {
        crc ^= (uint16_t)((uint16_t)data[i] << 8);
        for (int b = 0; b < 8; b++) {
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
        }
    }
    return crc;
}

uint8_t truck_message_checksum(uint16_t can_id, const uint8_t *data, size_t len)
{
    uint8_t buf[2u + TRUCK_MAX_PAYLOAD];
    size_t n = (len > 0u) ? len - 1u : 0u;
    if (n > TRUCK_MAX_PAYLOAD) {
        n = TRUCK_MAX_PAYLOAD;
    }
    buf[0] = (uint8_t)(can_id & 0xFFu);
    buf[1] = (uint8_t)(can_id >> 8);
    memcpy(&buf[2], data, n);
    return truck_crc8_j1850(buf, n + 2u);
}

void truck_seal(uint16_t can_id, uint8_t *data, size_t len)
{
    if (len > 0u) {
        data[len - 1u] = truck_message_checksum(can_id, data, len);
    }
}

int truck_checksum_ok(uint16_t can_id, const uint8_t *data, size_t len)
{
    return (len > 0u) && (data[len - 1u] == truck_message_checksum(can_id, data, len));
}

size_t truck_cobs_encode(const uint8_t *in, size_t len, uint8_t *out)
{
    size_t code_idx = 0;
    size_t o = 1;
    uint8_t code = 1;
    out[0] = 1;
    for (size_t i = 0; i < len; i++) {
        if (in[i] == 0u) {
            out[code_idx] = code;
            code_idx = o++;
            out[code_idx] = 1;
            code = 1;
        } else {
            out[o++] = in[i];
            code++;
            if (code == 0xFFu) {
                out[code_idx] = code;
                code_idx = o++;
                out[code_idx] = 1;
                code = 1;
            }
        }
    }
    out[code_idx] = code;
    return o;
}

int truck_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t out_size)
{
    size_t i = 0;
    size_t o = 0;
    if (len == 0u) {
        return -1;
    }
    while (i < len) {
        uint8_t code = in[i];
        if (code == 0u || i + code > len) {
            return -1;
        }
        for (size_t k = i + 1u; k < i + code; k++) {
            if (in[k] == 0u || o >= out_size) {
                return -1;
            }
            out[o++] = in[k];
        }
        i += code;
        if (code < 0xFFu && i < len) {
            if (o >= out_size) {
                return -1;
            }
            out[o++] = 0;
        }
    }
    return (int)o;
}

int truck_frame_encode(uint16_t can_id, const uint8_t *data, size_t len, uint8_t *out)
{
    uint8_t raw[TRUCK_MAX_DECODED];
    if (can_id >= 0x800u || len > TRUCK_MAX_PAYLOAD) {
        return -1;
    }
    raw[0] = (uint8_t)(can_id & 0xFFu);
    raw[1] = (uint8_t)(can_id >> 8);
    memcpy(&raw[2], data, len);
    uint16_t crc = truck_crc16_ccitt(raw, len + 2u);
    raw[len + 2u] = (uint8_t)(crc & 0xFFu);
    raw[len + 3u] = (uint8_t)(crc >> 8);
    out[0] = 0;
    size_t n = truck_cobs_encode(raw, len + 4u, &out[1]);
    out[n + 1u] = 0;
    return (int)(n + 2u);
}

void truck_deframer_init(struct truck_deframer_t *d)
{
    memset(d, 0, sizeof(*d));
}

static int deframe_body(struct truck_deframer_t *d, uint16_t *can_id, uint8_t *data,
                        size_t *len)
{
    uint8_t raw[TRUCK_MAX_BODY];
    int n = truck_cobs_decode(d->buf, d->len, raw, sizeof(raw));
    if (n < 0) {
        d->stats.cobs_errors++;
        return -1;
    }
    if (n < 4 || n > (int)TRUCK_MAX_DECODED) {
        d->stats.length_errors++;
        return -1;
    }
    uint16_t crc = truck_crc16_ccitt(raw, (size_t)n - 2u);
    if (crc != (uint16_t)(raw[n - 2] | (raw[n - 1] << 8))) {
        d->stats.crc_errors++;
        return -1;
    }
    uint16_t id = (uint16_t)(raw[0] | (raw[1] << 8));
    if (id >= 0x800u) {
        d->stats.length_errors++;
        return -1;
    }
    *can_id = id;
    *len = (size_t)n - 4u;
    memcpy(data, &raw[2], *len);
    return 0;
}

int truck_deframer_feed(struct truck_deframer_t *d, uint8_t byte, uint16_t *can_id,
                        uint8_t *data, size_t *len)
{
    if (byte != 0u) {
        if (d->overflow) {
            d->stats.bytes_discarded++;
        } else if (d->len >= TRUCK_MAX_BODY) {
            d->stats.bytes_discarded += (uint32_t)d->len + 1u;
            d->stats.length_errors++;
            d->len = 0;
            d->overflow = 1;
        } else {
            d->buf[d->len++] = byte;
        }
        return 0;
    }
    if (d->overflow) {
        d->stats.resyncs++;
        d->overflow = 0;
        d->len = 0;
        return 0;
    }
    if (d->len == 0u) {
        return 0;
    }
    int rc = deframe_body(d, can_id, data, len);
    if (rc != 0) {
        d->stats.resyncs++;
        d->stats.bytes_discarded += (uint32_t)d->len;
        d->len = 0;
        return 0;
    }
    d->len = 0;
    d->stats.frames_ok++;
    return 1;
}
