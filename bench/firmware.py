"""The trigger-box firmware's timing and resources, measured cycle by cycle under simavr, next
to the chip's limits.

    python -m bench.firmware [--pulses 2000] [--quick]

Builds the images (`make -C firmware/trigger_box`) and the harness, serves them with
`python -m firmware_sim.avr`, drives them with raw pyserial, and prints:

1. flash and RAM of every image against the chip (avr-size; usable flash excludes the
   Arduino bootloader, RAM for globals leaves 512 B of stack);
2. cycles spent in the Timer1 interrupts per pulse (the `_probe` build raises PB2 while its
   compare handler body runs; add ~40 cycles of entry, register saves and `reti`), against the
   cycles between two edges at 10 kHz;
3. edge placement: cycles from `16 * b_k` to the rising edge, worst over a run, at 1 kHz alone
   and at 1 kHz under a flood of commands at full baud, against one timer tick (8 cycles);
4. the highest rate whose pulse records all go out live (`DIAG?` records_dropped stays 0)
   at 1 Mbaud and at 115200, with the bytes per second the records need against the nominal
   line (simavr 1.6 sends a byte every 352 cycles under interrupt-driven transmit, 2.2x slower
   than the chip at 1 Mbaud: firmware/trigger_box/README.md);
5. the simulator's speed: simulated MHz per wall second, busy and idle.
"""

from __future__ import annotations

import argparse
import itertools
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from drivers.testing.trigger_protocol import RawPort, collect_run, host_line, pulses
from firmware_sim.testing.avr_box import CYCLES_PER_US, FirmwareProcess, build_firmware, build_harness

FLASH = {"atmega328p": (32256, 32768), "atmega2560": (253952, 262144)}
RAM = {"atmega328p": (1536, 2048), "atmega2560": (7680, 8192)}


def sizes(build: Path) -> None:
    print("\n## Flash and RAM (avr-size -B)\n")
    print("| image | flash used | usable (chip) | RAM globals | allowed (SRAM) |")
    print("|---|---|---|---|---|")
    for elf in sorted(build.glob("*.elf")):
        out = subprocess.run(["avr-size", "-B", str(elf)], capture_output=True, text=True, check=True)
        text, data, bss = (int(v) for v in out.stdout.splitlines()[1].split()[:3])
        mcu = "atmega2560" if "2560" in elf.name else "atmega328p"
        fu, fc = FLASH[mcu]
        ru, rc = RAM[mcu]
        print(
            f"| {elf.name} | {text + data} B ({100 * (text + data) / fu:.0f} %) | {fu} ({fc}) B "
            f"| {data + bss} B ({100 * (data + bss) / ru:.0f} %) | {ru} ({rc}) B |"
        )


def _run(port: RawPort, rate: str, width: int, n: int) -> tuple[int, list[str]]:
    port.cmd(f"RATE {rate}")
    port.cmd(f"WIDTH {width}")
    port.cmd("ARM")
    t0 = int(port.cmd(f"START {n}")[0].split()[2])
    return t0, collect_run(port, n, timeout=600.0)


def _diag(port: RawPort) -> dict[str, int]:
    return {k: int(v) for k, v in (f.split("=") for f in port.cmd("DIAG?")[0].split()[1:])}


def _serve(elf: Path, mcu: str, clock: str, tmp: Path, pins: list[str] | None = None) -> FirmwareProcess:
    return FirmwareProcess(
        elf, mcu=mcu, clock=clock, edges=tmp / f"edges-{time.monotonic_ns()}.txt", pins=pins
    )


def isr_cycles(build: Path, tmp: Path, n: int) -> None:
    box = _serve(
        build / "trigger_box_atmega328p_probe.elf", "atmega328p", "max", tmp, ["TRIG=B1", "PROBE=B2"]
    )
    port = RawPort(box.port, baudrate=1_000_000)
    try:
        port.sync()
        _run(port, "1000", 100, n)
        probe = box.wait_for_changes(2 * (2 * n), pin="PROBE")
        trig = box.wait_for_changes(2 * n + 1)
    finally:
        port.close()
        box.close()
    highs = [(a.cycle, b.cycle) for a, b in itertools.pairwise(probe) if a.value == 1 and b.value == 0]
    rises = [c.cycle for c in trig if c.value == 1]
    falls = [c.cycle for c in trig if c.value == 0 and c.cycle > rises[0]]
    rise_isr = [e - s for s, e in highs if _follows(rises, s)]
    fall_isr = [e - s for s, e in highs if _follows(falls, s)]
    print("\n## Timer1 interrupt cycles per pulse (probe build, 1 kHz, width 100 us)\n")
    print("| handler | median | max | budget |")
    print("|---|---|---|---|")
    for name, vals in (
        ("compare A after a rising edge", rise_isr),
        ("compare A after a falling edge", fall_isr),
    ):
        arr = np.array(vals)
        print(
            f"| {name} | {np.median(arr):.0f} | {arr.max()} "
            "| 1600 cycles between edges at 10 kHz, 20 us width |"
        )


def _follows(edges: list[int], start: int) -> bool:
    """The interrupt that began at `start` was the one after an edge of this list."""
    i = int(np.searchsorted(edges, start)) - 1
    return i >= 0 and start - edges[i] < 400


def placement(build: Path, tmp: Path, n: int) -> None:
    print("\n## Edge placement: cycles from 16 * b_k to the rising edge (one tick = 8 cycles)\n")
    print("| run | pulses | min | max | late edges (DIAG) |")
    print("|---|---|---|---|---|")
    for flood in (False, True):
        box = _serve(build / "trigger_box_atmega328p.elf", "atmega328p", "real", tmp)
        port = RawPort(box.port, baudrate=1_000_000)
        try:
            port.sync()
            port.cmd("RATE 1000")
            port.cmd("WIDTH 100")
            port.cmd("ARM")
            t0 = int(port.cmd(f"START {n}")[0].split()[2])
            if flood:
                lines = b"".join(host_line(b"PING #%d" % i) + b"X" * 80 + b"\n" for i in range(n * 4))
                port.send(lines)
            got: list[str] = []
            while f"END {n}" not in got:
                got.append(port.line(timeout=600.0))
            port.sync()
            diag = _diag(port)
        finally:
            port.close()
            box.close()
        rises = np.array([c.cycle for c in box.pin_changes() if c.value == 1][:n])
        b = t0 + np.round(np.arange(n) * 1000).astype(np.int64)
        late = rises - b * CYCLES_PER_US
        label = "1 kHz under a flood of PINGs and 80-byte lines at 1 Mbaud" if flood else "1 kHz"
        print(f"| {label} | {n} | {late.min()} | {late.max()} | {diag['late_edges']} |")


def live_rates(build: Path, tmp: Path, quick: bool) -> None:
    print("\n## Highest rate with every pulse record live (DIAG? records_dropped = 0)\n")
    print("| UART | rate | pulses | records dropped | P bytes/s the rate needs | of the nominal line |")
    print("|---|---|---|---|---|---|")
    sweeps = {
        ("", 1_000_000): [1000, 1250, 1500, 1750, 2000] if not quick else [1500, 2000],
        ("_115200", 117_647): [250, 300, 350, 400] if not quick else [300, 400],
    }
    for (variant, baud), rates in sweeps.items():
        for rate in rates:
            box = _serve(build / f"trigger_box_atmega328p{variant}.elf", "atmega328p", "max", tmp)
            port = RawPort(box.port, baudrate=baud)
            n = max(200, rate // 2)
            try:
                port.sync()
                _, run = _run(port, str(rate), 20, n)
                diag = _diag(port)
            finally:
                port.close()
                box.close()
            sent = [ln for ln in run if ln.startswith("P ")]
            framed = sum(len(ln) + 5 for ln in sent)  # '$', '*HH', '\n'
            per_s = framed / max(1, len(sent)) * rate
            use = per_s / (baud / 10)
            print(
                f"| {baud} | {rate} Hz | {n} | {diag['records_dropped']} | {per_s:,.0f} | {100 * use:.0f} % |"
            )


def sim_speed(build: Path, tmp: Path) -> None:
    print("\n## simavr speed (max clock)\n")
    print("| firmware doing | simulated s | wall s | simulated MHz |")
    print("|---|---|---|---|")
    for label, rate, width, n in (
        ("1 kHz pulses, records live", "1000", 100, 5000),
        ("30 Hz pulses", "30", 1000, 900),
    ):
        box = _serve(build / "trigger_box_atmega328p.elf", "atmega328p", "max", tmp)
        port = RawPort(box.port, baudrate=1_000_000)
        try:
            port.sync()
            t_wall = time.perf_counter()
            t0, run = _run(port, rate, width, n)
            wall = time.perf_counter() - t_wall
        finally:
            port.close()
            box.close()
        simulated = (pulses(run)[-1][1] - t0 + 20_000) / 1e6
        print(f"| {label} | {simulated:.2f} | {wall:.2f} | {simulated * 16 / wall:.0f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pulses", type=int, default=2000, help="pulses per timing run")
    ap.add_argument("--quick", action="store_true", help="fewer rates in the live-rate sweep")
    args = ap.parse_args()
    build = build_firmware()
    build_harness()
    print(f"# bench.firmware  {time.strftime('%Y-%m-%d %H:%M')}")
    sizes(build)
    with tempfile.TemporaryDirectory(prefix="rigd-fw-bench-") as tmp:
        isr_cycles(build, Path(tmp), args.pulses)
        placement(build, Path(tmp), args.pulses)
        live_rates(build, Path(tmp), args.quick)
        sim_speed(build, Path(tmp))


if __name__ == "__main__":
    main()
