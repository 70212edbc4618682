/* truck_fw_host.c: what the host build (the shared library the simulated truck loads
 * through ctypes, truckd/sim/fw_core.py) adds to the core: a clock the caller sets,
 * and the sizes the binding checks.  Everything else of the HAL comes from Python. */
#include "truck_fw.h"

/** The HAL ctx of the host build: the simulated clock, set by the caller. */
struct truck_host_clock {
    uint32_t now_ms;
};

uint32_t truck_host_millis(void *ctx)
{
    return ((const struct truck_host_clock *)ctx)->now_ms;
}

unsigned truck_fw_abi_version(void)
{
    return TRUCK_FW_ABI_VERSION;
}

size_t truck_fw_size(void)
{
    return sizeof(struct truck_fw);
}

size_t truck_fw_stats_size(void)
{
    return sizeof(struct truck_fw_stats);
}

size_t truck_fw_config_size(void)
{
    return sizeof(struct truck_fw_config);
}

size_t truck_hal_size(void)
{
    return sizeof(struct truck_hal);
}
