"""Logging setup for the CLI and the daemon: text for people, JSON lines for machines.

JSON lines carry the fields a caller passes with `extra=` (take, device, ...) as top-level
keys, so a log shipper can filter a take's records without parsing messages. The file handler
is a WatchedFileHandler: logrotate renames the file and the next record reopens the path, so
no copytruncate (which loses lines) and no SIGHUP handling are needed.

Under systemd (stderr connected to the journal, see $JOURNAL_STREAM) text lines carry no
timestamp, since journald stamps each line, and every line starts with a syslog `<N>`
priority prefix, which journald strips and turns into the entry's priority (systemd's
SyslogLevelPrefix=, on by default), so `journalctl -p warning` works.
"""

from __future__ import annotations

import atexit
import json
import logging
import logging.handlers
import os
import sys
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

LogFormat = Literal["text", "json"]

#: Attributes every LogRecord has; anything else on a record came from `extra=`.
_RECORD_ATTRS = frozenset(logging.LogRecord("", 0, "", 0, "", None, None).__dict__) | {
    "message",
    "asctime",
    "taskName",  # Python 3.12+
}
#: Marks handlers installed here, so a second setup_logging() replaces them instead of adding more.
_OURS = "_rigd_handler"

_SYSLOG_PRIORITY = {
    logging.CRITICAL: 2,
    logging.ERROR: 3,
    logging.WARNING: 4,
    logging.INFO: 6,
    logging.DEBUG: 7,
}


def _utc_iso(created: float) -> str:
    """UTC ISO-8601 with milliseconds and a `Z`, the form take files and telemetry use."""
    return datetime.fromtimestamp(created, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _extras(record: logging.LogRecord) -> dict[str, Any]:
    return {k: v for k, v in record.__dict__.items() if k not in _RECORD_ATTRS and not k.startswith("_")}


def _syslog_prefix(levelno: int) -> str:
    for threshold in (logging.CRITICAL, logging.ERROR, logging.WARNING, logging.INFO):
        if levelno >= threshold:
            return f"<{_SYSLOG_PRIORITY[threshold]}>"
    return "<7>"


class JsonFormatter(logging.Formatter):
    """One JSON object per line: ts, level, logger, msg, thread, the `extra=` fields, exc."""

    def __init__(self, syslog_prefix: bool = False) -> None:
        super().__init__()
        self._prefix = syslog_prefix

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, Any] = {
            "ts": _utc_iso(record.created),
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
            "thread": record.threadName,
        }
        for key, value in _extras(record).items():
            # An extra named like one of ours must not overwrite it, nor be dropped.
            doc[key if key not in doc else f"extra_{key}"] = value
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        elif record.exc_text:
            doc["exc"] = record.exc_text
        if record.stack_info:
            doc["stack"] = self.formatStack(record.stack_info)
        line = json.dumps(doc, default=str, ensure_ascii=False)
        return _syslog_prefix(record.levelno) + line if self._prefix else line


class TextFormatter(logging.Formatter):
    """`TS LEVEL logger: message [key=value ...]`; without TS (and with a priority prefix)
    for the journal."""

    def __init__(self, journal: bool = False) -> None:
        super().__init__()
        self._journal = journal

    def format(self, record: logging.LogRecord) -> str:
        line = f"{record.levelname} {record.name}: {record.getMessage()}"
        extras = _extras(record)
        if extras:
            line += " [" + " ".join(f"{k}={v}" for k, v in extras.items()) + "]"
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        elif record.exc_text:
            line += "\n" + record.exc_text
        if record.stack_info:
            line += "\n" + self.formatStack(record.stack_info)
        if self._journal:
            return _syslog_prefix(record.levelno) + line
        return f"{_utc_iso(record.created)} {line}"


def stderr_is_journal() -> bool:
    """True when stderr is the journal stream systemd set up for this service.

    $JOURNAL_STREAM is inherited by children whose stderr may point elsewhere, so compare its
    device:inode with stderr's, as systemd.exec(5) says to.
    """
    value = os.environ.get("JOURNAL_STREAM")
    if not value:
        return False
    try:
        dev, ino = (int(x) for x in value.split(":", 1))
        st = os.fstat(sys.stderr.fileno())
    except (ValueError, OSError, AttributeError) as exc:
        # AttributeError/OSError (io.UnsupportedOperation): stderr replaced by a non-file stream.
        logging.getLogger(__name__).debug("JOURNAL_STREAM=%r not usable: %s", value, exc)
        return False
    return (st.st_dev, st.st_ino) == (dev, ino)


#: Identical warnings (same logger, level and message template) pass once per this many seconds.
REPEAT_WINDOW_S = 10.0


class RepeatFilter(logging.Filter):
    """Lets a message template through once per window and counts the rest, so a device that
    drops a frame every 33 ms writes one line and a summary, not thirty a second.

    Records at ERROR and above always pass. When a template's window has passed, the next
    record of any kind first brings out a summary of what was held back: how many, over how
    long, and the first and last of them (their arguments give the range, e.g. frame numbers).
    `flush` brings out what is pending (at exit; tests)."""

    def __init__(
        self,
        handler: logging.Handler,
        window_s: float = REPEAT_WINDOW_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__()
        self._handler = handler
        self._window_s = window_s
        self._clock = clock
        self._lock = threading.Lock()
        self._seen: dict[tuple[str, int, str], list[Any]] = {}
        """key -> [window start, count held back, first held record, last held record]"""
        self._emitting = False

    def filter(self, record: logging.LogRecord) -> bool:
        if self._emitting:
            return True  # our own summary
        now = self._clock()
        self._emit_summaries(now, expired_only=True)
        if record.levelno >= logging.ERROR:
            return True
        key = (record.name, record.levelno, str(record.msg))
        with self._lock:
            slot = self._seen.get(key)
            if slot is None or now - slot[0] >= self._window_s:
                self._seen[key] = [now, 0, None, None]
                return True
            slot[1] += 1
            if slot[2] is None:
                slot[2] = record
            slot[3] = record
            return False

    def flush(self) -> None:
        """Bring out every pending summary now."""
        self._emit_summaries(self._clock(), expired_only=False)

    def _emit_summaries(self, now: float, *, expired_only: bool) -> None:
        with self._lock:
            due = [
                (key, slot)
                for key, slot in self._seen.items()
                if slot[1] and (not expired_only or now - slot[0] >= self._window_s)
            ]
            for key, _ in due:
                del self._seen[key]
        for _, (start, count, first, last) in due:
            self._summary(count, now - start, first, last)

    def _summary(self, count: int, span_s: float, first: logging.LogRecord, last: logging.LogRecord) -> None:
        text = f"{count} more like this in {span_s:.0f} s, not shown: first {first.getMessage()!r}"
        if count > 1:
            text += f", last {last.getMessage()!r}"
        stream = getattr(self._handler, "stream", None)
        if stream is not None and getattr(stream, "closed", False):
            return  # the handler was closed under us (someone else's teardown): nowhere to write
        rec = logging.LogRecord(last.name, last.levelno, last.pathname, last.lineno, text, None, None)
        rec.created = last.created
        self._emitting = True
        try:
            self._handler.handle(rec)
        finally:
            self._emitting = False


def setup_logging(level: int, fmt: LogFormat = "text", log_file: Path | None = None) -> None:
    """Configure the root logger: stderr, plus `log_file` when given, both in `fmt`.

    Idempotent: handlers from an earlier call are closed and replaced; handlers installed by
    others (pytest's caplog, an embedding application) are left alone. Python warnings are
    routed into logging so they reach the journal/file too.
    """
    if fmt not in ("text", "json"):
        raise ValueError(f"unknown log format {fmt!r} (use 'text' or 'json')")
    root = logging.getLogger()
    for handler in [h for h in root.handlers if getattr(h, _OURS, False)]:
        root.removeHandler(handler)
        for f in handler.filters:
            if isinstance(f, RepeatFilter):  # what it held back is written before it goes
                f.flush()
                atexit.unregister(f.flush)
        handler.close()

    journal = stderr_is_journal()
    console = logging.StreamHandler(sys.stderr)
    console.setFormatter(JsonFormatter(syslog_prefix=journal) if fmt == "json" else TextFormatter(journal))
    handlers: list[logging.Handler] = [console]
    if log_file is not None:
        log_file.parent.mkdir(parents=True, exist_ok=True)
        file_handler = logging.handlers.WatchedFileHandler(log_file, encoding="utf-8")
        file_handler.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
        handlers.append(file_handler)
    for handler in handlers:
        setattr(handler, _OURS, True)
        repeats = RepeatFilter(handler)
        handler.addFilter(repeats)
        atexit.register(repeats.flush)
        root.addHandler(handler)
    root.setLevel(level)
    logging.captureWarnings(True)
