/*
 * serial.h - USART0 with interrupt-driven receive and transmit rings, and framed output
 * lines `$<payload>*HH\n` (docs/trigger-protocol.md, "Framing").
 */
#ifndef SERIAL_H
#define SERIAL_H

#include <avr/pgmspace.h>
#include <stdint.h>

void serial_init(void);
/* Start listening (after READY: input before it is ignored). */
void serial_enable_rx(void);
/* Next received byte, or -1. */
int16_t serial_getc(void);
uint8_t serial_rx_pending(void);
/* Bytes lost on the way in (receive ring full, or a hardware overrun/framing error). */
uint32_t serial_rx_lost(void);
/* Free room in the transmit ring. */
uint16_t serial_tx_room(void);

/* One framed line: begin, payload pieces, end (which appends ` #tag` when tag >= 0). */
void line_begin(void);
void line_char(char c);
void line_str(const char *s);
void line_str_P(PGM_P s);
void line_u64(uint64_t v);
void line_u32(uint32_t v);
/* Text the host sent, at most `max` bytes, with '$' and '*' (framing bytes a payload must
 * not contain) shown as '?'; line_quoted puts it in single quotes. */
void line_shown(const char *s, uint8_t max);
void line_quoted(const char *s, uint8_t max);
void line_end(int32_t tag);

#endif
