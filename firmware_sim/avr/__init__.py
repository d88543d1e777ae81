"""Real trigger-box firmware (AVR ELF) under simavr: `AvrHarness` spawns the C harness in
firmware/avr_harness/, which serves the firmware's UART0 on a pseudo-terminal and reports pin
edges by AVR cycle. `python -m firmware_sim.avr` serves one firmware until killed."""

from firmware_sim.avr.harness import (
    BUILD_COMMAND,
    MCU_DEFAULTS,
    AvrHarness,
    ClockMode,
    Edge,
    McuDefaults,
    Step,
    find_binary,
    parse_edge_line,
)

__all__ = [
    "BUILD_COMMAND",
    "MCU_DEFAULTS",
    "AvrHarness",
    "ClockMode",
    "Edge",
    "McuDefaults",
    "Step",
    "find_binary",
    "parse_edge_line",
]
