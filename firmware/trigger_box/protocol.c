/*
 * protocol.c - commands, replies and the state machine (docs/trigger-protocol.md).
 *
 * Replies are written in the order the protocol promises: before any command's reply the
 * queued pulse records go out, then END if a counted run is over, so every P line of a run
 * precedes OK STOP, END and a STATUS? that shows the run over. Records that did not fit the
 * queue (a saturated line) are not lost: TS? recomputes any b_k of the run.
 */
#include <avr/eeprom.h>
#include <avr/pgmspace.h>
#include <stdint.h>
#include <string.h>

#include "board.h"
#include "protocol.h"
#include "pulse.h"
#include "serial.h"

#define MAX_LINE 64u          /* longest host line accepted, without the newline */
#define MAX_TS_COUNT 64u
#define START_LEAD_US 20000u
#define MIN_RATE_UHZ 1000ULL           /* 0.001 Hz */
#define MAX_RATE_UHZ 10000000000ULL    /* 10 kHz */
#define MAX_WIDTH_US 1000000UL
#define MAX_PULSES 2147483647UL
#define US_PER_S2 1000000000000ULL
#define RECORD_LINE_ROOM 48u  /* the longest P line, with room to spare */
#define SERIAL_EEPROM_LEN 16u

enum state { IDLE, ARMED, RUNNING };
static const char STATE_NAMES[3][8] PROGMEM = {"IDLE", "ARMED", "RUNNING"};

static enum state state = IDLE;
static uint64_t rate_uhz = 30000000ULL; /* power-on: 30 Hz */
static uint32_t width_us = 1000;
static uint32_t target;
static uint64_t t0_us;
static uint8_t has_t0;

static char line[MAX_LINE + 2]; /* + a tolerated CR + NUL */
static uint8_t line_len;
static uint8_t discarding;
static uint32_t lost_mark;

/* A reply in progress carries its command's tag (-1: none). */
static int32_t reply_tag;

/* ------------------------------------------------------------------ output helpers */

static void send_record(const pulse_record_t *rec)
{
    line_begin();
    line_str_P(PSTR("P "));
    line_u32(rec->index);
    line_char(' ');
    line_u64(rec->t_us);
    line_end(-1);
}

/* END, once a counted run is over and its last record is out; 1 if it was sent. */
static uint8_t send_end_if_over(void)
{
    if (!pulse_take_end())
        return 0;
    state = IDLE;
    line_begin();
    line_str_P(PSTR("END "));
    line_u32(pulse_count());
    line_end(-1);
    return 1;
}

/* Every queued pulse record, then END if a counted run is over. */
static void flush_pulse_lines(void)
{
    pulse_record_t rec;
    while (pulse_record_pop(&rec))
        send_record(&rec);
    send_end_if_over();
}

static void err_begin(PGM_P code)
{
    flush_pulse_lines();
    line_begin();
    line_str_P(PSTR("ERR "));
    line_str_P(code);
    line_char(' ');
}

static void ok_begin(PGM_P text)
{
    flush_pulse_lines();
    line_begin();
    line_str_P(text);
}

static void print_rate(uint64_t uhz)
{
    uint64_t whole = uhz / 1000000u;
    uint32_t frac = (uint32_t)(uhz - whole * 1000000u);
    line_u64(whole);
    line_char('.');
    for (uint32_t p = 100000u; p; p /= 10u) {
        line_char((char)('0' + frac / p));
        frac %= p;
    }
}

/* Period in us with one decimal, as the protocol's BADARG message shows it. */
static void print_period(uint64_t uhz)
{
    uint64_t tenths = (US_PER_S2 * 10u + uhz / 2u) / uhz;
    line_u64(tenths / 10u);
    line_char('.');
    line_char((char)('0' + (uint8_t)(tenths % 10u)));
}

/* ------------------------------------------------------------------ parsing */

static uint8_t is_digit(char c)
{
    return c >= '0' && c <= '9';
}

/* 1-10 decimal digits, nothing else (no sign, exponent, nan or inf). */
static uint8_t parse_uint(const char *s, uint64_t *out)
{
    uint64_t v = 0;
    uint8_t n = 0;
    for (; *s; s++, n++) {
        if (!is_digit(*s) || n >= 10)
            return 0;
        v = v * 10u + (uint8_t)(*s - '0');
    }
    if (n == 0)
        return 0;
    *out = v;
    return 1;
}

/* `\d{1,5}(\.\d{1,6})?` in micro-hertz, exactly. */
static uint8_t parse_rate(const char *s, uint64_t *out)
{
    uint64_t whole = 0, frac = 0;
    uint8_t nw = 0, nf = 0;
    while (is_digit(*s)) {
        if (++nw > 5)
            return 0;
        whole = whole * 10u + (uint8_t)(*s++ - '0');
    }
    if (nw == 0)
        return 0;
    if (*s == '.') {
        s++;
        while (is_digit(*s)) {
            if (++nf > 6)
                return 0;
            frac = frac * 10u + (uint8_t)(*s++ - '0');
        }
        if (nf == 0)
            return 0;
    }
    if (*s)
        return 0;
    for (; nf < 6; nf++)
        frac *= 10u;
    *out = whole * 1000000u + frac;
    return 1;
}

static uint8_t hex_value(char c, uint8_t *v)
{
    if (c >= '0' && c <= '9')
        *v = (uint8_t)(c - '0');
    else if (c >= 'A' && c <= 'F')
        *v = (uint8_t)(c - 'A' + 10);
    else if (c >= 'a' && c <= 'f')
        *v = (uint8_t)(c - 'a' + 10);
    else
        return 0;
    return 1;
}

/* ------------------------------------------------------------------ commands */

static void cmd_id(void)
{
    ok_begin(PSTR("ID " VENDOR " " BOARD_MODEL " "));
    /* The serial number lives in EEPROM bytes 0-15 (printable, no spaces; set it with
     * avrdude -U eeprom:w:...); an unprogrammed EEPROM reads 0xFF. */
    uint8_t n = 0;
    for (; n < SERIAL_EEPROM_LEN; n++) {
        uint8_t c = eeprom_read_byte((const uint8_t *)(uintptr_t)n);
        if (c <= 0x20 || c > 0x7E || c == '$' || c == '*')
            break;
        line_char((char)c);
    }
    if (n == 0)
        line_str_P(PSTR("UNSET"));
    line_str_P(PSTR(" " FIRMWARE_VERSION));
    line_end(reply_tag);
}

static void cmd_rate(const char *arg)
{
    uint64_t v;
    if (!parse_rate(arg, &v) || v < MIN_RATE_UHZ || v > MAX_RATE_UHZ) {
        err_begin(PSTR("BADARG"));
        line_str_P(PSTR("rate "));
        line_quoted(arg, 16);
        line_str_P(PSTR(" not a decimal in 0.001..10000 Hz"));
        line_end(reply_tag);
        return;
    }
    if (state == RUNNING) {
        err_begin(PSTR("STATE"));
        line_str_P(PSTR("RATE not allowed while RUNNING"));
        line_end(reply_tag);
        return;
    }
    rate_uhz = v;
    ok_begin(PSTR("OK RATE "));
    print_rate(rate_uhz);
    line_end(reply_tag);
}

static void cmd_width(const char *arg)
{
    uint64_t v;
    if (!parse_uint(arg, &v) || v < MIN_WIDTH_US || v > MAX_WIDTH_US) {
        err_begin(PSTR("BADARG"));
        line_str_P(PSTR("width "));
        line_quoted(arg, 16);
        line_str_P(PSTR(" not an integer in "));
        line_u32(MIN_WIDTH_US);
        line_str_P(PSTR("..1000000 us"));
        line_end(reply_tag);
        return;
    }
    if (state == RUNNING) {
        err_begin(PSTR("STATE"));
        line_str_P(PSTR("WIDTH not allowed while RUNNING"));
        line_end(reply_tag);
        return;
    }
    width_us = (uint32_t)v;
    ok_begin(PSTR("OK WIDTH "));
    line_u32(width_us);
    line_end(reply_tag);
}

static void cmd_arm(void)
{
    if (state == RUNNING) {
        err_begin(PSTR("STATE"));
        line_str_P(PSTR("ARM not allowed while RUNNING"));
        line_end(reply_tag);
        return;
    }
    pulse_arm();
    state = ARMED;
    target = 0;
    has_t0 = 0;
    ok_begin(PSTR("OK ARM"));
    line_end(reply_tag);
}

static void cmd_start(uint8_t nargs, const char *arg)
{
    uint64_t n = 0;
    if (nargs && (!parse_uint(arg, &n) || n < 1 || n > MAX_PULSES)) {
        err_begin(PSTR("BADARG"));
        line_str_P(PSTR("pulse count "));
        line_quoted(arg, 16);
        line_str_P(PSTR(" not an integer in 1..2147483647"));
        line_end(reply_tag);
        return;
    }
    if (state != ARMED) {
        err_begin(PSTR("STATE"));
        line_str_P(PSTR("START needs ARMED, box is "));
        line_str_P(STATE_NAMES[state]);
        line_end(reply_tag);
        return;
    }
    if ((uint64_t)width_us * rate_uhz >= US_PER_S2) {
        err_begin(PSTR("BADARG"));
        line_str_P(PSTR("width "));
        line_u32(width_us);
        line_str_P(PSTR(" us >= period "));
        print_period(rate_uhz);
        line_str_P(PSTR(" us"));
        line_end(reply_tag);
        return;
    }
    if ((uint64_t)(width_us + MIN_GAP_US) * rate_uhz > US_PER_S2) {
        err_begin(PSTR("BADARG"));
        line_str_P(PSTR("width "));
        line_u32(width_us);
        line_str_P(PSTR(" us leaves less than "));
        line_u32(MIN_GAP_US);
        line_str_P(PSTR(" us low in a period of "));
        print_period(rate_uhz);
        line_str_P(PSTR(" us"));
        line_end(reply_tag);
        return;
    }
    if (pulse_active()) {
        err_begin(PSTR("STATE"));
        line_str_P(PSTR("the last pulse of the stopped run is still high"));
        line_end(reply_tag);
        return;
    }
    t0_us = clock_us() + START_LEAD_US;
    has_t0 = 1;
    target = (uint32_t)n;
    pulse_start(t0_us, rate_uhz, width_us, target);
    state = RUNNING;
    ok_begin(PSTR("OK START "));
    line_u64(t0_us);
    line_char(' ');
    line_u32(target);
    line_end(reply_tag);
}

static void cmd_stop(void)
{
    pulse_stop();
    ok_begin(PSTR("OK STOP ")); /* flushes every record: none can follow a STOP */
    state = IDLE;
    line_u32(pulse_count());
    line_end(reply_tag);
}

static void cmd_status(void)
{
    ok_begin(PSTR("STATUS "));
    line_str_P(STATE_NAMES[state]);
    line_str_P(PSTR(" count="));
    line_u32(pulse_count());
    line_str_P(PSTR(" target="));
    line_u32(target);
    line_str_P(PSTR(" rate="));
    print_rate(rate_uhz);
    line_str_P(PSTR(" width="));
    line_u32(width_us);
    line_str_P(PSTR(" t0="));
    if (has_t0)
        line_u64(t0_us);
    else
        line_str_P(PSTR("-1"));
    line_end(reply_tag);
}

static void cmd_ts(const char *first_text, const char *count_text)
{
    uint64_t first, n;
    if (!parse_uint(first_text, &first)) {
        err_begin(PSTR("BADARG"));
        line_str_P(PSTR("first index "));
        line_quoted(first_text, 16);
        line_str_P(PSTR(" not a non-negative integer"));
        line_end(reply_tag);
        return;
    }
    if (!parse_uint(count_text, &n) || n < 1 || n > MAX_TS_COUNT) {
        err_begin(PSTR("BADARG"));
        line_str_P(PSTR("count "));
        line_quoted(count_text, 16);
        line_str_P(PSTR(" not an integer in 1..64"));
        line_end(reply_tag);
        return;
    }
    flush_pulse_lines();
    uint32_t have = pulse_count();
    uint32_t returned = 0;
    if (first < have) {
        uint64_t hi = first + n < have ? first + n : have;
        pulse_iter_t it;
        pulse_iter_init(&it, (uint32_t)first);
        for (uint32_t k = (uint32_t)first; k < hi; k++, returned++) {
            line_begin();
            line_str_P(PSTR("T "));
            line_u32(k);
            line_char(' ');
            line_u64(pulse_iter_next(&it));
            line_end(reply_tag);
        }
    }
    ok_begin(PSTR("OK TS "));
    line_u32(returned);
    line_end(reply_tag);
}

static void cmd_diag(void)
{
    pulse_stats_t st;
    pulse_get_stats(&st);
    ok_begin(PSTR("DIAG records_dropped="));
    line_u32(st.records_dropped);
    line_str_P(PSTR(" rx_lost="));
    line_u32(serial_rx_lost());
    line_str_P(PSTR(" late_edges="));
    line_u32(st.late_edges);
    line_end(reply_tag);
}

/* ------------------------------------------------------------------ dispatch */

typedef struct {
    char name[8];
    uint8_t min_args, max_args;
} command_t;

enum { C_PING, C_ID, C_RATE, C_WIDTH, C_ARM, C_START, C_STOP, C_COUNT, C_STATUS, C_CLOCK, C_TS, C_DIAG, C_N };
static const command_t COMMANDS[C_N] PROGMEM = {
    {"PING", 0, 0},   {"ID?", 0, 0},    {"RATE", 1, 1},     {"WIDTH", 1, 1},
    {"ARM", 0, 0},    {"START", 0, 1},  {"STOP", 0, 0},     {"COUNT?", 0, 0},
    {"STATUS?", 0, 0}, {"CLOCK?", 0, 0}, {"TS?", 2, 2},      {"DIAG?", 0, 0},
};

static void dispatch(char **tok, uint8_t ntok)
{
    uint64_t parsed_at = clock_us(); /* CLOCK? answers the time the command was parsed */
    for (char *p = tok[0]; *p; p++)
        if (*p >= 'a' && *p <= 'z')
            *p = (char)(*p - 'a' + 'A');
    uint8_t c = 0;
    command_t cmd;
    for (; c < C_N; c++) {
        memcpy_P(&cmd, &COMMANDS[c], sizeof cmd);
        if (strcmp(cmd.name, tok[0]) == 0)
            break;
    }
    if (c == C_N) {
        err_begin(PSTR("UNKNOWN"));
        line_str_P(PSTR("unknown command "));
        line_quoted(tok[0], 16);
        line_end(reply_tag);
        return;
    }
    uint8_t nargs = (uint8_t)(ntok - 1u);
    if (nargs < cmd.min_args || nargs > cmd.max_args) {
        err_begin(PSTR("BADARG"));
        line_str(cmd.name);
        line_str_P(PSTR(" takes "));
        line_u32(cmd.min_args);
        if (cmd.max_args != cmd.min_args) {
            line_str_P(PSTR(".."));
            line_u32(cmd.max_args);
        }
        line_str_P(PSTR(" argument(s), got "));
        line_u32(nargs);
        line_end(reply_tag);
        return;
    }
    switch (c) {
    case C_PING:
        ok_begin(PSTR("PONG"));
        line_end(reply_tag);
        break;
    case C_ID:
        cmd_id();
        break;
    case C_RATE:
        cmd_rate(tok[1]);
        break;
    case C_WIDTH:
        cmd_width(tok[1]);
        break;
    case C_ARM:
        cmd_arm();
        break;
    case C_START:
        cmd_start(nargs, nargs ? tok[1] : "");
        break;
    case C_STOP:
        cmd_stop();
        break;
    case C_COUNT:
        ok_begin(PSTR("COUNT "));
        line_u32(pulse_count());
        line_end(reply_tag);
        break;
    case C_STATUS:
        cmd_status();
        break;
    case C_CLOCK:
        ok_begin(PSTR("CLOCK "));
        line_u64(parsed_at);
        line_end(reply_tag);
        break;
    case C_TS:
        cmd_ts(tok[1], tok[2]);
        break;
    default:
        cmd_diag();
        break;
    }
}

/* One complete host line (without its newline). */
static void handle_line(char *raw, uint8_t n)
{
    reply_tag = -1;
    if (n && raw[n - 1] == '\r')
        n--;
    raw[n] = '\0';
    if (n == 0)
        return; /* empty lines flush a half line out of the buffer: no reply */
    if (n > MAX_LINE) {
        err_begin(PSTR("TOOLONG"));
        line_str_P(PSTR("line exceeds 64 bytes"));
        line_end(-1);
        return;
    }
    for (uint8_t i = 0; i < n; i++) {
        uint8_t b = (uint8_t)raw[i];
        if (b < 0x20 || b > 0x7E) {
            static const char HEX[] PROGMEM = "0123456789ABCDEF";
            err_begin(PSTR("BADCHAR"));
            line_str_P(PSTR("byte 0x"));
            line_char((char)pgm_read_byte(&HEX[b >> 4]));
            line_char((char)pgm_read_byte(&HEX[b & 0x0F]));
            line_str_P(PSTR(" at column "));
            line_u32(i);
            line_str_P(PSTR(" is not printable ASCII"));
            line_end(-1);
            return;
        }
    }
    char *text = raw;
    if (*text == '$')
        text++;
    char *star = strrchr(text, '*');
    if (star) {
        *star = '\0';
        const char *hh = star + 1;
        uint8_t hi, lo, sum = 0;
        for (const char *p = text; *p; p++)
            sum ^= (uint8_t)*p;
        if (strlen(hh) != 2 || !hex_value(hh[0], &hi) || !hex_value(hh[1], &lo) ||
            (uint8_t)((hi << 4) | lo) != sum) {
            err_begin(PSTR("CHECKSUM"));
            line_str_P(PSTR("checksum *"));
            line_shown(hh, 8);
            line_str_P(PSTR(" does not match the line"));
            line_end(-1);
            return;
        }
    }
    /* No command takes more than two arguments: keep the first three tokens and the last
     * (the tag), and count the rest, so a long line still names its command and its tag. */
    char *tok[3];
    char *last = 0;
    uint8_t ntok = 0;
    for (char *p = text; *p;) {
        while (*p == ' ')
            *p++ = '\0';
        if (!*p)
            break;
        if (ntok < 3)
            tok[ntok] = p;
        last = p;
        ntok++;
        while (*p && *p != ' ')
            p++;
    }
    if (ntok && last[0] == '#') {
        uint64_t tag;
        if (!parse_uint(last + 1, &tag) || tag > 65535u) {
            err_begin(PSTR("BADARG"));
            line_str_P(PSTR("tag #"));
            line_shown(last + 1, 16);
            line_str_P(PSTR(" is not an integer 0..65535"));
            line_end(-1);
            return;
        }
        reply_tag = (int32_t)tag;
        ntok--;
    }
    if (ntok == 0) {
        err_begin(PSTR("UNKNOWN"));
        line_str_P(PSTR("empty command"));
        line_end(reply_tag);
        return;
    }
    dispatch(tok, ntok);
}

/* Feed one received byte; 1 when it completed (and handled) a line. */
static uint8_t feed(uint8_t c)
{
    if (c == '\n') {
        uint32_t lost = serial_rx_lost();
        uint8_t n = line_len;
        uint8_t was_discarding = discarding;
        line_len = 0;
        discarding = 0;
        if (was_discarding) {
            err_begin(PSTR("TOOLONG"));
            line_str_P(PSTR("line exceeds 64 bytes"));
            line_end(-1);
        } else if (lost != lost_mark) {
            /* Bytes of this line were lost on the way in: it is not what the host sent. */
            err_begin(PSTR("OVERRUN"));
            line_str_P(PSTR("input bytes lost (receive buffer full); line discarded"));
            line_end(-1);
        } else {
            handle_line(line, n);
        }
        lost_mark = lost;
        return 1;
    }
    if (discarding)
        return 0;
    line[line_len++] = (char)c;
    if (line_len > MAX_LINE + 1u) { /* +1 tolerates a trailing CR */
        line_len = 0;
        discarding = 1;
    }
    return 0;
}

void proto_boot(void)
{
    line_begin();
    line_str_P(PSTR("READY " BOARD_MODEL " " FIRMWARE_VERSION));
    line_end(-1);
    lost_mark = serial_rx_lost();
    serial_enable_rx();
}

uint8_t proto_service(void)
{
    uint8_t did = 0;
    pulse_record_t rec;
    /* Records go out while the line has room; a full line never blocks the loop here. */
    while (serial_tx_room() >= RECORD_LINE_ROOM && pulse_record_pop(&rec)) {
        send_record(&rec);
        did = 1;
    }
    if (send_end_if_over())
        did = 1;
    int16_t c;
    while ((c = serial_getc()) >= 0) {
        did = 1;
        if (feed((uint8_t)c))
            break;
    }
    return did;
}
