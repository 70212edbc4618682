/*
 * board.c: the HAL of truck_fw.h for an STM32F407 board (register level, no vendor SDK),
 * and the firmware's main loop.  A minimal example: HSI 16 MHz clock, no PLL.
 *
 *   SysTick 1 kHz ........ millis
 *   TIM2 / TIM3 .......... quadrature encoders, left PA0/PA1, right PA6/PA7
 *   ADC1 IN10/IN11 + DMA . motor current (PC0, hall sensor 2.5 V = 0 A, 100 mV/A after a
 *                          2:3 divider) and battery (PC1, 1:3 divider), continuous scan
 *   TIM1 CH1 (PA8) ....... H-bridge PWM 20 kHz; PB0 direction, PB1 driver enable
 *   USART2 PA2/PA3 ....... serial link 115200 8N1 (default), ring buffers + interrupts
 *   CAN1 PB8/PB9 ......... CAN link 500 kbit/s (build with -DBOARD_LINK_CAN)
 *   range sensor ......... stub: a real driver (e.g. VL53L1X over I2C) calls
 *                          board_range_update(); until then NO_TARGET
 * Every HAL function returns at once.  The only waits on the hardware (the CAN
 * controller's mode acknowledges) are bounded (BOARD_WAIT_MS) and run after the watchdog
 * is started; a controller that does not answer leaves a fault code in board_fault
 * (BOARD_FAULT_*), the link down and the motor off, and is tried again every
 * CAN_RETRY_MS while the main loop runs on.
 */
#include <stdint.h>

#include "truck_fw.h"

#define REG(addr) (*(volatile uint32_t *)(addr))

/* RCC */
#define RCC_AHB1ENR REG(0x40023830u)
#define RCC_APB1ENR REG(0x40023840u)
#define RCC_APB2ENR REG(0x40023844u)
/* GPIO */
#define GPIOA 0x40020000u
#define GPIOB 0x40020400u
#define GPIOC 0x40020800u
#define GPIO_MODER(p) REG((p) + 0x00u)
#define GPIO_BSRR(p) REG((p) + 0x18u)
#define GPIO_AFRL(p) REG((p) + 0x20u)
#define GPIO_AFRH(p) REG((p) + 0x24u)
/* timers */
#define TIM1 0x40010000u
#define TIM2 0x40000000u
#define TIM3 0x40000400u
#define IWDG_KR REG(0x40003000u)
#define IWDG_PR REG(0x40003004u)
#define IWDG_RLR REG(0x40003008u)
#define TIM_BDTR_MOE (1u << 15)
#define TIM_CR1(t) REG((t) + 0x00u)
#define TIM_SMCR(t) REG((t) + 0x08u)
#define TIM_CCMR1(t) REG((t) + 0x18u)
#define TIM_CCER(t) REG((t) + 0x20u)
#define TIM_CNT(t) REG((t) + 0x24u)
#define TIM_PSC(t) REG((t) + 0x28u)
#define TIM_ARR(t) REG((t) + 0x2Cu)
#define TIM_CCR1(t) REG((t) + 0x34u)
#define TIM_BDTR(t) REG((t) + 0x44u)
/* ADC1 + DMA2 stream 0 */
#define ADC1 0x40012000u
#define ADC_CR1 REG(ADC1 + 0x04u)
#define ADC_CR2 REG(ADC1 + 0x08u)
#define ADC_SMPR1 REG(ADC1 + 0x0Cu)
#define ADC_SQR1 REG(ADC1 + 0x2Cu)
#define ADC_SQR3 REG(ADC1 + 0x34u)
#define ADC_DR_ADDR (ADC1 + 0x4Cu)
#define DMA2_S0CR REG(0x40026410u)
#define DMA2_S0NDTR REG(0x40026414u)
#define DMA2_S0PAR REG(0x40026418u)
#define DMA2_S0M0AR REG(0x4002641Cu)
/* USART2 */
#define USART2 0x40004400u
#define USART_SR REG(USART2 + 0x00u)
#define USART_DR REG(USART2 + 0x04u)
#define USART_BRR REG(USART2 + 0x08u)
#define USART_CR1 REG(USART2 + 0x0Cu)
/* CAN1 */
#define CAN1 0x40006400u
#define CAN_MCR REG(CAN1 + 0x000u)
#define CAN_MSR REG(CAN1 + 0x004u)
#define CAN_TSR REG(CAN1 + 0x008u)
#define CAN_RF0R REG(CAN1 + 0x00Cu)
#define CAN_IER REG(CAN1 + 0x014u)
#define CAN_BTR REG(CAN1 + 0x01Cu)
#define CAN_TIR(m) REG(CAN1 + 0x180u + 0x10u * (m))
#define CAN_TDTR(m) REG(CAN1 + 0x184u + 0x10u * (m))
#define CAN_TDLR(m) REG(CAN1 + 0x188u + 0x10u * (m))
#define CAN_TDHR(m) REG(CAN1 + 0x18Cu + 0x10u * (m))
#define CAN_RI0R REG(CAN1 + 0x1B0u)
#define CAN_RDT0R REG(CAN1 + 0x1B4u)
#define CAN_RDL0R REG(CAN1 + 0x1B8u)
#define CAN_RDH0R REG(CAN1 + 0x1BCu)
#define CAN_FMR REG(CAN1 + 0x200u)
#define CAN_FM1R REG(CAN1 + 0x204u)
#define CAN_FS1R REG(CAN1 + 0x20Cu)
#define CAN_FA1R REG(CAN1 + 0x21Cu)
#define CAN_F0R1 REG(CAN1 + 0x240u)
#define CAN_F0R2 REG(CAN1 + 0x244u)
/* core */
#define SYST_CSR REG(0xE000E010u)
#define SYST_RVR REG(0xE000E014u)
#define SYST_CVR REG(0xE000E018u)
#define NVIC_ISER(n) REG(0xE000E100u + 4u * (n))
#define NVIC_ICER(n) REG(0xE000E180u + 4u * (n))

#define HSI_HZ 16000000u
#define PWM_TOP 799u /* 16 MHz / 800 = 20 kHz */

#define BOARD_WAIT_MS 2u    /* a mode acknowledge takes microseconds on a working board */
#define CAN_RETRY_MS 1000u /* the CAN controller is tried again this often while failed */

/* board_fault: why the link is not up (readable with a debugger; 0 = none) */
#define BOARD_FAULT_NONE 0u
#define BOARD_FAULT_CAN_INIT 1u  /* bxCAN gave no init-mode acknowledge (clock, reset) */
#define BOARD_FAULT_CAN_START 2u /* bxCAN did not leave init mode: no bus (transceiver,
                                    wiring, termination) */
volatile uint8_t board_fault;
volatile uint32_t board_fault_count; /* failed attempts since reset */

/* -- clock --------------------------------------------------------------------------- */
static volatile uint32_t ms_ticks;

void SysTick_Handler(void);
void SysTick_Handler(void)
{
    ms_ticks++;
}

static uint32_t hal_millis(void *ctx)
{
    (void)ctx;
    return ms_ticks;
}

/* -- sensors ------------------------------------------------------------------------- */
static volatile uint16_t adc_buf[2]; /* [0] current, [1] battery (DMA, continuous) */
static volatile int32_t range_mm = -1;
static volatile uint8_t range_status = TRUCK_RANGE_NO_TARGET;

/** For the range sensor's driver: a new reading (status TRUCK_RANGE_*). */
void board_range_update(int32_t mm, uint8_t status);
void board_range_update(int32_t mm, uint8_t status)
{
    range_mm = mm;
    range_status = status;
}

static void hal_read_encoders(void *ctx, uint16_t *left, uint16_t *right, uint8_t *status)
{
    (void)ctx;
    *left = (uint16_t)TIM_CNT(TIM2);
    *right = (uint16_t)TIM_CNT(TIM3);
    *status = 0u;
}

static int32_t vbat_mv(void)
{
    return (int32_t)((uint32_t)adc_buf[1] * 3300u * 3u / 4095u);
}

static int32_t commanded_mv;

static void hal_read_power(void *ctx, struct truck_hal_power *out)
{
    (void)ctx;
    /* 2.5 V at 0 A, 100 mV/A, seen through a 2:3 divider: 1 LSB = 3300/4095 * 1.5 / 0.1 mA */
    int32_t mv = (int32_t)((uint32_t)adc_buf[0] * 3300u / 4095u) * 3 / 2;
    out->current_ma = (mv - 2500) * 10;
    out->vbat_mv = vbat_mv();
    out->u_applied_mv = commanded_mv;
}

static uint8_t hal_read_range(void *ctx, int32_t *distance_mm)
{
    (void)ctx;
    *distance_mm = range_mm;
    return range_status;
}

/* -- motor --------------------------------------------------------------------------- */
static void hal_set_motor(void *ctx, int32_t voltage_mv, uint8_t enable)
{
    (void)ctx;
    int32_t vb = vbat_mv();
    uint32_t mag = (uint32_t)((voltage_mv < 0) ? -voltage_mv : voltage_mv);
    uint32_t duty = (vb > 0) ? mag * (PWM_TOP + 1u) / (uint32_t)vb : 0u;
    if (duty > PWM_TOP + 1u) {
        duty = PWM_TOP + 1u;
    }
    if (!enable) {
        duty = 0u;
    }
    GPIO_BSRR(GPIOB) = (voltage_mv < 0) ? (1u << 0) : (1u << 16); /* direction PB0 */
    TIM_CCR1(TIM1) = duty;
    GPIO_BSRR(GPIOB) = enable ? (1u << 1) : (1u << 17); /* driver enable PB1 */
    commanded_mv = enable ? voltage_mv : 0;
}

/* -- serial link: ring buffers filled/drained by the USART2 interrupt ------------------ */
#define RING 512u
static volatile uint8_t rx_ring[RING], tx_ring[RING];
static volatile uint32_t rx_head, rx_tail, tx_head, tx_tail;

void USART2_IRQHandler(void);
void USART2_IRQHandler(void)
{
    uint32_t sr = USART_SR;
    if (sr & (1u << 5)) { /* RXNE */
        uint8_t b = (uint8_t)USART_DR;
        if (rx_head - rx_tail < RING) {
            rx_ring[rx_head % RING] = b;
            rx_head++;
        }
    }
    if ((sr & (1u << 7)) && (USART_CR1 & (1u << 7))) { /* TXE and its interrupt on */
        if (tx_tail != tx_head) {
            USART_DR = tx_ring[tx_tail % RING];
            tx_tail++;
        } else {
            USART_CR1 &= ~(1u << 7);
        }
    }
}

static int hal_send_bytes(void *ctx, const uint8_t *data, size_t len)
{
    (void)ctx;
    if (RING - (tx_head - tx_tail) < len) {
        return -1; /* no room: the frame is lost, counted by the core */
    }
    for (size_t i = 0; i < len; i++) {
        tx_ring[tx_head % RING] = data[i];
        tx_head++;
    }
    USART_CR1 |= (1u << 7); /* TXEIE */
    return 0;
}

/* -- CAN link: bxCAN mailboxes ------------------------------------------------------- */
static int hal_send_frame(void *ctx, uint16_t can_id, const uint8_t *data, uint8_t len)
{
    (void)ctx;
    if (board_fault != BOARD_FAULT_NONE) {
        return -1; /* the controller is not running: counted by the core (tx_failed) */
    }
    uint32_t tsr = CAN_TSR;
    unsigned m;
    if (tsr & (1u << 26)) {
        m = 0u;
    } else if (tsr & (1u << 27)) {
        m = 1u;
    } else if (tsr & (1u << 28)) {
        m = 2u;
    } else {
        return -1; /* every mailbox busy */
    }
    uint32_t lo = 0u, hi = 0u;
    for (uint8_t i = 0; i < len && i < 8u; i++) {
        if (i < 4u) {
            lo |= (uint32_t)data[i] << (8u * i);
        } else {
            hi |= (uint32_t)data[i] << (8u * (i - 4u));
        }
    }
    CAN_TDTR(m) = len;
    CAN_TDLR(m) = lo;
    CAN_TDHR(m) = hi;
    CAN_TIR(m) = ((uint32_t)can_id << 21) | 1u; /* standard id, TXRQ */
    return 0;
}

/* received frames wait here for the main loop (the core is not re-entrant) */
#define CAN_RING 16u
struct can_rx {
    uint16_t id;
    uint8_t len;
    uint8_t data[8];
};
static volatile struct can_rx can_ring[CAN_RING];
static volatile uint32_t can_head, can_tail;

void CAN1_RX0_IRQHandler(void);
void CAN1_RX0_IRQHandler(void)
{
    while (CAN_RF0R & 3u) {
        uint32_t rir = CAN_RI0R;
        uint8_t len = (uint8_t)(CAN_RDT0R & 0xFu);
        uint32_t lo = CAN_RDL0R, hi = CAN_RDH0R;
        CAN_RF0R |= (1u << 5); /* release the FIFO mailbox */
        if ((rir & 6u) || len > 8u || can_head - can_tail >= CAN_RING) {
            continue; /* extended or remote frame, or the ring is full */
        }
        volatile struct can_rx *f = &can_ring[can_head % CAN_RING];
        f->id = (uint16_t)(rir >> 21);
        f->len = len;
        for (unsigned i = 0; i < 8u; i++) {
            f->data[i] = (uint8_t)((i < 4u) ? (lo >> (8u * i)) : (hi >> (8u * (i - 4u))));
        }
        can_head++;
    }
}

/* -- init ---------------------------------------------------------------------------- */
static void gpio_af(uint32_t port, unsigned pin, unsigned af)
{
    GPIO_MODER(port) = (GPIO_MODER(port) & ~(3u << (2u * pin))) | (2u << (2u * pin));
    if (pin < 8u) {
        GPIO_AFRL(port) = (GPIO_AFRL(port) & ~(0xFu << (4u * pin))) | (af << (4u * pin));
    } else {
        unsigned p = pin - 8u;
        GPIO_AFRH(port) = (GPIO_AFRH(port) & ~(0xFu << (4u * p))) | (af << (4u * p));
    }
}

static void encoder_init(uint32_t tim)
{
    TIM_SMCR(tim) = 3u;                      /* encoder mode 3: count on both edges */
    TIM_CCMR1(tim) = (1u << 0) | (1u << 8); /* CC1S = TI1, CC2S = TI2 */
    TIM_ARR(tim) = 0xFFFFu;
    TIM_CR1(tim) = 1u;
}

static void board_init(uint8_t can)
{
    RCC_AHB1ENR |= (1u << 0) | (1u << 1) | (1u << 2) | (1u << 22); /* GPIOA-C, DMA2 */
    RCC_APB1ENR |= (1u << 0) | (1u << 1) | (1u << 17) | (1u << 25); /* TIM2, TIM3, USART2, CAN1 */
    RCC_APB2ENR |= (1u << 0) | (1u << 8);                           /* TIM1, ADC1 */

    SYST_RVR = HSI_HZ / 1000u - 1u;
    SYST_CVR = 0u;
    SYST_CSR = 7u; /* core clock, interrupt, enable */

    gpio_af(GPIOA, 0u, 1u); /* TIM2 CH1/CH2 */
    gpio_af(GPIOA, 1u, 1u);
    gpio_af(GPIOA, 6u, 2u); /* TIM3 CH1/CH2 */
    gpio_af(GPIOA, 7u, 2u);
    encoder_init(TIM2);
    encoder_init(TIM3);

    GPIO_MODER(GPIOC) |= (3u << 0) | (3u << 2); /* PC0, PC1 analog */
    ADC_SMPR1 = (7u << 0) | (7u << 3);          /* IN10, IN11: 480 cycles */
    ADC_SQR1 = (1u << 20);                      /* 2 conversions */
    ADC_SQR3 = 10u | (11u << 5);
    ADC_CR1 = (1u << 8);                        /* scan */
    DMA2_S0PAR = ADC_DR_ADDR;
    DMA2_S0M0AR = (uint32_t)(uintptr_t)adc_buf;
    DMA2_S0NDTR = 2u;
    /* channel 0, 16-bit both sides, memory increment, circular, enable */
    DMA2_S0CR = (1u << 13) | (1u << 11) | (1u << 10) | (1u << 8) | 1u;
    ADC_CR2 = (1u << 9) | (1u << 8) | (1u << 1) | 1u; /* DDS, DMA, continuous, on */
    ADC_CR2 |= (1u << 30);                            /* start */

    gpio_af(GPIOA, 8u, 1u); /* TIM1 CH1 */
    GPIO_MODER(GPIOB) = (GPIO_MODER(GPIOB) & ~0xFu) | 0x5u; /* PB0, PB1 outputs */
    TIM_PSC(TIM1) = 0u;
    TIM_ARR(TIM1) = PWM_TOP;
    TIM_CCR1(TIM1) = 0u;
    TIM_CCMR1(TIM1) = (6u << 4) | (1u << 3); /* PWM mode 1, preload */
    TIM_CCER(TIM1) = 1u;
    TIM_BDTR(TIM1) = (1u << 15); /* main output enable */
    TIM_CR1(TIM1) = 1u;

    if (can) {
        gpio_af(GPIOB, 8u, 9u); /* CAN1 RX/TX */
        gpio_af(GPIOB, 9u, 9u);
    } else {
        gpio_af(GPIOA, 2u, 7u); /* USART2 TX/RX */
        gpio_af(GPIOA, 3u, 7u);
        USART_BRR = (HSI_HZ + 115200u / 2u) / 115200u;
        USART_CR1 = (1u << 13) | (1u << 5) | (1u << 3) | (1u << 2); /* UE, RXNEIE, TE, RE */
        NVIC_ISER(1) = (1u << (38u - 32u));
    }
}

/* Wait until (CAN_MSR & mask) == want, at most BOARD_WAIT_MS (SysTick runs); 0 when it
 * came.  The watchdog runs: a wait never outlasts its 50 ms. */
static int can_wait_msr(uint32_t mask, uint32_t want)
{
    uint32_t t0 = ms_ticks;
    while ((CAN_MSR & mask) != want) {
        if (ms_ticks - t0 > BOARD_WAIT_MS) {
            return -1;
        }
    }
    return 0;
}

/* Configure and start bxCAN; BOARD_FAULT_NONE or the fault code (also in board_fault). */
static uint8_t can_start(void)
{
    uint8_t fault = BOARD_FAULT_NONE;
    NVIC_ICER(0) = (1u << 20);
    CAN_MCR = 1u; /* INRQ */
    if (can_wait_msr(1u, 1u) != 0) {
        fault = BOARD_FAULT_CAN_INIT;
    } else {
        /* 16 MHz / 2 = 8 MHz time quanta, 1 + 13 + 2 = 16 tq: 500 kbit/s, sample 87.5 % */
        CAN_BTR = (1u << 20) | (12u << 16) | 1u;
        CAN_FMR |= 1u; /* filter init: filter 0, 32-bit mask 0 = accept all */
        CAN_FS1R |= 1u;
        CAN_FM1R &= ~1u;
        CAN_F0R1 = 0u;
        CAN_F0R2 = 0u;
        CAN_FA1R |= 1u;
        CAN_FMR &= ~1u;
        CAN_IER = (1u << 1); /* FMPIE0 */
        CAN_MCR = (1u << 6); /* leave init (needs 11 recessive bits on the bus), ABOM */
        if (can_wait_msr(1u, 0u) != 0) {
            fault = BOARD_FAULT_CAN_START;
        } else {
            NVIC_ISER(0) = (1u << 20);
        }
    }
    if (fault != BOARD_FAULT_NONE) {
        board_fault_count++;
    }
    board_fault = fault;
    return fault;
}

/* Motor off at once: zero duty, the timer's outputs off, the driver disabled.  Called by
 * the fault handlers (startup.c): a fault must not leave the last duty on the motor. */
void board_motor_off(void)
{
    TIM_CCR1(TIM1) = 0u;
    TIM_BDTR(TIM1) &= ~TIM_BDTR_MOE;
    GPIO_BSRR(GPIOB) = (1u << 17); /* PB1 low: driver enable off */
}

/* The independent watchdog: 50 ms (LSI 32 kHz / 4, reload 400).  A hung main loop resets
 * the chip, and a reset leaves PB1 an input: the board's pull-down on the driver's enable
 * keeps the motor off until the firmware runs again. */
static void watchdog_start(void)
{
    IWDG_KR = 0xCCCCu; /* start */
    IWDG_KR = 0x5555u; /* unlock PR and RLR */
    IWDG_PR = 0u;      /* /4 */
    IWDG_RLR = 400u;
    IWDG_KR = 0xAAAAu; /* reload */
}

int main(void)
{
#ifdef BOARD_LINK_CAN
    const uint8_t can = 1u;
#else
    const uint8_t can = 0u;
#endif
    struct truck_fw_config cfg;
    truck_fw_default_config(&cfg);
    cfg.link = can ? TRUCK_FW_LINK_CAN : TRUCK_FW_LINK_SERIAL;
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
    watchdog_start(); /* first: every wait after this is bounded by it too */
    board_init(can);
    truck_fw_init(&fw, &cfg, &hal);
    uint32_t can_tried = ms_ticks;
    if (can) {
        (void)can_start();
    }
    for (;;) {
        IWDG_KR = 0xAAAAu; /* the loop runs: feed the watchdog */
        if (can && board_fault != BOARD_FAULT_NONE && ms_ticks - can_tried >= CAN_RETRY_MS) {
            can_tried = ms_ticks;
            (void)can_start(); /* the motor stays off meanwhile: no command arrives */
        }
        uint8_t chunk[32];
        size_t n = 0;
        while (rx_tail != rx_head && n < sizeof(chunk)) {
            chunk[n++] = rx_ring[rx_tail % RING];
            rx_tail++;
        }
        truck_fw_rx_bytes(&fw, chunk, n);
        while (can_tail != can_head) {
            volatile struct can_rx *f = &can_ring[can_tail % CAN_RING];
            uint8_t data[8];
            for (unsigned i = 0; i < 8u; i++) {
                data[i] = f->data[i];
            }
            truck_fw_rx_frame(&fw, f->id, data, f->len);
            can_tail++;
            n++;
        }
        truck_fw_poll(&fw);
        if (n == 0u) {
            __asm__ volatile("wfi"); /* SysTick wakes us every millisecond */
        }
    }
}
