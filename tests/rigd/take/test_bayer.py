"""Takes of bayer_rg8 cameras at the writer and reader level: the mosaic is stored as given with
attrs saying what it is, refused where it cannot be what the camera was declared, read back as
RGB; takes from before the attr read as rgb8 / mono8 by their shape."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from rigd.core.devices import DeviceInfo, PulseBatch
from rigd.core.errors import TakeError, TakeFormatError
from rigd.core.frames import Frame
from rigd.core.pixels import mosaic_rggb
from rigd.core.schema import SyncReport
from rigd.core.settings import WriterConfig
from rigd.core.timebase import ClockMap
from rigd.take import TakeWriter, open_take, validate_take
from rigd.take.seal import finalize_take

H, W, N = 24, 32, 4
#: Left half orange, right half teal: flat colours a demosaic must restore away from the edge.
RGB = np.zeros((H, W, 3), np.uint8)
RGB[:, : W // 2] = (240, 140, 20)
RGB[:, W // 2 :] = (10, 170, 160)


def _writer(path: Path) -> TakeWriter:
    w = TakeWriter(path, rig_config_json="{}", take_id="t", config=WriterConfig(), rigd_version="t")
    w.add_trigger(DeviceInfo(kind="trigger", spec="sim://t/trigger"))
    return w


def _bayer_take(path: Path) -> Path:
    w = _writer(path)
    w.add_camera(
        "cam0", DeviceInfo(kind="rgb_camera", spec="sim://t/cam0"), (H, W), np.uint8, "{}", "bayer_rg8"
    )
    w.add_camera("mono", DeviceInfo(kind="rgb_camera", spec="sim://t/mono"), (H, W), np.uint8, "{}")
    t = 1_000_000 + np.arange(N, dtype=np.int64) * 33_333
    mosaic = mosaic_rggb(RGB)
    for i in range(N):
        w.append_frame("cam0", Frame(mosaic, int(t[i]), 2000, i, 1000 + i, pixel_format="bayer_rg8"))
        w.append_frame("mono", Frame(mosaic, int(t[i]), 2000, i, 1000 + i))
    w.append_pulses(PulseBatch(np.arange(N, dtype=np.int64), t, t * 1000))
    report = SyncReport(rate_hz=30.0, n_pulses=N, t_first_pulse_us=int(t[0]), t_last_pulse_us=int(t[-1]))
    identity = ClockMap(device_ref_us=0, rig_ref_us=0, rate=1.0, frac_us=0.0)
    index = np.arange(N, dtype=np.int64)
    finalize_take(w, {"cam0": identity, "mono": identity}, {"cam0": index, "mono": index}, report)
    w.close()
    return path


def test_mosaic_is_stored_as_given_and_read_as_rgb(tmp_path: Path) -> None:
    path = _bayer_take(tmp_path / "b.h5")
    assert validate_take(path) == []
    with h5py.File(path, "r") as f:
        assert f["frames/cam0"].attrs["pixel_format"] == "bayer_rg8"
        assert f["frames/cam0"].attrs["bayer_pattern"] == "RGGB"
        assert f["frames/mono"].attrs["pixel_format"] == "mono8"
        assert "bayer_pattern" not in f["frames/mono"].attrs
        np.testing.assert_array_equal(f["frames/cam0/images"][2], mosaic_rggb(RGB))
    with open_take(path) as take:
        rgb = take.camera("cam0")[2].image
        assert rgb.shape == (H, W, 3)
        inner = np.abs(rgb.astype(np.int16) - RGB.astype(np.int16))[
            2:-2, np.r_[2 : W // 2 - 2, W // 2 + 2 : W - 2]
        ]
        assert inner.max() <= 1
        mono = take.camera("mono")  # the same bytes declared mono8 stay as they are
        assert mono.pixel_format == "mono8"
        assert mono[0].image.shape == (H, W)
        assert mono.rgb(0).shape == (H, W, 3)
        np.testing.assert_array_equal(mono.gray(0), mono[0].image)


def test_older_takes_without_the_attr_read_by_their_shape(tmp_path: Path) -> None:
    path = _bayer_take(tmp_path / "b.h5")
    with h5py.File(path, "r+") as f:
        for cam in ("cam0", "mono"):
            for key in ("pixel_format", "bayer_pattern"):
                if key in f[f"frames/{cam}"].attrs:
                    del f[f"frames/{cam}"].attrs[key]
    with open_take(path) as take:
        fs = take.camera("cam0")
        assert fs.pixel_format == "mono8"
        assert fs[0].image.shape == (H, W)
        assert take.summary().cameras["cam0"].pixel_format == "mono8"


def test_a_bad_pixel_format_attr_is_named(tmp_path: Path) -> None:
    path = _bayer_take(tmp_path / "b.h5")
    with h5py.File(path, "r+") as f:
        f["frames/cam0"].attrs["bayer_pattern"] = "GBRG"
    (problem,) = validate_take(path)
    assert "/frames/cam0: pixel_format 'bayer_rg8' with bayer_pattern 'GBRG'" in problem
    with (
        open_take(path) as take,
        pytest.raises(TakeFormatError, match=r"/frames/cam0: pixel_format 'bayer_rg8'"),
    ):
        take.camera("cam0")


def test_writer_refuses_what_a_format_cannot_hold(tmp_path: Path) -> None:
    w = _writer(tmp_path / "r.h5")
    info = DeviceInfo(kind="rgb_camera", spec="sim://t/cam0")
    with pytest.raises(TakeError, match=r"camera 'cam0': bayer_rg8 frames are \(H, W\) uint8"):
        w.add_camera("cam0", info, (H, W, 3), np.uint8, "{}", "bayer_rg8")
    with pytest.raises(TakeError, match="bayer_rg8 frames are"):
        w.add_camera("cam0", info, (H, W), np.uint16, "{}", "bayer_rg8")
    with pytest.raises(TakeError, match="'yuv422' is not one of"):
        w.add_camera("cam0", info, (H, W), np.uint8, "{}", "yuv422")
    w.add_camera("cam0", info, (H, W), np.uint8, "{}", "mono8")
    with pytest.raises(TakeError, match="frame 0 is bayer_rg8, the camera was declared mono8"):
        w.append_frame("cam0", Frame(np.zeros((H, W), np.uint8), 0, 1, 0, 0, pixel_format="bayer_rg8"))
    w.close()
