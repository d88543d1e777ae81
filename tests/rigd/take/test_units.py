"""Every time and length dataset of a take says its unit, and every dataset a plugin filter
compresses names the filter and how to read it, for users of plain h5py or h5dump."""

from __future__ import annotations

from pathlib import Path

import h5py
import pytest

from rigd.app.testing.board import capture_board_take
from rigd.take.units import FILTER_ATTR, UNITS_ATTR


@pytest.mark.slow
def test_units_and_filters_are_named(tmp_path: Path) -> None:
    path = capture_board_take(tmp_path, 0.2, (160, 90), world="t-units", clock="virtual").path
    seen: dict[str, str] = {}
    filtered: list[str] = []
    with h5py.File(path, "r") as f:

        def visit(name: str, obj: object) -> None:
            if not isinstance(obj, h5py.Dataset):
                return
            if UNITS_ATTR in obj.attrs:
                seen[name] = str(obj.attrs[UNITS_ATTR])
            plist = obj.id.get_create_plist()
            if any(plist.get_filter(i)[0] in (32015, 32004) for i in range(plist.get_nfilters())):
                filtered.append(name)
                assert "Zstd" in str(obj.attrs[FILTER_ATTR]) or "LZ4" in str(obj.attrs[FILTER_ATTR])
                assert "hdf5plugin" in str(obj.attrs[FILTER_ATTR])

        f.visititems(visit)
    assert seen["trigger/pulses/t_us"] == "us"
    assert seen["trigger/pulses/host_time_ns"] == "ns"
    assert seen["frames/cam0/t_exposure_start_device_us"] == "us"
    assert seen["frames/cam0/exposure_us"] == "us"
    assert seen["events/ev0/t_offset"] == "us"
    assert seen["events/ev0/trigger/t"] == "us"
    assert seen["calibration/cam1/t"] == "m"
    assert seen["calibration/cam1/K"] == "px"
    assert "events/ev0/evt_words" in filtered
