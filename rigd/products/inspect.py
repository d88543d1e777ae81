"""Take inspection for people: a validated summary and a contact sheet of frames and events."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, Field
from rich.console import RenderableType
from rich.markup import escape
from rich.table import Table

from rigd.core.errors import TakeError, TakeFormatError
from rigd.core.extras import require
from rigd.products.loss_times import loss_lines
from rigd.take.reader import Take, TakeSummary
from rigd.take.recover import needs_recovery
from rigd.take.validate import validate_take

log = logging.getLogger(__name__)

#: Width the contact sheet is kept under, and the height of one row of tiles.
_MAX_SHEET_WIDTH = 2000
_MAX_TILE_HEIGHT = 270
#: Events accumulated into one event image.
_EVENT_WINDOW_US = 10_000
_LABEL_BAR = 18


class StoredCalibration(BaseModel):
    """A device's calibration stored in the take (`rigd calibrate ... --into-take`), in brief."""

    model: str | None = None
    rms_px: float | None = None
    K: list[list[float]] | None = None
    image_size: list[int] | None = None
    in_rig_frame: bool = Field(False, description="A pose in the rig frame is stored too.")
    source: str = ""


class InspectedSummary(TakeSummary):
    """The take's summary with each loss said in seconds of the take (rigd.products.loss_times), the
    records in `losses` keeping their device times, and the calibrations stored in the take."""

    loss_lines: list[str] = Field(
        default_factory=list,
        description="Each loss record's reason with its times in seconds of the take, capped to its window.",
    )
    calibration: dict[str, StoredCalibration] = Field(
        default_factory=dict, description="Calibrations stored in the take, by device (/calibration)."
    )


def _stored_calibration(stored: dict[str, dict[str, Any]] | None) -> dict[str, StoredCalibration]:
    out: dict[str, StoredCalibration] = {}
    for device, entry in (stored or {}).items():
        result = entry.get("result") or {}
        intr = result.get("intrinsics") or {}
        out[device] = StoredCalibration(
            model=intr.get("model"),
            rms_px=intr.get("rms_px"),
            K=None if "K" not in entry else np.asarray(entry["K"], np.float64).tolist(),
            image_size=None if "image_size" not in entry else [int(v) for v in entry["image_size"]],
            in_rig_frame="R" in entry,
            source=str(result.get("source") or ""),
        )
    return out


def summarize(path: str | Path) -> InspectedSummary:
    """Summary of a take with its validation problems; one that cannot be opened, or whose data
    HDF5 refuses to read (a failed write left it damaged), raises TakeError in one line."""
    problems = validate_take(path)
    try:
        with Take(path) as take:
            plain = take.summary()
            summary = InspectedSummary(
                **dict(plain),
                loss_lines=loss_lines(take.sync_report, plain.losses),
                calibration=_stored_calibration(take.calibration),
            )
    except (OSError, RuntimeError, KeyError) as exc:  # h5py's errors for a damaged file
        hdf5 = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise TakeFormatError(
            f"{path}: damaged, its data cannot be read (HDF5: {hdf5}); `rigd recover {path}` seals "
            "what can be read and says what it cannot"
        ) from exc
    summary.problems = problems
    if problems:  # what the file says it holds is not to be trusted: damaged, before anything else
        summary.verdict = "damaged"
        summary.verdict_reasons = [*problems, *summary.verdict_reasons]
    return summary


def status_hint(summary: TakeSummary) -> str | None:
    """One line for a take that is not complete (`rigd inspect` exits 1 on it): what to run to
    seal it, or why it failed; None for a complete take."""
    path, status = summary.path, summary.status
    if status == "complete":
        return None
    if status == "recording":
        return (
            f"{path}: take is still recording (its writer died or is still running): "
            f"run `rigd recover {path}` to seal it"
        )
    if status == "failed":
        why = summary.failure_reason or "no reason recorded"
        recorded = (
            summary.pulses
            or any(c.frames for c in summary.cameras.values())
            or any(s.events or s.triggers for s in summary.event_sensors.values())
        )
        if not recorded:
            # Stopped before its first flush: `rigd recover` has nothing to bring back.
            return f"{path}: take failed ({why}) before anything was recorded in it: nothing to recover"
        if needs_recovery(path):
            return (
                f"{path}: take failed ({why}) and was never sealed: free space and run `rigd recover {path}`"
            )
        return f"{path}: take failed: {why}"
    return f"{path}: take status {status!r} is not complete"


#: What a missing value shows as in a table.
MISSING = "—"


def _cell(value: object, fmt: str = "{}") -> str:
    return MISSING if value is None else fmt.format(value)


def clock_label(summary: TakeSummary, pulses: int | None = None) -> str:
    """What the take's times are in, for people: the rig timebase only when a trigger box gave
    it one; a take finalized without pulses (a converted recording, a simulated one) keeps each
    device's own clock under an identity map, and an unsealed take is still in device time."""
    if summary.time_domain != "rig":
        return "device clocks (not yet mapped to the rig)"
    if (summary.pulses if pulses is None else pulses) == 0:
        return "the recording's own clock (no trigger box)"
    return "rig time (trigger box clock)"


#: How each verdict's first line looks (rich markup).
_VERDICT_STYLE = {
    "complete": "bold green",
    "degraded": "bold yellow",
    "failed": "bold red",
    "unfinished": "bold red",
    "damaged": "bold red",
}


def verdict_markup(summary: TakeSummary) -> str:
    """The summary's first line: the verdict and why (rich markup; the reasons are escaped)."""
    line = summary.verdict_line()
    head, sep, rest = line.partition(" — ")
    return f"[{_VERDICT_STYLE[summary.verdict]}]verdict: {escape(head)}[/]{sep}{escape(rest)}"


def summary_renderables(summary: TakeSummary) -> list[RenderableType]:
    """The summary `rigd capture` and `rigd inspect` print: the verdict first (did the take keep
    everything), a status line, a table per device kind present, and losses, warnings and
    problems as a table and sentences."""
    parts: list[RenderableType] = [
        verdict_markup(summary),
        f"status: {summary.status}   schema {summary.schema_version}   times: {clock_label(summary)}",
    ]
    if summary.end_reason:
        parts.append(f"ended: {summary.end_reason}")
    if summary.recovered_utc:
        parts.append(
            f"recovered after a crash at {summary.recovered_utc} (data after the last flush is lost)"
        )
    if summary.failure_reason:
        parts.append(f"failed: {summary.failure_reason}")
    for p in summary.parts or ():
        role = ", coordinator" if p.coordinator else ""
        why = f": {p.reason}" if p.reason else ""
        parts.append(f"part {p.host} ({', '.join(p.devices)}{role}): {p.file or 'no file'} {p.status}{why}")
    if summary.cameras:
        cams = Table(
            "camera", "frames", "fps", "shape", "format", "dropped", "missing pulses", "sync rms µs", "max µs"
        )
        cams.columns[3].no_wrap = True
        for name, c in summary.cameras.items():
            cams.add_row(
                name,
                f"{c.frames:,}",
                _cell(c.fps, "{:.2f}"),
                "x".join(str(v) for v in c.shape) or MISSING,
                c.pixel_format,
                _cell(c.dropped_frames),
                _cell(c.missing_pulses),
                _cell(c.sync_rms_us, "{:.2f}"),
                _cell(c.sync_max_us, "{:.2f}"),
            )
        parts.append(cams)
    if summary.event_sensors:
        sens = Table(
            "sensor", "events", "Mev/s", "size", "triggers", "missing pulses", "sync rms µs", "max µs"
        )
        for name, e in summary.event_sensors.items():
            sens.add_row(
                name,
                f"{e.events:,}",
                MISSING if e.event_rate_hz is None else f"{e.event_rate_hz / 1e6:.3f}",
                f"{e.width}x{e.height}",
                f"{e.triggers:,}",
                _cell(e.missing_pulses),
                _cell(e.sync_rms_us, "{:.2f}"),
                _cell(e.sync_max_us, "{:.2f}"),
            )
        parts.append(sens)
    if not summary.cameras and not summary.event_sensors:
        parts.append("no cameras and no event sensors in this take")
    parts.append(_pulse_line(summary))
    if summary.losses:
        losses = Table("lost from", "what", "count", "why", title="losses", title_justify="left")
        losses.columns[3].overflow = "fold"
        lines = summary.loss_lines if isinstance(summary, InspectedSummary) else []
        for i, rec in enumerate(summary.losses):
            why = lines[i] if i < len(lines) else rec.reason
            losses.add_row(rec.device, rec.what, f"{rec.count:,}", escape(why))
        parts.append(losses)
    if isinstance(summary, InspectedSummary):
        parts.extend(_calibration_lines(summary.calibration))
    parts.extend(f"warning: {w}" for w in summary.warnings)
    parts.extend(f"problem: {p}" for p in summary.problems)
    return parts


def _calibration_lines(calibration: dict[str, StoredCalibration]) -> list[str]:
    """`calibration: cam0 k1k2, fx 501.2 fy 500.9 cx 319.4 cy 180.2, RMS 0.046 px, posed in the rig
    frame (calibrate rig ...)`, one per device; or that none is stored (what `rigd export` needs)."""
    if not calibration:
        return [
            "calibration: none stored (`rigd calibrate ... --into-take` stores one; `rigd export` needs it)"
        ]
    lines = []
    for device, c in calibration.items():
        parts = [c.model or "pose only"]
        if c.K is not None:
            (fx, _, cx), (_, fy, cy) = c.K[0], c.K[1]
            parts.append(f"fx {fx:.1f} fy {fy:.1f} cx {cx:.1f} cy {cy:.1f}")
        if c.rms_px is not None:
            parts.append(f"RMS {c.rms_px:.3f} px")
        if c.in_rig_frame:
            parts.append("posed in the rig frame")
        source = f" ({escape(c.source)})" if c.source else ""
        lines.append(f"calibration: {device} " + ", ".join(parts) + source)
    return lines


def _pulse_line(summary: TakeSummary) -> str:
    if summary.pulses == 0:
        return "trigger pulses: none (no trigger box)"
    line = f"trigger pulses: {summary.pulses:,}"
    unseen = summary.pulses_seen_by_no_device
    if unseen:
        shown = ", ".join(str(i) for i in unseen[:10]) + (", ..." if len(unseen) > 10 else "")
        line += f"; {len(unseen)} seen by no device ({shown})"
    return line


def _to_bgr8(img: NDArray[np.generic]) -> NDArray[np.uint8]:
    cv2 = require("cv2", "drawing thumbnails")
    a = np.asarray(img)
    if a.dtype != np.uint8:
        hi = float(np.percentile(a, 99.5)) if a.size else 1.0
        a = np.clip(a.astype(np.float32) * (255.0 / max(hi, 1.0)), 0, 255).astype(np.uint8)
    if a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 1):
        gray = a.reshape(a.shape[0], a.shape[1])
        return np.asarray(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR), dtype=np.uint8)
    # Frames are stored RGB (rgb8); OpenCV writes BGR.
    rgb = np.ascontiguousarray(a[:, :, :3])
    return np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), dtype=np.uint8)


def event_image(
    x: NDArray[np.uint16], y: NDArray[np.uint16], p: NDArray[np.int8], width: int, height: int
) -> NDArray[np.uint8]:
    """BGR image of event counts: ON red, OFF blue, the square root of the count over its 99th
    percentile, so a pixel with one event is half bright, not a dim speck (a 10 ms window of a
    sparse scene is mostly single events)."""
    n_px = width * height
    idx = y.astype(np.int64) * width + x.astype(np.int64)
    on = np.bincount(idx[p > 0], minlength=n_px)[:n_px]
    off = np.bincount(idx[p <= 0], minlength=n_px)[:n_px]
    nz = np.concatenate([on[on > 0], off[off > 0]])
    top = max(float(np.percentile(nz, 99)) if nz.size else 1.0, 1.0)
    img = np.zeros((height, width, 3), np.uint8)
    img[..., 2] = (255 * np.sqrt(np.minimum(on / top, 1.0))).astype(np.uint8).reshape(height, width)
    img[..., 0] = (255 * np.sqrt(np.minimum(off / top, 1.0))).astype(np.uint8).reshape(height, width)
    return img


def _max_pool(img: NDArray[np.uint8], k: int) -> NDArray[np.uint8]:
    """Each k x k block's brightest pixel: shrinking an event image this way keeps every event
    visible, where averaging (INTER_AREA) would dim sparse events to black."""
    h, w = img.shape[:2]
    hp, wp = -(-h // k) * k, -(-w // k) * k
    padded = np.zeros((hp, wp, *img.shape[2:]), img.dtype)
    padded[:h, :w] = img
    return np.asarray(padded.reshape(hp // k, k, wp // k, k, *img.shape[2:]).max(axis=(1, 3)), np.uint8)


def _tile(
    img: NDArray[np.uint8], width: int, height: int, label: str, events: bool = False
) -> NDArray[np.uint8]:
    """Fit img into width x height (letterboxed) under a label bar; an event image is shrunk by
    its blocks' maxima first (`_max_pool`)."""
    cv2 = require("cv2", "drawing thumbnails")
    h, w = img.shape[:2]
    s = min(width / w, height / h)
    if events and s < 0.5:
        img = _max_pool(img, int(1 / s))
        h, w = img.shape[:2]
        s = min(width / w, height / h)
    nw, nh = max(1, round(w * s)), max(1, round(h * s))
    small = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_NEAREST)
    out = np.zeros((height + _LABEL_BAR, width, 3), np.uint8)
    y0, x0 = _LABEL_BAR + (height - nh) // 2, (width - nw) // 2
    out[y0 : y0 + nh, x0 : x0 + nw] = small
    cv2.putText(out, label, (3, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


Span = tuple[int, int]


def _sample_span(cameras: list[Span], sensors: list[Span], rig: bool) -> Span:
    """The span the sheet's columns sample. On one timebase: where every device has data, else
    where every camera has frames (an event sensor's span can run past the last frame, and a
    column there would only repeat it; an event tile with no events says so). Without one
    timebase each row spreads over its own data, so all of it."""
    for spans in (cameras + sensors, cameras) if rig else ():
        if spans and (lo := max(s[0] for s in spans)) < (hi := min(s[1] for s in spans)):
            return lo, hi
    spans = cameras + sensors
    return min(s[0] for s in spans), max(s[1] for s in spans)


def write_thumbnails(path: str | Path, out_png: str | Path, n_frames: int = 4) -> Path:
    """Contact sheet: one row per camera (n frames spread over the take) and one per event
    sensor (10 ms event images at the same rig times). Returns the PNG path."""
    cv2 = require("cv2", "drawing thumbnails")
    if n_frames < 1:
        raise TakeError(f"n_frames must be >= 1, got {n_frames}")
    out = Path(out_png)
    with Take(path) as take:
        rig = take.time_domain == "rig"
        report = take.sync_report
        pulses = 0 if report is None else report.n_pulses
        domain = "rig" if rig and pulses else "own clock" if rig else "device"
        cam_spans: list[Span] = []
        for cam in take.cameras:
            ts = take.camera(cam).timestamps_us
            if ts.size:
                cam_spans.append((int(ts[0]), int(ts[-1])))
        ev_spans = [span for sen in take.event_sensors if (span := take.sensor(sen).span)]
        if not cam_spans and not ev_spans:
            raise TakeError(f"{take.path}: nothing to draw: no frames and no events")
        t0, t1 = _sample_span(cam_spans, ev_spans, rig)
        # n times evenly inside the span, away from the ragged start and end.
        times = np.linspace(t0, t1, n_frames + 2)[1:-1].astype(np.int64)
        tile_w = max(32, _MAX_SHEET_WIDTH // n_frames)
        shapes = [take.camera(c).shape for c in take.cameras] + [
            take.sensor(s).geometry[::-1] for s in take.event_sensors
        ]
        aspect = max(sh[0] / sh[1] for sh in shapes)
        tile_h = max(24, min(_MAX_TILE_HEIGHT, round(tile_w * aspect)))
        rows: list[NDArray[np.uint8]] = []
        for cam in take.cameras:
            fs = take.camera(cam)
            tiles = []
            for t in times:
                if len(fs) == 0:
                    tiles.append(_tile(np.zeros((8, 8, 3), np.uint8), tile_w, tile_h, f"{cam}: no frames"))
                    continue
                # Without rig time cameras cannot be aligned: spread over each one's own frames.
                k = fs.nearest(int(t)) if rig else int((t - t0) * (len(fs) - 1) // max(t1 - t0, 1))
                fr = fs[k]
                label = f"{cam} #{k} t={fr.t_exposure_start_us / 1e6:.3f}s ({domain})"
                tiles.append(_tile(_to_bgr8(fr.image), tile_w, tile_h, label))
            rows.append(np.hstack(tiles))
        for sen in take.event_sensors:
            series = take.sensor(sen)
            width, height = series.geometry
            tiles = []
            for t in times:
                if rig:
                    ev = series.events(int(t) - _EVENT_WINDOW_US // 2, int(t) + _EVENT_WINDOW_US // 2)
                else:
                    n = series.count
                    k = int((t - t0) * max(n - 1, 0) // max(t1 - t0, 1))
                    ev = series.by_index(k, k + 100_000)
                img = event_image(ev.x, ev.y, ev.p, width, height)
                t_ev = int(t) if rig or not len(ev) else int(ev.t[0])
                label = f"{sen} t={t_ev / 1e6:.3f}s {len(ev)} ev ({domain})"
                tiles.append(_tile(img, tile_w, tile_h, label, events=True))
            rows.append(np.hstack(tiles))
    sheet = np.vstack(rows)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), sheet):
        raise TakeError(f"could not write contact sheet {out}")
    log.info("contact sheet %s: %dx%d", out, sheet.shape[1], sheet.shape[0])
    return out
