/* truck_fw.c: the firmware core; see truck_fw.h and docs/firmware.md. */
#include "truck_fw.h"

#include <string.h>

#include "truck.h"

/* One DBC message: id, length, period (ms). */
struct msg_spec {
    uint16_t id;
    uint8_t len;
    uint16_t period_ms;
};

static const struct msg_spec TX_SPEC[TRUCK_FW_N_TX] = {
    {TRUCK_WHEEL_ENCODERS_FRAME_ID, TRUCK_WHEEL_ENCODERS_LENGTH,
     TRUCK_WHEEL_ENCODERS_CYCLE_TIME_MS},
    {TRUCK_MOTOR_FEEDBACK_FRAME_ID, TRUCK_MOTOR_FEEDBACK_LENGTH,
     TRUCK_MOTOR_FEEDBACK_CYCLE_TIME_MS},
    {TRUCK_RANGE_FRAME_ID, TRUCK_RANGE_LENGTH, TRUCK_RANGE_CYCLE_TIME_MS},
    {TRUCK_FIRMWARE_HEARTBEAT_FRAME_ID, TRUCK_FIRMWARE_HEARTBEAT_LENGTH,
     TRUCK_FIRMWARE_HEARTBEAT_CYCLE_TIME_MS},
};

static const struct msg_spec RX_SPEC[TRUCK_FW_N_RX] = {
    {TRUCK_MOTOR_CMD_FRAME_ID, TRUCK_MOTOR_CMD_LENGTH, TRUCK_MOTOR_CMD_CYCLE_TIME_MS},
    {TRUCK_COMPANION_HEARTBEAT_FRAME_ID, TRUCK_COMPANION_HEARTBEAT_LENGTH,
     TRUCK_COMPANION_HEARTBEAT_CYCLE_TIME_MS},
};

/* wrap-safe: a - b as a signed difference of two ms clock values */
static int32_t elapsed(uint32_t a, uint32_t b)
{
    return (int32_t)(a - b);
}

static uint32_t now_ms(const struct truck_fw *fw)
{
    return fw->hal.millis(fw->hal.ctx);
}

void truck_fw_default_config(struct truck_fw_config *cfg)
{
    cfg->link = TRUCK_FW_LINK_SERIAL;
    cfg->timeout_periods = TRUCK_FRESHNESS_PERIODS; /* truck.dbc, via truck_timing.h */
    cfg->max_wrong_counters = TRUCK_COUNTER_MAX_WRONG;
    cfg->cmd_timeout_ms = TRUCK_MOTOR_CMD_TIMEOUT_MS;
    cfg->undervoltage_mv = TRUCK_UNDERVOLTAGE_MV; /* truck.dbc, via truck_timing.h */
    cfg->range_min_mm = TRUCK_RANGE_MIN_MM;
    cfg->range_max_mm = TRUCK_RANGE_MAX_MM;
}

static void set_motor(struct truck_fw *fw, int32_t mv, uint8_t enable)
{
    fw->voltage_mv = mv;
    fw->enabled = enable;
    fw->hal.set_motor(fw->hal.ctx, mv, enable);
}

void truck_fw_init(struct truck_fw *fw, const struct truck_fw_config *cfg,
                   const struct truck_hal *hal)
{
    memset(fw, 0, sizeof(*fw));
    fw->cfg = *cfg;
    fw->hal = *hal;
    truck_deframer_init(&fw->deframer);
    fw->t0 = now_ms(fw);
    for (unsigned i = 0; i < TRUCK_FW_N_RX; i++) {
        fw->rx[i].stale = 1u;
        fw->rx[i].timeout_ms = (uint16_t)(cfg->timeout_periods * RX_SPEC[i].period_ms);
    }
    for (unsigned i = 0; i < TRUCK_FW_N_TX; i++) {
        fw->tx[i].next_due = fw->t0;
    }
    set_motor(fw, 0, 0u);
}

/* -- receive ------------------------------------------------------------------------ */

static void rx_expire(struct truck_fw *fw, struct truck_fw_rx_state *ms, uint32_t now)
{
    if (!ms->stale && elapsed(now, ms->last_rx) > (int32_t)ms->timeout_ms) {
        ms->stale = 1u;
        ms->wrong_counters = 0u;
        fw->stats.rx.timeouts++;
    }
}

int truck_fw_rx_fresh(struct truck_fw *fw, unsigned msg)
{
    if (msg >= TRUCK_FW_N_RX) {
        return 0;
    }
    rx_expire(fw, &fw->rx[msg], now_ms(fw));
    return !fw->rx[msg].stale;
}

static int32_t read_vbat(struct truck_fw *fw)
{
    struct truck_hal_power p = {0}; /* a HAL that returns early leaves zeros, not garbage */
    fw->hal.read_power(fw->hal.ctx, &p);
    return p.vbat_mv;
}

static void apply_command(struct truck_fw *fw, const struct truck_motor_cmd_t *cmd,
                          uint32_t now)
{
    int32_t v = cmd->voltage;
    int32_t limit = read_vbat(fw);
    if (limit < 0) {
        limit = 0;
    }
    if (v > limit || v < -limit) {
        fw->sticky |= TRUCK_FW_FAULT_CMD_INVALID;
        v = (v > 0) ? limit : -limit;
    }
    set_motor(fw, cmd->enable ? v : 0, cmd->enable ? 1u : 0u);
    fw->last_cmd_mv = cmd->voltage;
    fw->last_cmd_enable = cmd->enable ? 1u : 0u;
    fw->last_cmd = now;
    fw->have_cmd = 1u;
    fw->timed_out = 0u;
    fw->stats.commands_applied++;
}

/* Decode like firmware_protocol.codec.decode_raw: -1 unknown id, -2 length, -3 checksum,
 * -4 payload (a value outside its DBC range or enum), else the counter. */
static int check_frame(uint16_t id, const uint8_t *data, uint8_t len)
{
    uint8_t want;
    int counter;
    switch (id) {
    case TRUCK_MOTOR_CMD_FRAME_ID: want = TRUCK_MOTOR_CMD_LENGTH; break;
    case TRUCK_COMPANION_HEARTBEAT_FRAME_ID: want = TRUCK_COMPANION_HEARTBEAT_LENGTH; break;
    case TRUCK_WHEEL_ENCODERS_FRAME_ID: want = TRUCK_WHEEL_ENCODERS_LENGTH; break;
    case TRUCK_MOTOR_FEEDBACK_FRAME_ID: want = TRUCK_MOTOR_FEEDBACK_LENGTH; break;
    case TRUCK_RANGE_FRAME_ID: want = TRUCK_RANGE_LENGTH; break;
    case TRUCK_FIRMWARE_HEARTBEAT_FRAME_ID: want = TRUCK_FIRMWARE_HEARTBEAT_LENGTH; break;
    default: return -1;
    }
    if (len != want) {
        return -2;
    }
    if (!truck_checksum_ok(id, data, len)) {
        return -3;
    }
    switch (id) {
    case TRUCK_MOTOR_CMD_FRAME_ID: {
        struct truck_motor_cmd_t m;
        (void)truck_motor_cmd_unpack(&m, data, len);
        if (m.voltage < -32767) {
            return -4;
        }
        counter = m.counter;
        break;
    }
    case TRUCK_COMPANION_HEARTBEAT_FRAME_ID: {
        struct truck_companion_heartbeat_t m;
        (void)truck_companion_heartbeat_unpack(&m, data, len);
        if (m.state > TRUCK_COMPANION_HEARTBEAT_STATE_FAULT_CHOICE) {
            return -4;
        }
        counter = m.counter;
        break;
    }
    case TRUCK_WHEEL_ENCODERS_FRAME_ID: {
        struct truck_wheel_encoders_t m;
        (void)truck_wheel_encoders_unpack(&m, data, len);
        counter = m.counter;
        break;
    }
    case TRUCK_MOTOR_FEEDBACK_FRAME_ID: {
        struct truck_motor_feedback_t m;
        (void)truck_motor_feedback_unpack(&m, data, len);
        counter = m.counter;
        break;
    }
    case TRUCK_RANGE_FRAME_ID: {
        struct truck_range_t m;
        (void)truck_range_unpack(&m, data, len);
        if (m.status > TRUCK_RANGE_STATUS_SENSOR_FAULT_CHOICE) {
            return -4;
        }
        counter = m.counter;
        break;
    }
    default: {
        struct truck_firmware_heartbeat_t m;
        (void)truck_firmware_heartbeat_unpack(&m, data, len);
        if (m.state > TRUCK_FIRMWARE_HEARTBEAT_STATE_FAILSAFE_CHOICE) {
            return -4;
        }
        counter = m.counter;
        break;
    }
    }
    return counter;
}

void truck_fw_rx_frame(struct truck_fw *fw, uint16_t can_id, const uint8_t *data, uint8_t len)
{
    struct truck_fw_rx_stats *st = &fw->stats.rx;
    int counter = check_frame(can_id, data, len);
    if (counter < 0) {
        switch (counter) {
        case -1: st->unknown_ids++; return;
        case -2: st->length_errors++; break;
        case -3: st->checksum_errors++; break;
        default: st->payload_errors++; break;
        }
        fw->sticky |= TRUCK_FW_FAULT_CMD_CHECKSUM;
        return;
    }
    unsigned idx;
    if (can_id == TRUCK_MOTOR_CMD_FRAME_ID) {
        idx = TRUCK_FW_RX_MOTOR_CMD;
    } else if (can_id == TRUCK_COMPANION_HEARTBEAT_FRAME_ID) {
        idx = TRUCK_FW_RX_COMPANION_HEARTBEAT;
    } else {
        st->unexpected++;
        return;
    }
    uint32_t now = now_ms(fw);
    struct truck_fw_rx_state *ms = &fw->rx[idx];
    rx_expire(fw, ms, now);
    if (ms->has_counter && counter == ms->last_counter) {
        st->counter_errors++; /* stuck sender or replay, even after a timeout */
        fw->sticky |= TRUCK_FW_FAULT_CMD_COUNTER;
        return;
    }
    if (ms->resync > 0u) {
        /* After a jump beyond TRUCK_FW_MAX_DELTA (a replayed loop of the last frames, or a
         * broken sender): a run of in-sequence frames first, timeouts included.  The loop
         * 6, 7, 6, 7, ... was accepted before and kept the motor driven. */
        unsigned step = ((unsigned)counter - ms->chain) & TRUCK_COUNTER_MASK;
        ms->resync = (step >= 1u && step <= TRUCK_FW_MAX_DELTA) ? (uint8_t)(ms->resync - 1u)
                                                                 : TRUCK_FW_RESYNC;
        ms->chain = (uint8_t)counter;
        if (ms->resync > 0u) {
            st->counter_errors++;
            fw->sticky |= TRUCK_FW_FAULT_CMD_COUNTER;
            return;
        }
        /* the run restarts the sequence, as after a timeout: accepted below, unscored */
    } else if (ms->has_counter && !ms->stale) {
        unsigned jump = ((unsigned)counter - ms->last_counter) & TRUCK_COUNTER_MASK;
        if (jump > TRUCK_FW_MAX_DELTA) {
            ms->resync = TRUCK_FW_RESYNC;
            ms->chain = (uint8_t)counter;
            st->counter_errors++;
            fw->sticky |= TRUCK_FW_FAULT_CMD_COUNTER;
            return;
        }
        ms->last_counter = (uint8_t)counter;
        if (jump != 1u) {
            st->counter_gaps += jump - 1u;
            fw->sticky |= TRUCK_FW_FAULT_CMD_COUNTER;
            if (ms->wrong_counters < 2u * fw->cfg.max_wrong_counters) {
                ms->wrong_counters++;
            }
        } else if (ms->wrong_counters > 0u) {
            ms->wrong_counters--;
        }
        if (ms->wrong_counters > fw->cfg.max_wrong_counters) {
            st->counter_errors++;
            return;
        }
    }
    ms->last_counter = (uint8_t)counter;
    ms->has_counter = 1u;
    ms->last_rx = now;
    ms->stale = 0u;
    st->frames_ok++;
    if (idx == TRUCK_FW_RX_MOTOR_CMD) {
        struct truck_motor_cmd_t cmd;
        (void)truck_motor_cmd_unpack(&cmd, data, len);
        apply_command(fw, &cmd, now);
    }
}

void truck_fw_rx_bytes(struct truck_fw *fw, const uint8_t *data, size_t len)
{
    uint8_t payload[TRUCK_MAX_PAYLOAD];
    for (size_t i = 0; i < len; i++) {
        uint16_t id;
        size_t n;
        if (truck_deframer_feed(&fw->deframer, data[i], &id, payload, &n)) {
            truck_fw_rx_frame(fw, id, payload, (uint8_t)n);
        }
    }
}

void truck_fw_link_reset(struct truck_fw *fw)
{
    fw->deframer.len = 0u;
    fw->deframer.overflow = 0;
}

/* -- state ---------------------------------------------------------------------------- */

uint8_t truck_fw_state(const struct truck_fw *fw)
{
    if (!fw->have_cmd) {
        return TRUCK_FW_STATE_IDLE;
    }
    if (fw->timed_out) {
        return TRUCK_FW_STATE_FAILSAFE;
    }
    return fw->enabled ? TRUCK_FW_STATE_ACTIVE : TRUCK_FW_STATE_IDLE;
}

uint16_t truck_fw_fault_bits(struct truck_fw *fw)
{
    uint32_t now = now_ms(fw);
    uint16_t bits = (uint16_t)(fw->sticky | fw->sensor_faults);
    if (fw->timed_out || (!fw->have_cmd && (fw->boot_timed_out ||
                                            elapsed(now, fw->t0) > (int32_t)fw->cfg.cmd_timeout_ms))) {
        bits |= TRUCK_FW_FAULT_CMD_TIMEOUT;
    }
    if (!truck_fw_rx_fresh(fw, TRUCK_FW_RX_COMPANION_HEARTBEAT)) {
        bits |= TRUCK_FW_FAULT_COMPANION_TIMEOUT;
    }
    if (read_vbat(fw) < fw->cfg.undervoltage_mv) {
        bits |= TRUCK_FW_FAULT_UNDERVOLTAGE;
    }
    return bits;
}

uint8_t truck_fw_cmd_errors(const struct truck_fw *fw)
{
    const struct truck_fw_rx_stats *st = &fw->stats.rx;
    return (uint8_t)(st->checksum_errors + st->length_errors + st->counter_errors +
                     st->payload_errors);
}

int32_t truck_fw_voltage_mv(const struct truck_fw *fw)
{
    return fw->voltage_mv;
}

uint8_t truck_fw_enabled(const struct truck_fw *fw)
{
    return fw->enabled;
}

int truck_fw_last_command(const struct truck_fw *fw, int16_t *voltage_mv, uint8_t *enable)
{
    *voltage_mv = fw->last_cmd_mv;
    *enable = fw->last_cmd_enable;
    return fw->have_cmd;
}

void truck_fw_get_stats(const struct truck_fw *fw, struct truck_fw_stats *out)
{
    *out = fw->stats;
    out->framing = fw->deframer.stats;
}

/* -- timeout and publishing ---------------------------------------------------------- */

static void check_timeout(struct truck_fw *fw, uint32_t now)
{
    if (!fw->have_cmd && !fw->boot_timed_out &&
        elapsed(now, fw->t0) > (int32_t)fw->cfg.cmd_timeout_ms) {
        fw->boot_timed_out = 1u;
    }
    if (!fw->timed_out && fw->have_cmd &&
        elapsed(now, fw->last_cmd) >= (int32_t)fw->cfg.cmd_timeout_ms) {
        fw->timed_out = 1u;
        fw->sticky |= TRUCK_FW_FAULT_CMD_TIMEOUT;
        fw->stats.cmd_timeouts++;
        set_motor(fw, 0, 0u);
    }
}

static int16_t sat16(int32_t v)
{
    return (int16_t)((v > 32767) ? 32767 : (v < -32768) ? -32768 : v);
}

static uint16_t satu16(int32_t v)
{
    return (uint16_t)((v > 65535) ? 65535 : (v < 0) ? 0 : v);
}

/* x / d rounded half away from zero (d > 0) */
static int32_t div_round(int32_t x, int32_t d)
{
    /* x within d of INT32_MAX or INT32_MIN overflowed (undefined behaviour): the ends
     * saturate (the caller saturates the result to 16 bits anyway) */
    if (x > INT32_MAX - d) {
        return INT32_MAX / d;
    }
    if (x < INT32_MIN + d) {
        return INT32_MIN / d;
    }
    return (x >= 0) ? (x + d / 2) / d : -((-x + d / 2) / d);
}

static void make(struct truck_fw *fw, unsigned i, uint32_t now, union truck_fw_tx_msg *m)
{
    uint16_t sample = (uint16_t)((uint32_t)(now - fw->t0) * 10u); /* 100 us, wraps */
    switch (i) {
    case TRUCK_FW_MSG_WHEEL_ENCODERS: {
        uint8_t status = 0u;
        fw->hal.read_encoders(fw->hal.ctx, &m->enc.ticks_left, &m->enc.ticks_right, &status);
        m->enc.sample_time = sample;
        m->enc.status = (uint8_t)(status & 0xFu);
        if (m->enc.status != 0u) {
            fw->sensor_faults |= TRUCK_FW_FAULT_ENCODER;
        } else {
            fw->sensor_faults &= (uint16_t)~TRUCK_FW_FAULT_ENCODER;
        }
        break;
    }
    case TRUCK_FW_MSG_MOTOR_FEEDBACK: {
        struct truck_hal_power p = {0};
        fw->hal.read_power(fw->hal.ctx, &p);
        m->fb.current = sat16(div_round(p.current_ma, 10));
        m->fb.vbat = satu16(p.vbat_mv);
        m->fb.u_applied = sat16(p.u_applied_mv);
        m->fb.status = fw->enabled ? 1u : 0u;
        break;
    }
    case TRUCK_FW_MSG_RANGE: {
        int32_t mm = 0;
        uint8_t st = fw->hal.read_range(fw->hal.ctx, &mm);
        m->range.sample_time = sample;
        m->range.distance = 0u;
        if (st == TRUCK_RANGE_VALID && mm > fw->cfg.range_max_mm) {
            st = TRUCK_RANGE_NO_TARGET;
        } else if (st == TRUCK_RANGE_VALID) {
            m->range.distance = satu16((mm < fw->cfg.range_min_mm) ? fw->cfg.range_min_mm : mm);
        } else if (st != TRUCK_RANGE_NO_TARGET) {
            st = TRUCK_RANGE_SENSOR_FAULT;
        }
        m->range.status = st;
        if (st == TRUCK_RANGE_SENSOR_FAULT) {
            fw->sensor_faults |= TRUCK_FW_FAULT_RANGE_SENSOR;
        } else {
            fw->sensor_faults &= (uint16_t)~TRUCK_FW_FAULT_RANGE_SENSOR;
        }
        break;
    }
    default:
        m->hb.state = truck_fw_state(fw);
        m->hb.faults = truck_fw_fault_bits(fw);
        m->hb.cmd_errors = truck_fw_cmd_errors(fw);
        break; /* the event bits are cleared once this heartbeat is sent (publish) */
    }
}

static int pack(unsigned i, union truck_fw_tx_msg *m, uint8_t counter, uint8_t *out)
{
    switch (i) {
    case TRUCK_FW_MSG_WHEEL_ENCODERS:
        m->enc.counter = counter;
        m->enc.checksum = 0u;
        return truck_wheel_encoders_pack(out, &m->enc, TRUCK_MAX_PAYLOAD);
    case TRUCK_FW_MSG_MOTOR_FEEDBACK:
        m->fb.counter = counter;
        m->fb.checksum = 0u;
        return truck_motor_feedback_pack(out, &m->fb, TRUCK_MAX_PAYLOAD);
    case TRUCK_FW_MSG_RANGE:
        m->range.counter = counter;
        m->range.checksum = 0u;
        return truck_range_pack(out, &m->range, TRUCK_MAX_PAYLOAD);
    default:
        m->hb.counter = counter;
        m->hb.checksum = 0u;
        return truck_firmware_heartbeat_pack(out, &m->hb, TRUCK_MAX_PAYLOAD);
    }
}

static void publish(struct truck_fw *fw, unsigned i, uint32_t now)
{
    struct truck_fw_tx_state *tx = &fw->tx[i];
    uint8_t data[TRUCK_MAX_PAYLOAD];
    uint8_t hooks = 0u;
#ifdef TRUCK_FW_FAULT_HOOKS
    hooks = tx->fault;
#endif
    uint16_t reported = 0u; /* event fault bits this message carries */
    if (!((hooks & TRUCK_FW_TX_FREEZE) && tx->has_last)) {
        if (i == TRUCK_FW_MSG_FIRMWARE_HEARTBEAT) {
            reported = fw->sticky;
        }
        make(fw, i, now, &tx->last);
        tx->has_last = 1u;
    }
    uint8_t counter = tx->counter;
    if (!(hooks & TRUCK_FW_TX_STUCK_COUNTER)) {
        tx->counter = (uint8_t)((counter + 1u) & TRUCK_COUNTER_MASK);
    }
#ifdef TRUCK_FW_FAULT_HOOKS
    if (fw->silent) {
        return;
    }
    if (tx->drop != 0) {
        if (tx->drop > 0) {
            tx->drop--;
        }
        fw->stats.frames_dropped++;
        return;
    }
#endif
    int n = pack(i, &tx->last, counter, data);
    if (n != (int)TX_SPEC[i].len) {
        fw->stats.tx_failed++;
        return;
    }
    truck_seal(TX_SPEC[i].id, data, (size_t)n);
    if (hooks & TRUCK_FW_TX_BAD_CHECKSUM) {
        data[n - 1] ^= 0xA5u;
    }
    int rc;
    if (fw->cfg.link == TRUCK_FW_LINK_CAN) {
        rc = fw->hal.send_frame(fw->hal.ctx, TX_SPEC[i].id, data, (uint8_t)n);
    } else {
        uint8_t wire[TRUCK_MAX_WIRE];
        int w = truck_frame_encode(TX_SPEC[i].id, data, (size_t)n, wire);
        rc = (w < 0) ? -1 : fw->hal.send_bytes(fw->hal.ctx, wire, (size_t)w);
    }
    if (rc == 0) {
        fw->stats.frames_sent++;
        fw->sticky &= (uint16_t)~reported; /* reported: an event unsent stays for the next */
    } else {
        fw->stats.tx_failed++;
    }
}

void truck_fw_poll(struct truck_fw *fw)
{
    uint32_t now = now_ms(fw);
    check_timeout(fw, now);
    for (unsigned i = 0; i < TRUCK_FW_N_RX; i++) {
        rx_expire(fw, &fw->rx[i], now);
    }
    for (unsigned i = 0; i < TRUCK_FW_N_TX; i++) {
        struct truck_fw_tx_state *tx = &fw->tx[i];
        if (elapsed(now, tx->next_due) < 0) {
            continue;
        }
        publish(fw, i, now);
        tx->next_due += TX_SPEC[i].period_ms;
        while (elapsed(now, tx->next_due) >= 0) { /* late: skip, keep the phase */
            tx->next_due += TX_SPEC[i].period_ms;
            fw->stats.schedule_slips++;
        }
    }
}

uint32_t truck_fw_next_event(const struct truck_fw *fw)
{
    uint32_t now = now_ms(fw);
    int32_t best = elapsed(fw->tx[0].next_due, now);
    for (unsigned i = 1; i < TRUCK_FW_N_TX; i++) {
        int32_t d = elapsed(fw->tx[i].next_due, now);
        if (d < best) {
            best = d;
        }
    }
    if (fw->have_cmd && !fw->timed_out) {
        int32_t d = elapsed(fw->last_cmd + fw->cfg.cmd_timeout_ms, now);
        if (d < best) {
            best = d;
        }
    }
    return now + (uint32_t)((best > 0) ? best : 0);
}

/* -- test hooks ------------------------------------------------------------------------ */

#ifdef TRUCK_FW_FAULT_HOOKS
int truck_fw_set_tx_fault(struct truck_fw *fw, unsigned msg, uint8_t bits)
{
    if (msg >= TRUCK_FW_N_TX) {
        return -1;
    }
    fw->tx[msg].fault = bits;
    return 0;
}

int truck_fw_set_drop(struct truck_fw *fw, unsigned msg, int32_t count)
{
    if (msg >= TRUCK_FW_N_TX || count < -1) {
        return -1;
    }
    fw->tx[msg].drop = count;
    return 0;
}

void truck_fw_set_silent(struct truck_fw *fw, uint8_t on)
{
    fw->silent = on ? 1u : 0u;
}

void truck_fw_clear_faults(struct truck_fw *fw)
{
    for (unsigned i = 0; i < TRUCK_FW_N_TX; i++) {
        fw->tx[i].fault = 0u;
        fw->tx[i].drop = 0;
    }
    fw->silent = 0u;
}
#endif
