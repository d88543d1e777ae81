/*
 * board.h - what differs between the supported chips: pins, buffer sizes, vector names.
 *
 * ATmega328P (Arduino Uno R3, Nano): trigger on PB1 = OC1A = Arduino D9, LED on PB5 = D13.
 * ATmega2560 (Arduino Mega 2560):    trigger on PB5 = OC1A = Arduino D11, LED on PB7 = D13.
 * Both run at 16 MHz; Timer1 with prescaler 8 ticks every 0.5 us.
 */
#ifndef BOARD_H
#define BOARD_H

#include <avr/io.h>

#if defined(__AVR_ATmega328P__)
#define BOARD_MODEL "trigbox-avr328p"
#define TRIG_DDR DDRB
#define TRIG_PORT PORTB
#define TRIG_BIT PB1
#define LED_DDR DDRB
#define LED_PORT PORTB
#define LED_BIT PB5
#define UART_RX_VECT USART_RX_vect
#define UART_UDRE_VECT USART_UDRE_vect
/* 2 KiB of SRAM: buffers sized so that data + bss stay under 1.5 KiB (the rest is stack). */
#define RX_RING 128u
#define TX_RING 512u
#define RECORD_QUEUE 16u
#elif defined(__AVR_ATmega2560__)
#define BOARD_MODEL "trigbox-avr2560"
#define TRIG_DDR DDRB
#define TRIG_PORT PORTB
#define TRIG_BIT PB5
#define LED_DDR DDRB
#define LED_PORT PORTB
#define LED_BIT PB7
#define UART_RX_VECT USART0_RX_vect
#define UART_UDRE_VECT USART0_UDRE_vect
#define RX_RING 256u
#define TX_RING 2048u
#define RECORD_QUEUE 128u
#else
#error "unsupported MCU: build for atmega328p or atmega2560"
#endif

#if F_CPU != 16000000UL
#error "the timebase assumes a 16 MHz clock (Timer1 / 8 = 0.5 us ticks)"
#endif

#define FIRMWARE_VERSION "1.1.0"
#define VENDOR "rigd"

#endif
