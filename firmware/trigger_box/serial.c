/*
 * serial.c - USART0 rings and framed lines.
 *
 * 1 Mbaud (U2X, UBRR 1) is exact at 16 MHz; the 115200 build uses U2X, UBRR 16 (117647
 * baud, +2.1 %, what the Arduino core calls 115200). The receive interrupt only moves a byte
 * into the ring; the transmit side is fed by the main loop and drained by the data-register-
 * empty interrupt, so pulse interrupts are never held up by the line.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <util/atomic.h>

#include "board.h"
#include "serial.h"

#ifndef BAUD
#define BAUD 1000000UL
#endif
#define UBRR_VALUE ((F_CPU + 4UL * BAUD) / (8UL * BAUD) - 1UL)

#if (RX_RING & (RX_RING - 1)) != 0 || (TX_RING & (TX_RING - 1)) != 0
#error "ring sizes must be powers of two"
#endif

static uint8_t rx_buf[RX_RING];
static volatile uint16_t rx_head, rx_tail;
static volatile uint32_t rx_lost;
static uint8_t tx_buf[TX_RING];
static volatile uint16_t tx_head, tx_tail;
static uint8_t line_sum;

void serial_init(void)
{
    UBRR0 = (uint16_t)UBRR_VALUE;
    UCSR0A = _BV(U2X0);
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00); /* 8N1 */
    UCSR0B = _BV(TXEN0);
}

void serial_enable_rx(void)
{
    UCSR0B |= _BV(RXEN0) | _BV(RXCIE0);
}

ISR(UART_RX_VECT)
{
    uint8_t status = UCSR0A;
    uint8_t c = UDR0;
    if (status & _BV(DOR0))
        rx_lost++; /* a byte before this one was overwritten in the hardware buffer */
    if (status & _BV(FE0)) {
        rx_lost++; /* this byte is not what was sent */
        return;
    }
    uint16_t next = (uint16_t)((rx_head + 1u) & (RX_RING - 1u));
    if (next == rx_tail) {
        rx_lost++;
        return;
    }
    rx_buf[rx_head] = c;
    rx_head = next;
}

ISR(UART_UDRE_VECT)
{
    uint16_t tail = tx_tail;
    if (tail == tx_head) {
        UCSR0B &= (uint8_t)~_BV(UDRIE0);
        return;
    }
    UDR0 = tx_buf[tail];
    tx_tail = (uint16_t)((tail + 1u) & (TX_RING - 1u));
}

int16_t serial_getc(void)
{
    int16_t c = -1;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        uint16_t tail = rx_tail;
        if (tail != rx_head) {
            c = rx_buf[tail];
            rx_tail = (uint16_t)((tail + 1u) & (RX_RING - 1u));
        }
    }
    return c;
}

uint8_t serial_rx_pending(void)
{
    uint8_t p;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { p = rx_head != rx_tail; }
    return p;
}

uint32_t serial_rx_lost(void)
{
    uint32_t n;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { n = rx_lost; }
    return n;
}

uint16_t serial_tx_room(void)
{
    uint16_t used;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { used = (uint16_t)((tx_head - tx_tail) & (TX_RING - 1u)); }
    return (uint16_t)(TX_RING - 1u - used);
}

/* Queue one byte, waiting for room (the transmit interrupt drains the ring meanwhile). */
static void tx_put(uint8_t c)
{
    uint16_t head = tx_head;
    uint16_t next = (uint16_t)((head + 1u) & (TX_RING - 1u));
    while (next == tx_tail) {
    }
    tx_buf[head] = c;
    tx_head = next;
    UCSR0B |= _BV(UDRIE0);
}

void line_begin(void)
{
    line_sum = 0;
    tx_put('$');
}

void line_char(char c)
{
    line_sum ^= (uint8_t)c;
    tx_put((uint8_t)c);
}

void line_str(const char *s)
{
    while (*s)
        line_char(*s++);
}

void line_str_P(PGM_P s)
{
    char c;
    while ((c = (char)pgm_read_byte(s++)) != 0)
        line_char(c);
}

/* Powers of ten for decimal output by repeated subtraction: a 64-bit division costs far
 * more on an 8-bit core than the few subtractions per digit. */
static const uint64_t POW10[20] PROGMEM = {
    10000000000000000000ULL, 1000000000000000000ULL, 100000000000000000ULL, 10000000000000000ULL,
    1000000000000000ULL, 100000000000000ULL, 10000000000000ULL, 1000000000000ULL,
    100000000000ULL, 10000000000ULL, 1000000000ULL, 100000000ULL, 10000000ULL, 1000000ULL,
    100000ULL, 10000ULL, 1000ULL, 100ULL, 10ULL, 1ULL,
};

void line_u64(uint64_t v)
{
    uint8_t started = 0;
    for (uint8_t i = 0; i < 20; i++) {
        uint64_t p;
        memcpy_P(&p, &POW10[i], sizeof p);
        char d = '0';
        while (v >= p) {
            v -= p;
            d++;
        }
        if (d != '0' || started || i == 19) {
            line_char(d);
            started = 1;
        }
    }
}

void line_u32(uint32_t v)
{
    static const uint32_t P32[10] PROGMEM = {
        1000000000UL, 100000000UL, 10000000UL, 1000000UL, 100000UL, 10000UL, 1000UL, 100UL, 10UL, 1UL,
    };
    uint8_t started = 0;
    for (uint8_t i = 0; i < 10; i++) {
        uint32_t p = pgm_read_dword(&P32[i]);
        char d = '0';
        while (v >= p) {
            v -= p;
            d++;
        }
        if (d != '0' || started || i == 9) {
            line_char(d);
            started = 1;
        }
    }
}

void line_shown(const char *s, uint8_t max)
{
    for (uint8_t i = 0; i < max && s[i]; i++)
        line_char(s[i] == '$' || s[i] == '*' ? '?' : s[i]);
}

void line_quoted(const char *s, uint8_t max)
{
    line_char('\'');
    line_shown(s, max);
    line_char('\'');
}

static char hex_digit(uint8_t v)
{
    return (char)(v < 10 ? '0' + v : 'A' + v - 10);
}

void line_end(int32_t tag)
{
    if (tag >= 0) {
        line_char(' ');
        line_char('#');
        line_u32((uint32_t)tag);
    }
    uint8_t sum = line_sum;
    tx_put('*');
    tx_put((uint8_t)hex_digit(sum >> 4));
    tx_put((uint8_t)hex_digit(sum & 0x0F));
    tx_put('\n');
}
