"""Drawing helpers for the report pictures: text, axes, colour bars, hatching, image-area panels.

OpenCV has no plotting library, so the few things a readable chart needs live here: anchored text
(Hershey fonts are ASCII-only, so degree signs and sigmas are spelled out), "nice" tick values,
a colour bar with numbers, a pixel-coordinate frame around an image-sized panel. Everything draws
in place on BGR uint8 images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

FONT = cv2.FONT_HERSHEY_SIMPLEX
INK = (40, 40, 40)  # text and axes
GRID = (225, 225, 225)  # light grid lines
MISSING = (235, 235, 235)  # background of cells without data
HATCH = (60, 60, 200)  # red-ish hatching over cells without data
GOOD = (70, 160, 60)
BAD = (60, 60, 210)
NEUTRAL = (175, 175, 175)
ACCENT = (200, 120, 30)  # blue bars
TITLE_H = 64
_ASCII = {"°": " deg", "σ": "sigma", "±": "+/-", "≥": ">=", "≤": "<=", "×": "x", "µ": "u", "–": "-", "—": "-", "²": "^2"}


def ascii_text(text: str) -> str:
    """`text` with the symbols Hershey fonts lack spelled out (degree sign -> " deg"), others as '?'."""
    out = "".join(_ASCII.get(ch, ch) for ch in text)
    return out.encode("ascii", "replace").decode("ascii")


def text_width(text: str, scale: float = 0.55, thickness: int = 1) -> int:
    (w, _), _ = cv2.getTextSize(ascii_text(text), FONT, scale, thickness)
    return int(w)


def put_text(
    img: np.ndarray,
    text: str,
    org: tuple[float, float],
    *,
    scale: float = 0.55,
    color: tuple[int, int, int] = INK,
    thickness: int = 1,
    align: str = "left",
    valign: str = "baseline",
) -> None:
    """Draw `text` anchored at `org`: align left/centre/right, valign baseline/middle/top."""
    text = ascii_text(text)
    (w, h), _ = cv2.getTextSize(text, FONT, scale, thickness)
    x = org[0] - {"left": 0, "centre": w / 2, "right": w}[align]
    y = org[1] + {"baseline": 0, "middle": h / 2, "top": h}[valign]
    cv2.putText(img, text, (int(round(x)), int(round(y))), FONT, scale, color, thickness, cv2.LINE_AA)


def put_vertical_text(img: np.ndarray, text: str, centre: tuple[float, float], *, scale: float = 0.55) -> None:
    """Text rotated 90 degrees counter-clockwise (reads bottom to top), centred on `centre`."""
    w, h = text_width(text, scale) + 4, int(30 * scale) + 8
    tile = np.full((h, w, 3), 255, np.uint8)
    put_text(tile, text, (2, h / 2), scale=scale, valign="middle")
    tile = cv2.rotate(tile, cv2.ROTATE_90_COUNTERCLOCKWISE)
    x0, y0 = int(centre[0] - tile.shape[1] / 2), int(centre[1] - tile.shape[0] / 2)
    x0, y0 = max(0, x0), max(0, y0)
    region = img[y0 : y0 + tile.shape[0], x0 : x0 + tile.shape[1]]
    np.minimum(region, tile[: region.shape[0], : region.shape[1]], out=region)


def new_canvas(width: int, height: int, title: str, subtitle: str = "") -> np.ndarray:
    """A white picture with a title band (and an optional grey subtitle line under the title)."""
    img = np.full((int(height), int(width), 3), 255, np.uint8)
    put_text(img, title, (24, 34), scale=0.9, thickness=2)
    if subtitle:
        put_text(img, subtitle, (24, 56), scale=0.5, color=(110, 110, 110))
    return img


def nice_ticks(vmin: float, vmax: float, count: int = 5) -> list[float]:
    """Round tick values (1, 2, 2.5 or 5 times a power of ten), about `count` steps across [vmin, vmax].

    Example:
        >>> nice_ticks(0, 0.93)
        [0.0, 0.2, 0.4, 0.6000000000000001, 0.8]
    """
    if not math.isfinite(vmin) or not math.isfinite(vmax) or vmax <= vmin:
        return [float(vmin)]
    raw = (vmax - vmin) / max(count, 1)
    power = 10 ** math.floor(math.log10(raw))
    step = min((m * power for m in (1, 2, 2.5, 5, 10)), key=lambda s: abs(math.log(s / raw)))  # nearest in ratio
    first = math.ceil(vmin / step - 1e-9) * step
    return [first + i * step for i in range(int((vmax - first) / step + 1e-9) + 1)]


def fmt(value: float) -> str:
    """A short human label for a number: 3 significant digits below 100, whole numbers up to 1e6.

    Example:
        >>> [fmt(v) for v in (0, 0.1234, 12.345, 1500.0, 0.0004)]
        ['0', '0.123', '12.3', '1500', '0.0004']
    """
    if value == 0:
        return "0"
    if abs(value) >= 1e6 or abs(value) < 1e-3:
        return f"{value:.3g}"
    return f"{value:.0f}" if abs(value) >= 100 else f"{value:.3g}"


def colourise(values: np.ndarray, vmin: float, vmax: float, *, fade: float = 0.0) -> np.ndarray:
    """(..., ) values -> (..., 3) BGR uint8 on the viridis map; `fade` blends towards white (0..1)."""
    t = np.clip((np.asarray(values, np.float64) - vmin) / max(vmax - vmin, 1e-12), 0, 1)
    idx = np.round(t * 255).astype(np.uint8)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(-1, 1), cv2.COLORMAP_VIRIDIS).reshape(256, 3)
    lut = (lut * (1 - fade) + 255 * fade).astype(np.uint8)
    return lut[idx]


def colour_bar(
    img: np.ndarray,
    x: int,
    y: int,
    height: int,
    vmin: float,
    vmax: float,
    *,
    label: str,
    fade: float = 0.0,
    open_top: bool = False,
    marks: tuple[tuple[float, str], ...] = (),
) -> None:
    """A vertical colour bar at (x, y), 22 px wide, with numbered ticks and a label above it.

    `open_top` writes ">=" on the top tick (values beyond vmax are clipped to its colour); `marks`
    draws labelled lines across the bar, e.g. a target value.
    """
    ramp = np.linspace(vmax, vmin, height)
    img[y : y + height, x : x + 22] = colourise(ramp, vmin, vmax, fade=fade)[:, None, :]
    cv2.rectangle(img, (x, y), (x + 22, y + height), INK, 1)
    put_text(img, label, (x - 4, y - 14), scale=0.5)

    def row(v: float) -> int:
        return int(round(y + (vmax - v) / max(vmax - vmin, 1e-12) * height))

    ticks = nice_ticks(vmin, vmax, 5)
    if open_top:  # the top colour also stands for everything above vmax
        ticks = [v for v in ticks if row(v) - y > 16]
        cv2.line(img, (x + 22, y), (x + 28, y), INK, 1)
        put_text(img, ">= " + fmt(vmax), (x + 32, y), scale=0.5, valign="middle")
    for v in ticks:
        cv2.line(img, (x + 22, row(v)), (x + 28, row(v)), INK, 1)
        put_text(img, fmt(v), (x + 32, row(v)), scale=0.5, valign="middle")
    for v, text in marks:
        if vmin <= v <= vmax:
            cv2.line(img, (x - 6, row(v)), (x + 28, row(v)), BAD, 2)
            put_text(img, text, (x - 10, row(v)), scale=0.45, color=BAD, align="right", valign="middle")


def hatch(img: np.ndarray, x0: int, y0: int, x1: int, y1: int, *, spacing: int = 10, color=HATCH) -> None:
    """Fill the rectangle with a light background and 45 degree hatching (cells without data)."""
    cv2.rectangle(img, (x0, y0), (x1, y1), MISSING, -1)
    tile = img[y0 : y1 + 1, x0 : x1 + 1]
    h, w = tile.shape[:2]
    for k in range(-h, w, spacing):
        cv2.line(tile, (k, h), (k + h, 0), color, 1, cv2.LINE_AA)


def dashed_hline(img: np.ndarray, y: int, x0: int, x1: int, color, *, dash: int = 10, thickness: int = 2) -> None:
    for x in range(x0, x1, 2 * dash):
        cv2.line(img, (x, y), (min(x + dash, x1), y), color, thickness)


def legend(img: np.ndarray, x: int, y: int, items: list[tuple[str, tuple[int, int, int], str]]) -> None:
    """A one-row legend: items of (kind "box" | "line" | "dash" | "hatch", colour, label), left to right."""
    for kind, color, label in items:
        if kind == "dash":
            dashed_hline(img, y - 4, x, x + 22, color, dash=5)
        elif kind == "box":
            cv2.rectangle(img, (x, y - 12), (x + 22, y + 4), color, -1)
        elif kind == "hatch":
            hatch(img, x, y - 12, x + 22, y + 4, spacing=6, color=color)
        else:
            cv2.line(img, (x, y - 4), (x + 22, y - 4), color, 2, cv2.LINE_AA)
        if kind in ("box", "hatch"):
            cv2.rectangle(img, (x, y - 12), (x + 22, y + 4), INK, 1)
        put_text(img, label, (x + 30, y), scale=0.5)
        x += 30 + text_width(label, 0.5) + 28


@dataclass(frozen=True, slots=True)
class ImagePanel:
    """Where an image-sized area sits in a picture: top-left (x, y) and the display scale."""

    x: int
    y: int
    scale: float  # display pixels per image pixel
    image_size: tuple[int, int]  # (width, height) image pixels

    @property
    def size(self) -> tuple[int, int]:
        return int(round(self.image_size[0] * self.scale)), int(round(self.image_size[1] * self.scale))

    def to_display(self, points_px: np.ndarray) -> np.ndarray:
        """(N, 2) image pixels -> (N, 2) float display coordinates (pixel centres map to centres)."""
        p = np.asarray(points_px, np.float64).reshape(-1, 2)
        return np.stack([self.x + (p[:, 0] + 0.5) * self.scale, self.y + (p[:, 1] + 0.5) * self.scale], axis=1)

    def cell_rect(self, row: int, col: int, rows: int, cols: int) -> tuple[int, int, int, int]:
        """Display rectangle (x0, y0, x1, y1) of grid cell (row, col) of a rows x cols grid."""
        w, h = self.size
        return (
            self.x + int(round(col * w / cols)),
            self.y + int(round(row * h / rows)),
            self.x + int(round((col + 1) * w / cols)) - 1,
            self.y + int(round((row + 1) * h / rows)) - 1,
        )


def fit_panel(image_size: tuple[int, int], x: int, y: int, *, max_width: int = 1100, max_height: int = 720) -> ImagePanel:
    """An `ImagePanel` at (x, y) as large as fits in max_width x max_height, keeping the aspect ratio."""
    w, h = image_size
    return ImagePanel(x, y, min(max_width / w, max_height / h), (int(w), int(h)))


def pixel_frame(img: np.ndarray, panel: ImagePanel) -> None:
    """Frame the panel and label its edges in image pixels: "x [px]" below, "y [px]" on the left."""
    w, h = panel.size
    cv2.rectangle(img, (panel.x - 1, panel.y - 1), (panel.x + w, panel.y + h), INK, 1)
    iw, ih = panel.image_size
    for v in nice_ticks(0, iw, 6):
        px = int(round(panel.x + v * panel.scale))
        cv2.line(img, (px, panel.y + h), (px, panel.y + h + 6), INK, 1)
        put_text(img, fmt(v), (px, panel.y + h + 22), scale=0.45, align="centre")
    for v in nice_ticks(0, ih, 5):
        py = int(round(panel.y + v * panel.scale))
        cv2.line(img, (panel.x - 6, py), (panel.x, py), INK, 1)
        put_text(img, fmt(v), (panel.x - 9, py), scale=0.45, align="right", valign="middle")
    put_text(img, "x [px]", (panel.x + w / 2, panel.y + h + 44), scale=0.5, align="centre")
    put_vertical_text(img, "y [px]", (panel.x - 62, panel.y + h / 2), scale=0.5)
