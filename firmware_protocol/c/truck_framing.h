/**
 * truck_framing.h: checksums and serial framing of the truckd firmware protocol.
 *
 * Hand-written companion of the cantools-generated truck.h/truck.c; byte-identical
 * with firmware_protocol/crc.py and firmware_protocol/framing.py (proved by
 * tests/test_protocol_c.py).
 *
 * - CRC-8/SAE-J1850 (poly 0x1D, init 0xFF, xorout 0xFF): the CHECKSUM signal, the last
 *   payload byte, over the 11-bit id (2 bytes little-endian) and the payload before it.
 * - Serial frame: 0x00 | COBS(id_lo id_hi payload crc16_lo crc16_hi) | 0x00 with
 *   CRC-16/CCITT-FALSE over id and payload.
 */
#ifndef TRUCK_FRAMING_H
#define TRUCK_FRAMING_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define TRUCK_MAX_PAYLOAD 8u
#define TRUCK_MAX_DECODED (2u + TRUCK_MAX_PAYLOAD + 2u)
#define TRUCK_MAX_BODY (TRUCK_MAX_DECODED + 1u)
/** Longest wire frame: two delimiters and the longest COBS body. */
#define TRUCK_MAX_WIRE (TRUCK_MAX_BODY + 2u)

uint8_t truck_crc8_j1850(const uint8_t *data, size_t len);
uint16_t truck_crc16_ccitt(const uint8_t *data, size_t len);

/** CHECKSUM of a message: CRC-8 over id (2 bytes LE) and data[0..len-2]. */
uint8_t truck_message_checksum(uint16_t can_id, const uint8_t *data, size_t len);

/** Write the CHECKSUM into the last byte of a packed message (len >= 1). */
void truck_seal(uint16_t can_id, uint8_t *data, size_t len);

/** 1 when the last byte of data is the right CHECKSUM, else 0. */
int truck_checksum_ok(uint16_t can_id, const uint8_t *data, size_t len);

/** COBS-encode len bytes into out (room for len + len/254 + 1); returns bytes written. */
size_t truck_cobs_encode(const uint8_t *in, size_t len, uint8_t *out);

/** COBS-decode; returns decoded length, or -1 when malformed or longer than out_size. */
int truck_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t out_size);

/** Wire bytes of one frame (delimiters included) into out (>= TRUCK_MAX_WIRE bytes);
 *  returns the length, or -1 when the id is not 11-bit or len > TRUCK_MAX_PAYLOAD. */
int truck_frame_encode(uint16_t can_id, const uint8_t *data, size_t len, uint8_t *out);

struct truck_framing_stats_t {
    uint32_t frames_ok;
    uint32_t crc_errors;
    uint32_t cobs_errors;
    uint32_t length_errors;
    uint32_t resyncs;
    uint32_t bytes_discarded;
};

/** Streaming receiver: feed one byte at a time. */
struct truck_deframer_t {
    uint8_t buf[TRUCK_MAX_BODY];
    size_t len;
    int overflow;
    struct truck_framing_stats_t stats;
};

void truck_deframer_init(struct truck_deframer_t *d);

/** Feed one byte; returns 1 and fills can_id/data/len when a frame completes, else 0. */
int truck_deframer_feed(struct truck_deframer_t *d, uint8_t byte, uint16_t *can_id,
                        uint8_t *data, size_t *len);

#ifdef __cplusplus
}
#endif

#endif
