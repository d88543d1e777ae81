"""`python -m firmware_sim.avr --elf ELF`: serve AVR firmware on a pseudo-terminal until killed.

The first stdout line is `pty: /dev/pts/N` (what to give the rig as the trigger box's serial
port); edges of the watched pins go to `--edges FILE` as `<cycle> <pin> <0|1>`. SIGTERM or
SIGINT stop it; a harness that dies on its own (the firmware crashed) exits non-zero.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from pathlib import Path
from types import FrameType

from firmware_sim.avr.harness import MCU_DEFAULTS, AvrHarness
from rigd.core.errors import RigdError

log = logging.getLogger("firmware_sim.avr")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m firmware_sim.avr", description=__doc__.splitlines()[0])
    parser.add_argument("--elf", type=Path, required=True, help="firmware ELF (avr-gcc output)")
    known = ", ".join(MCU_DEFAULTS)
    parser.add_argument("--mcu", default="atmega328p", help=f"MCU (default pins known for: {known})")
    parser.add_argument("--freq", type=int, default=16_000_000, help="CPU clock in Hz")
    parser.add_argument("--edges", type=Path, help="write '<cycle> <pin> <0|1>' per edge here")
    parser.add_argument(
        "--clock", choices=["real", "max"], default="real", help="real time or as fast as possible"
    )
    parser.add_argument(
        "--pin",
        action="append",
        metavar="NAME=PORTBIT",
        help="watch this pin (repeatable; default: the MCU's TRIG and LED pins)",
    )
    return parser.parse_args(argv)


def parse_pins(specs: list[str]) -> dict[str, str]:
    """['TRIG=B1', ...] -> {'TRIG': 'B1'}; the harness checks the port and bit."""
    pins: dict[str, str] = {}
    for spec in specs:
        name, sep, where = spec.partition("=")
        if not sep or not name or not where:
            raise SystemExit(f"--pin {spec}: want NAME=PORTBIT, e.g. TRIG=B1")
        pins[name] = where
    return pins


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        harness = AvrHarness(
            args.elf,
            mcu=args.mcu,
            freq_hz=args.freq,
            clock=args.clock,
            pins=parse_pins(args.pin) if args.pin else None,
            edges_path=args.edges,
        )
    except RigdError as exc:
        log.error("%s", exc)
        return 2
    print(f"pty: {harness.port_path}", flush=True)
    try:
        while not stop.wait(0.2):
            if harness.returncode is not None:
                log.error("avr_harness stopped on its own (status %s)", harness.returncode)
                break
        harness.close()
    except RigdError as exc:
        log.error("%s", exc)
        return 1
    return 0 if stop.is_set() else 1


if __name__ == "__main__":
    sys.exit(main())
