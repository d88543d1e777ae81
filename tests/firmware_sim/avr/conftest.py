"""Builds the simavr harness and its test firmware once per session (`make -C
firmware/avr_harness`); skips when the toolchain or simavr's headers are missing, fails when
they are present and the build breaks."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from firmware_sim.avr.harness import BINARY_ENV, DEFAULT_BINARY, HARNESS_DIR

BUILD = HARNESS_DIR / "build"


@pytest.fixture(scope="session")
def avr_build() -> Path:
    """The build folder holding avr_harness and the testfw_*.elf firmware."""
    missing = [tool for tool in ("make", "cc", "avr-gcc") if shutil.which(tool) is None]
    if missing:
        pytest.skip(f"cannot build the simavr harness: {', '.join(missing)} not installed (gcc-avr, make)")
    if not Path("/usr/include/simavr/sim_avr.h").is_file():
        pytest.skip("cannot build the simavr harness: /usr/include/simavr/sim_avr.h missing (libsimavr-dev)")
    run = subprocess.run(["make", "-C", str(HARNESS_DIR)], capture_output=True, text=True)
    if run.returncode != 0:
        pytest.fail(f"make -C {HARNESS_DIR} failed:\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}")
    return BUILD


@pytest.fixture
def harness_env(avr_build: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The checkout's harness binary, whatever RIGD_AVR_HARNESS says outside the tests."""
    monkeypatch.delenv(BINARY_ENV, raising=False)
    assert os.access(DEFAULT_BINARY, os.X_OK)
    return avr_build


@pytest.fixture
def echo_elf(harness_env: Path) -> Path:
    """UART echo at 1 Mbaud; OC1A toggles every 8000 cycles once 'S' arrives; INT0 -> PB5."""
    return harness_env / "testfw_echo_timer.elf"
