"""Every fault the capture can post is one the daemon's protocol carries and the console words.

An `overload` fault once broke the daemon's telemetry (the protocol's list of codes lacked it), so
`rigd status` and the console failed exactly when the host was overloaded."""

from __future__ import annotations

import re
from pathlib import Path

from rigd.app.capture.faults import FaultBoard
from rigd.app.service.rig_slot import fault
from rigd.core.fault_codes import FAULT_CODES

DASHBOARD = Path(__file__).resolve().parents[4] / "rigd" / "app" / "console" / "static" / "dashboard.js"


def test_every_fault_code_goes_through_the_protocol() -> None:
    board = FaultBoard()
    for code in FAULT_CODES:
        board.set(code, "ev0", f"{code} now")  # type: ignore[arg-type]
    faults = [fault(f) for f in board.active()]
    assert sorted(f.code for f in faults) == sorted(FAULT_CODES)
    assert "overload" in FAULT_CODES


def test_the_console_has_words_for_every_fault_code() -> None:
    text = DASHBOARD.read_text()
    block = text[text.index("const FAULT_WORDS = {") : text.index("};", text.index("const FAULT_WORDS = {"))]
    keys = set(re.findall(r"^\s*(\w+):", block, flags=re.MULTILINE))
    assert keys == set(FAULT_CODES)
