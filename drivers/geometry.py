"""Small rigid-body helpers shared by the simulator (drivers) and the coverage map (coverage).

Here, in the bottom layer, so that the simulator's notion of tilt and the coverage map's are one
piece of code: a test that says "the careful path reaches 45 deg" and a coverage cell that says
"steep tilt seen" must measure the same angle.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

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
    # `align_z_to(sight).T @ n` written out (Rodrigues' formula, axis z x sight, cos = sight_z): the
    # final solve poses hundreds of views, and the matrix route cost ~0.3 ms of NumPy calls a view.
    cx, cy, cz = (float(v) for v in np.asarray(centre_cam, np.float64).reshape(3))
    nx, ny, nz = (float(v) for v in np.asarray(normal_cam, np.float64).reshape(3))
    sight_norm, normal_norm = math.sqrt(cx * cx + cy * cy + cz * cz), math.sqrt(nx * nx + ny * ny + nz * nz)
    dx, dy, dz = cx / sight_norm, cy / sight_norm, cz / sight_norm
    nx, ny, nz = nx / normal_norm, ny / normal_norm, nz / normal_norm
    if nx * dx + ny * dy + nz * dz > 0:
        nx, ny, nz = -nx, -ny, -nz  # the normal that faces the camera
    s = math.hypot(dx, dy)
    if s >= 1e-12:
        kx, ky = -dy / s, dx / s  # the rotation axis, in the image plane
        along = (kx * nx + ky * ny) * (1.0 - dz)
        # v cos(t) - (k x v) sin(t) + k (k . v)(1 - cos(t)), with cos(t) = dz and sin(t) = s
        nx, ny, nz = (nx * dz - ky * nz * s + kx * along,
                      ny * dz + kx * nz * s + ky * along,
                      nz * dz - (kx * ny - ky * nx) * s)
    tilt = math.degrees(math.acos(min(max(-nz, -1.0), 1.0)))
    return tilt, math.degrees(math.atan2(-ny, -nz)), math.degrees(math.atan2(nx, -nz))


def pose_matrix(rvec: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix of a Rodrigues vector (3,)."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3))
    return R


def board_centre_m(squares_x: int, squares_y: int, square_m: float) -> np.ndarray:
    """(3,) float64 centre of a ChArUco board's chessboard area in the board frame, metres."""
    return np.array([squares_x * square_m / 2.0, squares_y * square_m / 2.0, 0.0])


def facing_orientation(ray: np.ndarray, tilt_x_deg: float, tilt_y_deg: float, roll_deg: float, *,
                       aligned: np.ndarray | None = None) -> np.ndarray:
    """(3, 3) R_cam_board of a board facing the line of sight `ray` (3,), then tilted and rolled.

    Rx(-tilt_x) tips the top edge away and Ry(-tilt_y) the right edge (docs/conventions.md); roll
    turns the board in its own plane first. `tilt_against_sight_deg` measures the same angles back.
    `aligned`: `align_z_to(ray)` where the caller has it (the candidate grid turns one ray nine ways).
    """
    tip_x, tip_y, turn = _turns(float(tilt_x_deg), float(tilt_y_deg), float(roll_deg))
    return (align_z_to(ray) if aligned is None else aligned) @ tip_x @ tip_y @ turn


@functools.lru_cache(maxsize=256)
def _turns(tilt_x_deg: float, tilt_y_deg: float, roll_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The three rotations of `facing_orientation`, kept (read-only): the candidate grid asks for the same
    nine tilts at every position after every lens change."""
    tx, ty, roll = np.radians([tilt_x_deg, tilt_y_deg, roll_deg])
    turns = pose_matrix([-tx, 0.0, 0.0]), pose_matrix([0.0, -ty, 0.0]), pose_matrix([0.0, 0.0, roll])
    for matrix in turns:
        matrix.flags.writeable = False
    return turns


def pose_facing_pixel(ray: np.ndarray, centre_board_m: np.ndarray, distance_m: float, *, tilt_x_deg: float = 0.0,
                      tilt_y_deg: float = 0.0, roll_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """T_cam_board putting the board point `centre_board_m` (3,) `distance_m` away along the unit `ray` (3,).

    Returns (rvec (3,), tvec (3,) metres); the board is oriented by `facing_orientation`.
    """
    rvec, (t,) = poses_facing_pixel(ray, centre_board_m, [distance_m], tilt_x_deg=tilt_x_deg, tilt_y_deg=tilt_y_deg,
                                    roll_deg=roll_deg)
    return rvec, t


def poses_facing_pixel(ray: np.ndarray, centre_board_m: np.ndarray, distances_m: Sequence[float], *,
                       tilt_x_deg: float = 0.0, tilt_y_deg: float = 0.0,
                       roll_deg: float = 0.0, aligned: np.ndarray | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    """`pose_facing_pixel` at several distances along one ray: (rvec (3,), one tvec (3,) per distance).

    The orientation does not depend on the distance, so it is built once (the candidate grid asks
    for three ranges of every position and tilt; each tvec is the same number as one by one).
    `aligned`: as for `facing_orientation`.
    """
    R = facing_orientation(ray, tilt_x_deg, tilt_y_deg, roll_deg, aligned=aligned)
    direction = np.asarray(ray, np.float64)
    norm = np.linalg.norm(ray)
    offset = R @ np.asarray(centre_board_m, np.float64)
    tvecs = [distance_m * direction / norm - offset for distance_m in distances_m]
    rvec, _ = cv2.Rodrigues(R)
    return rvec.reshape(3), tvecs
