/*
 * Test firmware for the simavr harness (ATmega328P or ATmega2560, 16 MHz):
 *  - UART0 at 1 Mbaud (U2X, UBRR=1), interrupt-driven RX, echoes every byte it receives;
 *  - Timer1 in normal mode, prescaler 8, toggles OC1A (328P PB1, 2560 PB5) by output compare every
 *    1000 timer ticks (8000 CPU cycles): OCR1A advanced in the compare ISR;
 *  - OCIE1A (and so the toggling) is enabled only after the byte 'S' arrives, so the harness's
 *    quiet register (TIMSK1 & 0x06) is "quiet" until then; 'Q' disables it again;
 *  - mirrors INT0 (328P PD2, 2560 PD0; any change) onto the LED pin (328P PB5, 2560 PB7) in
 *    the INT0 ISR, for the harness's SET;
 *  - sleeps in SLEEP_MODE_IDLE whenever there is nothing to do.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <stdint.h>

#if defined(__AVR_ATmega2560__)
#define RX_VECT USART0_RX_vect
#define UDRE_VECT USART0_UDRE_vect
#define OC1A_BIT PB5
#define LED_BIT PB7
#define INT0_BIT PD0
#else
#define RX_VECT USART_RX_vect
#define UDRE_VECT USART_UDRE_vect
#define OC1A_BIT PB1
#define LED_BIT PB5
#define INT0_BIT PD2
#endif

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

ISR(RX_VECT)
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

ISR(UDRE_VECT)
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
	if (PIND & _BV(INT0_BIT))
		PORTB |= _BV(LED_BIT);
	else
		PORTB &= (uint8_t)~_BV(LED_BIT);
}

ISR(TIMER1_COMPA_vect)
{
	OCR1A += PERIOD_TICKS;
}

int main(void)
{
	DDRB = _BV(OC1A_BIT) | _BV(LED_BIT);
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
