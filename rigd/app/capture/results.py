"""What a capture reports: progress while it runs, telemetry snapshots, the final result."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from rigd.core.kinds import DeviceKind
from rigd.core.schema import SyncReport

DeviceState = Literal["ok", "failed", "reconnecting", "idle"]
SessionState = Literal["new", "starting", "capturing", "stopping", "done", "failed"]


#: What a take does after its last pulse, in order: the devices deliver up to the window end,
#: the writer empties its queue, the clocks are fitted and the take sealed. On a loaded host
#: these can take longer than the pulses did, so a progress display names them.
StopPhase = Literal["waiting for devices", "draining", "finalizing"]
Phase = Literal["capturing"] | StopPhase


@dataclass(slots=True)
class Progress:
    """What the pipeline reports while it runs (for progress bars and telemetry).

    `phase_done` / `phase_total` count the current phase in its own unit (pulses; devices
    that reached the window end; queued items written), None where it has none (finalizing).
    `phases` lists every phase entered so far, so a reader polling now and then misses none;
    `entered_with` has the count each stop phase started from (queued items, devices), so a reader
    that first sees a phase after it ended can still say what it counted."""

    pulses: int
    pulses_total: int
    frames: dict[str, int]
    events: dict[str, int]
    queue_depth: int
    phase: Phase = "capturing"
    phase_done: int | None = None
    phase_total: int | None = None
    phases: tuple[Phase, ...] = ("capturing",)
    entered_with: dict[str, int] = field(default_factory=dict)


@dataclass(slots=True)
class CaptureResult:
    path: Path
    report: SyncReport
    frames: dict[str, int]
    events: dict[str, int]
    bytes_written: int
    wall_s: float
    """Whole run: opening devices to closing the take."""
    capture_s: float
    """From the trigger's START until the writer had written everything."""
    flushes: int = 0
    flush_max_s: float = 0.0
    """The longest periodic flush (the writer thread's stall; `writer.fsync` lengthens it)."""
    end_reason: str = ""
    """Why the recording ended (also the take's `end_reason` attr)."""
    stop_signal: int | None = None
    """The signal that stopped the take (`run_capture(stop_signals=...)`), if one did."""
    window_start_us: int | None = None
    """The take's trigger window in rig us: first pulse - `writer.window_margin_us` ..."""
    window_end_us: int | None = None
    """... last pulse + one period (None: no pulse was seen)."""
    outside_window: dict[str, dict[str, int]] = field(default_factory=dict)
    """Per device, what it delivered outside the window and was not written
    (before / after, events or frames; triggers_before / triggers_after, trigger edges), and for
    an EVT-word sensor what is stored but outside it (stored_before / stored_after)."""

    @property
    def window_s(self) -> float | None:
        """Length of the trigger window, the span the counts and rates refer to."""
        if self.window_start_us is None or self.window_end_us is None:
            return None
        return (self.window_end_us - self.window_start_us) / 1e6

    def rates(self) -> dict[str, float]:
        """Frames or events per second of each device over the trigger window."""
        span = self.window_s
        if not span:
            return {}
        return {name: n / span for name, n in {**self.frames, **self.events}.items()}


@dataclass(slots=True)
class DeviceSnapshot:
    name: str
    kind: DeviceKind
    state: DeviceState
    total: int
    rate_hz: float
    lost: int
    reconnects: int
    queued: int
    last_data_age_s: float | None
    interval_jitter_us: float | None
    shed: int = 0
    """Events shed at the source while the host could not keep up (see `overload`)."""


@dataclass(slots=True)
class ActiveFault:
    code: str
    device: str | None
    message: str
    since_utc: str
    since_mono: float

    def line(self, lasted_s: float) -> str:
        """The fault as one line of the take's warnings."""
        where = f" on {self.device}" if self.device else ""
        return f"fault {self.code}{where} from {self.since_utc} for {lasted_s:.2f} s: {self.message}"


@dataclass(slots=True)
class SessionSnapshot:
    """A consistent-enough view of a running session for telemetry (cheap to take)."""

    state: SessionState
    path: Path
    elapsed_s: float
    pulses: int
    pulses_total: int | None
    queue_depth: int
    queue_capacity: int
    bytes_written: int
    devices: list[DeviceSnapshot]
    faults: list[ActiveFault]
    last_flush_age_s: float | None = None
    """Seconds since the take was last flushed (what a crash now would lose); None before
    the first flush."""
    flush_max_s: float = 0.0
    """The longest flush so far (the writer's stall; fsync waits for the disk)."""
    writer_busy: float = 0.0
    """Share of the last seconds the writer thread was busy: 1 - the headroom."""
    queue_bytes: int = 0
    queue_max_bytes: int = 0
