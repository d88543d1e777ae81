"""Calibration boards: spec strings, detection with sub-pixel refinement, sharpness check.

Board spec grammar (all lengths in metres)::

    chessboard:COLSxROWS:SQUARE              e.g. chessboard:9x6:0.025
    charuco:COLSxROWS:SQUARE:MARKER[:DICT]   e.g. charuco:7x5:0.04:0.03:DICT_5X5_100

For a chessboard COLS x ROWS counts the *inner* corners (what OpenCV's pattern size means, and
what people count on a printed board); for a ChArUco board it counts the *squares* (what
`cv2.aruco.CharucoBoard` takes), so a 7x5 ChArUco board has 6x4 inner corners. DICT is the name
of a predefined ArUco dictionary (`cv2.aruco.DICT_*`), DICT_5X5_100 when omitted.

Board coordinates: X along the columns, Y along the rows, Z = 0 on the board, origin at the
first inner corner (chessboard) or the outer corner (ChArUco, OpenCV's convention). A
chessboard's corner grid is symmetric under a 180 degree rotation, so its
detections are put in a canonical order (first corner nearest the image's top-left) that two
roughly upright cameras seeing the same board agree on; without it stereo pairs can disagree.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict

from calibration.errors import BoardSpecError, CalibrationError

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: Edge width (pixels, see _edge_width) above which a view is called blurred. Sharp real views
#: measure 2-4 px (the 640x512 stereo set), renders 2 px; 15 px of motion blur gives over 8 px.
DEFAULT_MAX_EDGE_WIDTH_PX = 6.0

_SPEC_RE = re.compile(r"^(?P<kind>chessboard|charuco):(?P<cols>\d+)x(?P<rows>\d+):(?P<rest>.+)$")


class BoardSpec(BaseModel):
    """A parsed board spec; `str(spec)` gives the spec string back."""

    model_config = ConfigDict(frozen=True)

    kind: Literal["chessboard", "charuco"]
    cols: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = "DICT_5X5_100"

    def __str__(self) -> str:
        if self.kind == "chessboard":
            return f"chessboard:{self.cols}x{self.rows}:{self.square_m:g}"
        return f"charuco:{self.cols}x{self.rows}:{self.square_m:g}:{self.marker_m:g}:{self.dictionary}"

    @property
    def inner_corners(self) -> tuple[int, int]:
        """(cols, rows) of inner corners."""
        if self.kind == "chessboard":
            return self.cols, self.rows
        return self.cols - 1, self.rows - 1

    @property
    def n_corners(self) -> int:
        c, r = self.inner_corners
        return c * r

    def object_points(self) -> F64:
        """All inner corners on the board plane, (N, 3) metres, in corner-id order (row-major).

        ChArUco boards use OpenCV's own coordinates (origin at the board's outer corner) so that
        poses agree with cv2.aruco; chessboards have the origin at the first inner corner."""
        if self.kind == "charuco":
            return np.asarray(self.charuco_board().getChessboardCorners(), np.float64).reshape(-1, 3)
        c, r = self.inner_corners
        grid = np.mgrid[0:c, 0:r].T.reshape(-1, 2).astype(np.float64) * self.square_m
        return np.hstack([grid, np.zeros((grid.shape[0], 1))])

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV ChArUco board; a BoardSpecError for chessboards."""
        if self.kind != "charuco":
            raise BoardSpecError(f"board {self} is not a ChArUco board")
        dict_id = getattr(cv2.aruco, self.dictionary, None)
        if not isinstance(dict_id, int):
            raise BoardSpecError(f"board {self}: unknown ArUco dictionary {self.dictionary!r}")
        dictionary = cv2.aruco.getPredefinedDictionary(dict_id)
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, dictionary)


def parse_board(spec: str) -> BoardSpec:
    """Parse a spec string (grammar in the module docstring); BoardSpecError says what is wrong."""
    m = _SPEC_RE.match(spec.strip())
    if m is None:
        raise BoardSpecError(
            f"bad board spec {spec!r}: expected chessboard:COLSxROWS:SQUARE_M or "
            "charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT]"
        )
    kind, cols, rows = m["kind"], int(m["cols"]), int(m["rows"])
    parts = m["rest"].split(":")
    try:
        square = float(parts[0])
        marker = float(parts[1]) if kind == "charuco" and len(parts) > 1 else 0.0
    except ValueError as exc:
        raise BoardSpecError(f"bad board spec {spec!r}: lengths must be numbers in metres") from exc
    if square <= 0:
        raise BoardSpecError(f"bad board spec {spec!r}: square size must be > 0 m")
    if kind == "chessboard":
        if len(parts) != 1:
            raise BoardSpecError(f"bad board spec {spec!r}: a chessboard takes only COLSxROWS:SQUARE_M")
        if cols < 2 or rows < 2:
            raise BoardSpecError(f"bad board spec {spec!r}: need at least 2x2 inner corners")
        return BoardSpec(kind="chessboard", cols=cols, rows=rows, square_m=square)
    if len(parts) not in (2, 3):
        raise BoardSpecError(
            f"bad board spec {spec!r}: a ChArUco board takes COLSxROWS:SQUARE_M:MARKER_M[:DICT]"
        )
    if not 0 < marker < square:
        raise BoardSpecError(f"bad board spec {spec!r}: need 0 < marker size < square size")
    if cols < 3 or rows < 3:
        raise BoardSpecError(f"bad board spec {spec!r}: a ChArUco board needs at least 3x3 squares")
    board = BoardSpec(
        kind="charuco",
        cols=cols,
        rows=rows,
        square_m=square,
        marker_m=marker,
        dictionary=parts[2] if len(parts) == 3 else "DICT_5X5_100",
    )
    board.charuco_board()  # validates the dictionary name now, not at the first detection
    return board


def nearby_boards(board: BoardSpec) -> list[BoardSpec]:
    """Boards a miscounted spec may mean: cols/rows +-1 and swapped, same kind and lengths."""
    c, r = board.cols, board.rows
    low = 2 if board.kind == "chessboard" else 3
    sizes = [(c + 1, r), (c - 1, r), (c, r + 1), (c, r - 1), (r, c), (c + 1, r + 1), (c - 1, r - 1)]
    seen = {(c, r)}
    out: list[BoardSpec] = []
    for cols, rows in sizes:
        if (cols, rows) in seen or min(cols, rows) < low:
            continue
        seen.add((cols, rows))
        out.append(board.model_copy(update={"cols": cols, "rows": rows}))
    return out


@dataclass
class Detection:
    """Corners of one board found in one image.

    `ids` index `BoardSpec.object_points()`; `edge_width_px` is the sharpness measure (smaller is
    sharper, NaN when it could not be measured).
    """

    name: str
    image_size: tuple[int, int]
    image_points: F64
    ids: NDArray[np.int64]
    object_points: F64
    edge_width_px: float

    @property
    def n(self) -> int:
        return int(self.ids.size)

    def is_complete(self, board: BoardSpec) -> bool:
        return self.n == board.n_corners


def _gray(image: NDArray[np.generic], name: str) -> NDArray[np.uint8]:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.ndim != 2:
        raise CalibrationError(f"{name}: expected a 2-D gray or BGR image, got shape {img.shape}")
    if img.dtype != np.uint8:
        lo, hi = float(img.min()), float(img.max())
        img = ((img.astype(np.float64) - lo) * (255.0 / max(hi - lo, 1e-12))).astype(np.uint8)
    return np.ascontiguousarray(img)


def load_image(path: str | Path) -> NDArray[np.uint8]:
    """Read an image file as 8-bit gray; CalibrationError naming the file when it cannot be read."""
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise CalibrationError(f"{path}: cannot read image (missing file or unknown format)")
    return np.asarray(img, dtype=np.uint8)


def _subpix_window(pts: F64, cols: int) -> int:
    """Half-size of the cornerSubPix window: under half the corner spacing so that a window never
    reaches the next corner, at most 11 px (OpenCV's usual) and at least 2 px."""
    grid = pts.reshape(-1, cols, 2)
    spacing = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))
    return int(np.clip(spacing * 0.45, 2, 11))


def _edge_width(gray: NDArray[np.uint8], pts: F64) -> float:
    """Edge width (px) of the board's black/white edges, the worse of the two image directions.

    For an edge of contrast C blurred over w pixels the steepest gradient is about C / w, so
    C / (99th percentile of |dI/dx|) measures the width along x (same for y). Taking the worse
    direction catches motion blur, which widens only edges across the motion. Measured inside the
    corners' convex hull, so the background does not count. (cv2.estimateChessboardSharpness
    barely reacts to one-directional motion blur, hence this measure.)
    """
    hull = cv2.convexHull(pts.astype(np.float32)).astype(np.int32)
    mask = np.zeros(gray.shape, np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    inside = mask.astype(bool)
    if inside.sum() < 100:
        return float("nan")
    g = gray.astype(np.float32)
    vals = g[inside]
    contrast = float(np.percentile(vals, 95) - np.percentile(vals, 5))
    if contrast < 10:
        return float("nan")
    widths = []
    for dx, dy in ((1, 0), (0, 1)):
        grad = np.abs(cv2.Sobel(g, cv2.CV_32F, dx, dy, ksize=3)) / 8.0
        widths.append(contrast / max(float(np.percentile(grad[inside], 99)), 1e-6))
    return float(max(widths))


def _canonical_chessboard_order(pts: F64, cols: int, rows: int) -> F64:
    """Reverse the corner list when its first corner is farther from the image's top-left than the
    last one: the chessboard grid is symmetric under 180 degrees, so both orders are valid."""
    if pts[0].sum() > pts[-1].sum():
        return pts[::-1].copy()
    return pts


def detect(image: NDArray[np.generic], board: BoardSpec, name: str = "image") -> Detection | None:
    """Find the board in `image` and refine its corners to sub-pixel accuracy; None if not found.

    Chessboards use findChessboardCorners + cornerSubPix (on real data it beats the SB detector's
    accuracy), with findChessboardCornersSB as a fallback for hard views (strong distortion).
    """
    gray = _gray(image, name)
    size = (int(gray.shape[1]), int(gray.shape[0]))
    if board.kind == "chessboard":
        pattern = board.inner_corners
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
        if ok:
            raw = np.asarray(corners, np.float32).reshape(-1, 1, 2)
            win = _subpix_window(raw.reshape(-1, 2).astype(np.float64), pattern[0])
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
            pts = np.asarray(cv2.cornerSubPix(gray, raw, (win, win), (-1, -1), crit), np.float64).reshape(
                -1, 2
            )
        else:
            ok, corners = cv2.findChessboardCornersSB(
                gray, pattern, flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY
            )
            if not ok:
                log.debug("%s: no %s found", name, board)
                return None
            pts = np.asarray(corners, np.float64).reshape(-1, 2)
        p64 = _canonical_chessboard_order(pts, *pattern)
        ids = np.arange(board.n_corners, dtype=np.int64)
    else:
        detector = cv2.aruco.CharucoDetector(board.charuco_board())
        ch_corners, ch_ids, _, _ = detector.detectBoard(gray)
        if ch_ids is None or len(ch_ids) < 6:
            log.debug("%s: no %s found (%s corners)", name, board, 0 if ch_ids is None else len(ch_ids))
            return None
        p64 = ch_corners.reshape(-1, 2).astype(np.float64)
        ids = ch_ids.ravel().astype(np.int64)
    obj = board.object_points()[ids]
    return Detection(
        name=name,
        image_size=size,
        image_points=p64,
        ids=ids,
        object_points=obj,
        edge_width_px=_edge_width(gray, p64),
    )


def render_board(board: BoardSpec, px_per_square: int = 80, margin_squares: float = 1.0) -> NDArray[np.uint8]:
    """A printable image of the board (white margin around it), for printing and synthetic tests.

    Chessboard: (cols + 1) x (rows + 1) squares, top-left square black; the first inner corner is
    at pixel (margin + 1 square, margin + 1 square).
    """
    m = round(margin_squares * px_per_square)
    if board.kind == "charuco":
        w, h = board.cols * px_per_square, board.rows * px_per_square
        img = board.charuco_board().generateImage((w, h), marginSize=0, borderBits=1)
        return np.asarray(cv2.copyMakeBorder(img, m, m, m, m, cv2.BORDER_CONSTANT, value=255), np.uint8)
    c, r = board.cols + 1, board.rows + 1
    yy, xx = np.mgrid[0:r, 0:c]
    squares = np.where((xx + yy) % 2 == 0, 0, 255).astype(np.uint8)
    img = np.kron(squares, np.ones((px_per_square, px_per_square), np.uint8))
    return np.asarray(cv2.copyMakeBorder(img, m, m, m, m, cv2.BORDER_CONSTANT, value=255), np.uint8)


def board_image_origin(board: BoardSpec, px_per_square: int = 80, margin_squares: float = 1.0) -> float:
    """Pixel coordinate (x and y) in `render_board`'s image of the board's origin (first inner
    corner for a chessboard, the board's outer corner for ChArUco, as OpenCV defines them)."""
    m = round(margin_squares * px_per_square)
    return float(m + (px_per_square if board.kind == "chessboard" else 0)) - 0.5
