"""Run a `rigd` command with this process's wall clock moved, as on a host whose clock is off.

    python -m rigd.app.testing.wall_clock SECONDS serve --config rig.json --host C

Moves `time.time`, `time.time_ns` and `datetime.datetime.now` by SECONDS before rigd is
imported (so every wall-clock label rigd writes comes from the moved clock); the monotonic clock
and the simulated world's time are left alone. The multi-host tests use it to show that host wall
clocks only label host times: the rig times come from the trigger.
"""

from __future__ import annotations

import datetime as _dt
import sys
import time


def move_wall_clock(seconds: float) -> None:
    real_time, real_time_ns = time.time, time.time_ns
    shift = _dt.timedelta(seconds=seconds)

    class MovedDatetime(_dt.datetime):
        @classmethod
        def now(cls, tz: _dt.tzinfo | None = None) -> MovedDatetime:
            return super().now(tz) + shift

    time.time = lambda: real_time() + seconds
    time.time_ns = lambda: real_time_ns() + int(seconds * 1e9)
    _dt.datetime = MovedDatetime  # type: ignore[misc]


def main() -> None:
    move_wall_clock(float(sys.argv[1]))
    from rigd.app.cli import main as cli_main

    sys.argv = ["rigd", *sys.argv[2:]]
    cli_main()


if __name__ == "__main__":
    main()
