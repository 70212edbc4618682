/* startup.c: vector table and reset handler of the STM32F4 board example (no CMSIS). */
#include <stdint.h>
#include <string.h>

extern uint32_t _estack, _sidata, _sdata, _edata, _sbss, _ebss;

int main(void);
void Reset_Handler(void);
void Default_Handler(void);
void SysTick_Handler(void);
/* a board without one of these leaves it to the default handler */
void USART1_IRQHandler(void) __attribute__((weak, alias("Default_Handler")));
void USART2_IRQHandler(void) __attribute__((weak, alias("Default_Handler")));
void CAN1_RX0_IRQHandler(void) __attribute__((weak, alias("Default_Handler")));

void board_motor_off(void);

void Default_Handler(void)
{
    /* A fault (HardFault, NMI, ...): the motor off first, then wait for the watchdog to
     * reset the chip (the timer would otherwise keep the last duty on the motor). */
    board_motor_off();
    for (;;) {
    }
}

void Reset_Handler(void)
{
    memcpy(&_sdata, &_sidata, (size_t)((char *)&_edata - (char *)&_sdata));
    memset(&_sbss, 0, (size_t)((char *)&_ebss - (char *)&_sbss));
    /* enable the FPU (CP10, CP11 full access) */
    *(volatile uint32_t *)0xE000ED88u |= (0xFu << 20);
    (void)main();
    for (;;) {
    }
}

typedef void (*vector_t)(void);

/* 16 core exceptions + 82 interrupts; only the ones the board uses are named */
__attribute__((section(".isr_vector"), used)) static const vector_t vectors[16 + 82] = {
    [0] = (vector_t)(uintptr_t)&_estack,
    [1] = Reset_Handler,
    [2] = Default_Handler, /* NMI */
    [3] = Default_Handler, /* HardFault */
    [4] = Default_Handler,
    [5] = Default_Handler,
    [6] = Default_Handler,
    [11] = Default_Handler, /* SVCall */
    [14] = Default_Handler, /* PendSV */
    [15] = SysTick_Handler,
    [16 + 20] = CAN1_RX0_IRQHandler,
    [16 + 37] = USART1_IRQHandler,
    [16 + 38] = USART2_IRQHandler,
};
