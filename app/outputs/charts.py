"""Bar charts of the report: coverage bins (tilt, distance) and the per-frame reprojection error.

Split from `pictures.py` (which re-exports both functions) to keep each module to one kind of
picture: these are plain charts with value axes; `pictures.py` draws over the image area.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2
import numpy as np

from calibcoach.app.outputs.drawing import (
    ACCENT,
    BAD,
    GOOD,
    GRID,
    INK,
    NEUTRAL,
    TITLE_H,
    ascii_text,
    dashed_hline,
    fmt,
    legend,
    new_canvas,
    nice_ticks,
    put_text,
    put_vertical_text,
    text_width,
)


def _value_axis(img: np.ndarray, x0: int, y0: int, x1: int, y1: int, vmax: float, label: str) -> Callable[[float], int]:
    """Grid lines and numbered ticks of a 0..vmax axis in the box; returns value -> display row."""

    def row(v: float) -> int:
        return int(round(y1 - v / vmax * (y1 - y0)))

    for v in nice_ticks(0, vmax, 7):
        cv2.line(img, (x0, row(v)), (x1, row(v)), GRID, 1)
        cv2.line(img, (x0 - 6, row(v)), (x0, row(v)), INK, 1)
        put_text(img, fmt(v), (x0 - 9, row(v)), scale=0.45, align="right", valign="middle")
    cv2.line(img, (x0, y0), (x0, y1), INK, 1)
    cv2.line(img, (x0, y1), (x1, y1), INK, 1)
    put_vertical_text(img, label, (x0 - 58, (y0 + y1) / 2), scale=0.5)
    return row


def bars_picture(
    groups: Sequence[tuple[str, Sequence[str], Sequence[float]]],
    *,
    title: str,
    subtitle: str = "",
    y_label: str = "share of what is needed",
) -> np.ndarray:
    """One bar panel per group (name, bin labels, values); a bar is green at >= 1 (enough), else red.

    Values are meant as "observed / required", so the dashed line at 1 is the target. Panels are
    laid out two per row (one full-width panel when there is a single group).

    Returns:
        (H, W, 3) uint8 BGR picture, W >= 1000.
    """
    if not groups:
        raise ValueError("bars_picture needs at least one group")
    for name, labels, values in groups:
        if len(labels) != len(values):
            raise ValueError(f"group {name!r} has {len(labels)} labels but {len(values)} values")
    cols = 1 if len(groups) == 1 else 2
    panel_w, panel_h = (1040, 380) if cols == 1 else (620, 380)
    rows = (len(groups) + cols - 1) // cols
    img = new_canvas(cols * panel_w + 40, TITLE_H + rows * panel_h + 50, title, subtitle)
    for k, (name, labels, values) in enumerate(groups):
        ox, oy = 20 + (k % cols) * panel_w, TITLE_H + (k // cols) * panel_h
        _bar_panel(img, ox, oy, panel_w, panel_h, name, list(labels), np.asarray(values, np.float64), y_label)
    legend(img, 40, img.shape[0] - 20, [("box", GOOD, "enough (>= 1)"), ("box", BAD, "not enough (< 1)"), ("dash", INK, "target = 1")])
    return img


def _bar_panel(img, ox: int, oy: int, w: int, h: int, name: str, labels: list[str], values: np.ndarray, y_label: str) -> None:
    x0, y0, x1, y1 = ox + 90, oy + 50, ox + w - 30, oy + h - 70
    put_text(img, name, (ox + 90, oy + 30), scale=0.65, thickness=2)
    vmax = max(1.25, float(np.nanmax(values)) * 1.15 if values.size else 1.25)
    row = _value_axis(img, x0, y0, x1, y1, vmax, y_label)
    dashed_hline(img, row(1.0), x0, x1, INK, thickness=1)
    slot = (x1 - x0) / max(len(values), 1)
    for i, (label, v) in enumerate(zip(labels, values, strict=True)):
        cx = x0 + (i + 0.5) * slot
        half = max(2, int(slot * 0.32))
        value = 0.0 if not np.isfinite(v) else float(v)
        cv2.rectangle(img, (int(cx - half), row(value)), (int(cx + half), y1), GOOD if value >= 1 else BAD, -1)
        put_text(img, fmt(value), (cx, row(value) - 6), scale=0.45, align="centre")
        lines = _wrap(ascii_text(label), slot - 6)
        scale = 0.48
        while scale > 0.3 and max(text_width(line, scale) for line in lines) > slot - 4:
            scale -= 0.02
        for j, line in enumerate(lines):
            put_text(img, line, (cx, y1 + 20 + 18 * j), scale=scale, align="centre")


def _wrap(label: str, width: float) -> list[str]:
    """Split a bin label over two lines at the space nearest its middle when it is wider than its bar slot."""
    if text_width(label, 0.48) <= width or " " not in label:
        return [label]
    spaces = [i for i, ch in enumerate(label) if ch == " "]
    cut = min(spaces, key=lambda i: abs(i - len(label) / 2))
    return [label[:cut], label[cut + 1 :]]


def per_frame_error_picture(
    frame_labels: Sequence[str],
    rms_px: Sequence[float] | np.ndarray,
    *,
    dropped: set[int] | frozenset[int] = frozenset(),
    threshold_px: float | None = None,
    title: str = "Reprojection error per frame",
) -> np.ndarray:
    """Bar chart of each frame's RMS reprojection error in pixels.

    Args:
        frame_labels: one label per bar (frame name or index), shown under the bars (every k-th
            when there are too many to read).
        rms_px: (F,) per-frame RMS in pixels.
        dropped: positions (into `rms_px`) of frames the solve dropped; drawn grey.
        threshold_px: the drop threshold, drawn as a dashed red line; bars above it are red.

    Returns:
        (H, W, 3) uint8 BGR picture, 1000 <= W <= 2400.
    """
    values = np.asarray(rms_px, np.float64).reshape(-1)
    if len(frame_labels) != values.size:
        raise ValueError(f"{len(frame_labels)} frame labels for {values.size} RMS values")
    n = max(values.size, 1)
    plot_w = int(np.clip(n * 14, 900, 2200))
    x0, y0 = 110, TITLE_H + 30
    x1, y1 = x0 + plot_w, y0 + 430
    finite = values[np.isfinite(values)]
    median = float(np.median(finite)) if finite.size else 0.0
    kept = [i for i in range(values.size) if i not in dropped]
    subtitle = (
        f"{values.size} frames, {len(dropped)} dropped; median {fmt(median)} px"
        + (f"; kept frames max {fmt(float(np.nanmax(values[kept])))} px" if kept else "")
    )
    longest = max((text_width(_short(str(label)), 0.42) for label in frame_labels), default=0)
    img = new_canvas(x1 + 170, y1 + longest + 90, title, subtitle)
    top = max([*finite.tolist(), threshold_px or 0.0, 1e-3]) * 1.15
    row = _value_axis(img, x0, y0, x1, y1, top, "RMS reprojection error [px]")
    slot = plot_w / n
    for i, v in enumerate(values):
        value = float(v) if np.isfinite(v) else 0.0
        colour = NEUTRAL if i in dropped else (BAD if threshold_px is not None and value > threshold_px else ACCENT)
        left, right = int(x0 + i * slot + slot * 0.15), int(x0 + (i + 1) * slot - slot * 0.15)
        cv2.rectangle(img, (left, row(value)), (max(right, left + 1), y1), colour, -1)
    dashed_hline(img, row(median), x0, x1, INK, dash=4, thickness=1)
    put_text(img, f"median {fmt(median)} px", (x1 + 8, row(median)), scale=0.45, valign="middle")
    if threshold_px is not None:
        dashed_hline(img, row(threshold_px), x0, x1, BAD)
        put_text(img, f"threshold {fmt(threshold_px)} px", (x1 + 8, row(threshold_px)), scale=0.5, color=BAD, valign="middle")
    step = max(1, int(np.ceil(18 / slot)))
    for i in range(0, values.size, step):
        label = _short(str(frame_labels[i]))
        put_vertical_text(img, label, (x0 + (i + 0.5) * slot, y1 + 12 + text_width(label, 0.42) / 2), scale=0.42)
    axis = "frame" + (f" (one label every {step} frames)" if step > 1 else "")
    put_text(img, axis, ((x0 + x1) / 2, y1 + longest + 42), scale=0.5, align="centre")
    items = [("box", ACCENT, "kept frame"), ("box", NEUTRAL, "dropped by the solve"), ("dash", INK, "median")]
    if threshold_px is not None:
        items[1:1] = [("box", BAD, "above threshold")]
        items.append(("dash", BAD, "threshold"))
    legend(img, x0, img.shape[0] - 14, items)
    return img


def _short(label: str) -> str:
    return label if len(label) <= 18 else "..." + label[-15:]
