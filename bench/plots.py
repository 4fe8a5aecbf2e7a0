"""Small charts for the benchmark reports, drawn with OpenCV (the project carries no plotting library).

Two kinds, both returned as BGR uint8 images for `cv2.imwrite`:

    line_chart({"pinhole": (xs, ys), ...}, title=..., x_label=..., y_label=..., log_y=False, hline=None)
    grouped_bars(["720p", "1080p"], {"decode": [..], "detect": [..]}, title=..., y_label=...)

Titles, axis labels, tick values and the legend use the report helpers in app/outputs/drawing.py,
so the charts look like the rest of calibcoach's pictures.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calibcoach.app.outputs.drawing import (
    GRID,
    INK,
    TITLE_H,
    dashed_hline,
    fmt,
    legend,
    new_canvas,
    nice_ticks,
    put_text,
    put_vertical_text,
    text_width,
)

# Distinct BGR colours (a tab10-like set), in the order series are given.
PALETTE = [(180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148), (75, 86, 140),
           (194, 119, 227), (127, 127, 127), (34, 189, 188), (207, 190, 23)]
HLINE_COLOUR = (60, 60, 210)
_MARGIN = {"left": 96, "right": 32, "bottom": 76}  # room for ticks and labels; the top depends on the legend
_LEGEND_ROW_H = 26


@dataclass(frozen=True, slots=True)
class _Axes:
    """The plot rectangle in pixels and the value ranges it shows; maps values to pixels."""

    left: int
    top: int
    right: int
    bottom: int
    x_range: tuple[float, float]
    y_range: tuple[float, float]
    log_y: bool = False

    def _y_value(self, v: float) -> float:
        return math.log10(v) if self.log_y else v

    def px(self, x: float) -> int:
        lo, hi = self.x_range
        return int(round(self.left + (x - lo) / max(hi - lo, 1e-12) * (self.right - self.left)))

    def py(self, y: float) -> int:
        lo, hi = (self._y_value(v) for v in self.y_range)
        return int(round(self.bottom - (self._y_value(y) - lo) / max(hi - lo, 1e-12) * (self.bottom - self.top)))


def _plot_area(img: np.ndarray, x_range, y_range, *, legend_rows: int = 1, log_y: bool = False) -> _Axes:
    h, w = img.shape[:2]
    top = TITLE_H + 24 + _LEGEND_ROW_H * legend_rows
    return _Axes(_MARGIN["left"], top, w - _MARGIN["right"], h - _MARGIN["bottom"], x_range, y_range, log_y)


def _legend_rows(items: list[tuple[str, tuple[int, int, int], str]], width: int) -> list[list]:
    """Legend items split into rows that fit `width` (each item takes its label plus ~58 px)."""
    rows: list[list] = [[]]
    used = 0
    for item in items:
        need = 58 + text_width(item[2], 0.5)
        if rows[-1] and used + need > width:
            rows.append([])
            used = 0
        rows[-1].append(item)
        used += need
    return rows


def _draw_legend(img: np.ndarray, rows: list[list]) -> None:
    for i, row in enumerate(rows):
        legend(img, _MARGIN["left"], TITLE_H + 24 + _LEGEND_ROW_H * i, row)


def log_ticks(vmin: float, vmax: float) -> list[float]:
    """Tick values for a log axis: powers of ten, plus 2x and 5x when the range spans few decades."""
    lo, hi = math.floor(math.log10(vmin)), math.ceil(math.log10(vmax))
    steps = (1,) if hi - lo > 3 else (1, 2, 5)
    ticks = [m * 10.0**e for e in range(lo, hi + 1) for m in steps]
    return [t for t in ticks if vmin * (1 - 1e-9) <= t <= vmax * (1 + 1e-9)]


def _y_axis(img: np.ndarray, axes: _Axes, ticks: Sequence[float], label: str) -> None:
    for v in ticks:
        y = axes.py(v)
        cv2.line(img, (axes.left, y), (axes.right, y), GRID, 1)
        cv2.line(img, (axes.left - 6, y), (axes.left, y), INK, 1)
        put_text(img, fmt(v), (axes.left - 10, y), scale=0.45, align="right", valign="middle")
    cv2.line(img, (axes.left, axes.top), (axes.left, axes.bottom), INK, 1)
    put_vertical_text(img, label, (26, (axes.top + axes.bottom) / 2), scale=0.55)


def _x_axis(img: np.ndarray, axes: _Axes, ticks: Sequence[tuple[float, str]], label: str) -> None:
    cv2.line(img, (axes.left, axes.bottom), (axes.right, axes.bottom), INK, 1)
    for v, text in ticks:
        x = axes.px(v)
        cv2.line(img, (x, axes.bottom), (x, axes.bottom + 6), INK, 1)
        put_text(img, text, (x, axes.bottom + 22), scale=0.45, align="centre")
    put_text(img, label, ((axes.left + axes.right) / 2, img.shape[0] - 18), scale=0.55, align="centre")


def _padded_range(values: Sequence[float], *, log: bool, from_zero: bool) -> tuple[float, float]:
    """A value range holding `values` with a little room above (and below, on log axes)."""
    finite = [v for v in values if math.isfinite(v) and (v > 0 or not log)]
    if not finite:
        return (1.0, 10.0) if log else (0.0, 1.0)
    lo, hi = min(finite), max(finite)
    if log:
        return (lo / 1.3, hi * 1.3) if hi > lo else (lo / 2, hi * 2)
    lo = min(lo, 0.0) if from_zero else lo
    span = hi - lo if hi > lo else max(abs(hi), 1.0)
    return (lo if from_zero else lo - 0.05 * span), hi + 0.08 * span


def line_chart(
    series: dict[str, tuple[Sequence[float], Sequence[float]]],
    *,
    title: str,
    x_label: str,
    y_label: str,
    log_y: bool = False,
    hline: float | tuple[float, str] | None = None,
    subtitle: str = "",
    size: tuple[int, int] = (1000, 600),
) -> np.ndarray:
    """One line with dot markers per series {name: (xs, ys)}; the line breaks at NaN points.

    `hline` draws a dashed horizontal reference line (a value, or (value, label) for the legend),
    e.g. a target error. `log_y` puts y on a log scale (non-positive values are left out).
    Returns a BGR uint8 image of `size` (width, height).
    """
    img = new_canvas(*size, title, subtitle)
    xs_all = [float(x) for xs, _ in series.values() for x in xs]
    ys_all = [float(y) for _, ys in series.values() for y in ys]
    ref_value, ref_label = (hline if isinstance(hline, tuple) else (hline, f"{fmt(hline)}" if hline is not None else ""))
    if ref_value is not None:
        ys_all.append(float(ref_value))
    x_range = _padded_range(xs_all, log=False, from_zero=False)
    y_range = _padded_range(ys_all, log=log_y, from_zero=not log_y)
    colours = _colours(len(series))
    items = [("line", c, name) for c, name in zip(colours, series, strict=True)]
    if ref_value is not None:
        items.append(("dash", HLINE_COLOUR, ref_label))
    rows = _legend_rows(items, size[0] - _MARGIN["left"] - _MARGIN["right"])
    axes = _plot_area(img, x_range, y_range, legend_rows=len(rows), log_y=log_y)
    y_ticks = log_ticks(*y_range) if log_y else nice_ticks(*y_range, 6)
    _y_axis(img, axes, y_ticks, y_label)
    _x_axis(img, axes, [(v, fmt(v)) for v in nice_ticks(*x_range, 8)], x_label)
    for colour, (xs, ys) in zip(colours, series.values(), strict=True):
        _draw_line(img, axes, xs, ys, colour)
    if ref_value is not None:
        dashed_hline(img, axes.py(ref_value), axes.left, axes.right, HLINE_COLOUR)
    _draw_legend(img, rows)
    return img


def _colours(n: int) -> list[tuple[int, int, int]]:
    return [PALETTE[i % len(PALETTE)] for i in range(n)]


def _draw_line(img: np.ndarray, axes: _Axes, xs: Sequence[float], ys: Sequence[float], colour) -> None:
    """Dots joined by a line, broken where a point is missing (NaN, or <= 0 on a log axis)."""
    segments: list[list[tuple[int, int]]] = [[]]
    for x, y in zip(xs, ys, strict=True):
        if math.isfinite(x) and math.isfinite(y) and (y > 0 or not axes.log_y):
            segments[-1].append((axes.px(x), axes.py(y)))
        elif segments[-1]:
            segments.append([])
    for points in segments:
        if len(points) > 1:
            cv2.polylines(img, [np.array(points, np.int32)], False, colour, 2, cv2.LINE_AA)
        for p in points:
            cv2.circle(img, p, 4, colour, -1, cv2.LINE_AA)


def grouped_bars(
    groups: list[str],
    series: dict[str, Sequence[float]],
    *,
    title: str,
    y_label: str,
    subtitle: str = "",
    size: tuple[int, int] = (1100, 600),
    value_labels: bool = True,
) -> np.ndarray:
    """Bars side by side per group: series {name: one value per group}; NaN bars are left out.

    Each bar carries its value on top when `value_labels`. Returns a BGR uint8 image.
    """
    img = new_canvas(*size, title, subtitle)
    values = [float(v) for vs in series.values() for v in vs]
    colours = _colours(len(series))
    rows = _legend_rows([("box", c, name) for c, name in zip(colours, series, strict=True)],
                        size[0] - _MARGIN["left"] - _MARGIN["right"])
    axes = _plot_area(img, (0.0, float(len(groups))), _padded_range(values, log=False, from_zero=True),
                      legend_rows=len(rows))
    _y_axis(img, axes, nice_ticks(*axes.y_range, 6), y_label)
    _x_axis(img, axes, [(i + 0.5, g) for i, g in enumerate(groups)], "")
    slot = 0.8 / max(len(series), 1)  # 80% of each group's width holds its bars, the rest separates groups
    for k, (colour, vs) in enumerate(zip(colours, series.values(), strict=True)):
        for i, v in enumerate(vs):
            if math.isfinite(v):
                _draw_bar(img, axes, i + 0.1 + k * slot, slot, float(v), colour, value_labels)
    _draw_legend(img, rows)
    return img


def _draw_bar(img: np.ndarray, axes: _Axes, x0: float, width: float, value: float, colour, label: bool) -> None:
    left, right = axes.px(x0) + 1, axes.px(x0 + width) - 1
    top = axes.py(value)
    cv2.rectangle(img, (left, top), (right, axes.py(0.0)), colour, -1)
    if label:
        put_text(img, fmt(value), ((left + right) / 2, top - 5), scale=0.38, align="centre")


def save(img: np.ndarray, path: str | Path) -> Path:
    """Write `img` as a PNG, creating the folder; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")
    return path
