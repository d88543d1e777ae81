"""Degenerate and extreme inputs give warnings or clear errors, never silent nonsense."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.boards import detect, parse_board
from calibration.errors import BoardSpecError, CalibrationError, NoBoardFoundError
from calibration.intrinsics import calibrate_images, calibrate_intrinsics, detect_images
from firmware_sim.testing.board_views import (
    SYNTH_BOARD,
    SynthCamera,
    look_at,
    render,
    synth_detections,
    view_poses,
)

K0 = np.array([[600.0, 0.0, 322.3], [0.0, 598.5, 241.7], [0.0, 0.0, 1.0]])
DIST = np.array([-0.12, 0.05, 0.0, 0.0, 0.0])


@pytest.mark.parametrize(
    "spec",
    [
        "chessboard:9x6",
        "chessboard:9x6:-1",
        "chessboard:1x6:0.02",
        "charuco:5x7:0.04:0.05",
        "charuco:5x7:0.04:0.03:DICT_NOPE",
        "circles:4x11:0.02",
        "chessboard:9x6:abc",
    ],
)
def test_bad_board_specs_are_clear_errors(spec: str) -> None:
    with pytest.raises(BoardSpecError, match=r"board spec|dictionary"):
        parse_board(spec)


def test_board_spec_roundtrip() -> None:
    b = parse_board("charuco:7x5:0.04:0.03")
    assert parse_board(str(b)) == b
    assert b.inner_corners == (6, 4)
    c = parse_board("chessboard:9x6:0.025")
    assert str(c) == "chessboard:9x6:0.025"
    assert c.n_corners == 54


def test_no_board_found_names_the_files(tmp_path: Path) -> None:
    files = []
    for i in range(3):
        p = tmp_path / f"blank{i}.png"
        cv2.imwrite(str(p), np.full((120, 160), 128, np.uint8))
        files.append(p)
    with pytest.raises(NoBoardFoundError, match=r"not found in any of 3 images \(blank0.png"):
        calibrate_images(files, parse_board("chessboard:9x6:0.025"))


def test_unreadable_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match=r"missing\.png"):
        calibrate_images([tmp_path / "missing.png"], parse_board("chessboard:9x6:0.025"))


def test_two_views_warn() -> None:
    board = parse_board(SYNTH_BOARD)
    cam = SynthCamera(K0, DIST)
    dets = synth_detections(board, cam, view_poses(board, cam, 2, 0.5, seed=7), seed=7)
    res = calibrate_intrinsics(dets, board)
    assert any("only 2 usable views" in w for w in res.warnings)
    assert any("too few for cross-validated model selection" in w for w in res.warnings)
    with pytest.raises(CalibrationError, match=r"need at least 2"):
        calibrate_intrinsics(dets[:1], board)


@pytest.mark.slow
def test_all_fronto_parallel_warns() -> None:
    board = parse_board(SYNTH_BOARD)
    cam = SynthCamera(K0, DIST)
    poses = [
        look_at(board, np.array([x, y, 0.5]), 2.0, a, r)
        for x, y, a, r in [
            (-0.08, -0.05, 0, 0),
            (0.08, -0.05, 90, 10),
            (0.0, 0.0, 45, -10),
            (-0.08, 0.05, 180, 5),
            (0.08, 0.05, 270, -5),
            (0.0, -0.03, 30, 15),
        ]
    ]
    dets = synth_detections(board, cam, poses, seed=8)
    res = calibrate_intrinsics(dets, board)
    assert any("fronto-parallel" in w for w in res.warnings)


@pytest.mark.slow
def test_board_partly_outside_and_blurred_views_are_reported(tmp_path: Path) -> None:
    board = parse_board(SYNTH_BOARD)
    cam = SynthCamera(K0, DIST)
    rv, tv = look_at(board, np.array([0.0, 0.0, 0.5]), 25.0, 30.0)
    sharp = render(board, cam, rv, tv)
    cv2.imwrite(str(tmp_path / "a_sharp.png"), sharp)
    rv2, tv2 = look_at(board, np.array([0.2, 0.0, 0.45]), 25.0, 30.0)  # half of it off the right edge
    cv2.imwrite(str(tmp_path / "b_outside.png"), render(board, cam, rv2, tv2))
    kernel = np.zeros((15, 15), np.float32)
    kernel[7, :] = 1.0 / 15  # horizontal motion blur
    cv2.imwrite(str(tmp_path / "c_blur.png"), cv2.filter2D(sharp, -1, kernel))
    dets, rej, _ = detect_images(sorted(tmp_path.glob("*.png")), board)
    assert [r.name for r in rej] == ["b_outside.png"]
    assert "partly outside" in rej[0].reason
    blurred = next(d for d in dets if d.name == "c_blur.png")
    assert blurred.edge_width_px > detect(sharp, board).edge_width_px + 1  # type: ignore[union-attr]
    more = synth_detections(board, cam, view_poses(board, cam, 8, 0.5, seed=9), seed=9)
    res = calibrate_intrinsics([*more, *dets], board, rejected=rej)
    reasons = {r.name: r.reason for r in res.rejected}
    assert "blurred" in reasons["c_blur.png"]
    assert "b_outside.png" in reasons


def test_charuco_partial_view_detected_and_warned(tmp_path: Path) -> None:
    board = parse_board("charuco:7x5:0.04:0.03")
    cam = SynthCamera(K0, DIST)
    rv, tv = look_at(board, np.array([0.17, 0.0, 0.55]), 20.0, 0.0)
    cv2.imwrite(str(tmp_path / "partial.png"), render(board, cam, rv, tv))
    dets, rej, warn = detect_images([tmp_path / "partial.png"], board)
    assert len(dets) == 1
    assert 6 <= dets[0].n < board.n_corners
    assert not rej
    assert any("partly outside" in w for w in warn)
