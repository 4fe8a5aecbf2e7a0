"""Synthetic views with known answers: the default board's corners projected through a known lens.

Shared by the solve-core unit tests (test_uncertainty.py, test_robust.py, test_model_choice.py,
...). Poses are placed in image space (`pose_at`: the board centre on a pixel's ray at a distance,
tilted), so every view is visible by construction; `observe` adds gaussian corner noise of a
known sigma per coordinate. Imported as `_synthetic` (pytest's `pythonpath` holds tests/app).
"""

from __future__ import annotations

import cv2
import numpy as np

from calibcoach.app.solve.result import View
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.lens import CameraModel

SIZE = (1280, 720)
BOARD = BoardSpec().corner_points_m()  # (70, 3) the default 8x11 board
IDS = np.arange(BOARD.shape[0], dtype=np.int32)


def pose_at(camera, pixel, distance_m, tilt_x_deg, tilt_y_deg, roll_deg=0.0):
    """T_cam_board putting the board centre on `pixel`'s ray at `distance_m`, tilted (rvec, tvec)."""
    ray = camera.unproject(np.asarray(pixel, float).reshape(1, 2))[0]
    R = cv2.Rodrigues(np.radians([tilt_x_deg, 0.0, 0.0]))[0] @ cv2.Rodrigues(np.radians([0.0, tilt_y_deg, roll_deg]))[0]
    return cv2.Rodrigues(R)[0].reshape(3), ray * distance_m - R @ BOARD.mean(axis=0)


def random_poses(camera, n, rng, *, region=(0.15, 0.85), distance_m=(0.6, 1.0), tilt_deg=35.0, margin_px=5.0,
                 max_off_axis_deg=None):
    """n poses whose 70 corners all land inside the image (`margin_px` margin), in front of the camera.

    `max_off_axis_deg` also keeps every corner's ray within that angle of the optical axis (a
    fisheye's image shows rays past 90 deg; `project` is only trusted where the point is visible).
    """
    w, h = camera.image_size
    poses = []
    while len(poses) < n:
        pixel = rng.uniform([region[0] * w, region[0] * h], [region[1] * w, region[1] * h])
        r, t = pose_at(camera, pixel, rng.uniform(*distance_m), *rng.uniform(-tilt_deg, tilt_deg, 2), rng.uniform(-20, 20))
        cam_pts = BOARD @ cv2.Rodrigues(r)[0].T + t
        if max_off_axis_deg is not None:
            off_axis = np.degrees(np.arccos(cam_pts[:, 2] / np.linalg.norm(cam_pts, axis=1)))
            if off_axis.max() > max_off_axis_deg:
                continue
        px = camera.project(BOARD, r, t)
        if np.all((px >= margin_px) & (px <= [w - 1 - margin_px, h - 1 - margin_px])):
            poses.append((r, t))
    return poses


def observe(camera, poses, rng=None, noise_px=0.2):
    """Views of the board at `poses`, with gaussian corner noise per coordinate when rng is given."""
    views = []
    for i, (r, t) in enumerate(poses):
        px = camera.project(BOARD, r, t)
        if rng is not None:
            px = px + rng.normal(0.0, noise_px, px.shape)
        views.append(View(i, "", IDS, px, BOARD))
    return views


def stacked(poses):
    return np.array([p[0] for p in poses]), np.array([p[1] for p in poses])


def fisheye_lens(hfov_deg: float, size=SIZE, dist=(0.0, 0.0, 0.0, 0.0)) -> CameraModel:
    """An equidistant (Kannala-Brandt) lens whose horizontal field of view is `hfov_deg` (k = 0)."""
    w, h = size
    f = (w / 2.0) / np.radians(hfov_deg / 2.0)
    return CameraModel("fisheye", [[f, 0, (w - 1) / 2.0 + 1.3], [0, f * 0.999, (h - 1) / 2.0 - 0.8], [0, 0, 1]], dist, size)


def detection_at(camera, centre_px, distance_m=0.9, *, tilt_x=0.0, tilt_y=0.0, roll=0.0, keep=None, spec=None):
    """An exact detection of the board placed in image space (`sim_paths.place_board`): the corners
    that land inside the image (and in `keep`, a (N,) bool over the board's corners), float32."""
    from calibcoach.coverage.detector import Detection
    from calibcoach.drivers.sim_paths import place_board

    spec = spec or BoardSpec()
    w, h = camera.image_size
    rvec, tvec = place_board(camera, spec, centre_px, distance_m, tilt_x_deg=tilt_x, tilt_y_deg=tilt_y, roll_deg=roll)
    obj = spec.corner_points_m()
    px = camera.project(obj, rvec, tvec)
    inside = (px[:, 0] >= 0) & (px[:, 0] <= w - 1) & (px[:, 1] >= 0) & (px[:, 1] <= h - 1)
    if keep is not None:
        inside &= keep
    ids = np.nonzero(inside)[0].astype(np.int32)
    return Detection(px[inside].astype(np.float32), ids, obj[inside].astype(np.float32), np.arange(44, dtype=np.int32))
