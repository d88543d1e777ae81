/* Benchmark firmware for the simavr harness: never sleeps; toggles PB5 every 65536 loop turns
 * so a run shows it is alive. Measures the simulator's speed on a busy CPU. */
#include <avr/io.h>
#include <stdint.h>

int main(void)
{
	DDRB = _BV(DDB5);
	for (;;) {
		for (volatile uint16_t i = 0; i != 0xffff; i++) {
		}
		PINB = _BV(PINB5);
	}
}
