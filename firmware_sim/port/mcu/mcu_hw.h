/*
 * mcu_hw.h - the few Cortex-M4 and STM32F405 registers the processor-in-the-loop port uses
 * (no vendor headers needed). Addresses: ARMv7-M ARM (SysTick, SCB, NVIC) and the STM32F405
 * reference manual RM0090 (RCC, GPIOA, USART1).
 */
#ifndef MCU_HW_H
#define MCU_HW_H

#include <stdint.h>

#define MCU_REG(addr) (*(volatile uint32_t *)(addr))

/* core clock: 168 MHz (HSE + PLL on a real board; QEMU's netduinoplus2 models it fixed) */
#define MCU_CPU_HZ 168000000u
/* USART1 on APB2 = 84 MHz */
#define MCU_APB2_HZ 84000000u

/* SysTick */
#define MCU_SYST_CSR MCU_REG(0xE000E010u)
#define MCU_SYST_RVR MCU_REG(0xE000E014u)
#define MCU_SYST_CVR MCU_REG(0xE000E018u)
#define MCU_SYST_CSR_ENABLE (1u << 0)
#define MCU_SYST_CSR_TICKINT (1u << 1)
#define MCU_SYST_CSR_CLKSOURCE (1u << 2) /* 1: processor clock */
#define MCU_SYST_CSR_COUNTFLAG (1u << 16)

/* System control block */
#define MCU_SCB_ICSR MCU_REG(0xE000ED04u)
#define MCU_SCB_VTOR MCU_REG(0xE000ED08u)
#define MCU_SCB_SHPR3 MCU_REG(0xE000ED20u) /* bits 31:24 SysTick priority */
#define MCU_SCB_CPACR MCU_REG(0xE000ED88u)
#define MCU_SCB_ICSR_PENDSTSET (1u << 26)

/* NVIC */
#define MCU_NVIC_ISER(n) MCU_REG(0xE000E100u + 4u * (n))
#define MCU_NVIC_IPR8(irq) (*(volatile uint8_t *)(0xE000E400u + (irq)))

/* RCC / GPIOA (alternate function 7 = USART1 on PA9 TX / PA10 RX) */
#define MCU_RCC_AHB1ENR MCU_REG(0x40023830u)
#define MCU_RCC_APB2ENR MCU_REG(0x40023844u)
#define MCU_RCC_AHB1ENR_GPIOAEN (1u << 0)
#define MCU_RCC_APB2ENR_USART1EN (1u << 4)
#define MCU_GPIOA_MODER MCU_REG(0x40020000u)
#define MCU_GPIOA_AFRH MCU_REG(0x40020024u)

/* USART1 */
#define MCU_USART1_BASE 0x40011000u
#define MCU_USART1_IRQ 37u
#define MCU_USART_SR MCU_REG(MCU_USART1_BASE + 0x00u)
#define MCU_USART_DR MCU_REG(MCU_USART1_BASE + 0x04u)
#define MCU_USART_BRR MCU_REG(MCU_USART1_BASE + 0x08u)
#define MCU_USART_CR1 MCU_REG(MCU_USART1_BASE + 0x0Cu)
#define MCU_USART_SR_ORE (1u << 3)
#define MCU_USART_SR_RXNE (1u << 5)
#define MCU_USART_SR_TXE (1u << 7)
#define MCU_USART_CR1_RE (1u << 2)
#define MCU_USART_CR1_TE (1u << 3)
#define MCU_USART_CR1_RXNEIE (1u << 5)
#define MCU_USART_CR1_UE (1u << 13)

/* Interrupt priorities (4 bits implemented, upper nibble): the UART above the control
 * interrupt, so that no received byte waits for a control step; BASEPRI at the control
 * interrupt's level masks it (and nothing above) for the CANopen critical sections. */
#define MCU_PRIO_UART 0x40u
#define MCU_PRIO_CONTROL 0x80u

static inline void mcu_set_basepri(uint32_t v)
{
    __asm volatile("msr basepri, %0" ::"r"(v) : "memory");
}
static inline void mcu_irq_disable(void)
{
    __asm volatile("cpsid i" ::: "memory");
}
static inline void mcu_irq_enable(void)
{
    __asm volatile("cpsie i" ::: "memory");
}
static inline void mcu_wfi(void)
{
    __asm volatile("wfi" ::: "memory");
}
static inline void mcu_dsb_isb(void)
{
    __asm volatile("dsb\n\tisb" ::: "memory");
}

#endif /* MCU_HW_H */
