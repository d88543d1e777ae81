"""summarize() numbers and the contact sheet."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from firmware_sim.testing.takes import MAPS, make_take
from rigd.app.cli import app
from rigd.app.testing.crash import append_step, open_writer, step
from rigd.core.errors import TakeFormatError
from rigd.products.inspect import event_image, summarize, write_thumbnails
from rigd.take import Take, recover_take
from rigd.take.seal import fail_take


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


# -- exit codes and damaged takes ------------------------------------------------------------
def _inspect(path: Path, *args: str) -> tuple[int, str]:
    res = CliRunner().invoke(app, ["inspect", str(path), *args])
    assert res.exception is None or isinstance(res.exception, SystemExit), res.output
    return res.exit_code, res.output


@pytest.mark.slow
def test_inspect_exit_codes_by_status(take_path: Path, tmp_path: Path) -> None:
    assert _inspect(take_path)[0] == 0
    rec = make_take(tmp_path / "rec.h5", finalize=False).path
    for args in ((), ("--json",)):
        code, text = _inspect(rec, *args)
        assert code == 1
        assert "still recording" in text
        assert f"rigd recover {rec}" in text
    failed = tmp_path / "failed.h5"
    w = open_writer(failed)
    for k in range(5):
        append_step(w, k)
    fail_take(w, "disk full")
    w.close()
    code, text = _inspect(failed)
    assert code == 1
    assert "take failed (disk full) and was never sealed: free space and run `rigd recover" in text
    sealed_failed = tmp_path / "nopulse.h5"
    w = open_writer(sealed_failed)
    w.append_frame("cam0", step(0).frame)
    fail_take(w, "camera fault")
    w.close()
    assert recover_take(sealed_failed).outcome == "sealed_failed"
    code, text = _inspect(sealed_failed)
    assert code == 1
    assert "take failed: camera fault; recovered but not finalized" in text
    assert "rigd recover" not in text.split("take failed:")[1]


@pytest.mark.parametrize(
    "hpath",
    [
        "events/ev0/t",
        "events/ev0/x",
        "events/ev0/ms_to_idx",
        "events/ev0/t_offset",
        "events/ev0/trigger/t_device",
        "frames/cam0/t_exposure_start_us",
        "frames/cam0/images",
        "trigger/pulses/t_us",
    ],
)
@pytest.mark.slow
def test_missing_dataset_is_named_in_one_line(take_path: Path, tmp_path: Path, hpath: str) -> None:
    p = tmp_path / "cut.h5"
    shutil.copy(take_path, p)
    with h5py.File(p, "r+") as f:
        del f[hpath]
    for args in ((), ("--json",)):
        code, text = _inspect(p, *args)
        assert code != 0
        assert f"/{hpath}" in text
        assert "Traceback" not in text
        assert "KeyError" not in text
    with pytest.raises(TakeFormatError, match=f"/{hpath}: required dataset is missing"):
        Take(p)


def test_event_tiles_keep_sparse_events_visible() -> None:
    """A 10 ms window of a sparse scene is mostly single events: each is drawn half bright or
    more, and shrinking the image into a tile keeps it (block maxima, not averages)."""
    from rigd.products.inspect import _max_pool, _tile, event_image

    x = np.array([5, 100, 101, 101, 101], np.uint16)
    y = np.array([7, 50, 50, 50, 50], np.uint16)
    p = np.array([1, 0, 1, 1, 1], np.int8)
    img = event_image(x, y, p, 640, 360)
    assert img[7, 5, 2] >= 127  # one ON event
    assert img[50, 100, 0] >= 127  # one OFF event
    assert img[50, 101, 2] == 255  # the most active pixel
    pooled = _max_pool(img, 4)
    assert pooled.shape == (90, 160, 3)
    assert pooled[1, 1, 2] == img[7, 5, 2]
    tile = _tile(img, 160, 90, "ev0", events=True)
    assert (tile[18:, :, 2] >= 127).sum() >= 2  # both ON pixels survive the shrink


def test_a_take_that_failed_before_recording_anything_is_not_sent_to_recover() -> None:
    from rigd.products.inspect import status_hint
    from rigd.take.summary import CameraSummary, TakeSummary

    empty = TakeSummary.model_construct(
        path="/takes/t.h5",
        status="failed",
        failure_reason="disk full",
        pulses=0,
        cameras={"cam0": CameraSummary.model_construct(frames=0)},
        event_sensors={},
    )
    hint = status_hint(empty)
    assert (
        hint == "/takes/t.h5: take failed (disk full) before anything was recorded in it: nothing to recover"
    )
    assert "rigd recover" not in hint
