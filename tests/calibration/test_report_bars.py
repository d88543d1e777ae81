"""The per-view bar graph stays readable with many views: labels that do not run into each other
(numbers every k-th bar instead of 106 names smeared into a black band) and the RMS legend off
the bars."""

from __future__ import annotations

import numpy as np

from calibration.report import bar_graph


def _dark_share(img: np.ndarray, rows: slice) -> float:
    return float((img[rows].min(axis=2) < 128).mean())


def test_many_views_keep_their_labels_apart() -> None:
    rng = np.random.default_rng(0)
    names = [f"img_{i:04d}.png" for i in range(106)]
    img = bar_graph(names, list(rng.uniform(0.1, 0.5, 106)), "RMS per view", overall_rms=0.31)
    h, bottom = img.shape[0], 60
    label_band = slice(h - bottom + 3, h - bottom + 14)
    assert _dark_share(img, label_band) < 0.15
    # the legend is in the top margin, right of the title (the plot starts at row 30)
    red = (img[..., 2] > 150) & (img[..., 0] < 100) & (img[..., 1] < 100)
    assert red[8:24, -220:].any()
    # inside the plot the only red is the dashed line: one or two rows, no text over the bars
    red_rows = np.flatnonzero(red[30 : h - bottom, 61:-10].any(axis=1))
    assert 1 <= red_rows.size <= 2, red_rows


def test_few_views_are_labelled_by_name() -> None:
    few = bar_graph(["left01.png", "left02.png"], [0.2, 0.3], "RMS per view")
    h, bottom = few.shape[0], 60
    assert _dark_share(few, slice(h - bottom + 3, h - bottom + 14)) > 0.0
