/*
 * pulse.h - the box clock (a 64-bit microsecond counter since power-on) and the pulse engine
 * that raises the trigger line from Timer1's output-compare hardware.
 */
#ifndef PULSE_H
#define PULSE_H

#include <stdint.h>

/* Shortest pulse, and shortest gap between a falling edge and the next rising edge, in us.
 * Each edge is armed by an interrupt after the previous one; the worst interrupt latency of
 * this firmware is well under this (see bench/firmware.py), so no edge can be missed. */
#define MIN_WIDTH_US 16u
#define MIN_GAP_US 16u

/* A pulse record for the host: pulse index and its scheduled box time b_k. */
typedef struct {
    uint32_t index;
    uint64_t t_us;
} pulse_record_t;

/* Diagnostics the host can read with DIAG?. */
typedef struct {
    uint32_t records_dropped; /* P records the queue had no room for (the host reads them with TS?) */
    uint32_t late_edges;      /* edges armed too late for the hardware to place them exactly */
} pulse_stats_t;

void pulse_init(void);
uint64_t clock_us(void);
/* Forget the last run: count 0, no records, TS? returns nothing. */
void pulse_arm(void);
/* Start a run whose pulse 0 rises at t0_us; rate in micro-hertz; target 0 = until stopped. */
void pulse_start(uint64_t t0_us, uint64_t rate_uhz, uint32_t width_us, uint32_t target);
/* No further rising edge; a pulse already high keeps its width. */
void pulse_stop(void);
/* Edges still scheduled (a run, or the fall of a stopped run's last pulse). */
uint8_t pulse_active(void);
uint32_t pulse_count(void);
/* 1 once after a counted run emitted its last pulse and lowered the line. */
uint8_t pulse_take_end(void);
uint8_t pulse_record_pop(pulse_record_t *out);
uint8_t pulse_records_pending(void);
/* b_k of the last started run, recomputed exactly as the engine scheduled it: start at k,
 * then each call of pulse_iter_next returns b_k and steps to k + 1 (no division per step). */
typedef struct {
    uint64_t t0, rate, q, r; /* the run's parameters */
    uint64_t acc_q, acc_m;   /* k*q + floor(k*r/rate), (k*r) mod rate */
} pulse_iter_t;
void pulse_iter_init(pulse_iter_t *it, uint32_t k);
uint64_t pulse_iter_next(pulse_iter_t *it);
void pulse_get_stats(pulse_stats_t *out);

#endif
