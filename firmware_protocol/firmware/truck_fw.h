/**
 * truck_fw.h: the truck microcontroller's firmware core (C99, no allocation, no blocking).
 *
 * What it does (docs/firmware.md):
 * - publishes WHEEL_ENCODERS (10 ms), MOTOR_FEEDBACK (10 ms), RANGE (20 ms) and
 *   FIRMWARE_HEARTBEAT (100 ms) at their DBC periods, first at init, with COUNTER and
 *   CHECKSUM (generated pack functions of firmware_protocol/c/truck.c);
 * - checks every received frame like firmware_protocol/checks.py (id, length, CHECKSUM,
 *   value ranges, COUNTER continuity, freshness) and applies valid MOTOR_CMDs (voltage
 *   clamped to the battery, CMD_INVALID when it had to; ENABLE 0 = motor off);
 * - switches the motor off (0 V, disabled) when no valid MOTOR_CMD arrived for
 *   cmd_timeout_ms: state FAILSAFE, CMD_TIMEOUT; the next valid command drives again;
 * - heartbeat: state, fault bits (event bits stay set until one heartbeat reported them),
 *   count of rejected commands (wraps at 256).
 * Serial links carry COBS + CRC-16 frames (truck_framing.c), CAN links bare frames.
 *
 * Main loop on a board: feed received bytes/frames with truck_fw_rx_bytes() /
 * truck_fw_rx_frame(), call truck_fw_poll() at least every millisecond.
 */
#ifndef TRUCK_FW_H
#define TRUCK_FW_H

#include <stddef.h>
#include <stdint.h>

#include "truck.h"
#include "truck_framing.h"
#include "truck_timing.h"
#include "truck_hal.h"

#ifdef __cplusplus
extern "C" {
#endif

#define TRUCK_FW_ABI_VERSION 1u

/** The largest forward counter jump taken as lost frames (two lost in a row; truck.dbc). */
#define TRUCK_FW_MAX_DELTA TRUCK_COUNTER_MAX_DELTA
/** In-sequence frames needed after a larger jump before commands are accepted again (more
 *  than any replay loop a 4-bit counter can tell; truck.dbc). */
#define TRUCK_FW_RESYNC TRUCK_COUNTER_RESYNC

/* Link kinds. */
#define TRUCK_FW_LINK_SERIAL 0u
#define TRUCK_FW_LINK_CAN 1u

/* Published messages, in the order they leave when due together. */
#define TRUCK_FW_MSG_WHEEL_ENCODERS 0u
#define TRUCK_FW_MSG_MOTOR_FEEDBACK 1u
#define TRUCK_FW_MSG_RANGE 2u
#define TRUCK_FW_MSG_FIRMWARE_HEARTBEAT 3u
#define TRUCK_FW_N_TX 4u

/* Received messages. */
#define TRUCK_FW_RX_MOTOR_CMD 0u
#define TRUCK_FW_RX_COMPANION_HEARTBEAT 1u
#define TRUCK_FW_N_RX 2u

/* FIRMWARE_HEARTBEAT.STATE */
#define TRUCK_FW_STATE_BOOT 0u
#define TRUCK_FW_STATE_IDLE 1u
#define TRUCK_FW_STATE_ACTIVE 2u
#define TRUCK_FW_STATE_FAILSAFE 3u

/* FIRMWARE_HEARTBEAT.FAULTS bits. */
#define TRUCK_FW_FAULT_CMD_TIMEOUT (1u << 0)
#define TRUCK_FW_FAULT_CMD_CHECKSUM (1u << 1)
#define TRUCK_FW_FAULT_CMD_COUNTER (1u << 2)
#define TRUCK_FW_FAULT_RANGE_SENSOR (1u << 3)
#define TRUCK_FW_FAULT_ENCODER (1u << 4)
#define TRUCK_FW_FAULT_UNDERVOLTAGE (1u << 5)
#define TRUCK_FW_FAULT_CMD_INVALID (1u << 6)
#define TRUCK_FW_FAULT_COMPANION_TIMEOUT (1u << 7)

/* Test hooks (fault injection on the published messages), compiled in only with
 * -DTRUCK_FW_FAULT_HOOKS (the host build), never on the microcontroller. */
#define TRUCK_FW_TX_FREEZE (1u << 0)       /**< repeat the last values (counters advance) */
#define TRUCK_FW_TX_BAD_CHECKSUM (1u << 1) /**< wrong CHECKSUM (XOR 0xA5) */
#define TRUCK_FW_TX_STUCK_COUNTER (1u << 2) /**< COUNTER stops advancing */

struct truck_fw_config {
    uint8_t link;               /**< TRUCK_FW_LINK_SERIAL or TRUCK_FW_LINK_CAN */
    uint8_t timeout_periods;    /**< freshness timeout of received messages, periods (5) */
    uint8_t max_wrong_counters; /**< counter score limit (5), see checks.py */
    uint16_t cmd_timeout_ms;    /**< motor off after this long without a valid command (100) */
    int32_t undervoltage_mv;    /**< UNDERVOLTAGE below this battery voltage (TRUCK_UNDERVOLTAGE_MV) */
    int32_t range_min_mm;       /**< readings below are reported as this (TRUCK_RANGE_MIN_MM) */
    int32_t range_max_mm;       /**< readings beyond are NO_TARGET (TRUCK_RANGE_MAX_MM) */
};

/** Receive statistics, same names and meaning as firmware_protocol.checks.RxStats. */
struct truck_fw_rx_stats {
    uint32_t frames_ok;
    uint32_t checksum_errors;
    uint32_t length_errors;
    uint32_t unknown_ids;
    uint32_t payload_errors;
    uint32_t counter_errors;
    uint32_t counter_gaps;
    uint32_t timeouts;
    uint32_t unexpected;
};

/** What the firmware did (counts since init). */
struct truck_fw_stats {
    struct truck_fw_rx_stats rx;
    struct truck_framing_stats_t framing; /**< serial deframer (zero on CAN) */
    uint32_t commands_applied;
    uint32_t cmd_timeouts;
    uint32_t frames_sent;
    uint32_t frames_dropped; /**< dropped by the drop fault hook */
    uint32_t tx_failed;      /**< the HAL refused a frame (buffer full, link down) */
    uint32_t schedule_slips; /**< periods skipped because poll() came too late */
};

struct truck_fw_rx_state {
    uint32_t last_rx;
    uint16_t timeout_ms;
    uint8_t last_counter;
    uint8_t has_counter;
    uint8_t wrong_counters;
    uint8_t stale;
    uint8_t resync; /**< frames still to run in sequence after a large jump (a replay) */
    uint8_t chain;  /**< counter of the last frame of that run */
};

/** The last values of a published message (the freeze hook repeats them). */
union truck_fw_tx_msg {
    struct truck_wheel_encoders_t enc;
    struct truck_motor_feedback_t fb;
    struct truck_range_t range;
    struct truck_firmware_heartbeat_t hb;
};

struct truck_fw_tx_state {
    uint32_t next_due;
    union truck_fw_tx_msg last;
    uint8_t counter;
    uint8_t has_last;
#ifdef TRUCK_FW_FAULT_HOOKS
    uint8_t fault;   /**< TRUCK_FW_TX_* bits */
    int32_t drop;    /**< frames still to drop, -1 = until cleared */
#endif
};

/** The whole firmware state: allocate one statically (no heap). */
struct truck_fw {
    struct truck_fw_config cfg;
    struct truck_hal hal;
    struct truck_deframer_t deframer;
    struct truck_fw_rx_state rx[TRUCK_FW_N_RX];
    struct truck_fw_tx_state tx[TRUCK_FW_N_TX];
    struct truck_fw_stats stats;
    uint32_t t0;           /**< clock at init, ms */
    uint32_t last_cmd;     /**< clock at the last valid command, ms */
    int32_t voltage_mv;    /**< what the driver is commanded now */
    int16_t last_cmd_mv;   /**< last valid command as received (before clamping) */
    uint8_t last_cmd_enable;
    uint8_t have_cmd;
    uint8_t enabled;
    uint8_t timed_out;
    uint8_t boot_timed_out; /**< no command within the timeout after start (latched: the
                                 elapsed time since start wraps after 24.9 days) */
    uint16_t sticky;       /**< event fault bits not yet reported */
    uint16_t sensor_faults; /**< RANGE_SENSOR / ENCODER as last read */
#ifdef TRUCK_FW_FAULT_HOOKS
    uint8_t silent;
#endif
};

/** Defaults of the protocol (docs/protocol.md). */
void truck_fw_default_config(struct truck_fw_config *cfg);

/** Start: motor off, every message due now. cfg and hal are copied. */
void truck_fw_init(struct truck_fw *fw, const struct truck_fw_config *cfg,
                   const struct truck_hal *hal);

/** Received serial bytes (COBS frames; garbage is counted and skipped). */
void truck_fw_rx_bytes(struct truck_fw *fw, const uint8_t *data, size_t len);

/** One received CAN frame (standard id). */
void truck_fw_rx_frame(struct truck_fw *fw, uint16_t can_id, const uint8_t *data, uint8_t len);

/** Forget a partial serial frame (after the link came back). */
void truck_fw_link_reset(struct truck_fw *fw);

/** Command timeout and every message that is due. */
void truck_fw_poll(struct truck_fw *fw);

/** Clock value (ms) of the next thing poll() will do: a message due or the timeout. */
uint32_t truck_fw_next_event(const struct truck_fw *fw);

uint8_t truck_fw_state(const struct truck_fw *fw);

/** Fault bits the next heartbeat reports (reads the battery voltage). */
uint16_t truck_fw_fault_bits(struct truck_fw *fw);

/** Rejected commands (checksum, length, counter, payload), mod 256. */
uint8_t truck_fw_cmd_errors(const struct truck_fw *fw);

/** Voltage commanded to the driver now (mV) and whether it is enabled. */
int32_t truck_fw_voltage_mv(const struct truck_fw *fw);
uint8_t truck_fw_enabled(const struct truck_fw *fw);

/** The last valid MOTOR_CMD as received (before clamping); 0 when none yet. */
int truck_fw_last_command(const struct truck_fw *fw, int16_t *voltage_mv, uint8_t *enable);

/** Copy of the statistics (framing included). */
void truck_fw_get_stats(const struct truck_fw *fw, struct truck_fw_stats *out);

/** True (1) when msg (TRUCK_FW_RX_*) arrived within its freshness timeout. */
int truck_fw_rx_fresh(struct truck_fw *fw, unsigned msg);

#ifdef TRUCK_FW_FAULT_HOOKS
/** Fault hook on published message msg (TRUCK_FW_MSG_*): TRUCK_FW_TX_* bits. */
int truck_fw_set_tx_fault(struct truck_fw *fw, unsigned msg, uint8_t bits);
/** Drop the next count frames of msg (-1 = until set to 0). */
int truck_fw_set_drop(struct truck_fw *fw, unsigned msg, int32_t count);
/** Send nothing (still receives and drives). */
void truck_fw_set_silent(struct truck_fw *fw, uint8_t on);
/** Every hook off. */
void truck_fw_clear_faults(struct truck_fw *fw);
#endif

#ifdef __cplusplus
}
#endif

#endif
