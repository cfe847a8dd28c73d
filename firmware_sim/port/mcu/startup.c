/*
 * startup.c - reset handler and vector table of the STM32F405 (Cortex-M4F).
 *
 * Reset: enable the FPU (CPACR CP10/CP11 full access) before any C code can use it, copy
 * .data from flash, zero .bss, call mcu_main(). Exceptions without a handler of the port
 * stop in mcu_fault_handler (a debugger finds the cause in the SCB fault registers).
 */
#include <stdint.h>

#include "mcu_hw.h"

extern uint32_t _mcu_data_load, _mcu_data_start, _mcu_data_end, _mcu_bss_start, _mcu_bss_end, _mcu_stack_top;

void mcu_reset_handler(void);
void mcu_fault_handler(void);
void mcu_systick_handler(void);
void mcu_usart1_handler(void);
int mcu_main(void);

#define MCU_NUM_IRQ 82u

typedef void (*mcu_vector_t)(void);

__attribute__((section(".isr_vector"), used)) static const mcu_vector_t mcu_vectors[16u + MCU_NUM_IRQ] = {
    [0] = (mcu_vector_t)(uintptr_t)&_mcu_stack_top,
    [1] = mcu_reset_handler,
    [2] = mcu_fault_handler,  /* NMI */
    [3] = mcu_fault_handler,  /* HardFault */
    [4] = mcu_fault_handler,  /* MemManage */
    [5] = mcu_fault_handler,  /* BusFault */
    [6] = mcu_fault_handler,  /* UsageFault */
    [11] = mcu_fault_handler, /* SVCall */
    [12] = mcu_fault_handler, /* DebugMon */
    [14] = mcu_fault_handler, /* PendSV */
    [15] = mcu_systick_handler,
    [16u + MCU_USART1_IRQ] = mcu_usart1_handler,
};

volatile uint32_t mcu_fault_count;

void mcu_fault_handler(void)
{
    mcu_fault_count++;
    for (;;) {
        mcu_wfi();
    }
}

void mcu_reset_handler(void)
{
    MCU_SCB_CPACR |= 0xFu << 20; /* CP10, CP11: full access */
    mcu_dsb_isb();
    const uint32_t *src = &_mcu_data_load;
    for (uint32_t *dst = &_mcu_data_start; dst < &_mcu_data_end;) {
        *dst++ = *src++;
    }
    for (uint32_t *dst = &_mcu_bss_start; dst < &_mcu_bss_end;) {
        *dst++ = 0u;
    }
    (void)mcu_main();
    for (;;) {
        mcu_wfi();
    }
}
