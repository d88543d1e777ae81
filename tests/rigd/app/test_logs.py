"""rigd.app.logs: JSON lines, extra fields, exceptions, journald mode, rotation by rename."""

from __future__ import annotations

import io
import json
import logging
import os
import sys
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path

import pytest

from rigd.app import logs


@pytest.fixture(autouse=True)
def _restore_root_logger(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """setup_logging configures the root logger; leave it as pytest had it."""
    monkeypatch.delenv("JOURNAL_STREAM", raising=False)
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    yield
    for h in root.handlers:
        if h not in handlers:
            root.removeHandler(h)
            h.close()
    root.setLevel(level)
    logging.captureWarnings(False)


def _ours() -> list[logging.Handler]:
    return [h for h in logging.getLogger().handlers if getattr(h, "_rigd_handler", False)]


def _lines(path: Path) -> list[dict[str, object]]:
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


def test_json_lines_with_extra_fields(tmp_path: Path) -> None:
    log_file = tmp_path / "rigd.log"
    logs.setup_logging(logging.INFO, "json", log_file)
    log = logging.getLogger("rigd.test")
    log.info("take %s started with %d devices", "take-0001", 5, extra={"take": "take-0001", "device": "cam0"})
    log.debug("not at INFO")

    (doc,) = _lines(log_file)
    assert doc["msg"] == "take take-0001 started with 5 devices"
    assert doc["level"] == "INFO"
    assert doc["logger"] == "rigd.test"
    assert doc["thread"] == "MainThread"
    assert doc["take"] == "take-0001"
    assert doc["device"] == "cam0"
    assert "exc" not in doc
    ts = str(doc["ts"])
    assert ts.endswith("Z")
    assert len(ts.split(".")[1]) == len("123Z")  # milliseconds
    assert datetime.fromisoformat(ts).utcoffset() is not None


def test_json_exception_and_odd_extras(tmp_path: Path) -> None:
    log_file = tmp_path / "rigd.log"
    logs.setup_logging(logging.INFO, "json", log_file)
    log = logging.getLogger("rigd.test")
    try:
        raise RuntimeError("writer failed")
    except RuntimeError:
        log.exception("take aborted", extra={"take": "t1", "level": "shadow", "path": Path("/x")})

    (doc,) = _lines(log_file)
    assert doc["level"] == "ERROR"
    assert doc["extra_level"] == "shadow"  # does not overwrite the record's level
    assert doc["path"] == "/x"  # not JSON-serializable: str()
    assert "Traceback" in str(doc["exc"])
    assert "RuntimeError: writer failed" in str(doc["exc"])


def test_idempotent(tmp_path: Path) -> None:
    log_file = tmp_path / "rigd.log"
    logs.setup_logging(logging.INFO, "json", log_file)
    logs.setup_logging(logging.INFO, "json", log_file)
    assert len(_ours()) == 2  # stderr + file, once
    logging.getLogger("rigd.test").warning("once")
    assert len(_lines(log_file)) == 1

    logs.setup_logging(logging.DEBUG, "text")
    assert len(_ours()) == 1
    assert logging.getLogger().level == logging.DEBUG


def test_rotated_file_is_reopened(tmp_path: Path) -> None:
    """logrotate renames rigd.log; the next record goes to a new rigd.log (no copytruncate)."""
    log_file = tmp_path / "rigd.log"
    logs.setup_logging(logging.INFO, "json", log_file)
    log = logging.getLogger("rigd.test")
    log.info("before rotation")
    rotated = tmp_path / "rigd.log.1"
    os.rename(log_file, rotated)
    log.info("after rotation")

    assert [d["msg"] for d in _lines(rotated)] == ["before rotation"]
    assert [d["msg"] for d in _lines(log_file)] == ["after rotation"]


def test_text_format_has_timestamp_and_extras(monkeypatch: pytest.MonkeyPatch) -> None:
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    logs.setup_logging(logging.INFO, "text")
    logging.getLogger("rigd.test").warning("disk low", extra={"take": "t2"})
    line = stream.getvalue().strip()
    ts, rest = line.split(" ", 1)
    assert ts.endswith("Z")
    assert rest == "WARNING rigd.test: disk low [take=t2]"


def test_journal_text_has_no_timestamp_but_a_priority(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With stderr being the journal stream, journald adds the time and reads `<N>` as priority."""
    with open(tmp_path / "journal", "w+", encoding="utf-8") as fake_journal:
        st = os.fstat(fake_journal.fileno())
        monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
        monkeypatch.setattr(sys, "stderr", fake_journal)
        assert logs.stderr_is_journal()
        logs.setup_logging(logging.INFO, "text")
        logging.getLogger("rigd.test").error("trigger silent")
        logging.getLogger("rigd.test").info("idle")
        fake_journal.flush()
    lines = (tmp_path / "journal").read_text(encoding="utf-8").splitlines()
    assert lines == ["<3>ERROR rigd.test: trigger silent", "<6>INFO rigd.test: idle"]


def test_journal_stream_of_another_file_is_ignored(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """JOURNAL_STREAM inherited from a parent whose stderr was the journal: not ours."""
    other = tmp_path / "other"
    other.write_text("")
    st = os.stat(other)
    monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
    with open(tmp_path / "stderr", "w", encoding="utf-8") as f:
        monkeypatch.setattr(sys, "stderr", f)
        assert not logs.stderr_is_journal()
    monkeypatch.setenv("JOURNAL_STREAM", "garbage")
    assert not logs.stderr_is_journal()


def test_unknown_format() -> None:
    with pytest.raises(ValueError, match="unknown log format"):
        logs.setup_logging(logging.INFO, "xml")  # type: ignore[arg-type]


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _out(stream: io.StringIO) -> list[str]:
    return stream.getvalue().splitlines()


def test_repeated_warnings_are_one_line_and_a_summary() -> None:
    """A camera dropping a frame per pulse: one line, then a count with the first and last."""
    stream, clock = io.StringIO(), _Clock()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logging.Formatter("%(levelname)s %(message)s"))
    handler.addFilter(logs.RepeatFilter(handler, window_s=10.0, clock=clock))
    log = logging.getLogger("test.repeats")
    log.propagate = False
    log.addHandler(handler)
    log.setLevel(logging.DEBUG)
    try:
        for i in range(300):  # 300 drops in 9.97 s: one window
            clock.t = i / 30
            log.warning("camera %s: frame buffer full, frame %d dropped", "cam1", i)
        log.error("an error always gets through (%d)", 1)
        log.error("an error always gets through (%d)", 2)
        assert _out(stream) == [
            "WARNING camera cam1: frame buffer full, frame 0 dropped",
            "ERROR an error always gets through (1)",
            "ERROR an error always gets through (2)",
        ]
        clock.t = 10.5  # the window is over: the next record of any kind brings out the summary
        log.info("something else")
        lines = _out(stream)
        assert lines[3] == (
            "WARNING 299 more like this in 10 s, not shown: first 'camera cam1: frame buffer full, "
            "frame 1 dropped', last 'camera cam1: frame buffer full, frame 299 dropped'"
        )
        assert lines[4] == "INFO something else"
        log.warning("camera %s: frame buffer full, frame %d dropped", "cam1", 400)  # a new window
        log.warning("camera %s: frame buffer full, frame %d dropped", "cam1", 401)
        assert _out(stream)[5:] == ["WARNING camera cam1: frame buffer full, frame 400 dropped"]
        handler.filters[0].flush()  # type: ignore[union-attr]
        assert _out(stream)[6].startswith("WARNING 1 more like this in 0 s, not shown: first 'camera cam1")
    finally:
        log.removeHandler(handler)


def test_setup_logging_aggregates_repeats(tmp_path: Path) -> None:
    logs.setup_logging(logging.INFO, "text", tmp_path / "rigd.log")
    log = logging.getLogger("test.setup.repeats")
    for i in range(50):
        log.warning("reader is behind, queue full: %d item(s) dropped so far", i)
    text = (tmp_path / "rigd.log").read_text()
    assert text.count("reader is behind") == 1
