# ruff: noqa: N803, N806  (K, R, T, J follow the notation of the calibration literature)
"""Self-contained HTML calibration report; plots drawn with cv2 and embedded as base64 PNG.

It shows what the course notes say to check after a calibration: the reprojection-error bar graph
per view (to spot views to remove), the coverage of the image by corners, residual vectors (a
pattern in them means the lens model is too simple), an extrinsics plot (top and side views of the
boards or of the rig's cameras) and an undistorted sample image (straight lines must be straight).
"""

from __future__ import annotations

import base64
import html
import logging
import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.errors import CalibrationError
from calibration.extrinsics import RigResult
from calibration.intrinsics import IntrinsicsResult, undistort
from calibration.lens_models import CV_MARGIN

log = logging.getLogger(__name__)

U8 = NDArray[np.uint8]
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_PALETTE = [
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
]


def _color(i: int) -> tuple[int, int, int]:
    r, g, b = _PALETTE[i % len(_PALETTE)]
    return (b, g, r)


def _png(img: U8) -> str:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise CalibrationError("PNG encoding of a report figure failed")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode()


def nice_step(span: float, max_ticks: int = 6) -> float:
    """A tick step of 1, 2 or 5 times a power of ten giving at most `max_ticks` steps over `span`."""
    raw = max(span, 1e-12) / max_ticks
    power = 10.0 ** math.floor(math.log10(raw))
    return next(m * power for m in (1.0, 2.0, 5.0, 10.0) if m * power >= raw)


def _tick_text(v: float, step: float) -> str:
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    return f"{v:.{decimals}f}"


def bar_graph(
    names: Sequence[str],
    values: Sequence[float],
    title: str,
    w: int = 800,
    h: int = 320,
    overall_rms: float | None = None,
) -> U8:
    """Per-view RMS bars on round ticks, with a dashed line at `overall_rms` (the RMS over every
    corner of every view, the headline number) when given, else at the mean of the bars. The two
    differ: views with more corners weigh more in the overall RMS, and an RMS is not a mean.

    Labels never overlap: with more views than their names fit under, every k-th bar is labelled
    with its view number (1-based) instead; the line's label sits in the top margin, off the bars."""
    img = np.full((h, w, 3), 255, np.uint8)
    left, bottom, top = 60, 60, 30
    step = nice_step(max(max(values, default=1e-3) * 1.1, 1e-3))
    vmax = step * math.ceil(max(max(values, default=1e-3) * 1.1, 1e-3) / step)
    n = max(len(values), 1)
    bw = (w - left - 10) / n
    cv2.putText(img, title, (left, 20), _FONT, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.line(img, (left, h - bottom), (w - 10, h - bottom), (0, 0, 0), 1)
    cv2.line(img, (left, top), (left, h - bottom), (0, 0, 0), 1)
    for k in range(round(vmax / step) + 1):
        v = k * step
        y = int(h - bottom - (h - bottom - top) * v / vmax)
        cv2.line(img, (left - 4, y), (left, y), (0, 0, 0), 1)
        cv2.putText(img, _tick_text(v, step), (5, y + 4), _FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    labels = [name[-10:] for name in names]
    widest = max((cv2.getTextSize(t, _FONT, 0.3, 1)[0][0] for t in labels), default=0)
    if widest + 4 > bw:  # names would run into each other: numbers, every k-th bar
        labels = [str(i + 1) for i in range(len(names))]
        widest = cv2.getTextSize(str(len(names)), _FONT, 0.3, 1)[0][0]
    every = max(1, math.ceil((widest + 6) / bw))
    gap = min(4.0, bw * 0.25)
    for i, v in enumerate(values):
        x0 = int(left + i * bw + gap / 2)
        y = int(h - bottom - (h - bottom - top) * v / vmax)
        cv2.rectangle(
            img, (x0, y), (max(x0, int(left + (i + 1) * bw - gap / 2) - 1), h - bottom), _color(0), -1
        )
        if i % every == 0:
            cv2.putText(img, labels[i], (x0, h - bottom + 12), _FONT, 0.3, (0, 0, 0), 1, cv2.LINE_AA)
    if every > 1 or labels[:1] == ["1"]:
        cv2.putText(img, "view", (left, h - bottom + 28), _FONT, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    if values:
        level = float(np.mean(values)) if overall_rms is None else overall_rms
        text = f"mean of views {level:.4f} px" if overall_rms is None else f"RMS, all corners {level:.4f} px"
        y = int(h - bottom - (h - bottom - top) * level / vmax)
        for x in range(left, w - 10, 12):
            cv2.line(img, (x, y), (x + 6, y), (0, 0, 200), 1)
        # The legend in the top margin, right-aligned: a dash and the text, never over a bar.
        tw = cv2.getTextSize(text, _FONT, 0.4, 1)[0][0]
        cv2.line(img, (w - 10 - tw - 24, 16), (w - 10 - tw - 8, 16), (0, 0, 200), 1)
        cv2.putText(img, text, (w - 10 - tw, 20), _FONT, 0.4, (0, 0, 200), 1, cv2.LINE_AA)
    return img


def coverage_map(result: IntrinsicsResult) -> U8:
    """Corners of every kept view over the image area, one colour per view, board outlines too."""
    w, h = result.image_size
    img = np.full((h, w, 3), 245, np.uint8)
    for i, v in enumerate(result.views):
        pts = np.asarray(v.image_points, np.float32)
        hull = cv2.convexHull(pts).astype(np.int32)
        cv2.polylines(img, [hull], True, _color(i), 1, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, (round(float(p[0])), round(float(p[1]))), 2, _color(i), -1)
    return img


def residual_plot(result: IntrinsicsResult, scale: float | None = None) -> U8:
    """Residual vectors (projected minus detected) at the corners, magnified `scale` times."""
    w, h = result.image_size
    img = np.full((h, w, 3), 255, np.uint8)
    res = [np.asarray(v.residuals) for v in result.views]
    mag = float(np.percentile(np.linalg.norm(np.concatenate(res), axis=1), 95)) if res else 1.0
    s = scale if scale is not None else 20.0 / max(mag, 1e-6)
    for i, v in enumerate(result.views):
        for p, r in zip(np.asarray(v.image_points), res[i], strict=True):
            a = (round(float(p[0])), round(float(p[1])))
            b = (round(float(p[0] + s * r[0])), round(float(p[1] + s * r[1])))
            cv2.arrowedLine(img, a, b, _color(i), 1, cv2.LINE_AA, tipLength=0.3)
    cv2.putText(img, f"residuals x{s:.0f}", (10, 20), _FONT, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def _frustum(R: np.ndarray, t: np.ndarray, size: float) -> np.ndarray:
    """Camera centre and 4 far corners of a small frustum, in the frame (R, t) maps from."""
    c = -R.T @ t
    corners = np.array([[-1, -0.75, 1.5], [1, -0.75, 1.5], [1, 0.75, 1.5], [-1, 0.75, 1.5]]) * size
    return np.vstack([c, (R.T @ corners.T).T + c])


#: A label drawn at a 3-D point: (point, text, colour).
Mark = tuple[np.ndarray, str, tuple[int, int, int]]


def _length_text(m: float) -> str:
    return f"{m * 1000:g} mm" if m < 0.01 else f"{m * 100:g} cm" if m < 1 else f"{m:g} m"


def _plot_3d(
    polys: list[tuple[np.ndarray, tuple[int, int, int], bool]],
    axes: tuple[int, int],
    labels: tuple[str, str],
    w: int = 400,
    h: int = 400,
    marks: Sequence[Mark] = (),
    title: str = "",
) -> U8:
    """Orthographic projection of 3-D polylines onto two axes (0=X, 1=Y, 2=Z), with a title, the
    `marks` written beside their points, and a scale bar (the plot has no other length on it)."""
    img = np.full((h, w, 3), 255, np.uint8)
    pts = np.vstack([p for p, _, _ in polys])[:, list(axes)]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = float(max(hi - lo)) * 1.1 + 1e-9
    mid = (lo + hi) / 2

    def to_px(p: np.ndarray) -> np.ndarray:
        q = (p[:, list(axes)] - mid) / span
        return np.stack([w / 2 + q[:, 0] * (w - 40), h / 2 + q[:, 1] * (h - 40)], 1).astype(np.int32)

    for poly, col, closed in polys:
        cv2.polylines(img, [to_px(poly)], closed, col, 1, cv2.LINE_AA)
    for point, text, col in marks:
        x, y = to_px(np.asarray(point, np.float64).reshape(1, 3))[0]
        cv2.circle(img, (int(x), int(y)), 3, col, -1, cv2.LINE_AA)
        cv2.putText(img, text, (int(x) + 5, int(y) - 5), _FONT, 0.45, col, 1, cv2.LINE_AA)
    if title:
        cv2.putText(img, title, (10, 18), _FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    bar_m = nice_step(span, 4)
    bar_px = round(bar_m / span * (w - 40))
    x1, y0 = w - 12, h - 28
    cv2.line(img, (x1 - bar_px, y0), (x1, y0), (0, 0, 0), 2)
    for x in (x1 - bar_px, x1):
        cv2.line(img, (x, y0 - 4), (x, y0 + 4), (0, 0, 0), 1)
    cv2.putText(img, _length_text(bar_m), (x1 - bar_px, y0 - 7), _FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    axes_text = f"{labels[0]} right, {labels[1]} down"
    cv2.putText(img, axes_text, (10, h - 10), _FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def _cam_polys(
    R: np.ndarray, t: np.ndarray, size: float, col: tuple[int, int, int]
) -> list[tuple[np.ndarray, tuple[int, int, int], bool]]:
    f = _frustum(R, t, size)
    out = [(f[1:], col, True)]
    out += [(np.vstack([f[0], f[k]]), col, False) for k in range(1, 5)]
    return out


def extrinsics_plots(result: IntrinsicsResult | RigResult, board_size_m: float = 0.2) -> tuple[U8, U8]:
    """Top (X-Z) and side (Z-Y) views: boards around the camera, or the rig's camera frusta."""
    polys: list[tuple[np.ndarray, tuple[int, int, int], bool]] = []
    marks: list[Mark] = []
    if isinstance(result, IntrinsicsResult):
        title = f"{result.camera} (black) and its {len(result.views)} board poses"
        polys += _cam_polys(np.eye(3), np.zeros(3), board_size_m * 0.5, (0, 0, 0))
        marks.append((np.zeros(3), result.camera, (0, 0, 0)))
        for i, v in enumerate(result.views):
            R = cv2.Rodrigues(np.asarray(v.rvec))[0]
            t = np.asarray(v.tvec)
            sq = np.array(
                [
                    [0, 0, 0],
                    [board_size_m, 0, 0],
                    [board_size_m, board_size_m * 0.7, 0],
                    [0, board_size_m * 0.7, 0],
                ]
            )
            polys.append(((R @ sq.T).T + t, _color(i), True))
    else:
        title = f"cameras in the frame of {result.reference}"
        centers = np.array([c.center_m for c in result.cameras])
        size = max(float(np.ptp(centers, axis=0).max()) * 0.15, 0.02)
        for i, c in enumerate(result.cameras):
            polys += _cam_polys(np.asarray(c.R), np.asarray(c.t), size, _color(i))
            marks.append((np.asarray(c.center_m), c.camera, _color(i)))
    return (
        _plot_3d(polys, (0, 2), ("X", "Z"), marks=marks, title=f"top: {title}"),
        _plot_3d(polys, (2, 1), ("Z", "Y"), marks=marks, title=f"side: {title}"),
    )


def _num(v: float | None) -> str:
    return "" if v is None else f"{v:.4f}"


def _img_tag(src: str, alt: str) -> str:
    a = html.escape(alt)
    return f'<figure><img src="{src}" alt="{a}"><figcaption>{a}</figcaption></figure>'


def intrinsics_report(result: IntrinsicsResult, sample_image: np.ndarray | None = None) -> str:
    """HTML for one camera's intrinsics; `sample_image` (any view) is shown undistorted."""
    parts = [
        f"<h2>Camera {html.escape(result.camera)}</h2>",
        f"<p>Board {html.escape(result.board)}, image {result.image_size[0]}x{result.image_size[1]}, "
        f"model <b>{html.escape(result.model)}</b>, reprojection RMS <b>{result.rms_px:.4f} px</b> over "
        f"every corner of {len(result.views)} views (the camera's own fit: intrinsics and one board "
        "pose per view; <code>avg_reprojection_error</code> in the OpenCV YAML).</p>",
    ]
    K = result.camera_matrix()
    sd = result.std_devs
    rows = "".join(
        f"<tr><td>{n}</td><td>{val:.5g}</td><td>{sd.get(n, float('nan')):.3g}</td></tr>"
        for n, val in [("fx", K[0, 0]), ("fy", K[1, 1]), ("cx", K[0, 2]), ("cy", K[1, 2])]
        + [
            (k, v)
            for k, v in zip(
                ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4"),
                result.dist,
                strict=False,
            )
            if k in sd
        ]
    )
    parts.append(f"<table><tr><th>parameter</th><th>value</th><th>std dev</th></tr>{rows}</table>")
    if result.model_scores:
        rows = "".join(
            f"<tr><td>{s.model}</td><td>{s.n_params}</td><td>{_num(s.train_rms_px)}</td>"
            f"<td>{_num(s.cv_rms_px)}</td><td>{html.escape(s.note)}</td></tr>"
            for s in result.model_scores
        )
        parts.append(
            "<h3>Lens model selection (k-fold over views)</h3>"
            "<p>Models are tried from the fewest parameters up. A richer model replaces the one kept so "
            f"far only when its held-out RMS is at least {CV_MARGIN * 100:g} % lower: below that, its "
            "extra parameters fit the noise of these views rather than the lens, and a lower held-out "
            "RMS alone does not choose it.</p>"
            "<table><tr><th>model</th><th>params</th>"
            f"<th>train RMS px</th><th>held-out RMS px</th><th>outcome</th></tr>{rows}</table>"
        )
    if result.warnings:
        parts.append(
            "<h3>Warnings</h3><ul>" + "".join(f"<li>{html.escape(w)}</li>" for w in result.warnings) + "</ul>"
        )
    if result.rejected:
        parts.append(
            "<h3>Rejected views</h3><ul>"
            + "".join(f"<li>{html.escape(r.name)}: {html.escape(r.reason)}</li>" for r in result.rejected)
            + "</ul>"
        )
    names = [v.name for v in result.views]
    parts.append(
        _img_tag(
            _png(
                bar_graph(
                    names,
                    [v.rms_px for v in result.views],
                    "Reprojection RMS per view (px)",
                    overall_rms=result.rms_px,
                )
            ),
            "reprojection RMS per view; dashed: the RMS over every corner of every view (the headline)",
        )
    )
    parts.append(_img_tag(_png(coverage_map(result)), "coverage of the image by detected corners"))
    parts.append(_img_tag(_png(residual_plot(result)), "residual vectors"))
    top, side = extrinsics_plots(result)
    parts.append(_img_tag(_png(np.hstack([top, side])), "board poses: top view (X-Z) and side view (Z-Y)"))
    if sample_image is not None:
        src = np.asarray(sample_image, np.uint8)
        und = np.asarray(undistort(src, result), np.uint8)
        a = src if src.ndim == 3 else cv2.cvtColor(src, cv2.COLOR_GRAY2BGR)
        b = und if und.ndim == 3 else cv2.cvtColor(und, cv2.COLOR_GRAY2BGR)
        b = cv2.resize(b, (a.shape[1], a.shape[0]))
        parts.append(
            _img_tag(_png(np.hstack([a, b]).astype(np.uint8)), "sample image: original and undistorted")
        )
    return "\n".join(parts)


def _vec(v: Sequence[float], digits: int) -> str:
    return "(" + ", ".join(f"{x:+.{digits}f}" for x in v) + ")"


def rig_report(rig: RigResult, intrinsics: Sequence[IntrinsicsResult] = ()) -> str:
    """The rig's poses, each camera's two RMS values side by side, saying which fit each is from."""
    own = {r.camera: r for r in intrinsics}
    rows = "".join(
        f"<tr><td>{html.escape(c.camera)}</td><td>{_vec(c.center_m, 4)}</td><td>{_vec(c.t, 4)}</td>"
        f"<td>{_vec(c.t_std_m, 5)}</td><td>{np.degrees(np.linalg.norm(c.rvec)):.3f}</td>"
        f"<td>{max(c.rot_std_deg, default=0.0):.4f}</td><td>{c.rms_px:.3f} ({c.n_views})</td>"
        f"<td>{_own_rms(own.get(c.camera))}</td></tr>"
        for c in rig.cameras
    )
    parts = [
        f"<h2>Rig extrinsics (reference {html.escape(rig.reference)})</h2>",
        f"<p>{rig.n_views} views seen by two or more cameras, joint reprojection RMS "
        f"{rig.rms_px:.4f} px.</p>",
        f"<p><b>centre</b>: where the camera is, in the frame of {html.escape(rig.reference)} (x right, "
        "y down, z forward, metres). <b>T</b>: the translation of the transform into the camera "
        "(x_cam = R x_ref + T), as written to the YAML. <b>Rig RMS</b> is from the joint fit: "
        "intrinsics fixed, one board pose per view shared by every camera, shared views only. "
        "<b>Own RMS</b> is the camera's intrinsic calibration (its own board pose per view, all of its "
        "views), the YAML's <code>avg_reprojection_error</code>. The rig RMS is usually the larger: "
        "the board pose shared across cameras is one constraint more, on other views.</p>",
        "<table><tr><th>camera</th><th>centre (m)</th><th>T (m)</th><th>T std (m)</th>"
        "<th>rotation from reference (deg)</th><th>rot std (deg)</th><th>rig RMS px (views)</th>"
        f"<th>own RMS px (views)</th></tr>{rows}</table>",
    ]
    if rig.warnings:
        parts.append("<ul>" + "".join(f"<li>{html.escape(w)}</li>" for w in rig.warnings) + "</ul>")
    names = list(rig.per_view_rms_px)
    parts.append(
        _img_tag(
            _png(
                bar_graph(
                    names,
                    list(rig.per_view_rms_px.values()),
                    "Rig reprojection RMS per view (px)",
                    overall_rms=rig.rms_px,
                )
            ),
            "rig reprojection error per view",
        )
    )
    top, side = extrinsics_plots(rig)
    parts.append(_img_tag(_png(np.hstack([top, side])), "camera frusta: top view (X-Z) and side view (Z-Y)"))
    return "\n".join(parts)


def _own_rms(result: IntrinsicsResult | None) -> str:
    return "" if result is None else f"{result.rms_px:.3f} ({len(result.views)})"


def write_report(
    path: str | Path,
    intrinsics: Sequence[IntrinsicsResult] = (),
    rig: RigResult | None = None,
    samples: dict[str, np.ndarray] | None = None,
    title: str = "rigd calibration report",
) -> None:
    """Write the HTML file; `samples` maps camera name to an image shown undistorted."""
    body = [intrinsics_report(r, (samples or {}).get(r.camera)) for r in intrinsics]
    if rig is not None:
        body.append(rig_report(rig, intrinsics))
    style = (
        "body{font-family:sans-serif;max-width:1000px;margin:auto}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:2px 6px}img{max-width:100%}"
    )
    doc = (
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
        f"<style>{style}</style></head><body><h1>{html.escape(title)}</h1>{''.join(body)}</body></html>"
    )
    Path(path).write_text(doc)
    log.info("wrote report %s", path)
