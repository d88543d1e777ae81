"""summarize() numbers and the contact sheet."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from rigd.app.inspect import event_image, summarize, write_thumbnails
from tests.rigd.test_take_roundtrip import MAPS, make_take


@pytest.fixture(scope="module")
def take_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_take(tmp_path_factory.mktemp("i") / "take.h5").path


def test_summary_numbers(take_path: Path) -> None:
    s = summarize(take_path)
    assert s.status == "complete"
    assert s.problems == []
    cam = s.cameras["cam0"]
    assert cam.frames == 9
    assert cam.shape == [12, 16, 3]
    # 33 333 us device period, stretched by the camera clock rate.
    assert cam.fps == pytest.approx(1e6 / (33_333 * MAPS["cam0"].rate), rel=1e-4)
    ev = s.event_sensors["ev0"]
    assert ev.events == 20_000
    assert ev.triggers == 20
    assert (ev.width, ev.height) == (64, 48)
    assert ev.event_rate_hz == pytest.approx(ev.events / (ev.span_us / 1e6))
    assert s.pulses == 10
    assert '"cameras"' in s.model_dump_json()


def test_summary_includes_problems(take_path: Path, tmp_path: Path) -> None:
    p = tmp_path / "bad.h5"
    shutil.copy(take_path, p)
    with h5py.File(p, "r+") as f:
        f["events/ev0/x"][3] = 64
    s = summarize(p)
    assert len(s.problems) == 1
    assert "/events/ev0/x" in s.problems[0]


def test_thumbnails(take_path: Path, tmp_path: Path) -> None:
    out = write_thumbnails(take_path, tmp_path / "sheet.png", n_frames=3)
    img = cv2.imread(str(out))
    assert img is not None
    h, w = img.shape[:2]
    assert 300 <= w <= 2000
    assert h >= 2 * 30  # one camera row and one sensor row
    assert img.max() > 0


def test_thumbnails_of_unfinalized_take(tmp_path: Path) -> None:
    wr = make_take(tmp_path / "rec.h5", finalize=False)
    out = write_thumbnails(wr.path, tmp_path / "rec.png", n_frames=2)
    assert out.stat().st_size > 1000


def test_event_image_colours() -> None:
    x = np.array([0, 0, 3], np.uint16)
    y = np.array([0, 0, 1], np.uint16)
    p = np.array([1, 1, -1], np.int8)
    img = event_image(x, y, p, 4, 2)
    assert img.shape == (2, 4, 3)
    assert img[0, 0, 2] > 0
    assert img[0, 0, 0] == 0  # ON: red only (BGR)
    assert img[1, 3, 0] > 0
    assert img[1, 3, 2] == 0  # OFF: blue only
    assert img[1, 1].sum() == 0
