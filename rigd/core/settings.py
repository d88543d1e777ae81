"""Settings models shared by the drivers, the rig config and the take writer.

They are read from rig config files, so they are strict (pydantic strict mode: `true` is not
1 Hz, "30" is not a number, 1.5 is not an integer) and every number is bounded by what a device
or a take can do: a file cannot ask for a 1e30-event chunk or an infinite timeout.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

#: Strict, finite, no extra keys: what every settings model read from a file is.
STRICT = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


class CameraSettings(BaseModel):
    """Acquisition settings of a camera; backends reject what they cannot do."""

    model_config = STRICT

    trigger_mode: Literal["hardware", "free_run"] = "hardware"
    exposure_us: int = Field(10_000, gt=0, le=10_000_000, description="Exposure time in microseconds.")
    gain_db: float = Field(0.0, ge=0.0, le=60.0)
    pixel_format: Literal["mono8", "rgb8", "bayer_rg8"] | None = Field(
        None,
        description="None keeps the camera's default format. bayer_rg8: the raw RGGB mosaic, "
        "1 byte/pixel, stored as sent and demosaiced on read (rigd.core.pixels).",
    )
    free_run_fps: float = Field(30.0, gt=0.0, le=10_000.0)


#: A sensor coordinate, strict inside the ROI tuple (a list in a file).
_Coord = Annotated[int, Field(strict=True, ge=0, le=65535)]


class EventSensorSettings(BaseModel):
    """Acquisition settings of an event sensor."""

    model_config = STRICT

    trigger_in_channel: int = Field(0, ge=0, le=255)
    enable_trigger_in: bool = True
    sync_mode: Literal["standalone", "master", "slave"] = Field(
        "standalone",
        description="Camera synchronization: a slave takes its clock from the master over the sync cable.",
    )
    sync_master: str | None = Field(
        None, description="For a slave: the rig name of the event sensor whose clock it shares."
    )
    biases: dict[str, Annotated[int, Field(ge=-(2**31), le=2**31 - 1)]] = Field(
        default_factory=dict, description="Sensor biases by name, e.g. bias_diff_on."
    )
    roi: tuple[_Coord, _Coord, _Coord, _Coord] | None = Field(
        None, strict=False, description="(x, y, width, height) window, or None (a list in a file)."
    )
    erc_rate_ev_s: float | None = Field(
        None, gt=0, le=1e10, description="Event rate controller limit, events/s; dropped events are counted."
    )


class TriggerSettings(BaseModel):
    """What the trigger source should emit."""

    model_config = STRICT

    rate_hz: float = Field(30.0, gt=0.0, le=10_000.0)
    pulse_width_us: int = Field(1000, gt=0, le=1_000_000)


class WriterConfig(BaseModel):
    """How takes are written; compression is a measured choice (see bench/)."""

    model_config = STRICT

    event_compression: Literal["none", "lz4", "zstd", "gzip"] = "lz4"
    frame_compression: Literal["none", "lz4", "zstd", "gzip"] = "none"
    event_storage: Literal["evt_words", "columns"] = Field(
        "evt_words",
        description="How event sensors that send an EVT stream are stored: their words as sent "
        "(Zstd, decoded on read; decision 0021) or decoded x/y/p/t columns. Sensors whose "
        "packets carry no words (DAT replays) are stored as columns either way.",
    )
    event_chunk: int = Field(
        1 << 15,
        ge=1024,
        le=1 << 22,
        description="Events per HDF5 chunk of x, y, p, t: a random 50 ms window decodes about "
        "its own events plus one chunk per column (bench.random_windows, decision 0012).",
    )
    queue_items: int = Field(
        4096,
        ge=4,
        le=1 << 20,
        description="Bound of the acquisition -> writer queue in items (queue_mb bounds its memory).",
    )
    queue_mb: int = Field(
        1024,
        ge=16,
        le=1 << 20,
        description="Bound of the writer queue's memory: what a burst above the writer's speed can fill "
        "before event slices are shed (bench.capacity --parts device: the burst level).",
    )
    uncompressed_when_behind: float = Field(
        0.25,
        ge=0.0,
        le=1.0,
        description="Writer queue fill (fraction of its bounds) from which EVT words are stored "
        "uncompressed until the queue is back under half of it: the writer catches up by "
        "spending disk (2.81 instead of 2.37 B/ev on the real Gen4.1 stream) before any event "
        "slice is shed. 0: always compress.",
    )
    overload_max_lag_s: float = Field(
        5.0,
        gt=0,
        le=600.0,
        description="An event packet that waited longer than this since it reached the host is shed "
        "(overload, like a sensor's event-rate controller), so the take never lags further behind.",
    )
    queue_put_timeout_s: float = Field(
        2.0,
        gt=0,
        le=600.0,
        description="How long an acquisition thread waits on a full queue before counting a drop.",
    )
    flush_interval_s: float = Field(
        1.0,
        ge=0.05,
        le=60.0,
        description="Seconds between flushes of the take; a crash loses at most this much data.",
    )
    fsync: bool = Field(
        True,
        description="fsync the take at every flush and on close: what was flushed survives a power "
        "cut or kernel crash too, not only a killed process; costs writer time (bench.capture_throughput).",
    )
    disk_reserve_mb: int = Field(
        1024,
        ge=0,
        le=10_000_000,
        description="A take does not start, and a running one stops cleanly, below this much free disk.",
    )
    disk_ballast_mb: int = Field(
        64,
        ge=0,
        le=65_536,
        description="Disk space held while a take runs and freed if the disk fills anyway, so the "
        "take can still be closed.",
    )
    window_margin_us: int | None = Field(
        None,
        ge=0,
        le=10_000_000,
        description="How far before the first trigger pulse a take starts (rig us); None = one trigger "
        "period, so the first frame has the same span of events before it as every later frame "
        "(event-based reconstruction of frame 0). The take ends one period after its last pulse.",
    )
    stop_backlog_s: float = Field(
        2.0,
        gt=0,
        le=600.0,
        description="At the end of a take: how long to wait for the devices to deliver up to the end "
        "of the trigger window before stopping them, and again to read what they still hold after "
        "the stop; what is not delivered by then is recorded in the take's losses.",
    )
    window_hold_s: float = Field(
        5.0,
        gt=0,
        le=600.0,
        description="How long an event sensor's data is held until its first trigger edge places the "
        "take's window in its clock; without an edge by then its window is applied by host time.",
    )
