"""Guidance in words: where and how to hold the board next.

The most useful missing requirement of each axis is combined into one instruction a person can
carry out in one move ("move the board to the top-left corner, tilt it about 40 deg so its right
edge is further away, and bring it closer"), plus a target a viewer can draw as a ghost outline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibcoach.coverage.grid import CoverageMap

_TILT_WORDS = {
    "frontal": ("hold it facing the camera", 0.0, 0.0),
    "top_away": ("tilt it about 30 deg so its top edge is further away (turn it about the horizontal axis)", 30.0, 0.0),
    "bottom_away": ("tilt it about 30 deg so its bottom edge is further away (turn it about the horizontal axis)", -30.0, 0.0),
    "right_away": ("tilt it about 30 deg so its right edge is further away (turn it about the vertical axis)", 0.0, 30.0),
    "left_away": ("tilt it about 30 deg so its left edge is further away (turn it about the vertical axis)", 0.0, -30.0),
    "steep_x": ("tilt it steeply, about 45 deg, so its top edge is further away", 45.0, 0.0),
    "steep_y": ("tilt it steeply, about 45 deg, so its left edge is further away", 0.0, -45.0),
}
_DISTANCE_WORDS = {
    "near": ("bring it closer, so it fills about three quarters of the image height", 0.38),
    "far": ("move it further away, so it fills about a quarter of the image height", 0.13),
    "mid": ("hold it at a middle distance, so it fills about half the image height", 0.24),
}


@dataclass(frozen=True, slots=True)
class Guidance:
    """The next instruction and where the board should go."""

    sentence: str
    target_centre_px: tuple[float, float] | None  # where the board's centre should go
    target_footprint: float | None  # sqrt(area fraction) the board should cover, 0..1
    target_tilt_x_deg: float  # top edge away = positive
    target_tilt_y_deg: float  # right edge away = positive
    coverage_complete: bool


def region_words(row: int, col: int, rows: int, cols: int) -> str:
    """'the top-left corner', 'the bottom edge', 'the centre', ... for a region grid cell."""
    vertical = "top" if row == 0 else "bottom" if row == rows - 1 else ""
    horizontal = "left" if col == 0 else "right" if col == cols - 1 else ""
    if vertical and horizontal:
        return f"the {vertical}-{horizontal} corner of the image"
    if vertical:
        side = "" if cols % 2 == 1 and col == cols // 2 else (" (left half)" if col < cols / 2 else " (right half)")
        return f"the {vertical} edge of the image{side}"
    if horizontal:
        return f"the {horizontal} edge of the image"
    return "the centre of the image"


def next_guidance(cmap: CoverageMap) -> Guidance:
    """One instruction that fills the most useful missing region, tilt and distance at once."""
    w, h = cmap.image_size
    regions = cmap.missing_regions()
    tilts = cmap.missing_tilts()
    distances = cmap.missing_distances()
    if not regions and not tilts and not distances:
        return Guidance(
            "Coverage is complete. Keep moving the board to new places and angles, holding it still each time, "
            "until the uncertainty reaches its target.",
            None, None, 0.0, 0.0, True,
        )
    parts: list[str] = []
    centre: tuple[float, float] | None = None
    if regions:
        row, col, _fill = regions[0]
        centre = ((col + 0.5) / cmap.cols * w, (row + 0.5) / cmap.rows * h)
        parts.append(f"move the board to {region_words(row, col, cmap.rows, cmap.cols)}")
    tilt_x = tilt_y = 0.0
    if tilts:
        words, tilt_x, tilt_y = _TILT_WORDS[tilts[0]]
        parts.append(words)
    footprint = None
    if distances:
        words, footprint = _DISTANCE_WORDS[distances[0]]
        parts.append(words)
    sentence = _join(parts)
    if regions and footprint is not None and footprint > 0.3 and centre is not None:
        sentence += " Part of the board may leave the image: that is fine, the corners that stay count."
    return Guidance(sentence, centre, footprint, float(tilt_x), float(tilt_y), False)


def _join(parts: list[str]) -> str:
    if len(parts) == 1:
        text = parts[0]
    else:
        text = ", ".join(parts[:-1]) + ", and " + parts[-1]
    return text[0].upper() + text[1:] + ", then hold it still."


def worst_uncertainty_words(sigma_px: np.ndarray, rows: int, cols: int) -> str:
    """Name the region of an uncertainty map (GY, GX) with the highest uncertainty."""
    gy, gx = np.unravel_index(int(np.argmax(sigma_px)), sigma_px.shape)
    row = min(int(gy / sigma_px.shape[0] * rows), rows - 1)
    col = min(int(gx / sigma_px.shape[1] * cols), cols - 1)
    return region_words(row, col, rows, cols)
