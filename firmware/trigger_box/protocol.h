/*
 * protocol.h - the line protocol of docs/trigger-protocol.md: line assembly, parsing, the
 * command table and the IDLE/ARMED/RUNNING state machine.
 */
#ifndef PROTOCOL_H
#define PROTOCOL_H

#include <stdint.h>

/* Send READY and start listening. */
void proto_boot(void);
/* One pass of the main loop's work: pulse records, END, at most one command line.
 * Returns 1 if it did anything (the caller sleeps only when it did not). */
uint8_t proto_service(void);

#endif
