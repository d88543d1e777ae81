"""Fixtures for the trigger-box firmware: the images built with `make` (Debian's gcc-avr) and
run under simavr through `python -m firmware_sim.avr`, exactly as docs/hardware.md shows."""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from firmware_sim.testing.avr_box import FirmwareProcess, build_firmware, build_harness

REPO = Path(__file__).resolve().parents[2]
#: CI sets it: a missing toolchain is a failure there, not a skip.
REQUIRED = os.environ.get("RIGD_REQUIRE_FIRMWARE") == "1"


def _missing(why: str) -> None:
    if REQUIRED:
        pytest.fail(f"{why} (RIGD_REQUIRE_FIRMWARE=1)")
    pytest.skip(why)


@pytest.fixture(scope="session")
def firmware_build() -> Path:
    """`make -C firmware/trigger_box`: every image, or a skip naming the missing toolchain."""
    if shutil.which("avr-gcc") is None:
        _missing("avr-gcc not installed (apt-get install gcc-avr avr-libc binutils-avr)")
    try:
        return build_firmware()
    except subprocess.CalledProcessError as exc:
        pytest.fail(f"make -C firmware/trigger_box failed:\n{exc.stdout}\n{exc.stderr}")


@pytest.fixture(scope="session")
def harness_binary() -> Path:
    if not Path("/usr/include/simavr/sim_avr.h").exists():
        _missing("simavr headers not installed (apt-get install simavr libsimavr-dev libelf-dev)")
    try:
        return build_harness()
    except subprocess.CalledProcessError as exc:
        pytest.fail(f"make -C firmware/avr_harness failed:\n{exc.stdout}\n{exc.stderr}")


@pytest.fixture
def serve(firmware_build: Path, harness_binary: Path, tmp_path: Path) -> Iterator[type[FirmwareProcess]]:
    """Start `python -m firmware_sim.avr` for an image; every process started is stopped."""
    started: list[FirmwareProcess] = []

    class Serve(FirmwareProcess):
        def __init__(self, mcu: str = "atmega328p", *, variant: str = "", clock: str = "real") -> None:
            elf = firmware_build / f"trigger_box_{mcu}{variant}.elf"
            super().__init__(elf, mcu=mcu, clock=clock, edges=tmp_path / f"edges-{len(started)}.txt")
            started.append(self)

    yield Serve
    for proc in started:
        proc.close()
