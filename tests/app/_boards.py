"""A printed board in a camera frame, for tests of detection and of what is said about boards."""

from __future__ import annotations

import cv2
import numpy as np

from calibcoach.coverage.board import BoardSpec


def board_photo(spec: BoardSpec, *, legacy: bool = False, tilt: float = 0.12) -> np.ndarray:
    """The board printed by OpenCV, put in a 1280x720 frame under a mild perspective."""
    flat = spec.cv_board(legacy=legacy).generateImage((440, 605), marginSize=20)
    h, w = flat.shape
    src = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
    dst = np.float32([[400, 60], [400 + w * (1 - tilt), 90], [400 + w * (1 - tilt), 60 + h - 30], [400, 60 + h]])
    H = cv2.getPerspectiveTransform(src, dst)
    return cv2.warpPerspective(flat, H, (1280, 720), borderValue=128)


def board_on_axis(spec: BoardSpec, tilt_deg: float, distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(rvec, tvec) of `spec`'s board with its centre on the optical axis at `distance_m`, turned
    `tilt_deg` about its vertical axis (and 10 deg about its horizontal one)."""
    R = cv2.Rodrigues(np.array([np.radians(10.0), np.radians(tilt_deg), 0.0]))[0]
    centre = np.array([*spec.size_mm, 0.0]) / 2000.0
    return cv2.Rodrigues(R)[0].ravel(), np.array([0.0, 0.0, distance_m]) - R @ centre
