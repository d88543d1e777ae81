"""Sync engine: tie every device clock to the rig clock through the trigger pulses.

Each device saw (some of) the box's pulses in its own clock: a camera as the exposure
start of one frame per pulse, an event sensor as rising trigger-in edges. Matching those
observations to box pulse indices is done in two stages. A coarse stage uses host receive
times (millisecond-accurate, latency >= 0) to find which pulse each observation belongs
to, which only needs the host latency spread to stay under half a trigger period; a fine
stage fits offset + drift on the matched pairs and re-matches with that fit, so drift over
hours does not break the matching. Nothing is fixed silently: missing pulses, frame counter
gaps and unmatched observations all go into the report.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

from rigd.core.errors import SyncError
from rigd.core.kinds import SensorKind
from rigd.core.schema import DeviceSync, LossRecord, SyncReport
from rigd.core.timebase import ClockFit, ClockMap, fit_clock_map

log = logging.getLogger(__name__)

#: Observations further than this many robust sigmas from the fit are treated as unmatched.
_OUTLIER_SIGMAS = 8.0
#: Floor of the fine matching tolerance, so a few-us jitter never unmatches a good pulse.
_MIN_TOLERANCE_US = 50.0
#: Largest device-vs-rig clock drift the coarse stage allows for (crystals: < 100 ppm).
_MAX_DRIFT_PPM = 500.0


@dataclass(slots=True)
class PulseLog:
    """Pulses as the trigger box reported them (rig time)."""

    index: NDArray[np.int64]
    t_us: NDArray[np.int64]
    host_time_ns: NDArray[np.int64]
    n_emitted: int
    """Pulse count the box reports at STOP; indices 0..n_emitted-1 should all be present."""

    @classmethod
    def from_records(
        cls,
        index: NDArray[np.int64],
        t_us: NDArray[np.int64],
        host_time_ns: NDArray[np.int64],
        emitted: int = 0,
    ) -> PulseLog:
        """The box's pulse records sorted by index, one per index (a re-read after a gap may
        repeat some); `emitted` is what the box said at STOP (0: unknown, the highest index)."""
        order = np.argsort(index, kind="stable")
        uniq = np.concatenate([[True], np.diff(index[order]) > 0]) if index.size else np.empty(0, bool)
        sel = order[uniq]
        return cls(index[sel], t_us[sel], host_time_ns[sel], max(emitted, int(index.max(initial=-1)) + 1))


@dataclass(slots=True)
class DeviceObservations:
    """Trigger observations of one device, in the order they were delivered."""

    name: str
    kind: SensorKind
    t_device_us: NDArray[np.int64]
    host_time_ns: NDArray[np.int64]
    frame_counter: NDArray[np.int64] | None = None
    anchors: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None
    """(device us, host ns) of data as it arrived: an event sensor without trigger-in has no
    trigger observations, and its clock can only be placed by when its data reached the host."""


@dataclass(slots=True)
class DeviceMatch:
    pulse_index: NDArray[np.int64]
    """Box pulse index per observation, -1 where unmatched."""
    fit: ClockFit | None
    warnings: list[str] = field(default_factory=list)


@dataclass(slots=True)
class SyncResult:
    maps: dict[str, ClockMap]
    observation_pulse_index: dict[str, NDArray[np.int64]]
    report: SyncReport


def _assign(pred_rig: NDArray[np.float64], pulse_t: NDArray[np.int64], tol_us: float) -> NDArray[np.int64]:
    """Position in `pulse_t` of the nearest pulse within tol of each prediction, else -1.

    When two observations claim one pulse, the closer keeps it.
    """
    n = pulse_t.size
    out = np.full(pred_rig.size, -1, np.int64)
    if n == 0 or pred_rig.size == 0:
        return out
    pos = np.searchsorted(pulse_t, pred_rig)
    lo = np.clip(pos - 1, 0, n - 1)
    hi = np.clip(pos, 0, n - 1)
    d_lo = np.abs(pred_rig - pulse_t[lo])
    d_hi = np.abs(pred_rig - pulse_t[hi])
    best = np.where(d_hi < d_lo, hi, lo)
    dist = np.minimum(d_lo, d_hi)
    ok = dist <= tol_us
    out[ok] = best[ok]
    # Resolve duplicate claims: keep the closest observation for each pulse.
    claimed = np.flatnonzero(ok)
    if claimed.size:
        order = np.lexsort((dist[claimed], out[claimed]))
        c_sorted = claimed[order]
        p_sorted = out[c_sorted]
        dup = np.empty(p_sorted.size, bool)
        dup[0] = False
        dup[1:] = p_sorted[1:] == p_sorted[:-1]
        out[c_sorted[dup]] = -1
    return out


def host_to_rig_map(pulses: PulseLog) -> ClockMap:
    """Coarse host-monotonic -> rig map from when the box's pulse records arrived."""
    host_us = pulses.host_time_ns // 1000
    fit = fit_clock_map(host_us, pulses.t_us, fit_drift=pulses.t_us.size >= 10)
    # Host receive time lags the pulse by a latency >= 0. The least-squares line sits at the
    # mean latency; shift it onto the fastest arrivals so it maps a host time to the rig time
    # at which the host received something.
    fastest = float(np.percentile(fit.residuals_us, 5)) if fit.n else 0.0
    m = fit.map
    return ClockMap(m.device_ref_us, m.rig_ref_us, m.rate, m.frac_us - fastest)


def _coarse_offset(
    d: NDArray[np.int64],
    c: NDArray[np.float64],
    pulse_t: NDArray[np.int64],
    period_us: float,
    window_us: float,
) -> float | None:
    """Device -> rig offset (rig = device + offset) good to well under half a period.

    Candidates pair the first observation with each box pulse near the host estimate; each
    is scored by how many observations of the first window land on a pulse. Latency is
    never negative, so an offset above min(c) is impossible; among the best candidates the
    one with the least implied latency wins. This tolerates host latency spreads of many
    periods (a loaded host) as long as the fastest arrival is prompt.
    """
    upper = float(c.min()) + 2_000.0
    lower = upper - max(2e6, 40 * period_us)
    lo_k, hi_k = np.searchsorted(pulse_t, [d[0] + lower, d[0] + upper])
    if hi_k <= lo_k:
        return None
    offsets = (pulse_t[lo_k:hi_k] - d[0]).astype(np.float64)
    in_win = d[d - d[0] <= window_us].astype(np.float64)
    tol = period_us / 4.0
    scores = np.empty(offsets.size, np.int64)
    for i, off in enumerate(offsets):  # a few dozen candidates, each vectorized
        scores[i] = int((_assign(in_win + off, pulse_t, tol) >= 0).sum())
    best = scores == scores.max()
    return float(offsets[best].max())


def _offset_by_intervals(
    d: NDArray[np.int64], c: NDArray[np.float64], pulses: PulseLog, period_us: float
) -> float | None:
    """Offset from the pulse train's own structure, independent of host latency.

    Intervals between a device's observations are whole numbers of periods (more than one
    where it missed pulses), so observation j is pulse `s + K[j]` for one unknown shift s.
    Devices start before the box does, so when a device saw the first and the last pulse
    only s = 0 fits the count; otherwise the feasible shifts are few and the host arrival
    times choose among them (least non-negative latency). None when the intervals are not
    clean multiples (extra edges, clock far off nominal): the caller then scores candidates.
    """
    if d.size < 2 or pulses.n_emitted < 1:
        return None
    ratio = np.diff(d).astype(np.float64) / period_us
    m = np.rint(ratio)
    if (m < 1).any() or np.abs(ratio - m).max() > 0.25:
        return None
    k = np.concatenate([[0], np.cumsum(m).astype(np.int64)])
    n_shifts = pulses.n_emitted - int(k[-1])
    if n_shifts < 1:
        return None
    by_index = np.full(pulses.n_emitted, -1, np.int64)
    ok = (pulses.index >= 0) & (pulses.index < pulses.n_emitted)
    by_index[pulses.index[ok]] = pulses.t_us[ok]
    best: tuple[int, float] | None = None  # (matched, offset) of the best shift so far
    upper = float(c.min()) + 2_000.0
    for shift in range(n_shifts):
        idx = shift + k
        rig = by_index[idx]
        have = rig >= 0
        if not have.any():
            continue
        # Offset at the start of the take (drift moves it later on; the fit follows).
        first = np.flatnonzero(have)[:64]
        off = float(np.median(rig[first] - d[first]))
        if n_shifts > 1 and off > upper:
            continue  # would need a negative host latency
        score = int(have.sum())
        # Later shifts imply less latency: on equal support keep the latest feasible one.
        if best is None or score >= best[0]:
            best = (score, off)
    return None if best is None else best[1]


def match_device(
    obs: DeviceObservations, pulses: PulseLog, period_us: float, host_to_rig: ClockMap
) -> DeviceMatch:
    """Match one device's observations to box pulses and fit its clock map."""
    n_obs = obs.t_device_us.size
    warnings: list[str] = []
    if n_obs == 0 or pulses.t_us.size == 0:
        what = "no trigger observations" if n_obs == 0 else "no box pulses"
        return DeviceMatch(np.full(n_obs, -1, np.int64), None, [f"{obs.name}: {what}; clock not fitted"])
    d = obs.t_device_us.astype(np.int64)
    # c = (rig time the host received it) - device time = offset + latency (+ drift * t).
    c = host_to_rig.to_rig_float(obs.host_time_ns // 1000) - d.astype(np.float64)
    # Window over which +-_MAX_DRIFT_PPM keeps a fixed offset within a quarter period.
    window = max(period_us, 0.25 * period_us / (_MAX_DRIFT_PPM * 1e-6))
    off = _offset_by_intervals(d, c, pulses, period_us)
    if off is None:
        off = _coarse_offset(d, c[d - d[0] <= window], pulses.t_us, period_us, window)
    if off is None:
        warnings.append(f"{obs.name}: no box pulse near its observations; clock not fitted")
        return DeviceMatch(np.full(n_obs, -1, np.int64), None, warnings)
    span = float(d[-1] - d[0])
    fit: ClockFit | None = None
    pos = np.full(n_obs, -1, np.int64)
    while True:
        # Grow the matched span geometrically, predicting with the fit of the span before.
        win = d - d[0] <= window
        pred = fit.map.to_rig_float(d[win]) if fit is not None else d[win] + off
        pos[:] = -1
        pos[win] = _assign(pred, pulses.t_us, period_us / 4.0)
        ok = pos >= 0
        if not ok.any():
            break
        fit = fit_clock_map(d[ok], pulses.t_us[pos[ok]], fit_drift=ok.sum() >= 3)
        if window >= span:
            break
        window *= 4.0
    if fit is None:
        warnings.append(f"{obs.name}: no observation matched a box pulse; clock not fitted")
        return DeviceMatch(np.full(n_obs, -1, np.int64), None, warnings)
    for _ in range(3):  # fine re-matching at a tolerance set by the residuals
        sigma = 1.4826 * float(np.median(np.abs(fit.residuals_us))) if fit.n >= 5 else 0.0
        tol = min(max(_MIN_TOLERANCE_US, _OUTLIER_SIGMAS * sigma), period_us / 4.0)
        new_pos = _assign(fit.map.to_rig_float(d), pulses.t_us, tol)
        ok = new_pos >= 0
        if not ok.any():
            break
        fit = fit_clock_map(d[ok], pulses.t_us[new_pos[ok]], fit_drift=ok.sum() >= 3)
        if np.array_equal(new_pos, pos):
            break
        pos = new_pos
    ok = pos >= 0
    index = np.where(ok, pulses.index[np.clip(pos, 0, None)], -1).astype(np.int64)
    return DeviceMatch(index, fit, warnings)


def _counter_gaps(counters: NDArray[np.int64]) -> list[int]:
    if counters.size < 2:
        return []
    c = np.unique(counters)
    full = np.arange(c[0], c[-1] + 1, dtype=np.int64)
    return [int(v) for v in np.setdiff1d(full, c, assume_unique=True)]


def synchronize(
    pulses: PulseLog,
    observations: list[DeviceObservations],
    rate_hz: float,
    losses: list[LossRecord] | None = None,
    shares_clock_with: dict[str, str] | None = None,
    software_synced: set[str] | None = None,
) -> SyncResult:
    """Fit every device clock to the rig clock and write down everything that is missing.

    `shares_clock_with` maps a slave device to its master (same clock over a sync cable): a
    slave without trigger observations of its own takes its master's map.
    """
    shared = shares_clock_with or {}
    software = software_synced or set()
    _check_pulse_indices(pulses)
    period_us = 1e6 / rate_hz
    warnings: list[str] = []
    missing_from_log = _pulses_missing_from_log(pulses, warnings)
    host_map = host_to_rig_map(pulses) if pulses.t_us.size else ClockMap.identity()
    matches = {
        obs.name: match_device(obs, pulses, period_us, host_map)
        for obs in observations
        if obs.name not in software
    }
    maps: dict[str, ClockMap] = {}
    obs_index: dict[str, NDArray[np.int64]] = {}
    devices: dict[str, DeviceSync] = {}
    for obs in observations:
        if obs.name in software:
            devices[obs.name], maps[obs.name], obs_index[obs.name] = _software_sync(
                obs, pulses, period_us, host_map
            )
            warnings.append(f"{obs.name}: free-running, synchronized by the host clock only (ms accuracy)")
            continue
        m = matches[obs.name]
        master = shared.get(obs.name)
        clock = _choose_clock(obs, m, matches[master].fit if master in matches else None, host_map, warnings)
        maps[obs.name], obs_index[obs.name] = clock.map, m.pulse_index
        devices[obs.name] = _device_sync(obs, m, clock, master, pulses.n_emitted, warnings)
    unseen = _pulses_seen_by_no_device(pulses, list(matches.values())) if observations else []
    if unseen:
        warnings.append(f"{len(unseen)} pulse(s) seen by no device: {unseen[:10]}")
    report = SyncReport(
        rate_hz=rate_hz,
        n_pulses=pulses.n_emitted,
        t_first_pulse_us=int(pulses.t_us[0]) if pulses.t_us.size else None,
        t_last_pulse_us=int(pulses.t_us[-1]) if pulses.t_us.size else None,
        pulses_missing_from_box_log=missing_from_log,
        pulses_seen_by_no_device=unseen,
        devices=devices,
        losses=list(losses or []),
        warnings=warnings,
    )
    return SyncResult(maps, obs_index, report)


def _check_pulse_indices(pulses: PulseLog) -> None:
    if pulses.index.size and np.any(np.diff(pulses.index) <= 0):
        raise SyncError("box pulse indices are not strictly increasing")


def _pulses_missing_from_log(pulses: PulseLog, warnings: list[str]) -> list[int]:
    """Pulses the box says it emitted but did not report: a gap in its log, not in the devices."""
    expected = np.arange(pulses.n_emitted, dtype=np.int64)
    missing = [int(i) for i in np.setdiff1d(expected, pulses.index)]
    if missing:
        warnings.append(f"{len(missing)} pulse(s) absent from the box's timestamp log")
    return missing


def _pulses_seen_by_no_device(pulses: PulseLog, matches: list[DeviceMatch]) -> list[int]:
    seen = np.zeros(max(pulses.n_emitted, int(pulses.index.max(initial=-1)) + 1), bool)
    for m in matches:
        seen[m.pulse_index[m.pulse_index >= 0]] = True
    return [int(i) for i in np.flatnonzero(~seen[: pulses.n_emitted])]


class _Clock(NamedTuple):
    """A device's map to rig time, its fit residuals (us) and where it came from."""

    map: ClockMap
    rms_us: float
    max_us: float
    source: Literal["own_pulses", "master", "host"]


def _choose_clock(
    obs: DeviceObservations,
    m: DeviceMatch,
    master_fit: ClockFit | None,
    host_map: ClockMap,
    warnings: list[str],
) -> _Clock:
    """The device's own fit; else its master's (one clock over a sync cable); else the coarse
    host map, which keeps the data usable and says loudly how its time was derived."""
    if m.fit is not None:
        warnings.extend(m.warnings)
        return _Clock(m.fit.map, m.fit.rms_us, m.fit.max_abs_us, "own_pulses")
    if master_fit is not None:
        return _Clock(master_fit.map, master_fit.rms_us, master_fit.max_abs_us, "master")
    warnings.extend(m.warnings)
    cmap = _fallback_map(obs, host_map)
    warnings.append(f"{obs.name}: times mapped with the coarse host clock (ms accuracy)")
    return _Clock(cmap, float("nan"), float("nan"), "host")


def _device_sync(
    obs: DeviceObservations,
    m: DeviceMatch,
    clock: _Clock,
    master: str | None,
    n_emitted: int,
    warnings: list[str],
) -> DeviceSync:
    """The report entry of one triggered device: its map, what it matched, missed and lost."""
    matched = m.pulse_index[m.pulse_index >= 0]
    dropped = _counter_gaps(obs.frame_counter) if obs.frame_counter is not None else []
    # A slave reading its master's clock without trigger-in is not missing pulses.
    missing = (
        []
        if clock.source == "master" and obs.t_device_us.size == 0
        else [int(i) for i in np.setdiff1d(np.arange(n_emitted, dtype=np.int64), matched)]
    )
    dev = _report_entry(
        obs,
        clock,
        n_matched=int(matched.size),
        unmatched=int((m.pulse_index < 0).sum()),
        missing=missing,
        dropped=dropped,
        shares_clock_with=master,
    )
    if dropped:
        warnings.append(f"{obs.name}: {len(dropped)} frame(s) lost (counter gaps)")
    return dev


def _software_sync(
    obs: DeviceObservations, pulses: PulseLog, period_us: float, host_map: ClockMap
) -> tuple[DeviceSync, ClockMap, NDArray[np.int64]]:
    """A free-running device stamped with the host's monotonic clock (us): its clock *is* the
    host clock, so the host-to-rig fit maps it; each observation goes to the nearest pulse
    within half a period, and the distance to it is reported (phase, not an error)."""
    pos = _assign(host_map.to_rig_float(obs.t_device_us), pulses.t_us, period_us / 2.0)
    ok = pos >= 0
    index = np.where(ok, pulses.index[np.clip(pos, 0, None)], -1).astype(np.int64)
    dist = host_map.to_rig_float(obs.t_device_us[ok]) - pulses.t_us[pos[ok]]
    rms = float(np.sqrt(np.mean(dist**2))) if dist.size else float("nan")
    mx = float(np.max(np.abs(dist))) if dist.size else float("nan")
    dev = _report_entry(
        obs,
        _Clock(host_map, rms, mx, "host"),
        n_matched=int(ok.sum()),
        unmatched=int((~ok).sum()),
        missing=[],
        dropped=_counter_gaps(obs.frame_counter) if obs.frame_counter is not None else [],
        sync="software",
    )
    return dev, host_map, index


def _report_entry(
    obs: DeviceObservations,
    clock: _Clock,
    *,
    n_matched: int,
    unmatched: int,
    missing: list[int],
    dropped: list[int],
    shares_clock_with: str | None = None,
    sync: Literal["hardware", "software"] = "hardware",
) -> DeviceSync:
    cmap = clock.map
    return DeviceSync(
        device=obs.name,
        kind=obs.kind,
        device_ref_us=cmap.device_ref_us,
        rig_ref_us=cmap.rig_ref_us,
        rate=cmap.rate,
        frac_us=cmap.frac_us,
        drift_ppm=cmap.drift_ppm,
        n_matched=n_matched,
        residual_rms_us=clock.rms_us,
        residual_max_us=clock.max_us,
        missing_pulses=missing,
        dropped_frames=dropped,
        unmatched_observations=unmatched,
        shares_clock_with=shares_clock_with,
        sync=sync,
        clock_from=clock.source,
    )


def _fallback_map(obs: DeviceObservations, host_map: ClockMap) -> ClockMap:
    if obs.t_device_us.size:
        rig = host_map.to_rig(obs.host_time_ns // 1000)
        return fit_clock_map(obs.t_device_us, rig, fit_drift=False).map
    if obs.anchors is None or obs.anchors[0].size == 0:
        return ClockMap.identity()
    # Data reaches the host after it was made (latency >= 0): shift the line onto the fastest
    # arrivals, as host_to_rig_map does, so device time maps to when it happened.
    t, host = obs.anchors
    fit = fit_clock_map(t, host_map.to_rig(host // 1000), fit_drift=False)
    fastest = float(np.percentile(fit.residuals_us, 5)) if fit.n else 0.0
    m = fit.map
    return ClockMap(m.device_ref_us, m.rig_ref_us, m.rate, m.frac_us + fastest)
