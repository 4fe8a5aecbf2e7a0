"""What the detector would find of the board at a pose: the corners of a virtual view.

Next-best-pose guidance must only ask for poses whose frames calibcoach can register. Rather than
a rule of thumb ("not too far, not too steep"), each candidate pose is projected through the
current intrinsics and the detector's own limits are applied to every marker:

- every marker corner in front of the lens, on the lens model's invertible branch, and at least
  `BORDER_MARGIN_PX` inside the image (OpenCV's `minDistanceToBorder` is 3 px);
- every side of the projected marker at least `min_marker_px` long: the marker's bit cells
  (5 bits + 2 border cells across a 5x5 marker) must each span `MIN_BIT_PX` pixels to be read.
  Fitted on 120 random poses rendered through the 70 and 150 deg lenses (any tilt to 60 deg,
  any roll, 30-80% of the image height): at 2.8 px per cell the predicted corner counts total
  1671 and 1524 against 1732 and 1661 found by detectBoard; at 2.2 px the model promised 35%
  more than was found, nearly all of it at far distances. Where the two disagree the model errs
  on the safe side of asking for poses that register;
- every side nearly straight: a fisheye bends the sides of large off-axis markers, and OpenCV's
  contour-to-quad step rejects a contour whose sides bow more than its polygon tolerance (3% of
  the perimeter, about 12% of a side); the limit here is 10% of the side.

A ChArUco corner is found when both markers beside it are (OpenCV's `minMarkers` = 2).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from calibcoach.coverage.board import BoardSpec, dictionary_id
from calibcoach.drivers.geometry import board_centre_m, pose_matrix
from calibcoach.drivers.lens import CameraModel, radial_fold

MIN_BIT_PX = 2.8  # px per marker bit cell for a reliable read (see the module docstring)
BORDER_MARGIN_PX = 3.0  # OpenCV's minDistanceToBorder
MAX_SIDE_BOW = 0.10  # a marker side's midpoint off its chord, as a share of the side


@dataclass(frozen=True, slots=True)
class BoardGeometry:
    """The board's points in its own frame, precomputed once per board."""

    corners_m: np.ndarray  # (N, 3) float64 ChArUco corners, board frame, metres (index = corner id)
    marker_corners_m: np.ndarray  # (M, 4, 3) float64 each marker's corners, board frame, metres
    marker_mids_m: np.ndarray  # (M, 4, 3) float64 midpoints of each marker's sides
    corner_markers: np.ndarray  # (N, 2) int64 the two markers beside each corner (indices into markers)
    centre_m: np.ndarray  # (3,) float64 centre of the chessboard area
    outline_m: np.ndarray  # (4, 3) float64 outer corners of the chessboard area, clockwise from the origin
    min_marker_px: float  # shortest projected marker side the detector reads reliably
    height_m: float  # chessboard height (squares_y * square), metres
    marker_m: float  # marker side, metres

    @staticmethod
    def of(spec: BoardSpec) -> BoardGeometry:
        board = spec.cv_board()
        corners = np.asarray(board.getChessboardCorners(), np.float64).reshape(-1, 3)
        markers = np.asarray(board.getObjPoints(), np.float64).reshape(-1, 4, 3)
        mids = 0.5 * (markers + np.roll(markers, -1, axis=1))
        centres = markers.mean(axis=1)
        sq = spec.square_mm / 1000.0
        # The markers sit in the white squares touching a corner diagonally, sq / sqrt(2) from it.
        dist = np.linalg.norm(corners[:, None, :2] - centres[None, :, :2], axis=2)
        beside = np.argsort(dist, axis=1)[:, :2]
        if not np.all(np.take_along_axis(dist, beside, axis=1) < 0.8 * sq):
            raise ValueError("every ChArUco corner should have two markers beside it")  # a board OpenCV cannot make
        bits = cv2.aruco.getPredefinedDictionary(dictionary_id(spec.dictionary)).markerSize
        w, h = spec.squares_x * sq, spec.squares_y * sq
        return BoardGeometry(
            corners_m=corners, marker_corners_m=markers, marker_mids_m=mids, corner_markers=beside,
            centre_m=board_centre_m(spec.squares_x, spec.squares_y, sq),
            outline_m=np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], np.float64),
            min_marker_px=MIN_BIT_PX * (bits + 2), height_m=h, marker_m=spec.marker_mm / 1000.0,
        )


@dataclass(frozen=True, slots=True)
class VirtualView:
    """The corners a frame at `rvec`, `tvec` would give, as the current intrinsics predict them."""

    rvec: np.ndarray  # (3,) float64 T_cam_board
    tvec: np.ndarray  # (3,) float64 T_cam_board, metres
    ids: np.ndarray  # (K,) int32 corner ids the detector would find
    object_points_m: np.ndarray  # (K, 3) float64
    image_points_px: np.ndarray  # (K, 2) float64
    outline_px: np.ndarray  # (4, 2) float64 the chessboard's outer corners (may lie outside the image)

    @property
    def corner_count(self) -> int:
        return int(self.ids.size)


def seen_in_image(camera: CameraModel, points_cam: np.ndarray, margin_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Project (N, 3) camera-frame points; ((N, 2) pixels, (N,) bool seen inside the image).

    Seen means: in front of the lens on the model's invertible branch (a pinhole point in front of
    the camera within the radial profile's fold, a fisheye ray within its fold angle, which may
    pass 90 deg), and inside the image by `margin_px`. Checking the fold instead of round-tripping
    through `unproject` keeps scoring hundreds of candidate poses cheap.
    """
    pts = np.asarray(points_cam, np.float64).reshape(-1, 3)
    fold = radial_fold(camera)
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    r = np.hypot(x, y)
    if camera.model == "fisheye":
        ok = np.arctan2(r, z) < fold
    else:
        ok = (z > 1e-6) & (r < fold * np.maximum(z, 1e-6))
    px = np.full((pts.shape[0], 2), np.nan)
    if ok.any():
        px[ok] = camera.project(pts[ok])
    w, h = camera.image_size
    inside = ok & np.all(np.isfinite(px), axis=1)
    inside &= (px[:, 0] >= margin_px - 0.5) & (px[:, 0] <= w - 0.5 - margin_px)
    inside &= (px[:, 1] >= margin_px - 0.5) & (px[:, 1] <= h - 0.5 - margin_px)
    return px, inside


def virtual_view(camera: CameraModel, board: BoardGeometry, rvec: np.ndarray, tvec: np.ndarray) -> VirtualView:
    """The detectable corners of the board at T_cam_board (`rvec` (3,), `tvec` (3,) metres)."""
    return virtual_views(camera, board, [(rvec, tvec)])[0]


def virtual_views(camera: CameraModel, board: BoardGeometry, poses: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[VirtualView]:
    """`virtual_view` of each (rvec, tvec), projected in one batch (the candidates are hundreds of poses)."""
    if not poses:
        return []
    R = np.stack([pose_matrix(rvec) for rvec, _t in poses])  # (K, 3, 3)
    t = np.stack([np.asarray(tvec, np.float64).reshape(3) for _r, tvec in poses])  # (K, 3)
    M, n = board.marker_corners_m.shape[0], board.corners_m.shape[0]
    local = np.concatenate([board.marker_corners_m.reshape(-1, 3), board.marker_mids_m.reshape(-1, 3),
                            board.corners_m, board.outline_m])  # (Q, 3)
    pts = np.einsum("qj,kij->kqi", local, R) + t[:, None, :]  # (K, Q, 3) in the camera frame
    px, seen = seen_in_image(camera, pts.reshape(-1, 3), BORDER_MARGIN_PX)
    K = len(poses)
    px, seen = px.reshape(K, -1, 2), seen.reshape(K, -1)
    quad, quad_seen = px[:, : 4 * M].reshape(K, M, 4, 2), seen[:, : 4 * M].reshape(K, M, 4)
    mids, mids_seen = px[:, 4 * M : 8 * M].reshape(K, M, 4, 2), seen[:, 4 * M : 8 * M].reshape(K, M, 4)
    corner_px, corner_seen = px[:, 8 * M : 8 * M + n], seen[:, 8 * M : 8 * M + n]
    outline_px = px[:, 8 * M + n :]
    with np.errstate(invalid="ignore"):
        following = np.roll(quad, -1, axis=2)
        sides = np.linalg.norm(following - quad, axis=3)  # (K, M, 4)
        bow = np.linalg.norm(mids - 0.5 * (quad + following), axis=3) / np.maximum(sides, 1e-9)
        readable = quad_seen.all(2) & mids_seen.all(2) & (sides.min(2) >= board.min_marker_px) & (bow.max(2) <= MAX_SIDE_BOW)
    found = corner_seen & readable[:, board.corner_markers].all(axis=2)  # (K, n)
    views = []
    for k, (rvec, _t) in enumerate(poses):
        ids = np.nonzero(found[k])[0].astype(np.int32)
        views.append(VirtualView(np.asarray(rvec, np.float64).reshape(3), t[k], ids, board.corners_m[ids],
                                 corner_px[k][ids], outline_px[k]))
    return views
