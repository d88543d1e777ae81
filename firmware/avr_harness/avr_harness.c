/*
 * avr_harness: runs AVR firmware under simavr (1.6) with UART0 bridged to a pseudo-terminal,
 * chosen pins watched for edges (stamped with the AVR cycle) and three clock modes:
 *
 *   real     cycle c runs no earlier than start + c / freq (the trigger box as the rig sees it)
 *   max      as fast as the host allows
 *   control  a test drives time line by line on stdin (RUN / FREE / SET / NOP / QUIT)
 *
 * Nothing is dropped silently: host bytes wait in a buffer until the UART FIFO has room,
 * firmware bytes wait in a 1 MiB buffer for the pty (max/control stall the AVR while it is
 * full; real mode cannot stall time, so it counts the overflow and reports it on stderr).
 *
 * See README.md next to this file for the options and the control protocol.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <getopt.h>
#include <inttypes.h>
#include <poll.h>
#include <pty.h>
#include <signal.h>
#include <sys/prctl.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_irq.h"
#include "sim_io.h"
#include "sim_cycle_timers.h"
#include "avr_uart.h"
#include "avr_ioport.h"

/* the FIFO accessors (static inline) for the UART input FIFO declared in avr_uart.h */
DEFINE_FIFO(uint16_t, uart_fifo);

#define MAX_PINS 16
#define MAX_SETS 32                 /* pending SET commands (simavr has 64 cycle timers) */
#define OUT_BUF_SIZE (1u << 20)     /* firmware -> host (default of --out-buffer) */
#define IN_BUF_SIZE (64u << 10)     /* host -> firmware */
#define LINE_MAX_LEN 4096
#define STEPS_PER_SERVICE 4096      /* instructions between I/O polls and pacing checks */
#define EDGE_FLUSH_S 0.1
#define LAG_REPORT_S 3.0
#define LAG_REPORT_MIN_S 0.005      /* lag below this is scheduling noise, not "behind" */
#define FREE_LINE_MAX 4096          /* FREE feeds a newline-less stream in pieces this big */

enum clock_mode { CLOCK_REAL, CLOCK_MAX, CLOCK_CONTROL };

/* A byte ring buffer (host <-> UART). */
typedef struct {
	uint8_t *data;
	size_t cap, head, len;
} ring_t;

typedef struct {
	char name[32];
	char port;
	int bit;
	avr_irq_t *irq;
	int value;      /* last value seen (watched pins) */
} pin_t;

/* One pending `SET`: its own param pointer, because simavr keys cycle timers by
 * (callback, param) and would otherwise replace an earlier SET by a later one. */
typedef struct {
	bool used;
	avr_irq_t *irq;
	uint8_t value;
} set_req_t;

static struct {
	avr_t *avr;
	avr_uart_t *uart;
	avr_irq_t *uart_input;
	enum clock_mode mode;
	uint32_t freq;
	int master, slave;
	ring_t to_avr, from_avr;
	uint64_t overflowed, overflow_reported;
	bool xoff;
	pin_t pins[MAX_PINS];
	int npins;
	pin_t inputs[MAX_PINS];
	int ninputs;
	set_req_t sets[MAX_SETS];
	FILE *edges;
	bool edges_dirty;
	double edges_flushed_at;
	bool has_quiet;
	/* FREE hands the firmware one host line at a time, each when it is idle: free_feeding is
	 * on during FREE, free_budget the bytes of the current line not yet fed. */
	bool free_lines;      /* --free-lines: the host speaks in lines (off: a byte stream) */
	bool free_feeding;
	size_t free_budget;
	uint16_t quiet_addr;
	uint8_t quiet_mask;
	double wall_start;
	double lag_worst, lag_window_start;
	char line[LINE_MAX_LEN];
	size_t line_len;
	bool stdin_eof;
} H;

static volatile sig_atomic_t stop_signal;

static void on_signal(int sig) { stop_signal = sig; }

static void die(const char *fmt, ...) __attribute__((noreturn, format(printf, 1, 2)));
static void die(const char *fmt, ...)
{
	va_list ap;
	va_start(ap, fmt);
	fputs("avr_harness: ", stderr);
	vfprintf(stderr, fmt, ap);
	fputc('\n', stderr);
	va_end(ap);
	if (H.edges)
		fflush(H.edges);
	exit(2);
}

static double now_s(void)
{
	struct timespec ts;
	clock_gettime(CLOCK_MONOTONIC, &ts);
	return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

/* ---------------------------------------------------------------- ring buffers */

static void ring_init(ring_t *r, size_t cap)
{
	r->data = malloc(cap);
	if (!r->data)
		die("out of memory for a %zu byte buffer", cap);
	r->cap = cap;
	r->head = r->len = 0;
}

static bool ring_push(ring_t *r, uint8_t b)
{
	if (r->len == r->cap)
		return false;
	r->data[(r->head + r->len) % r->cap] = b;
	r->len++;
	return true;
}

static uint8_t ring_pop(ring_t *r)
{
	uint8_t b = r->data[r->head];
	r->head = (r->head + 1) % r->cap;
	r->len--;
	return b;
}

/* read() from fd into the free space; returns read()'s result (0 / -1 as read() does). */
static ssize_t ring_fill(ring_t *r, int fd)
{
	size_t tail = (r->head + r->len) % r->cap;
	size_t room = r->cap - r->len;
	size_t chunk = tail + room > r->cap ? r->cap - tail : room;
	ssize_t n = read(fd, r->data + tail, chunk);
	if (n > 0)
		r->len += (size_t)n;
	return n;
}

/* write() the oldest bytes to fd; returns write()'s result. */
static ssize_t ring_drain(ring_t *r, int fd)
{
	size_t chunk = r->head + r->len > r->cap ? r->cap - r->head : r->len;
	ssize_t n = write(fd, r->data + r->head, chunk);
	if (n > 0) {
		r->head = (r->head + (size_t)n) % r->cap;
		r->len -= (size_t)n;
	}
	return n;
}

/* ---------------------------------------------------------------- edges */

static void edges_flush(void)
{
	if (H.edges && H.edges_dirty) {
		if (fflush(H.edges) != 0)
			die("cannot write the edges file: %s", strerror(errno));
		H.edges_dirty = false;
	}
	H.edges_flushed_at = now_s();
}

/* Pin IRQ hook: simavr raises pin IRQs on every PORT/DDR write (and twice for a compare
 * output), so only a change of value is an edge. */
static void pin_notify(avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	pin_t *p = param;
	int v = (value & 0xff) ? 1 : 0;
	if (v == p->value)
		return;
	p->value = v;
	uint64_t cycle = H.avr->cycle;
	if (H.edges) {
		fprintf(H.edges, "%" PRIu64 " %s %d\n", cycle, p->name, v);
		H.edges_dirty = true;
	}
	if (H.mode == CLOCK_CONTROL)
		printf("EDGE %" PRIu64 " %s %d\n", cycle, p->name, v);
}

/* ---------------------------------------------------------------- UART bridge */

static void uart_output_notify(avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	if (!ring_push(&H.from_avr, (uint8_t)value))
		H.overflowed++;  /* real mode only: max/control stall before the buffer fills */
}

static void uart_xoff_notify(avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	H.xoff = value != 0;
}

static void uart_xon_notify(avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	if (value)
		H.xoff = false;
}

/* Push waiting host bytes while the UART can take them: the receiver must be enabled (simavr
 * drops input while RXEN is off) and its 64-byte FIFO must have room (a full FIFO drops). */
static void feed_uart(void)
{
	avr_uart_t *u = H.uart;
	while (H.to_avr.len && !H.xoff && avr_regbit_get(H.avr, u->rxen) &&
	       !uart_fifo_isfull(&u->input)) {
		if (H.free_feeding) {
			if (!H.free_budget)
				break;
			H.free_budget--;
		}
		avr_raise_irq(H.uart_input, ring_pop(&H.to_avr));
	}
}

/* Bytes up to and including the first newline waiting for the firmware (a whole host line),
 * or, with no newline in FREE_LINE_MAX bytes, that many; 0 while a line is still coming. */
static size_t next_line_len(void)
{
	const ring_t *r = &H.to_avr;
	size_t limit = r->len < FREE_LINE_MAX ? r->len : FREE_LINE_MAX;
	for (size_t i = 0; i < limit; i++)
		if (r->data[(r->head + i) % r->cap] == '\n')
			return i + 1;
	return r->len >= FREE_LINE_MAX ? FREE_LINE_MAX : 0;
}

static avr_uart_t *find_uart0(avr_t *avr)
{
	for (avr_io_t *io = avr->io_port; io; io = io->next)
		if (io->kind && strcmp(io->kind, "uart") == 0 && ((avr_uart_t *)io)->name == '0')
			return (avr_uart_t *)io;
	return NULL;
}

/* ---------------------------------------------------------------- I/O service */

/* Moves bytes between the pty master and the buffers, reads stdin (control mode) and flushes
 * the edges file when due. Waits up to timeout_s (negative: until something happens). Returns
 * true when a complete stdin line is buffered. */
static bool service_io(double timeout_s)
{
	struct pollfd fds[2];
	int n = 0;
	fds[n++] = (struct pollfd){
		.fd = H.master,
		.events = (short)((H.to_avr.len < H.to_avr.cap ? POLLIN : 0) |
				  (H.from_avr.len ? POLLOUT : 0)),
	};
	bool want_stdin = H.mode == CLOCK_CONTROL && !H.stdin_eof &&
			  !memchr(H.line, '\n', H.line_len);
	if (want_stdin)
		fds[n++] = (struct pollfd){ .fd = STDIN_FILENO, .events = POLLIN };

	if (H.edges_dirty) {
		double due = H.edges_flushed_at + EDGE_FLUSH_S - now_s();
		if (due <= 0) {
			edges_flush();
			due = EDGE_FLUSH_S;
		}
		if (timeout_s < 0 || timeout_s > due)
			timeout_s = due;
	}
	struct timespec ts, *tsp = NULL;
	if (timeout_s >= 0) {
		ts.tv_sec = (time_t)timeout_s;
		ts.tv_nsec = (long)((timeout_s - (double)ts.tv_sec) * 1e9);
		tsp = &ts;
	}
	int r = ppoll(fds, (nfds_t)n, tsp, NULL);
	if (r < 0) {
		if (errno == EINTR)
			return false;
		die("poll: %s", strerror(errno));
	}
	if (fds[0].revents & POLLIN) {
		ssize_t got = ring_fill(&H.to_avr, H.master);
		if (got < 0 && errno != EAGAIN && errno != EINTR)
			die("reading the pty master: %s", strerror(errno));
	}
	if (fds[0].revents & POLLOUT) {
		ssize_t put = ring_drain(&H.from_avr, H.master);
		if (put < 0 && errno != EAGAIN && errno != EINTR)
			die("writing the pty master: %s", strerror(errno));
	}
	if (n > 1 && (fds[1].revents & (POLLIN | POLLHUP))) {
		ssize_t got = read(STDIN_FILENO, H.line + H.line_len, sizeof(H.line) - H.line_len);
		if (got == 0)
			H.stdin_eof = true;
		else if (got < 0 && errno != EAGAIN && errno != EINTR)
			die("reading stdin: %s", strerror(errno));
		else if (got > 0)
			H.line_len += (size_t)got;
		if (H.line_len == sizeof(H.line) && !memchr(H.line, '\n', H.line_len))
			die("a stdin line is longer than %d bytes", LINE_MAX_LEN);
	}
	return memchr(H.line, '\n', H.line_len) != NULL;
}

static bool line_ready(void) { return memchr(H.line, '\n', H.line_len) != NULL; }

/* ---------------------------------------------------------------- real-time pacing */

static void note_lag(double lag, double now)
{
	if (lag > H.lag_worst)
		H.lag_worst = lag;
	if (now - H.lag_window_start >= LAG_REPORT_S) {
		if (H.lag_worst >= LAG_REPORT_MIN_S)
			fprintf(stderr, "avr_harness: behind real time by up to %.1f ms "
				"in the last %.0f s (cycle %" PRIu64 ")\n",
				H.lag_worst * 1e3, LAG_REPORT_S, H.avr->cycle);
		if (H.overflowed != H.overflow_reported) {
			fprintf(stderr, "avr_harness: %" PRIu64 " firmware bytes lost: the pty "
				"output buffer (%zu bytes) was full (nobody reading the pty)\n",
				H.overflowed - H.overflow_reported, H.from_avr.cap);
			H.overflow_reported = H.overflowed;
		}
		H.lag_worst = 0;
		H.lag_window_start = now;
	}
}

/* Real mode: wait (serving I/O) until the wall time of `cycle`; if already late, note it. */
static void pace_to(uint64_t cycle)
{
	double due = H.wall_start + (double)cycle / H.freq;
	for (;;) {
		double now = now_s();
		if (now >= due) {
			note_lag(now - due, now);
			return;
		}
		if (stop_signal)
			return;
		service_io(due - now);
	}
}

/* simavr calls this when the CPU sleeps, then adds how_long + 1 cycles. */
static void sleep_hook(avr_t *avr, avr_cycle_count_t how_long)
{
	if (H.mode == CLOCK_REAL)
		pace_to(avr->cycle + how_long);
}

/* A timer that does nothing: its presence bounds a sleep jump (simavr jumps to the next
 * timer), so a run can stop exactly at a cycle, and real mode polls its I/O at least once a
 * millisecond of AVR time. */
static avr_cycle_count_t limit_timer(avr_t *avr, avr_cycle_count_t when, void *param)
{
	(void)avr;
	(void)when;
	(void)param;
	return 0;
}

static avr_cycle_count_t tick_timer(avr_t *avr, avr_cycle_count_t when, void *param)
{
	(void)avr;
	(void)param;
	return when + H.freq / 1000;
}

static avr_cycle_count_t set_timer(avr_t *avr, avr_cycle_count_t when, void *param)
{
	(void)avr;
	(void)when;
	set_req_t *s = param;
	avr_raise_irq(s->irq, s->value);
	s->used = false;
	return 0;
}

/* ---------------------------------------------------------------- running */

static bool is_quiet(void)
{
	return H.has_quiet && (H.avr->data[H.quiet_addr] & H.quiet_mask) == 0;
}

/* The firmware has nothing to do: quiet, asleep, its UART FIFO empty and done sending. */
static bool firmware_idle(void)
{
	return is_quiet() && H.avr->state == cpu_Sleeping && uart_fifo_isempty(&H.uart->input) &&
	       H.uart->tx_cnt == 0;
}

/* Control mode FREE: nothing can change until the host or the test says something. Host bytes
 * are given to the firmware a whole line at a time, each only once it is idle, so how the host's
 * writes were split in time never shows in the firmware's cycle count: its clock at START, and
 * every pulse time after it, depend on the commands alone. */
static bool is_idle(void)
{
	if (!H.free_lines)
		return firmware_idle() && H.to_avr.len == 0;
	if (!firmware_idle() || H.free_budget)
		return false;
	H.free_budget = next_line_len();
	return H.free_budget == 0;
}

static void check_state(void)
{
	avr_t *avr = H.avr;
	if (avr->state == cpu_Crashed)
		die("the AVR crashed at cycle %" PRIu64 ", PC 0x%04x (byte address)",
		    (uint64_t)avr->cycle, (unsigned)avr->pc);
	if (avr->state == cpu_Done)
		die("the AVR stopped (sleeping with interrupts off) at cycle %" PRIu64
		    ", PC 0x%04x (byte address)", (uint64_t)avr->cycle, (unsigned)avr->pc);
	if (avr->state != cpu_Running && avr->state != cpu_Sleeping)
		die("the AVR entered simavr state %d at cycle %" PRIu64 ", PC 0x%04x (byte address)",
		    avr->state, (uint64_t)avr->cycle, (unsigned)avr->pc);
}

/* The instruction at PC is SLEEP (0x9588; simavr's pc is a byte address). */
static bool next_is_sleep(avr_t *avr)
{
	return avr->pc + 1u <= avr->flashend &&
	       (avr->flash[avr->pc] | (avr->flash[avr->pc + 1] << 8)) == 0x9588;
}

/* Bytes from the host wait in the harness or the UART FIFO (the firmware has not read them). */
static bool host_waiting(void)
{
	return H.to_avr.len > 0 || !uart_fifo_isempty(&H.uart->input);
}

enum stop_reason { STOP_LIMIT, STOP_NOT_QUIET, STOP_LINE, STOP_SIGNAL };

/* Runs until avr->cycle >= limit, a signal, or (free) the firmware stops being quiet or a
 * stdin line arrives. */
static enum stop_reason run(uint64_t limit, bool free_run)
{
	avr_t *avr = H.avr;
	H.free_feeding = free_run && H.free_lines;
	H.free_budget = 0;
	if (limit != UINT64_MAX && limit > avr->cycle)
		/* at limit - 1: a sleep jump adds 1 + the timer distance, so it lands on limit */
		avr_cycle_timer_register(avr, limit - 1 - avr->cycle, limit_timer, NULL);
	unsigned steps = 0;
	for (;;) {
		if (avr->cycle >= limit)
			return STOP_LIMIT;
		if (stop_signal)
			return STOP_SIGNAL;
		if (free_run && !is_quiet())
			return STOP_NOT_QUIET;
		if (H.mode != CLOCK_REAL && H.from_avr.len == H.from_avr.cap) {
			/* an instruction writes at most one UART byte: stall before the next one */
			service_io(-1);
			continue;
		}
		if (H.to_avr.len && !H.xoff)
			feed_uart();
		if (free_run && is_quiet() && (avr->state == cpu_Sleeping || next_is_sleep(avr)))
			/* A sleep jump goes to the next timer event (a timer overflow, tens of ms
			 * away), past the moment the firmware became idle (its last UART byte out,
			 * say): bound it to two cycles (the SLEEP itself takes one), so FREE stops
			 * where the firmware went idle, whatever the host's timing. */
			avr_cycle_timer_register(avr, 2, limit_timer, &H);
		if (free_run && is_idle()) {
			/* time stands still until the host, the test or a signal says something */
			if (line_ready() || H.stdin_eof || service_io(-1))
				return STOP_LINE;
			continue;
		}
		avr_run(avr);
		if (avr->state != cpu_Running && avr->state != cpu_Sleeping)
			check_state();
		if (++steps >= STEPS_PER_SERVICE) {
			steps = 0;
			if ((service_io(0) || H.stdin_eof) && free_run)
				return STOP_LINE;
			if (H.mode == CLOCK_REAL)
				pace_to(avr->cycle);
		}
	}
}

/* ---------------------------------------------------------------- control protocol */

/* `AT <cycle> quiet|scheduled[ host]`: " host" while host bytes wait for the firmware, so a
 * controller that paces the AVR behind something else can let it run to answer them. */
static void answer_at(const char *what)
{
	service_io(0);
	printf("AT %" PRIu64 " %s%s\n", (uint64_t)H.avr->cycle, what, host_waiting() ? " host" : "");
	fflush(stdout);
}

static void answer(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
static void answer(const char *fmt, ...)
{
	va_list ap;
	va_start(ap, fmt);
	vprintf(fmt, ap);
	va_end(ap);
	putchar('\n');
	fflush(stdout);
}

static bool parse_u64(const char *s, uint64_t *out)
{
	if (!s || !*s)
		return false;
	char *end;
	errno = 0;
	unsigned long long v = strtoull(s, &end, 10);
	if (errno || *end || *s == '-')
		return false;
	*out = v;
	return true;
}

static void cmd_set(char *args)
{
	char *cyc = strtok(args, " \t");
	char *name = strtok(NULL, " \t");
	char *val = strtok(NULL, " \t");
	uint64_t cycle;
	if (!parse_u64(cyc, &cycle) || !name || !val || strtok(NULL, " \t") ||
	    (strcmp(val, "0") && strcmp(val, "1"))) {
		answer("ERR SET wants: SET <cycle> <input-pin> <0|1>");
		return;
	}
	pin_t *pin = NULL;
	for (int i = 0; i < H.ninputs; i++)
		if (strcmp(H.inputs[i].name, name) == 0)
			pin = &H.inputs[i];
	if (!pin) {
		answer("ERR SET: %s is not an --input-pin", name);
		return;
	}
	if (cycle < H.avr->cycle) {
		answer("ERR SET: cycle %" PRIu64 " is in the past (now %" PRIu64 ")", cycle,
		       (uint64_t)H.avr->cycle);
		return;
	}
	uint8_t v = val[0] == '1';
	if (cycle == H.avr->cycle) {
		avr_raise_irq(pin->irq, v);
		answer("OK");
		return;
	}
	for (int i = 0; i < MAX_SETS; i++) {
		if (!H.sets[i].used) {
			H.sets[i] = (set_req_t){ .used = true, .irq = pin->irq, .value = v };
			avr_cycle_timer_register(H.avr, cycle - H.avr->cycle, set_timer, &H.sets[i]);
			answer("OK");
			return;
		}
	}
	answer("ERR SET: %d SETs already pending", MAX_SETS);
}

/* Handles one command line; returns false on QUIT. */
static bool handle_line(char *line)
{
	char *cmd = strtok(line, " \t\r");
	char *rest = strtok(NULL, "\r");
	if (!cmd)
		return true;  /* blank line: nothing to do */
	if (strcmp(cmd, "RUN") == 0) {
		uint64_t cycle;
		if (!parse_u64(rest, &cycle)) {
			answer("ERR RUN wants: RUN <cycle>");
			return true;
		}
		if (run(cycle, false) == STOP_SIGNAL)
			return false;
		answer_at(is_quiet() ? "quiet" : "scheduled");
	} else if (strcmp(cmd, "FREE") == 0 && !rest) {
		enum stop_reason why = run(UINT64_MAX, true);
		if (why == STOP_SIGNAL)
			return false;
		answer_at(why == STOP_NOT_QUIET ? "scheduled" : "quiet");
	} else if (strcmp(cmd, "SET") == 0) {
		cmd_set(rest ? rest : (char[]){ 0 });
	} else if (strcmp(cmd, "NOP") == 0 && !rest) {
		answer("NOP");
	} else if (strcmp(cmd, "QUIT") == 0 && !rest) {
		return false;
	} else {
		answer("ERR unknown command: %s%s%s (RUN <cycle> | FREE | SET <cycle> <pin> <0|1> "
		       "| NOP | QUIT)", cmd, rest ? " " : "", rest ? rest : "");
	}
	return true;
}

static void control_loop(void)
{
	for (;;) {
		while (!line_ready()) {
			if (stop_signal)
				return;
			if (H.stdin_eof)
				return;  /* the driver went away: same as QUIT */
			service_io(-1);
		}
		char *nl = memchr(H.line, '\n', H.line_len);
		size_t n = (size_t)(nl - H.line);
		char line[LINE_MAX_LEN];
		memcpy(line, H.line, n);
		line[n] = 0;
		memmove(H.line, nl + 1, H.line_len - n - 1);
		H.line_len -= n + 1;
		if (!handle_line(line))
			return;
	}
}

/* ---------------------------------------------------------------- setup */

static void harness_logger(avr_t *avr, const int level, const char *format, va_list ap)
{
	(void)avr;
	if (level <= LOG_WARNING) {
		fputs("simavr: ", stderr);
		vfprintf(stderr, format, ap);
	}
}

static void parse_pin(const char *spec, pin_t *out, const char *opt)
{
	const char *eq = strchr(spec, '=');
	if (!eq || eq == spec || (size_t)(eq - spec) >= sizeof(out->name) || strlen(eq + 1) != 2 ||
	    eq[1] < 'A' || eq[1] > 'L' || eq[2] < '0' || eq[2] > '7')
		die("%s %s: want NAME=PORTBIT, e.g. TRIG=B1", opt, spec);
	memset(out, 0, sizeof(*out));
	memcpy(out->name, spec, (size_t)(eq - spec));
	out->port = eq[1];
	out->bit = eq[2] - '0';
}

static void usage(FILE *f)
{
	fputs("usage: avr_harness --elf ELF [--mcu atmega328p] [--freq 16000000]\n"
	      "       [--pin NAME=PORTBIT]... [--input-pin NAME=PORTBIT]... [--edges FILE]\n"
	      "       [--clock real|max|control] [--quiet-reg ADDR:MASK] [--out-buffer BYTES]\n"
	      "       [--free-lines]\n", f);
}

static void open_pty(void)
{
	char name[256];
	struct termios tio;
	if (openpty(&H.master, &H.slave, name, NULL, NULL) < 0)
		die("openpty: %s", strerror(errno));
	/* raw both ways: no echo, no line discipline, every byte as it is */
	for (int i = 0; i < 2; i++) {
		int fd = i ? H.slave : H.master;
		if (tcgetattr(fd, &tio) < 0)
			die("tcgetattr: %s", strerror(errno));
		cfmakeraw(&tio);
		if (tcsetattr(fd, TCSANOW, &tio) < 0)
			die("tcsetattr: %s", strerror(errno));
	}
	int fl = fcntl(H.master, F_GETFL);
	if (fl < 0 || fcntl(H.master, F_SETFL, fl | O_NONBLOCK) < 0)
		die("fcntl O_NONBLOCK: %s", strerror(errno));
	/* H.slave stays open: output waits for a host, and the master never sees EIO */
	printf("pty: %s\n", name);
	fflush(stdout);
}

int main(int argc, char **argv)
{
	const char *elf = NULL, *mcu = "atmega328p", *edges = NULL, *clock = "real";
	const char *quiet = NULL;
	unsigned long freq = 16000000, out_buffer = OUT_BUF_SIZE;
	static const struct option opts[] = {
		{ "elf", required_argument, 0, 'e' },
		{ "mcu", required_argument, 0, 'm' },
		{ "freq", required_argument, 0, 'f' },
		{ "pin", required_argument, 0, 'p' },
		{ "input-pin", required_argument, 0, 'i' },
		{ "edges", required_argument, 0, 'o' },
		{ "clock", required_argument, 0, 'c' },
		{ "quiet-reg", required_argument, 0, 'q' },
		{ "free-lines", no_argument, 0, 'L' },
		{ "out-buffer", required_argument, 0, 'b' },
		{ "help", no_argument, 0, 'h' },
		{ 0, 0, 0, 0 },
	};
	int c;
	while ((c = getopt_long(argc, argv, "", opts, NULL)) != -1) {
		switch (c) {
		case 'e': elf = optarg; break;
		case 'm': mcu = optarg; break;
		case 'f': {
			char *end;
			freq = strtoul(optarg, &end, 10);
			if (*end || freq == 0 || freq > 100000000)
				die("--freq %s: want a frequency in Hz (1..100000000)", optarg);
			break;
		}
		case 'p':
			if (H.npins == MAX_PINS)
				die("at most %d --pin options", MAX_PINS);
			parse_pin(optarg, &H.pins[H.npins++], "--pin");
			break;
		case 'i':
			if (H.ninputs == MAX_PINS)
				die("at most %d --input-pin options", MAX_PINS);
			parse_pin(optarg, &H.inputs[H.ninputs++], "--input-pin");
			break;
		case 'o': edges = optarg; break;
		case 'c': clock = optarg; break;
		case 'q': quiet = optarg; break;
		case 'L': H.free_lines = true; break;
		case 'b': {
			char *end;
			out_buffer = strtoul(optarg, &end, 10);
			if (*end || out_buffer < 1 || out_buffer > (1ul << 30))
				die("--out-buffer %s: want a size in bytes (1..2^30)", optarg);
			break;
		}
		case 'h': usage(stdout); return 0;
		default: usage(stderr); return 2;
		}
	}
	if (optind != argc)
		die("unexpected argument %s", argv[optind]);
	if (!elf) {
		usage(stderr);
		die("--elf is required");
	}
	if (strcmp(clock, "real") == 0)
		H.mode = CLOCK_REAL;
	else if (strcmp(clock, "max") == 0)
		H.mode = CLOCK_MAX;
	else if (strcmp(clock, "control") == 0)
		H.mode = CLOCK_CONTROL;
	else
		die("--clock %s: want real, max or control", clock);
	H.freq = (uint32_t)freq;
	if (quiet) {
		char *end;
		unsigned long addr = strtoul(quiet, &end, 0), mask;
		if (*end != ':' || (mask = strtoul(end + 1, &end, 0), *end) || addr > 0xffff ||
		    mask == 0 || mask > 0xff)
			die("--quiet-reg %s: want ADDR:MASK (data-space address, 8-bit mask), "
			    "e.g. 0x6F:0x06", quiet);
		H.has_quiet = true;
		H.quiet_addr = (uint16_t)addr;
		H.quiet_mask = (uint8_t)mask;
	}

	avr_global_logger_set(harness_logger);
	elf_firmware_t fw;
	memset(&fw, 0, sizeof(fw));
	if (access(elf, R_OK) != 0)
		die("--elf %s: %s", elf, strerror(errno));
	if (elf_read_firmware(elf, &fw) != 0)
		die("--elf %s: not an AVR ELF simavr can load", elf);
	if (fw.flashsize == 0)  /* simavr 1.6 "loads" a file that is no ELF at all as empty */
		die("--elf %s: no program in it (not an AVR ELF?)", elf);
	/* the options win over the ELF's .mmcu section */
	snprintf(fw.mmcu, sizeof(fw.mmcu), "%s", mcu);
	fw.frequency = H.freq;
	avr_t *avr = avr_make_mcu_by_name(mcu);
	if (!avr)
		die("--mcu %s: simavr does not know this MCU", mcu);
	if (avr_init(avr) != 0)
		die("simavr could not initialise the %s", mcu);
	avr->log = LOG_WARNING;
	avr_load_firmware(avr, &fw);
	avr->frequency = H.freq;
	avr->sleep = sleep_hook;
	H.avr = avr;
	if (H.has_quiet && H.quiet_addr > avr->ramend)
		die("--quiet-reg 0x%x: beyond the %s data space (RAMEND 0x%x)", H.quiet_addr, mcu,
		    (unsigned)avr->ramend);

	H.uart = find_uart0(avr);
	if (!H.uart)
		die("the %s has no UART0 in simavr", mcu);
	/* no console echo of firmware lines, no usleep when the firmware polls UCSRA */
	uint32_t uart_flags = 0;
	avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &uart_flags);
	H.uart_input = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
				uart_output_notify, NULL);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF),
				uart_xoff_notify, NULL);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON),
				uart_xon_notify, NULL);

	for (int i = 0; i < H.npins + H.ninputs; i++) {
		bool input = i >= H.npins;
		pin_t *p = input ? &H.inputs[i - H.npins] : &H.pins[i];
		p->irq = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(p->port), p->bit);
		if (!p->irq)
			die("%s %s=%c%d: the %s has no port %c", input ? "--input-pin" : "--pin",
			    p->name, p->port, p->bit, mcu, p->port);
		if (!input)
			avr_irq_register_notify(p->irq, pin_notify, p);
	}
	if (edges && !(H.edges = fopen(edges, "w")))
		die("--edges %s: %s", edges, strerror(errno));
	if (H.edges)
		setvbuf(H.edges, NULL, _IOFBF, 1 << 16);

	ring_init(&H.to_avr, IN_BUF_SIZE);
	ring_init(&H.from_avr, out_buffer);

	struct sigaction sa;
	memset(&sa, 0, sizeof(sa));
	sa.sa_handler = on_signal;  /* no SA_RESTART: poll() returns EINTR */
	sigaction(SIGTERM, &sa, NULL);
	sigaction(SIGINT, &sa, NULL);
	/* A harness whose parent died (a killed test, a killed `python -m firmware_sim.avr`) would
	 * run a max-clock firmware at full CPU forever: it is told, and stops like on SIGTERM. */
	if (prctl(PR_SET_PDEATHSIG, SIGTERM) != 0)
		die("prctl(PR_SET_PDEATHSIG): %s", strerror(errno));
	signal(SIGPIPE, SIG_IGN);
	if (H.mode == CLOCK_CONTROL) {
		int fl = fcntl(STDIN_FILENO, F_GETFL);
		if (fl < 0 || fcntl(STDIN_FILENO, F_SETFL, fl | O_NONBLOCK) < 0)
			die("fcntl stdin: %s", strerror(errno));
	}

	open_pty();
	H.wall_start = H.lag_window_start = H.edges_flushed_at = now_s();
	if (H.mode == CLOCK_REAL)
		avr_cycle_timer_register(avr, H.freq / 1000, tick_timer, NULL);

	if (H.mode == CLOCK_CONTROL)
		control_loop();
	else
		run(UINT64_MAX, false);

	edges_flush();
	if (H.edges && fclose(H.edges) != 0)
		die("cannot close the edges file: %s", strerror(errno));
	H.edges = NULL;
	if (H.overflowed != H.overflow_reported)
		fprintf(stderr, "avr_harness: %" PRIu64 " firmware bytes lost: the pty output "
			"buffer was full\n", H.overflowed - H.overflow_reported);
	/* what is still buffered either way: hand over what the pty takes, count the rest */
	while (H.from_avr.len && ring_drain(&H.from_avr, H.master) > 0)
		;
	if (H.from_avr.len)
		fprintf(stderr, "avr_harness: %zu firmware bytes not delivered at exit (the pty "
			"was full)\n", H.from_avr.len);
	size_t in_uart = uart_fifo_get_read_size(&H.uart->input);
	if (H.to_avr.len || in_uart)
		fprintf(stderr, "avr_harness: %zu host bytes had not reached the firmware at exit "
			"(%zu waiting, %zu in the UART FIFO)\n", H.to_avr.len + in_uart,
			H.to_avr.len, in_uart);
	if (stop_signal)
		fprintf(stderr, "avr_harness: stopped by signal %d at cycle %" PRIu64 "\n",
			(int)stop_signal, (uint64_t)avr->cycle);
	fflush(stdout);
	return 0;
}
