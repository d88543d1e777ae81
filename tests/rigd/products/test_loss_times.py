"""Loss records said in seconds of the take: device times mapped through the device's clock fit,
capped to the take's window; the records themselves keep their device times."""

from __future__ import annotations

from rigd.core.schema import DeviceSync, LossRecord, SyncReport
from rigd.products.loss_times import TakeClock, loss_lines

#: ev0's clock: device us 79_000_000 is rig us 1_000_000, running 100 ppm fast.
EV0 = DeviceSync(
    device="ev0",
    kind="event_sensor",
    device_ref_us=79_000_000,
    rig_ref_us=1_000_000,
    rate=1 / 1.0001,
    drift_ppm=100.0,
    n_matched=150,
    residual_rms_us=1.0,
    residual_max_us=2.0,
)


def report(*losses: LossRecord) -> SyncReport:
    # 30 Hz, pulses from rig us 1_000_000 for 150 pulses: a 5.00 s take
    return SyncReport(
        rate_hz=30.0,
        n_pulses=150,
        t_first_pulse_us=1_000_000,
        t_last_pulse_us=1_000_000 + 149 * 33_333,
        devices={"ev0": EV0},
        losses=list(losses),
    )


def test_a_short_delivery_is_said_in_seconds_of_the_take() -> None:
    rec = LossRecord(
        device="ev0",
        what="events",
        count=0,
        reason="did not deliver up to the end of the take window (device us 83468000 of 84000500) "
        "before it was stopped (writer.stop_backlog_s = 2 s); the rest of its window is not in the take",
        t_first_us=83_468_000,
        t_last_us=84_000_500,
    )
    (line,) = loss_lines(report(rec), [rec])
    # 4_468_000 device us after the reference at 100 ppm fast: 4.4676 s of rig time
    assert "(reached 4.47 s of the take's 5.00 s)" in line
    assert "device us" not in line
    assert line.endswith("the rest of its window is not in the take")
    assert rec.t_first_us == 83_468_000  # the record (and so --json) keeps the device time


def test_a_span_longer_than_the_take_is_capped_to_it() -> None:
    rec = LossRecord(
        device="ev0",
        what="events",
        count=0,
        reason="the simulator fell behind real time and did not make 17.25 s of events "
        "(3 time(s); count unknown; a virtual clock never does)",
    )
    (line,) = loss_lines(report(rec), [rec])
    assert "did not make up to 5.00 s of the take's events (17.25 s of simulated time in all" in line
    short = rec.model_copy(update={"reason": "the simulator ... did not make 0.25 s of events (1 time(s))"})
    assert loss_lines(report(short), [short]) == [short.reason]


def test_record_times_become_a_span_capped_to_the_window() -> None:
    clock = TakeClock.of(report())
    assert clock is not None
    assert round(clock.length_s, 2) == 5.0
    rec = LossRecord(device="ev0", what="events", count=1500, reason="writer queue full")
    inside = rec.model_copy(update={"t_first_us": 80_000_000, "t_last_us": 80_200_000})
    assert clock.describe(inside) == "writer queue full [at 1.00-1.20 s of the take]"
    before = rec.model_copy(update={"t_first_us": 10_000_000, "t_last_us": 79_000_000})
    assert clock.describe(before) == "writer queue full [at 0.00 s of the take]"
    after = rec.model_copy(update={"t_first_us": 83_000_000, "t_last_us": None})
    assert clock.describe(after) == "writer queue full [from 4.00 s of the take]"
    # no clock fit for the device, or no pulses: the reason as it is
    other = rec.model_copy(update={"device": "cam9", "t_first_us": 80_000_000, "t_last_us": 80_100_000})
    assert clock.describe(other) == "writer queue full"
    assert loss_lines(None, [inside]) == ["writer queue full"]
