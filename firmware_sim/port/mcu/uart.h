/*
 * uart.h - USART1 of the STM32F405 as the SLCAN link: interrupt-driven receive into a
 * ring buffer (the interrupt is the only producer, the main loop the only consumer),
 * polled transmit from the main loop.
 */
#ifndef UART_H
#define UART_H

#include <stdbool.h>
#include <stdint.h>

#define UART_RX_RING 512u /* power of two */

typedef struct {
    uint8_t rx[UART_RX_RING];
    volatile uint32_t rx_head; /* written by the interrupt */
    volatile uint32_t rx_tail; /* written by the main loop */
    volatile uint32_t rx_dropped; /* bytes lost to a full ring */
    volatile uint32_t rx_overruns; /* bytes lost in the hardware (ORE) */
} uart_t;

/* 115200 8N1 on PA9/PA10, receive interrupt on at MCU_PRIO_UART. */
void uart_init(uart_t *u, uint32_t baud);
/* The USART1 interrupt's work (called from the vector). */
void uart_irq(uart_t *u);
/* One received byte; false when none is waiting. */
bool uart_read(uart_t *u, uint8_t *byte);
/* Bytes received and not yet read. */
uint32_t uart_rx_pending(const uart_t *u);
/* Sends one byte if the transmitter takes it now; false when it is busy. */
bool uart_try_write(uint8_t byte);

#endif /* UART_H */
