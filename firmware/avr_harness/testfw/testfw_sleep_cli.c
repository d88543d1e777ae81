/* Test firmware for the simavr harness: sleeps with interrupts off after blinking PB5 once,
 * which simavr treats as the end of the program (cpu_Done): the harness must say so and fail. */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>

int main(void)
{
	DDRB = _BV(DDB5);
	PORTB = _BV(PORTB5);
	PORTB = 0;
	cli();
	set_sleep_mode(SLEEP_MODE_IDLE);
	sleep_enable();
	sleep_cpu();
	for (;;) {
	}
}
