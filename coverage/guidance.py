"""Guidance in words: one concrete pose to hold next, said so that a person can carry it out.

Every instruction names where in the image the board's centre goes, which edge to tilt away and
by how much (or to face the camera), and how far away to hold it. The words are derived from the
target pose alone, so they cannot disagree with the ghost board the viewer draws from the same
target: `position_words` names the zone of the image the centre falls in (the image split into
five columns and three rows, every zone with a name of its own), `tilt_words` the signs and size
of the two tilts, and the range is said in metres. Short enough to read at arm's length.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

COLUMN_WORDS = ("left edge", "left", "centre", "right", "right edge")  # x zones of a fifth of the width each
ROW_WORDS = ("top", "middle", "bottom")  # y zones of a third of the height each
FRONTAL_DEG = 10.0  # tilts below this are said as "facing the camera"


@dataclass(frozen=True, slots=True)
class Target:
    """Where the board should go next: the board pose in the camera frame and what a person sees of it."""

    centre_px: tuple[float, float]  # where the board's centre should show in the image
    rvec: np.ndarray  # (3,) float64 Rodrigues, T_cam_board (OpenCV's board origin, docs/conventions.md)
    tvec_m: np.ndarray  # (3,) float64 metres, T_cam_board
    tilt_x_deg: float  # against the line of sight: top edge away = positive
    tilt_y_deg: float  # right edge away = positive
    distance_m: float  # camera to the board's centre
    outline_px: np.ndarray  # (4, 2) float64 the chessboard's outer corners at that pose, current intrinsics


@dataclass(frozen=True, slots=True)
class Guidance:
    """The next instruction; `target` is None only when the capture is done."""

    sentence: str
    target: Target | None
    why: str = ""  # what the target is for, e.g. "cuts the expected error by 9%"
    hint: str = ""  # how to hold it, when the frames say so (e.g. most of them smeared)


def zone(centre_px: tuple[float, float], image_size: tuple[int, int]) -> tuple[int, int]:
    """(column 0..4, row 0..2) of the image zone a pixel falls in."""
    w, h = image_size
    col = int(np.clip(np.floor(centre_px[0] / w * len(COLUMN_WORDS)), 0, len(COLUMN_WORDS) - 1))
    row = int(np.clip(np.floor(centre_px[1] / h * len(ROW_WORDS)), 0, len(ROW_WORDS) - 1))
    return col, row


def position_words(centre_px: tuple[float, float], image_size: tuple[int, int]) -> str:
    """'the top-left corner', 'the upper left', 'the left edge', 'the centre', ... for a pixel.

    Example:
        >>> position_words((100, 60), (1280, 720)), position_words((640, 360), (1280, 720))
        ('the top-left corner', 'the centre')
    """
    col, row = zone(centre_px, image_size)
    vertical, horizontal = ROW_WORDS[row], COLUMN_WORDS[col]
    if horizontal.endswith("edge") and vertical != "middle":
        return f"the {vertical}-{horizontal.split()[0]} corner"
    if vertical == "middle":
        return {"centre": "the centre", "left": "left of centre", "right": "right of centre"}.get(horizontal, f"the {horizontal}")
    if horizontal == "centre":
        return f"the {vertical} centre"
    return f"the {'upper' if vertical == 'top' else 'lower'} {horizontal}"


def tilt_words(tilt_x_deg: float, tilt_y_deg: float) -> str:
    """'facing the camera', 'top edge away ~30°', 'top edge ~30° and right edge ~20° away', ..."""
    parts = []
    if abs(tilt_x_deg) >= FRONTAL_DEG:
        parts.append(("top" if tilt_x_deg > 0 else "bottom", abs(tilt_x_deg)))
    if abs(tilt_y_deg) >= FRONTAL_DEG:
        parts.append(("right" if tilt_y_deg > 0 else "left", abs(tilt_y_deg)))
    if not parts:
        return "facing the camera"
    if len(parts) == 1:
        return f"{parts[0][0]} edge tilted away ~{_round_deg(parts[0][1])}°"
    (a, da), (b, db) = parts
    return f"{a} edge tilted away ~{_round_deg(da)}° and {b} edge ~{_round_deg(db)}°"


def sentence_for(target: Target, image_size: tuple[int, int]) -> str:
    """The instruction for a target, e.g. 'Board to the top-left corner, top edge tilted away ~30°, 0.6 m away.'"""
    where = position_words(target.centre_px, image_size)
    to = "to " if not where.startswith(("left of", "right of")) else ""
    return f"Board {to}{where}, {tilt_words(target.tilt_x_deg, target.tilt_y_deg)}, {target.distance_m:.1f} m away."


def _round_deg(value: float) -> int:
    return int(5 * round(value / 5))
