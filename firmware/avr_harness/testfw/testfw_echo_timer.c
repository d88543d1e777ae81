/*
 * Test firmware for the simavr harness (ATmega328P, 16 MHz):
 *  - UART0 at 1 Mbaud (U2X, UBRR=1), interrupt-driven RX, echoes every byte it receives;
 *  - Timer1 in normal mode, prescaler 8, toggles OC1A (PB1) by hardware output compare every
 *    1000 timer ticks (8000 CPU cycles): OCR1A advanced in the compare ISR;
 *  - OCIE1A (and so the toggling) is enabled only after the byte 'S' arrives, so the harness's
 *    quiet register (TIMSK1 & 0x06) is "quiet" until then; 'Q' disables it again;
 *  - mirrors INT0 (PD2, any change) onto PB5 (LED) in the INT0 ISR, for the harness's SET;
 *  - sleeps in SLEEP_MODE_IDLE whenever there is nothing to do.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <stdint.h>

#define PERIOD_TICKS 1000u
#define TX_SIZE 64u

static volatile uint8_t tx_buf[TX_SIZE];
static volatile uint8_t tx_head, tx_tail;

static void tx_put(uint8_t b)
{
	uint8_t next = (uint8_t)((tx_head + 1u) % TX_SIZE);
	if (next == tx_tail)
		return; /* host sends faster than 1 Mbaud echo can follow: cannot happen at equal rates */
	tx_buf[tx_head] = b;
	tx_head = next;
	UCSR0B |= _BV(UDRIE0);
}

ISR(USART_RX_vect)
{
	uint8_t b = UDR0;
	if (b == 'S') {
		TIFR1 = _BV(OCF1A);
		OCR1A = TCNT1 + PERIOD_TICKS;
		TCCR1A = _BV(COM1A0); /* toggle OC1A on compare match */
		TIMSK1 |= _BV(OCIE1A);
	} else if (b == 'Q') {
		TIMSK1 &= (uint8_t)~_BV(OCIE1A);
		TCCR1A = 0;
	}
	tx_put(b);
}

ISR(USART_UDRE_vect)
{
	if (tx_head == tx_tail) {
		UCSR0B &= (uint8_t)~_BV(UDRIE0);
		return;
	}
	UDR0 = tx_buf[tx_tail];
	tx_tail = (uint8_t)((tx_tail + 1u) % TX_SIZE);
}

ISR(INT0_vect)
{
	if (PIND & _BV(PIND2))
		PORTB |= _BV(PORTB5);
	else
		PORTB &= (uint8_t)~_BV(PORTB5);
}

ISR(TIMER1_COMPA_vect)
{
	OCR1A += PERIOD_TICKS;
}

int main(void)
{
	DDRB = _BV(DDB1) | _BV(DDB5);
	UCSR0A = _BV(U2X0);
	UBRR0 = 1; /* 16 MHz / (8 * (1 + 1)) = 1 Mbaud */
	UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
	UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
	EICRA = _BV(ISC00); /* INT0 on any change */
	EIMSK = _BV(INT0);
	TCCR1A = 0;
	TCCR1B = _BV(CS11); /* normal mode, clk/8 */
	set_sleep_mode(SLEEP_MODE_IDLE);
	sei();
	for (;;) {
		sleep_enable();
		sleep_cpu();
		sleep_disable();
	}
}
