/* uart.c - see uart.h. */
#include "uart.h"

#include "mcu_hw.h"

void uart_init(uart_t *u, uint32_t baud)
{
    u->rx_head = 0u;
    u->rx_tail = 0u;
    u->rx_dropped = 0u;
    u->rx_overruns = 0u;
    MCU_RCC_AHB1ENR |= MCU_RCC_AHB1ENR_GPIOAEN;
    MCU_RCC_APB2ENR |= MCU_RCC_APB2ENR_USART1EN;
    /* PA9, PA10: alternate function mode (MODER 10b), AF7 */
    MCU_GPIOA_MODER = (MCU_GPIOA_MODER & ~((3u << 18) | (3u << 20))) | (2u << 18) | (2u << 20);
    MCU_GPIOA_AFRH = (MCU_GPIOA_AFRH & ~((0xFu << 4) | (0xFu << 8))) | (7u << 4) | (7u << 8);
    /* oversampling by 16: BRR = f_pclk / baud as mantissa.fraction(4 bits), rounded */
    MCU_USART_BRR = (MCU_APB2_HZ + baud / 2u) / baud;
    MCU_USART_CR1 = MCU_USART_CR1_UE | MCU_USART_CR1_TE | MCU_USART_CR1_RE | MCU_USART_CR1_RXNEIE;
    MCU_NVIC_IPR8(MCU_USART1_IRQ) = MCU_PRIO_UART;
    MCU_NVIC_ISER(MCU_USART1_IRQ / 32u) = 1u << (MCU_USART1_IRQ % 32u);
}

void uart_irq(uart_t *u)
{
    uint32_t sr = MCU_USART_SR;
    while (sr & (MCU_USART_SR_RXNE | MCU_USART_SR_ORE)) {
        uint8_t b = (uint8_t)MCU_USART_DR; /* reading DR clears RXNE (and ORE after the SR read) */
        if (sr & MCU_USART_SR_ORE) {
            u->rx_overruns++;
        }
        if (sr & MCU_USART_SR_RXNE) {
            uint32_t head = u->rx_head;
            if (head - u->rx_tail < UART_RX_RING) {
                u->rx[head & (UART_RX_RING - 1u)] = b;
                __asm volatile("dmb" ::: "memory"); /* the byte before the index */
                u->rx_head = head + 1u;
            } else {
                u->rx_dropped++;
            }
        }
        sr = MCU_USART_SR;
    }
}

bool uart_read(uart_t *u, uint8_t *byte)
{
    uint32_t tail = u->rx_tail;
    if (tail == u->rx_head) {
        return false;
    }
    __asm volatile("dmb" ::: "memory");
    *byte = u->rx[tail & (UART_RX_RING - 1u)];
    u->rx_tail = tail + 1u;
    return true;
}

uint32_t uart_rx_pending(const uart_t *u)
{
    return u->rx_head - u->rx_tail;
}

bool uart_try_write(uint8_t byte)
{
    if (!(MCU_USART_SR & MCU_USART_SR_TXE)) {
        return false;
    }
    MCU_USART_DR = byte;
    return true;
}
