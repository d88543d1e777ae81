/*
 * main.c - trigger-box firmware for Arduino-class AVR boards (docs/trigger-protocol.md).
 *
 * Interrupts do the timing (pulse.c) and move bytes (serial.c); the main loop formats
 * records and replies (protocol.c) and sleeps in idle mode when there is nothing to do,
 * waking on any interrupt.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>

#include "board.h"
#include "protocol.h"
#include "pulse.h"
#include "serial.h"

int main(void)
{
    LED_DDR |= _BV(LED_BIT);
    pulse_init();
    serial_init();
    set_sleep_mode(SLEEP_MODE_IDLE);
    sei();
    proto_boot();
    for (;;) {
        if (proto_service())
            continue;
        /* Sleep unless an interrupt brought work since the check: sei takes effect after
         * the next instruction, so no wake-up can slip in between. */
        cli();
        if (!serial_rx_pending() && !pulse_records_pending()) {
            sleep_enable();
            sei();
            sleep_cpu();
            sleep_disable();
        }
        sei();
    }
}
