"""`rigd convert TAKE.h5 OUT.raw`: the EVT 2.1 header OpenEB writes for IMX636's half-swapped
words, little-endian EVT 2.1 for readers that only know that layout, and `--no-triggers`.
(evlib, a reader that is not rigd's, reads the evt21_le output exactly and ignores
`endianness=legacy`: checked by hand, docs/event-sensors.md "Converting".)"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rigd.app.cli import app
from rigd.evt import parse_raw_header, read_raw
from rigd.take.reader import open_take

runner = CliRunner()


@pytest.mark.parametrize(("fmt", "endianness"), [("evt21", "legacy"), ("evt21_le", "little")])
def test_evt21_header_names_the_word_layout(
    ros_take: Path, tmp_path: Path, fmt: str, endianness: str
) -> None:
    out = tmp_path / "ev0.raw"
    r = runner.invoke(app, ["convert", str(ros_take), str(out), "--sensor", "ev0", "--format", fmt])
    assert r.exit_code == 0, r.output
    with out.open("rb") as f:
        hdr = parse_raw_header(f)
    assert hdr.fields["format"].endswith(f";endianness={endianness}")
    assert hdr.fmt == fmt
    _, rec = read_raw(out)
    with open_take(ros_take) as take:
        ev = take.sensor("ev0").events()
        for k in "xypt":
            np.testing.assert_array_equal(getattr(rec.events, k), getattr(ev, k))
        assert len(rec.triggers) == len(take.sensor("ev0").triggers) > 0


@pytest.mark.parametrize("fmt", ["evt3", "evt2", "evt21"])
def test_no_triggers_leaves_out_the_trigger_words(ros_take: Path, tmp_path: Path, fmt: str) -> None:
    out = tmp_path / "ev0.raw"
    args = ["convert", str(ros_take), str(out), "--sensor", "ev0", "--format", fmt, "--no-triggers"]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    _, rec = read_raw(out)
    assert len(rec.triggers) == 0
    with open_take(ros_take) as take:
        assert len(rec.events) == take.sensor("ev0").count
