/*
 * board/qemu/board.c: the HAL of truck_fw.h on the emulated STM32F405 of QEMU's
 * `netduinoplus2` machine (processor in the loop; docs/firmware.md).  The same core and
 * startup as the STM32F4 board example; what the emulator lacks is replaced:
 *
 *   SysTick 1 kHz ........ millis, from the real core clock (168 MHz in the emulator)
 *   USART2 ............... serial link to the companion (the daemon), RX interrupt into
 *                          a ring, TX polled (the emulated USART raises no TX-empty
 *                          interrupt)
 *   USART1 ............... plant I/O with the simulated plant on the host, text lines:
 *     board -> host  "T <ms>\n"                      every PLANT_PERIOD_MS: the plant
 *                                                    runs on this clock, and answers
 *     host -> board  "S <enc_l> <enc_r> <enc_status> <range_mm> <range_status>
 *                       <current_ma> <vbat_mv> <ms> <enc_milli> <enc_rate>\n"
 *                                                    sensor snapshot at the board's
 *                                                    instant <ms>; <enc_milli> the counters'
 *                                                    fraction of a tick (1/1000), <enc_rate>
 *                                                    their rate (ticks/s)
 *     board -> host  "B <ms>\n"                      booted, core initialised
 *                    "M <ms> <mv> <enable>\n"        every set_motor (driver output), at the
 *                                                    core's time of the decision
 *                    "C <ms> <frames_ok> <checksum_errors> <crc_errors> <cobs_errors>
 *                       <length_errors> <cmd_timeouts> <frames_sent> <tx_failed>
 *                       <commands_applied> <state>\n"   counters, every 100 ms
 * No ADC, timers or watchdog in the emulator: encoders, current and battery come from the
 * host (until the first "S" line: battery 0 V, NO_TARGET).  Lines that do not parse are
 * counted (bad_lines, in no message) and skipped.
 */
#include <stdint.h>

#include "truck_fw.h"

#define REG(addr) (*(volatile uint32_t *)(addr))

#define USART1 0x40011000u
#define USART2 0x40004400u
#define USART_SR(u) REG((u) + 0x00u)
#define USART_DR(u) REG((u) + 0x04u)
#define USART_CR1(u) REG((u) + 0x0Cu)
#define SR_RXNE (1u << 5)
#define SR_TXE (1u << 7)

#define SYST_CSR REG(0xE000E010u)
#define SYST_RVR REG(0xE000E014u)
#define SYST_CVR REG(0xE000E018u)
#define NVIC_ISER(n) REG(0xE000E100u + 4u * (n))

#define CORE_HZ 168000000u /* the emulated core clock */
#define STATS_PERIOD_MS 100u
#define PLANT_PERIOD_MS 5u

/* -- clock --------------------------------------------------------------------------- */
static volatile uint32_t ms_ticks;
/* The core's clock as it last read it: the "M" lines carry this stamp, the time the core
 * decided on (a SysTick between the core's reading and the driver call would otherwise
 * stamp a command a millisecond after the time the core keeps for its timeout). */
static uint32_t core_ms;

void SysTick_Handler(void);
void SysTick_Handler(void)
{
    ms_ticks++;
}

static uint32_t hal_millis(void *ctx)
{
    (void)ctx;
    core_ms = ms_ticks;
    return core_ms;
}

/* -- rings: RX filled by interrupts, TX drained by polling in the main loop ------------ */
#define RING 1024u
struct ring {
    volatile uint8_t buf[RING];
    volatile uint32_t head, tail;
};
static struct ring link_rx, link_tx, plant_rx, plant_tx;

static void rx_irq(uint32_t usart, struct ring *r)
{
    while (USART_SR(usart) & SR_RXNE) {
        uint8_t b = (uint8_t)USART_DR(usart);
        if (r->head - r->tail < RING) {
            r->buf[r->head % RING] = b;
            r->head++;
        }
    }
}

void USART1_IRQHandler(void);
void USART1_IRQHandler(void)
{
    rx_irq(USART1, &plant_rx);
}

void USART2_IRQHandler(void);
void USART2_IRQHandler(void)
{
    rx_irq(USART2, &link_rx);
}

static int ring_put(struct ring *r, const uint8_t *data, uint32_t len)
{
    if (RING - (r->head - r->tail) < len) {
        return -1;
    }
    for (uint32_t i = 0; i < len; i++) {
        r->buf[r->head % RING] = data[i];
        r->head++;
    }
    return 0;
}

static void tx_poll(uint32_t usart, struct ring *r)
{
    while (r->tail != r->head && (USART_SR(usart) & SR_TXE)) {
        USART_DR(usart) = r->buf[r->tail % RING];
        r->tail++;
    }
}

/* -- plant lines --------------------------------------------------------------------- */
static char *put_int(char *p, int32_t v)
{
    char tmp[12];
    unsigned n = 0;
    uint32_t u = (v < 0) ? (uint32_t)(-(v + 1)) + 1u : (uint32_t)v;
    if (v < 0) {
        *p++ = '-';
    }
    do {
        tmp[n++] = (char)('0' + u % 10u);
        u /= 10u;
    } while (u != 0u);
    while (n > 0u) {
        *p++ = tmp[--n];
    }
    return p;
}

static void plant_line(char kind, const int32_t *v, unsigned n)
{
    char line[160];
    char *p = line;
    *p++ = kind;
    for (unsigned i = 0; i < n; i++) {
        *p++ = ' ';
        p = put_int(p, v[i]);
    }
    *p++ = '\n';
    (void)ring_put(&plant_tx, (const uint8_t *)line, (uint32_t)(p - line));
}

static volatile struct {
    uint16_t enc_l, enc_r;
    uint8_t enc_status;
    int32_t range_mm;
    uint8_t range_status;
    int32_t current_ma, vbat_mv;
    uint32_t ms;        /* the board's instant of the snapshot */
    int32_t enc_milli;  /* the counters' fraction of a tick at that instant, 1/1000 */
    int32_t enc_rate;   /* ticks/s */
} sensors = {0u, 0u, 0u, 0, TRUCK_RANGE_NO_TARGET, 0, 0, 0u, 0, 0};
static uint32_t bad_lines;

/* "S" and ten integers: the sensor snapshot; 0 when it parsed */
static int parse_sensors(const char *s, uint32_t len)
{
    int32_t v[10];
    unsigned n = 0;
    uint32_t i = 1;
    if (len < 2u || s[0] != 'S') {
        return -1;
    }
    while (i < len && n < 10u) {
        if (s[i] != ' ') {
            return -1;
        }
        i++;
        int neg = (i < len && s[i] == '-');
        i += (uint32_t)neg;
        if (i >= len || s[i] < '0' || s[i] > '9') {
            return -1;
        }
        int64_t x = 0;
        while (i < len && s[i] >= '0' && s[i] <= '9') {
            x = x * 10 + (s[i] - '0');
            if (x > 2147483647) {
                return -1;
            }
            i++;
        }
        v[n++] = (int32_t)(neg ? -x : x);
    }
    if (n != 10u || i != len || v[8] < 0 || v[8] > 999) {
        return -1;
    }
    sensors.enc_l = (uint16_t)v[0];
    sensors.enc_r = (uint16_t)v[1];
    sensors.enc_status = (uint8_t)v[2];
    sensors.range_mm = v[3];
    sensors.range_status = (uint8_t)v[4];
    sensors.current_ma = v[5];
    sensors.vbat_mv = v[6];
    sensors.ms = (uint32_t)v[7];
    sensors.enc_milli = v[8];
    sensors.enc_rate = v[9];
    return 0;
}

static char plant_line_buf[128];
static uint32_t plant_line_len;
static uint8_t plant_line_long; /* the line overflowed the buffer: bad, skipped */

static void plant_rx_poll(void)
{
    while (plant_rx.tail != plant_rx.head) {
        char c = (char)plant_rx.buf[plant_rx.tail % RING];
        plant_rx.tail++;
        if (c == '\n') {
            if (plant_line_long || parse_sensors(plant_line_buf, plant_line_len) != 0) {
                bad_lines++;
            }
            plant_line_len = 0u;
            plant_line_long = 0u;
        } else if (plant_line_len < sizeof(plant_line_buf)) {
            plant_line_buf[plant_line_len++] = c;
        } else {
            plant_line_long = 1u;
        }
    }
}

/* The encoder counters between snapshots run on at the snapshot's rate, as a hardware
 * counter would: a snapshot arrives some time after its instant (or is skipped while the
 * previous one is still unread), and a count held still for that time would read as a
 * truck that stopped and then jumped.  At most ENC_RUN_ON_MS past the snapshot (a host
 * that stopped answering: the counters then stop too). */
#define ENC_RUN_ON_MS 50

/* floor(x / 1000) */
static int32_t floor_div_1000(int64_t x)
{
    int64_t q = x / 1000;
    return (int32_t)((x % 1000 < 0) ? q - 1 : q);
}

/* -- HAL ----------------------------------------------------------------------------- */
static void hal_read_encoders(void *ctx, uint16_t *left, uint16_t *right, uint8_t *status)
{
    (void)ctx;
    int32_t dt = (int32_t)(core_ms - sensors.ms); /* the core read its clock just before */
    dt = (dt < 0) ? 0 : (dt > ENC_RUN_ON_MS) ? ENC_RUN_ON_MS : dt;
    /* ticks/s * ms = 1/1000 ticks */
    int32_t run_on = floor_div_1000((int64_t)sensors.enc_milli + (int64_t)sensors.enc_rate * dt);
    *left = (uint16_t)((int32_t)sensors.enc_l + run_on);
    *right = (uint16_t)((int32_t)sensors.enc_r + run_on);
    *status = sensors.enc_status;
}

static int32_t commanded_mv;

static void hal_read_power(void *ctx, struct truck_hal_power *out)
{
    (void)ctx;
    out->current_ma = sensors.current_ma;
    out->vbat_mv = sensors.vbat_mv;
    out->u_applied_mv = commanded_mv;
}

static uint8_t hal_read_range(void *ctx, int32_t *distance_mm)
{
    (void)ctx;
    *distance_mm = sensors.range_mm;
    return sensors.range_status;
}

static void hal_set_motor(void *ctx, int32_t voltage_mv, uint8_t enable)
{
    (void)ctx;
    commanded_mv = enable ? voltage_mv : 0;
    const int32_t v[3] = {(int32_t)core_ms, voltage_mv, enable};
    plant_line('M', v, 3u);
}

static int hal_send_bytes(void *ctx, const uint8_t *data, size_t len)
{
    (void)ctx;
    return ring_put(&link_tx, data, (uint32_t)len);
}

static int hal_send_frame(void *ctx, uint16_t can_id, const uint8_t *data, uint8_t len)
{
    (void)ctx;
    (void)can_id;
    (void)data;
    (void)len;
    return -1; /* serial link only */
}

/* The fault handlers (startup.c) call this: the driver output to 0 V, disabled. */
void board_motor_off(void);
void board_motor_off(void)
{
    const char line[] = "M 0 0 0\n";
    for (unsigned i = 0; i + 1u < sizeof(line); i++) {
        uint32_t spins = 100000u; /* bounded: a fault handler must not hang on the UART */
        while (!(USART_SR(USART1) & SR_TXE) && spins > 0u) {
            spins--;
        }
        USART_DR(USART1) = (uint8_t)line[i];
    }
}

static void board_init(void)
{
    SYST_RVR = CORE_HZ / 1000u - 1u;
    SYST_CVR = 0u;
    SYST_CSR = 7u; /* core clock, interrupt, enable */
    /* UE, RXNEIE, TE, RE; the emulator ignores the baud rate */
    USART_CR1(USART1) = (1u << 13) | (1u << 5) | (1u << 3) | (1u << 2);
    USART_CR1(USART2) = (1u << 13) | (1u << 5) | (1u << 3) | (1u << 2);
    NVIC_ISER(1) = (1u << (37u - 32u)) | (1u << (38u - 32u));
}

int main(void)
{
    struct truck_fw_config cfg;
    truck_fw_default_config(&cfg);
    cfg.link = TRUCK_FW_LINK_SERIAL;
    const struct truck_hal hal = {
        .ctx = 0,
        .millis = hal_millis,
        .read_encoders = hal_read_encoders,
        .read_power = hal_read_power,
        .read_range = hal_read_range,
        .set_motor = hal_set_motor,
        .send_bytes = hal_send_bytes,
        .send_frame = hal_send_frame,
    };
    static struct truck_fw fw;
    board_init();
    truck_fw_init(&fw, &cfg, &hal);
    const int32_t boot[1] = {(int32_t)ms_ticks};
    plant_line('B', boot, 1u);
    uint32_t next_stats = ms_ticks + STATS_PERIOD_MS;
    uint32_t next_plant = ms_ticks;
    for (;;) {
        uint8_t chunk[64];
        size_t n = 0;
        while (link_rx.tail != link_rx.head && n < sizeof(chunk)) {
            chunk[n++] = link_rx.buf[link_rx.tail % RING];
            link_rx.tail++;
        }
        truck_fw_rx_bytes(&fw, chunk, n);
        plant_rx_poll();
        truck_fw_poll(&fw);
        uint32_t now = ms_ticks;
        if ((int32_t)(now - next_plant) >= 0) {
            const int32_t t[1] = {(int32_t)now};
            plant_line('T', t, 1u);
            next_plant = now + PLANT_PERIOD_MS;
        }
        if ((int32_t)(now - next_stats) >= 0) {
            struct truck_fw_stats st;
            truck_fw_get_stats(&fw, &st);
            const int32_t v[11] = {
                (int32_t)now,
                (int32_t)st.rx.frames_ok,
                (int32_t)st.rx.checksum_errors,
                (int32_t)st.framing.crc_errors,
                (int32_t)st.framing.cobs_errors,
                (int32_t)st.framing.length_errors,
                (int32_t)st.cmd_timeouts,
                (int32_t)st.frames_sent,
                (int32_t)st.tx_failed,
                (int32_t)st.commands_applied,
                (int32_t)truck_fw_state(&fw),
            };
            plant_line('C', v, 11u);
            next_stats += STATS_PERIOD_MS;
        }
        tx_poll(USART2, &link_tx);
        tx_poll(USART1, &plant_tx);
        if (n == 0u && link_rx.tail == link_rx.head && plant_rx.tail == plant_rx.head) {
            __asm__ volatile("wfi"); /* SysTick (1 ms) or a received byte wakes us */
        }
    }
}
