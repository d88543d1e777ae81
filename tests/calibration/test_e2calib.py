# ruff: noqa: N806  (K follows the notation of the calibration literature)
"""e2calib on the simulated rig: a short take of the moving board, every reconstruction method,
scored against the simulator's ground-truth K (pinhole sim), plus the `calibrate events` CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from calibration.boards import detect, parse_board
from calibration.e2calib import ReconstructionParams, detector_image, reconstruct, to_uint8
from firmware_sim.board_scene import BoardScene
from firmware_sim.testing.board import BOARD, score, sensor_results, true_k
from rigd.app.commands.calibrate import calibrate_app
from rigd.app.testing.board import capture_board_take
from rigd.take.reader import open_take

pytestmark = pytest.mark.slow

RES = (480, 270)
runner = CliRunner()


@pytest.fixture(scope="module")
def board_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cap = capture_board_take(tmp_path_factory.mktemp("e2calib"), 2.5, RES, world="t-e2calib", clock="virtual")
    assert all(n > 10_000 for n in cap.events.values()), cap.events
    return cap.path


def test_board_scene_ground_truth_matches_detections() -> None:
    """The rendered board's detected corners sit on the ground-truth projections."""
    scene = BoardScene(seed=3)
    board = parse_board(scene.board_spec)
    for t in (0.0, 0.7e6, 1.9e6):
        img = scene.render(scene.view("ev1", *RES), t, gray=True)
        d = detect(img, board)
        assert d is not None
        gt = scene.board_corners("ev1", t, *RES)
        err = np.linalg.norm(d.image_points - gt, axis=1)
        assert float(np.median(err)) < 0.2, err


def test_reconstruction_shows_the_board(board_take: Path) -> None:
    with open_take(board_take) as take:
        cam = take.camera("cam1")
        t = int(cam.timestamps_us[40] + cam[40].exposure_us // 2)
        events, size = take.sensor("ev0").events(), take.sensor("ev0").geometry
    p = ReconstructionParams()
    hpf = reconstruct(events, size, [t], "hpf", p)
    assert detect(to_uint8(hpf[0]), parse_board(BOARD)) is not None
    # integrate: normalised per pixel, the board's squares at the two ends of [0, 1].
    img = reconstruct(events, size, [t, t - 1000], "integrate", p)
    assert img.shape == (2, size[1], size[0])
    assert img.min() >= 0.0
    assert img.max() <= 1.0
    assert np.mean((img[0] < 0.05) | (img[0] > 0.95) | (img[0] == 0.5)) > 0.8
    d = detect(detector_image(img[0], "integrate", p), parse_board(BOARD))
    assert d is not None
    # Reconstruction order does not depend on the order of the times.
    np.testing.assert_array_equal(img[1], reconstruct(events, size, [t - 1000], "integrate", p)[0])


def test_methods_calibrate_event_sensors(board_take: Path) -> None:
    results = sensor_results(board_take)
    K = true_k(RES[0])
    K[1, 2] = RES[1] / 2
    for res in results.values():
        rows = {r["method"]: r for r in score(res, K)}
        print({m: {k: v for k, v in r.items() if k != "sensor"} for m, r in rows.items()})
        # The take is captured on the virtual clock, so the board poses (and these numbers) are
        # the same every run. Measured twice at 480x270 / 2.5 s, identical to 1e-8 (ev0; ev1):
        # integrate 75/75 found, focal 0.037 %; 0.182 %, pp 0.28; 0.90 px, RMS 0.121; 0.126 px.
        # (The benchmark at 640x360 / 4 s, where the acceptance < 0.5 % applies, gives
        # 0.05-0.09 %.) Bounds about 1.5x the measured worst:
        acc = rows["integrate"]
        assert float(acc["focal_err_pct"]) < 0.3, acc  # type: ignore[arg-type]
        assert float(acc["rms_px"]) < 0.2, acc  # type: ignore[arg-type]
        assert float(acc["pp_err_px"]) < 1.5, acc  # type: ignore[arg-type]
        found, asked = (int(v) for v in str(acc["frames"]).split("/"))
        assert asked == len(res.times_us) == 75, acc
        assert found == asked, acc  # the board is found in every reconstruction
        # hpf, measured: 71/75 found, focal 0.724 %; 0.766 %, pp 1.71; 4.34 px, RMS 0.235; 0.249 px.
        hpf = rows["hpf"]
        assert float(hpf["focal_err_pct"]) < 1.2, hpf  # type: ignore[arg-type]
        assert float(hpf["rms_px"]) < 0.4, hpf  # type: ignore[arg-type]
        assert float(hpf["pp_err_px"]) < 6.5, hpf  # type: ignore[arg-type]
        found, asked = (int(v) for v in str(hpf["frames"]).split("/"))
        assert found >= asked - 6, hpf
        assert "window" in rows


def test_events_cli_writes_best_method(board_take: Path, tmp_path: Path) -> None:
    out = tmp_path / "ev0.json"
    r = runner.invoke(
        calibrate_app,
        [
            "events",
            str(board_take),
            "--sensor",
            "ev0",
            "--board",
            BOARD,
            "--out",
            str(out),
            "--json",
            "-m",
            "integrate",
        ],
    )
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert data["method"] == "integrate"
    assert data["methods"][0]["detected"] > 20
    assert out.exists()
    bad = runner.invoke(
        calibrate_app,
        ["events", str(board_take), "--sensor", "nope", "--board", BOARD, "--out", str(out)],
    )
    assert bad.exit_code == 2
