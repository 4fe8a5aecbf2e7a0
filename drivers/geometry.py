"""Small rigid-body helpers shared by the simulator (drivers) and the coverage map (coverage).

Here, in the bottom layer, so that the simulator's notion of tilt and the coverage map's are one
piece of code: a test that says "the careful path reaches 45 deg" and a coverage cell that says
"steep tilt seen" must measure the same angle.
"""

from __future__ import annotations

import cv2
import numpy as np


def align_z_to(direction: np.ndarray) -> np.ndarray:
    """(3, 3) smallest rotation taking the optical axis (0, 0, 1) onto `direction` (3,)."""
    d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    axis = np.cross([0.0, 0.0, 1.0], d)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.eye(3)
    R, _ = cv2.Rodrigues(axis / s * np.arctan2(s, d[2]))
    return R


def tilt_against_sight_deg(normal_cam: np.ndarray, centre_cam: np.ndarray) -> tuple[float, float, float]:
    """(tilt, tilt_x, tilt_y) in degrees of a plane against the line of sight to `centre_cam`.

    The normal is first rotated by the rotation that takes the line of sight onto the optical
    axis, so a board facing the camera in the image corner counts as frontal (foreshortening is
    what constrains the focal length, and it is measured against the line of sight). Signs follow
    docs/conventions.md: tilt_x > 0 when the top edge is further away, tilt_y > 0 for the right edge.

    Args:
        normal_cam: (3,) the plane's normal in the camera frame (either orientation).
        centre_cam: (3,) a point of the plane (its centre), camera frame, metres.
    """
    sight = np.asarray(centre_cam, np.float64) / np.linalg.norm(centre_cam)
    n = np.asarray(normal_cam, np.float64) / np.linalg.norm(normal_cam)
    if n @ sight > 0:
        n = -n  # the normal that faces the camera
    n = align_z_to(sight).T @ n
    tilt = float(np.degrees(np.arccos(np.clip(-n[2], -1.0, 1.0))))
    return tilt, float(np.degrees(np.arctan2(-n[1], -n[2]))), float(np.degrees(np.arctan2(n[0], -n[2])))
