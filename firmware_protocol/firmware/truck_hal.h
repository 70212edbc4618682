/**
 * truck_hal.h: the hardware the firmware core needs, behind function pointers.
 *
 * A board fills one struct truck_hal (see board/stm32f4/board.c); the host build fills it
 * from Python (truckd/sim/fw_core.py) with the simulated plant behind it.  Every function
 * gets the board's ctx pointer back.  None of them may block: the core calls them from
 * truck_fw_poll() and truck_fw_rx_*() in the main loop.
 *
 * Units are integers in the DBC's resolution or finer: mV, mA, mm, encoder ticks, ms.
 */
#ifndef TRUCK_HAL_H
#define TRUCK_HAL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Range sensor status (DBC RANGE.STATUS). */
#define TRUCK_RANGE_VALID 0u
#define TRUCK_RANGE_NO_TARGET 1u
#define TRUCK_RANGE_SENSOR_FAULT 2u

/** Motor driver and battery measurements at one instant. */
struct truck_hal_power {
    int32_t current_ma;   /**< armature current, mA (signed) */
    int32_t vbat_mv;      /**< battery terminal voltage, mV */
    int32_t u_applied_mv; /**< voltage the driver applies now, mV (signed) */
};

struct truck_hal {
    void *ctx;
    /** Free-running millisecond clock (wraps at 2^32; the core is wrap-safe). */
    uint32_t (*millis)(void *ctx);
    /** Encoder counts of both driven wheels (wrapping u16) and fault bits
     *  (bit 0 left, bit 1 right). */
    void (*read_encoders)(void *ctx, uint16_t *left, uint16_t *right, uint8_t *status);
    /** Current, battery and applied voltage. */
    void (*read_power)(void *ctx, struct truck_hal_power *out);
    /** Range to the vehicle ahead: returns TRUCK_RANGE_*; *distance_mm meaningful when
     *  VALID (may be below the sensor minimum or negative: the core clamps). */
    uint8_t (*read_range)(void *ctx, int32_t *distance_mm);
    /** Drive the motor: armature voltage (mV, already within +-vbat) and driver enable. */
    void (*set_motor)(void *ctx, int32_t voltage_mv, uint8_t enable);
    /** Serial link: queue wire bytes (non-blocking); 0 when queued, -1 when not sent. */
    int (*send_bytes)(void *ctx, const uint8_t *data, size_t len);
    /** CAN link: queue one standard frame (non-blocking); 0 when queued, -1 when not. */
    int (*send_frame)(void *ctx, uint16_t can_id, const uint8_t *data, uint8_t len);
};

#ifdef __cplusplus
}
#endif

#endif
