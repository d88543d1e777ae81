/*
 * pulse.c - box clock and pulse engine on Timer1.
 *
 * Timer1 runs free in normal mode at F_CPU / 8: one tick is 0.5 us. The overflow interrupt
 * extends TCNT1 to 64 bits, so the box clock is ticks / 2 microseconds since power-on; it is
 * never reset or adjusted (docs/trigger-protocol.md, "Box clock").
 *
 * Edges come from the output-compare unit, never from software timing. To make the line
 * change when tick T begins, OCR1A = T - 1 (a match takes effect as TCNT1 steps past OCR1A)
 * with COM1A = "toggle on match". An edge is armed only once it is less than half a timer
 * period away, so the next match of OCR1A is that edge; while a farther edge is awaited the
 * pin is parked (COM1A disconnected, PORT holding its level) and compare-B interrupts, which
 * touch no pin, approach it. The compare-A interrupt after each edge arms the next one; after
 * a rising edge it also queues the pulse record and computes the next pulse time.
 *
 * No compare flag is ever cleared by writing TIFR1: stale compare-A matches are told apart by
 * the interrupt itself (`armed`, `armed_ocr`), and an early compare-B wake-up only re-plans.
 * simavr 1.6 clears every raised Timer1 flag on any TIFR1 write, overflow included, which
 * loses an overflow (and so 32.8 ms of box clock) whenever one is pending at that moment.
 *
 * Toggle rather than set/clear: in normal mode the set/clear output modes must not act on
 * overflow, but simavr 1.6 (Debian's, which CI runs) applies their PWM-mode overflow action
 * on every overflow and OCR write. Toggle and disconnected have no overflow action on either,
 * so the image behaves the same on the chip and in the simulator.
 *
 * Pulse k of a run rises at b_k = t0 + round(k * 1e6 / rate) us, the exact rational with
 * halves rounded up, computed as integers: 1e12 / rate_uhz = q + r / rate_uhz, and the
 * engine accumulates k*q and k*r (mod rate_uhz) one pulse at a time, so nothing drifts.
 *
 * While no edge is scheduled, OCIE1A and OCIE1B are both off (the simulator harness reads
 * that as "quiet").
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <util/atomic.h>

#include "board.h"
#include "pulse.h"

#define ARM_WINDOW 32768u   /* arm OCR1A once an edge is at most this many ticks away */
#define MIN_ARM_TICKS 8u    /* an edge nearer than this cannot be armed before it is due */
#define US_PER_S2 1000000000000ULL /* 1e6 us * 1e6 uHz/Hz */

/* Start of the box clock: TCNT1 is written with the ticks that elapsed since reset, so the
 * box clock counts from power-on and tick k begins 8k (+1) CPU cycles after reset. The one
 * cycle (the nop below) is for simavr 1.6, whose Timer1 takes a timer base of exactly cycle 0
 * for "not started" and would then drop the first overflow interrupt. Checked by
 * tests/firmware/test_timing.py: every edge leaves 1-5 cycles after 16 * b_k. */
#ifndef TCNT1_START
#define TCNT1_START 2u
#endif

static volatile uint64_t ovf_ticks;   /* ticks at the last overflow */

/* Run parameters, kept after the run for TS?. */
static uint64_t run_t0;
static uint64_t run_rate;             /* uHz */
static uint64_t per_q, per_r;         /* 1e12 / run_rate: quotient (us) and remainder */
static uint32_t run_width_ticks;
static uint32_t run_target;           /* 0: until STOP */

/* Engine state: written by the compare interrupts while active. */
static volatile uint8_t active;
static volatile uint8_t stopping;
static volatile uint8_t ended;
static uint8_t phase;                 /* 0: the next edge rises; 1: it falls */
static uint64_t acc_q, acc_m;         /* k*q + floor(k*r/rate), (k*r) mod rate for pulse k */
static uint64_t next_b;               /* b_k of the next rising edge, us */
static uint64_t rise_tick;            /* rising edge of the next pulse */
static volatile uint32_t count;

/* An edge is armed on OCR1A (`armed_ocr`): its compare interrupt is that edge once TCNT1 has
 * passed it; before, it is a match flagged before the arming (a flag pending when the
 * interrupt is enabled is served at once on the chip, not in simavr 1.6). */
static volatile uint8_t armed;
static volatile uint16_t armed_ocr;
/* Per run: the next edge can be armed by one OCR1A write from the compare interrupt (it is
 * under half a timer period away), with no 64-bit arithmetic before it. */
static uint8_t fall_fast, rise_fast;
static uint64_t cur_fall_tick;        /* falling edge of the pulse now high */

static pulse_record_t queue[RECORD_QUEUE];
static volatile uint8_t q_head, q_tail;
static volatile uint32_t records_dropped;
static volatile uint32_t late_edges;

#if (RECORD_QUEUE & (RECORD_QUEUE - 1)) != 0 || RECORD_QUEUE > 128
#error "RECORD_QUEUE must be a power of two <= 128"
#endif

/* Start Timer1 before anything else runs (.init3: before .data/.bss are set up), so the box
 * clock and the CPU's cycle count since reset differ by a fixed, tiny constant. */
void timebase_start(void) __attribute__((naked, used, section(".init3")));
void timebase_start(void)
{
    TCCR1B = _BV(CS11);
    __asm__ __volatile__("nop");
    TCNT1 = TCNT1_START;
}

#ifdef ISR_PROBE_BIT
#define PROBE_ON() (PORTB |= _BV(ISR_PROBE_BIT))
#define PROBE_OFF() (PORTB &= (uint8_t)~_BV(ISR_PROBE_BIT))
#else
#define PROBE_ON() ((void)0)
#define PROBE_OFF() ((void)0)
#endif

void pulse_init(void)
{
    TRIG_DDR |= _BV(TRIG_BIT);        /* PORT bit stays 0: a disconnected OC1A pin is low */
#ifdef ISR_PROBE_BIT
    DDRB |= _BV(ISR_PROBE_BIT);
#endif
    TCCR1A = 0;
    TIMSK1 = _BV(TOIE1);
}

static uint64_t last_ticks; /* the newest ticks_locked() result: time never goes back */

/* Ticks now; interrupts must be off. A pending overflow not yet counted is added when TCNT1
 * has wrapped (a small value), not when the overflow came just after the read. simavr 1.6
 * can show TCNT1 wrapped a few cycles before it raises TOV1 (its overflow is a cycle timer
 * run after the instruction); a reading that would go back in time is that wrap, counted here. */
static uint64_t ticks_locked(void)
{
    uint16_t t = TCNT1;
    uint64_t hi = ovf_ticks;
    if ((TIFR1 & _BV(TOV1)) && t < 0x8000u)
        hi += 0x10000u;
    uint64_t now = hi + t;
    if (now < last_ticks)
        now += 0x10000u;
    last_ticks = now;
    return now;
}

uint64_t clock_us(void)
{
    uint64_t t;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { t = ticks_locked(); }
    return t >> 1;
}

ISR(TIMER1_OVF_vect)
{
    ovf_ticks += 0x10000u;
}

/* Arm the next edge on OCR1A if it is near, else a compare-B wake-up; interrupts off. */
static void arm_next_edge(void)
{
    uint64_t target = phase ? cur_fall_tick : rise_tick;
    uint64_t now = ticks_locked();
    if (target < now + MIN_ARM_TICKS) {
        /* Only possible if interrupts were held off far longer than this firmware ever does;
         * counted for DIAG? rather than hidden. The edge leaves late but leaves. */
        late_edges++;
        target = now + MIN_ARM_TICKS;
    }
    uint64_t d = target - now;
    if (d <= ARM_WINDOW) {
        armed_ocr = (uint16_t)(target - 1u);
        OCR1A = armed_ocr;
        TCCR1A = _BV(COM1A0);
        armed = 1;
        TIMSK1 = (uint8_t)((TIMSK1 & ~_BV(OCIE1B)) | _BV(OCIE1A));
    } else {
        /* Park: PORT holds the line's present level (high between a rise and its fall). */
        if (phase)
            TRIG_PORT |= _BV(TRIG_BIT);
        else
            TRIG_PORT &= (uint8_t)~_BV(TRIG_BIT);
        TCCR1A = 0;
        armed = 0;
        uint64_t step = d - ARM_WINDOW / 2u;
        if (step > ARM_WINDOW)
            step = ARM_WINDOW;
        OCR1B = (uint16_t)(now + step);
        TIMSK1 |= _BV(OCIE1B);
    }
}

/* The run is over: no compare interrupts, the pin parked low. */
static void finish_locked(void)
{
    TIMSK1 = (uint8_t)(TIMSK1 & ~(_BV(OCIE1A) | _BV(OCIE1B)));
    armed = 0;
    TRIG_PORT &= (uint8_t)~_BV(TRIG_BIT); /* called only while the line is low */
    TCCR1A = 0;
    if (!stopping)
        ended = 1;
    active = 0;
    LED_PORT &= (uint8_t)~_BV(LED_BIT);
}

/* b_k from pulse k's accumulators (k*q + floor(k*r/rate), (k*r) mod rate): halves round up. */
static inline uint64_t schedule_time(uint64_t t0, uint64_t acc_q_k, uint64_t acc_m_k, uint64_t rate)
{
    return t0 + acc_q_k + ((acc_m_k << 1) >= rate ? 1u : 0u);
}

/* Accumulators of pulse k -> pulse k+1: no division, no drift. */
static inline void schedule_step(uint64_t *q_acc, uint64_t *m_acc, uint64_t q, uint64_t r, uint64_t rate)
{
    *q_acc += q;
    *m_acc += r;
    if (*m_acc >= rate) {
        *m_acc -= rate;
        (*q_acc)++;
    }
}

/* Pulse k+1's time, from the interrupt of pulse k. */
static void advance_schedule(void)
{
    schedule_step(&acc_q, &acc_m, per_q, per_r, run_rate);
    next_b = schedule_time(run_t0, acc_q, acc_m, run_rate);
    rise_tick = next_b << 1;
}

/* Arm the edge at the tick whose low 16 bits are `tick_lo` with one OCR1A write: from the
 * compare interrupt of the previous edge, when it is known to be less than half a period
 * away. Should the interrupt have come too late for it, the slow path places it late and
 * counts it. */
static void fast_arm(uint16_t tick_lo)
{
    uint16_t ocr = (uint16_t)(tick_lo - 1u);
    OCR1A = ocr;
    armed_ocr = ocr;
    if ((int16_t)(TCNT1 - ocr) > 0) {
        arm_next_edge();
        return;
    }
    armed = 1;
}

ISR(TIMER1_COMPA_vect)
{
    /* OCR1A matches every timer period: a match while the pin is parked, or one flagged
     * before this edge was armed, is not the edge. */
    if (!armed || (int16_t)(TCNT1 - armed_ocr) <= 0)
        return;
    PROBE_ON();
    armed = 0;
    if (!phase) {
        /* Pulse `count` rose: arm its fall first, it is the only deadline here. */
        phase = 1;
        if (fall_fast)
            fast_arm((uint16_t)cur_fall_tick);
        else
            arm_next_edge();
        uint32_t k = count;
        count = k + 1u;
        uint8_t head = q_head;
        uint8_t next = (uint8_t)((head + 1u) & (RECORD_QUEUE - 1u));
        if (next == q_tail) {
            records_dropped++;
        } else {
            queue[head].index = k;
            queue[head].t_us = next_b;
            q_head = next;
        }
        if (!stopping && !(run_target && count >= run_target))
            advance_schedule();
    } else {
        phase = 0;
        if (stopping || (run_target && count >= run_target)) {
            finish_locked();
        } else {
            cur_fall_tick = rise_tick + run_width_ticks;
            if (rise_fast)
                fast_arm((uint16_t)rise_tick);
            else
                arm_next_edge();
        }
    }
    PROBE_OFF();
}

ISR(TIMER1_COMPB_vect)
{
    PROBE_ON();
    arm_next_edge();
    PROBE_OFF();
}

void pulse_arm(void)
{
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        count = 0;
        q_head = q_tail = 0;
        ended = 0;
        run_t0 = 0;
        run_rate = 0;
    }
}

void pulse_start(uint64_t t0_us, uint64_t rate_uhz, uint32_t width_us, uint32_t target)
{
    /* The divisions run once per START, in the main loop. */
    uint64_t q = US_PER_S2 / rate_uhz;
    uint64_t r = US_PER_S2 - q * rate_uhz;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        run_t0 = t0_us;
        run_rate = rate_uhz;
        per_q = q;
        per_r = r;
        run_width_ticks = width_us * 2u;
        run_target = target;
        count = 0;
        q_head = q_tail = 0;
        ended = 0;
        stopping = 0;
        phase = 0;
        acc_q = 0;
        acc_m = 0;
        next_b = t0_us;
        rise_tick = t0_us << 1;
        cur_fall_tick = rise_tick + run_width_ticks;
        fall_fast = run_width_ticks <= ARM_WINDOW;
        rise_fast = 2u * (q + 1u) - run_width_ticks <= ARM_WINDOW; /* the longest low time */
        armed = 0;
        active = 1;
        LED_PORT |= _BV(LED_BIT);
        arm_next_edge();
    }
}

void pulse_stop(void)
{
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        if (active) {
            stopping = 1;
            if (!phase) /* the line is low: nothing left to do */
                finish_locked();
        }
    }
}

uint8_t pulse_active(void)
{
    return active;
}

uint32_t pulse_count(void)
{
    uint32_t n;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { n = count; }
    return n;
}

uint8_t pulse_take_end(void)
{
    uint8_t e;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        e = ended && q_head == q_tail;
        if (e)
            ended = 0;
    }
    return e;
}

uint8_t pulse_record_pop(pulse_record_t *out)
{
    uint8_t got = 0;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        uint8_t tail = q_tail;
        if (tail != q_head) {
            *out = queue[tail];
            q_tail = (uint8_t)((tail + 1u) & (RECORD_QUEUE - 1u));
            got = 1;
        }
    }
    return got;
}

uint8_t pulse_records_pending(void)
{
    return q_head != q_tail;
}

void pulse_iter_init(pulse_iter_t *it, uint32_t k)
{
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        it->t0 = run_t0;
        it->rate = run_rate;
        it->q = per_q;
        it->r = per_r;
    }
    /* floor(k*r / rate) and (k*r) mod rate by binary long multiplication: k*r can exceed
     * 64 bits, every intermediate here stays below 2 * rate < 2^35. */
    uint64_t quo = 0, rem = 0;
    for (int8_t bit = 31; bit >= 0; bit--) {
        quo <<= 1;
        rem <<= 1;
        if (rem >= it->rate) {
            rem -= it->rate;
            quo++;
        }
        if (k & ((uint32_t)1 << bit)) {
            rem += it->r;
            if (rem >= it->rate) {
                rem -= it->rate;
                quo++;
            }
        }
    }
    it->acc_q = (uint64_t)k * it->q + quo;
    it->acc_m = rem;
}

uint64_t pulse_iter_next(pulse_iter_t *it)
{
    uint64_t b = schedule_time(it->t0, it->acc_q, it->acc_m, it->rate);
    schedule_step(&it->acc_q, &it->acc_m, it->q, it->r, it->rate);
    return b;
}

void pulse_get_stats(pulse_stats_t *out)
{
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        out->records_dropped = records_dropped;
        out->late_edges = late_edges;
    }
}
