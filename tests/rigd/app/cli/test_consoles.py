"""Off a terminal the CLI neither wraps nor truncates: a URL, a path and a status table reach a
pipe or a log whole (rich assumed 80 columns and printed `trigg...`, split URLs mid-word)."""

from __future__ import annotations

import io
from typing import Any

from rich.console import Console

from rigd.app.commands.consoles import OFF_TERMINAL_WIDTH, stdout_console
from rigd.app.commands.service import print_status


def _status(name: str) -> dict[str, Any]:
    dev = {
        "name": name,
        "kind": "rgb_camera",
        "state": "capturing",
        "total": 123_456,
        "rate_hz": 29.97,
        "lost": 0,
        "queued": 3,
        "reconnects": 0,
        "interval_jitter_us": 1.25,
    }
    return {
        "state": "capturing",
        "takes_completed": 2,
        "disk_free_bytes": 100e9,
        "disk_total_bytes": 500e9,
        "take": "/srv/rigd/takes/" + "a-very-long-take-name-" * 4 + ".h5",
        "take_elapsed_s": 12.5,
        "pulses": 375,
        "queue_depth": 4,
        "queue_capacity": 4096,
        "bytes_written": 3.2e9,
        "last_flush_age_s": 0.4,
        "flush_max_s": 0.05,
        "devices": [dev, {**dev, "name": "trigger_box_on_the_left_rack", "kind": "trigger"}],
        "faults": [],
        "last_take": None,
    }


def test_off_a_terminal_the_consoles_are_wide_and_do_not_wrap() -> None:
    out = stdout_console()  # pytest captures stdout: not a terminal
    assert not out.is_terminal
    assert out.width == OFF_TERMINAL_WIDTH
    assert out.soft_wrap


def test_status_table_keeps_every_cell_whole() -> None:
    buf = io.StringIO()
    console = Console(file=buf, width=OFF_TERMINAL_WIDTH, soft_wrap=True, force_terminal=False)
    doc = _status("rgb_camera_cam0_overhead_long_name")
    print_status(doc, console)
    text = buf.getvalue()
    assert "rgb_camera_cam0_overhead_long_name" in text
    assert "trigger_box_on_the_left_rack" in text
    assert doc["take"] in text  # the path on one line, not cut or wrapped
    assert "…" not in text
    assert "takes finalized since start: 2" in text
    assert max(len(line) for line in text.splitlines()) < 400  # a table as wide as its cells


def test_status_table_fits_an_80_column_terminal_whole() -> None:
    """On a terminal the table is as wide as the terminal lets it be: short words, light borders,
    large counts in M and k, so the default rig's table fits 80 columns without a cut cell."""
    doc = _status("cam0")
    doc["devices"][1]["name"] = "trigger"
    ev = {
        **doc["devices"][0],
        "name": "ev0",
        "kind": "event_sensor",
        "total": 123_456_789,
        "rate_hz": 24.95e6,
    }
    doc["devices"].append(ev)
    buf = io.StringIO()
    print_status(doc, Console(file=buf, width=80, force_terminal=False))
    text = buf.getvalue()
    assert "…" not in text
    lines = text.splitlines()
    assert any(line.split()[:3] == ["ev0", "events", "capturing"] and "24.95 M" in line for line in lines)
    assert any(line.split()[:2] == ["trigger", "trigger"] for line in lines)
    assert "jitter µs" in text


def test_status_names_every_other_host_of_a_multi_host_rig() -> None:
    doc = _status("cam0")
    doc["hosts"] = [
        {
            "name": "B",
            "endpoint": "tcp://10.0.0.2:5601",
            "reachable": True,
            "state": "capturing",
            "take": None,
            "devices": ["ev0"],
            "pulses": 370,
            "message": None,
        },
        {
            "name": "C",
            "endpoint": "tcp://10.0.0.3:5601",
            "reachable": False,
            "state": None,
            "take": None,
            "devices": ["ev1"],
            "pulses": 0,
            "message": "no answer for 12 s",
        },
    ]
    buf = io.StringIO()
    print_status(doc, Console(file=buf, width=OFF_TERMINAL_WIDTH, soft_wrap=True, force_terminal=False))
    lines = buf.getvalue().splitlines()
    assert "host B (tcp://10.0.0.2:5601): capturing, ev0, pulses 370" in lines
    assert "host C (tcp://10.0.0.3:5601): unreachable, ev1: no answer for 12 s" in lines
