"""Where the board is in one frame: tilt, distance and footprint, from the current intrinsics.

Before the first solve the intrinsics are a field-of-view guess, so tilt and distance are rough
then; the image-space quantities (centre, footprint) never depend on the intrinsics.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from calibcoach.coverage.detector import Detection
from calibcoach.drivers.geometry import tilt_against_sight_deg
from calibcoach.drivers.lens import CameraModel


@dataclass(frozen=True, slots=True)
class BoardPose:
    """The board's pose and footprint in one frame."""

    rvec: np.ndarray  # (3,) float64 Rodrigues, T_cam_board
    tvec: np.ndarray  # (3,) float64 metres, T_cam_board
    tilt_deg: float  # angle between the board normal and the line of sight to the board, 0 = facing the camera
    tilt_x_deg: float  # about the image x axis: positive = top edge further away (see docs/conventions.md)
    tilt_y_deg: float  # about the image y axis: positive = right edge further away
    distance_m: float  # camera to the board's centre (or the visible corners' centroid; see estimate_pose)
    centre_px: np.ndarray  # (2,) float64 centroid of the detected corners
    footprint: float  # sqrt(hull area / image area) of the detected corners, 0..1 ("board size in the image")
    fit_rms_px: float  # how well the board plane fits the corners with these intrinsics


def corner_footprint(corners_px: np.ndarray, image_size: tuple[int, int]) -> float:
    """sqrt(area of the corners' convex hull / image area): 1.0 fills the image."""
    hull = cv2.convexHull(corners_px.reshape(-1, 1, 2).astype(np.float32))
    return float(np.sqrt(max(cv2.contourArea(hull), 0.0) / (image_size[0] * image_size[1])))


def estimate_pose(detection: Detection, camera: CameraModel, board_centre_m: np.ndarray | None = None) -> BoardPose | None:
    """T_cam_board from one detection with fixed intrinsics; None when the corners do not fit a plane.

    Tilt and distance are measured to `board_centre_m` (3,), the board's centre in its own frame,
    when given (a person's sense of where the board is, also for partial views), else to the
    visible corners' centroid.
    """
    return estimate_poses([detection], camera, board_centre_m)[0]


def estimate_poses(detections: Sequence[Detection], camera: CameraModel,
                   board_centre_m: np.ndarray | None = None) -> list[BoardPose | None]:
    """`estimate_pose` of each detection; the rays and the fit are computed for all of them at once
    (a final solve poses hundreds of views)."""
    poses: list[BoardPose | None] = [None] * len(detections)
    usable = [i for i, d in enumerate(detections) if d.corner_count >= 4]
    if not usable:
        return poses
    sizes = [detections[i].corner_count for i in usable]
    bounds = np.cumsum([0, *sizes])
    rays = camera.unproject(np.concatenate([detections[i].corners_px for i in usable]))
    solved: list[tuple[int, np.ndarray, np.ndarray]] = []
    for k, i in enumerate(usable):
        view_rays = rays[bounds[k] : bounds[k + 1]]
        if np.any(view_rays[:, 2] <= 1e-3):
            continue
        normalised = (view_rays[:, :2] / view_rays[:, 2:3]).astype(np.float64).reshape(-1, 1, 2)
        obj = detections[i].object_points_m.astype(np.float64).reshape(-1, 1, 3)
        ok, rvec, tvec = cv2.solvePnP(obj, normalised, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
        if ok and tvec[2, 0] > 0:
            solved.append((i, rvec.reshape(3), tvec.reshape(3)))
    if not solved:
        return poses
    rotations = [cv2.Rodrigues(rvec)[0] for _i, rvec, _t in solved]
    # every solved view's corners in the camera frame, projected in one batch for the fit
    in_camera = np.concatenate([detections[i].object_points_m.astype(np.float64) @ R.T + tvec
                                for (i, _r, tvec), R in zip(solved, rotations, strict=True)])
    misfit = np.sum((camera.project(in_camera) - np.concatenate([detections[i].corners_px for i, _r, _t in solved])) ** 2, axis=1)
    fit_bounds = np.cumsum([0, *(detections[i].corner_count for i, _r, _t in solved)])
    for k, ((i, rvec, tvec), R) in enumerate(zip(solved, rotations, strict=True)):
        detection = detections[i]
        fit_rms = float(np.sqrt(np.mean(misfit[fit_bounds[k] : fit_bounds[k + 1]])))
        centre_board = detection.object_points_m.astype(np.float64).mean(axis=0) if board_centre_m is None else board_centre_m
        centre_cam = R @ np.asarray(centre_board, np.float64).reshape(3) + tvec
        tilt, tilt_x, tilt_y = tilt_against_sight_deg(R[:, 2], centre_cam)
        poses[i] = BoardPose(
            rvec=rvec,
            tvec=tvec,
            tilt_deg=tilt,
            tilt_x_deg=tilt_x,
            tilt_y_deg=tilt_y,
            distance_m=float(np.linalg.norm(centre_cam)),
            centre_px=detection.corners_px.astype(np.float64).mean(axis=0),
            footprint=corner_footprint(detection.corners_px, camera.image_size),
            fit_rms_px=fit_rms,
        )
    return poses
