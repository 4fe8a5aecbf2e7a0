"""Re-detection of the board on a locally undistorted view, for wide and fisheye lenses.

Why: through a 150 deg fisheye a board off axis or far away is bent and squeezed. OpenCV's marker
detector fits straight-sided quads to contours and reads the bits on a perspective grid, so bent
markers are rejected and squeezed ones are read at too few pixels per bit: on rendered fisheye
captures plain `detectBoard` found fewer than 6 corners on 39 of the 242 sharp frames that showed 20+
corners; this recovers 25-27 of them (bench/results/redetect.md).

What: once the lens is roughly known (an incremental solve, or a field-of-view guess), a virtual
pinhole camera is pointed at where the board is (from the markers and corners the plain detection
did find), with a field of view that covers the whole board plus a margin and a resolution that
loses nothing the frame has. The frame is resampled into it (the board is then a perspective
image again: straight sides, even bit cells), the same ChArUco detector runs there, and the
corners found are mapped back to the frame through the very maps that made the view, and checked
against a homography of the board in the view (a planar board in a pinhole view) before use.

Mapping back through the same maps makes the corners exact up to interpolation whatever the lens
model's error: a wrong model only bends the view, it does not move the corners. Measured on the
rendered fisheye (bench/redetect.py): with the focal length 2% off, the centre 3 px off and k1 off
by 0.01 the recovered corners' median error stayed 0.06 px (two captures). Refining them again in
the original image (`refine=True`: `cornerSubPix` with OpenCV's ChArUco window rule) made them
worse (95th percentile 0.88 px against 0.44 px over eight captures' recovered frames): the far
boards this recovers leave 1-3 px windows in the frame, where the magnified view's detector had
2.5x more pixels to fit. So it is off by default.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.coverage.virtual_view import seen_in_image
from calibcoach.drivers.geometry import align_z_to
from calibcoach.drivers.lens import CameraModel

# The view covers the board's predicted outline grown by this many squares on each side: the
# outline is extrapolated from a pose fitted to the few markers found (a single 12 px marker
# gives a tilt good to ~10 deg), and the corners at the board's edge need their markers in view.
VIEW_MARGIN_SQUARES = 1.5
# A pinhole view stretches as tan(angle): beyond 60 deg off its axis the resampling magnifies the
# frame 4x in one direction and nothing is gained; a board that large also spans most of the frame.
MAX_HALF_ANGLE_DEG = 60.0
# Cost cap: detectBoard on the view costs ~25 ms at 1280 px (opencv5.md); a board needing more
# is near and large, where the detail lost by a slight downsampling does not matter.
MAX_VIEW_SIDE_PX = 1280
# The view's scale against the frame's finest local scale at the board. Upsampled, the bit cells
# of far markers (~2 px per bit in the frame) come apart for the detector's thresholding, which
# merged them at 1x: on the lost frames of two fisheye captures 1x recovered 2 of 22 frames, 2x 8,
# 2.5x 12, 3x 11 (Lanczos). Magnifying only boards whose squares are small (to 40 or 60 px) made
# no difference on eight captures (26 and 25 of 37 against 25), so the rule stays this simple.
MAGNIFICATION = 2.5
# The maps are computed every MAP_STEP_PX pixels and interpolated: projecting every pixel through
# the fisheye model costs ~90 ms for 800x800; the maps are smooth and the corners are mapped back
# through the interpolated maps themselves, so interpolation never shifts a corner.
MAP_STEP_PX = 8
# A corner is kept when the board's homography in the view predicts it within this share of a
# square: a rough lens model leaves the view slightly curved, while a wrong corner id is a whole
# square off. Residuals of correctly found corners on the rendered fisheye's lost frames: max
# 0.015 square with the true lens, 0.020 with the field-of-view guess, 0.16 with a lens 5% off in
# focal length, 8 px in cx and 0.03 in k1 (99th percentile 0.14).
CONSISTENCY_SQUARES = 0.25
_OUTSIDE = -1.0e4  # map value where the lens shows nothing: remap then reads the border


@dataclass(frozen=True, slots=True)
class LocalView:
    """A virtual pinhole camera looking at the board, and the maps that render it from the frame."""

    rotation: np.ndarray  # (3, 3) virtual camera's axes in the real camera frame (ray_cam = rotation @ ray_view)
    camera_matrix: np.ndarray  # (3, 3) the virtual pinhole's intrinsics
    size: tuple[int, int]  # (width, height) pixels
    map_x: np.ndarray  # (h, w) float32 frame x of each view pixel (_OUTSIDE where the lens shows nothing)
    map_y: np.ndarray  # (h, w) float32 frame y

    def render(self, grey: np.ndarray) -> np.ndarray:
        # Lanczos: the view magnifies, and bilinear's blur merged the bit cells of far markers
        # (recovered 2 of 22 frames against 12 with Lanczos at the same MAGNIFICATION; cubic 10).
        return cv2.remap(grey, self.map_x, self.map_y, cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_CONSTANT, borderValue=128)

    def to_frame(self, view_px: np.ndarray) -> np.ndarray:
        """(N, 2) view pixels -> (N, 2) frame pixels by bilinear lookup of the maps (NaN outside)."""
        p = np.asarray(view_px, np.float64).reshape(-1, 2)
        w, h = self.size
        x0 = np.clip(np.floor(p[:, 0]).astype(int), 0, w - 2)
        y0 = np.clip(np.floor(p[:, 1]).astype(int), 0, h - 2)
        fx, fy = p[:, 0] - x0, p[:, 1] - y0
        out = np.zeros((p.shape[0], 2))
        for k, m in enumerate((self.map_x, self.map_y)):
            out[:, k] = ((1 - fx) * (1 - fy) * m[y0, x0] + fx * (1 - fy) * m[y0, x0 + 1]
                         + (1 - fx) * fy * m[y0 + 1, x0] + fx * fy * m[y0 + 1, x0 + 1])
        corners = np.stack([self.map_x[y0, x0], self.map_x[y0, x0 + 1], self.map_x[y0 + 1, x0], self.map_x[y0 + 1, x0 + 1]])
        out[np.any(corners <= _OUTSIDE / 2, axis=0)] = np.nan
        return out

    def from_frame(self, camera: CameraModel, frame_px: np.ndarray) -> np.ndarray:
        """(N, 2) frame pixels -> (N, 2) view pixels through the lens model (NaN behind the view)."""
        rays = camera.unproject(frame_px) @ self.rotation  # rotation.T @ ray, row-wise
        with np.errstate(divide="ignore", invalid="ignore"):
            plane = np.where(rays[:, 2:3] > 1e-6, rays[:, :2] / rays[:, 2:3], np.nan)
        K = self.camera_matrix
        return np.stack([K[0, 0] * plane[:, 0] + K[0, 2], K[1, 1] * plane[:, 1] + K[1, 2]], axis=1)


def hint_points(hint: Detection, board: cv2.aruco.CharucoBoard) -> tuple[np.ndarray, np.ndarray]:
    """((K, 2) frame pixels, (K, 3) board points, metres) of every corner and marker corner in `hint`."""
    index = {int(m): k for k, m in enumerate(np.asarray(board.getIds()).reshape(-1))}
    quads = np.asarray(board.getObjPoints(), np.float64).reshape(-1, 4, 3)
    px, obj = [hint.corners_px.astype(np.float64).reshape(-1, 2)], [hint.object_points_m.astype(np.float64).reshape(-1, 3)]
    for mid, quad in zip(hint.marker_ids, hint.marker_corners_px, strict=False):  # rebuilt detections have no quads
        k = index.get(int(mid))
        if k is not None:
            px.append(np.asarray(quad, np.float64).reshape(4, 2))
            obj.append(quads[k])
    return np.concatenate(px), np.concatenate(obj)


def local_view_of(camera: CameraModel, hint_px: np.ndarray, hint_board_m: np.ndarray,
                  board_size_m: tuple[float, float], square_m: float) -> LocalView | None:
    """The virtual pinhole view of the whole board, from a few of its points seen in the frame.

    A pose is fitted to the hint's rays in a frame looking along their mean (so rays beyond 90 deg
    of a fisheye still work), the board's outline (grown by `VIEW_MARGIN_SQUARES`) is put through
    it, and the view looks at the board's centre with the least rotation from the camera (so the
    view keeps the frame's up). None when the hint does not fix a pose.
    """
    if hint_px.shape[0] < 4:
        return None
    rays = camera.unproject(hint_px)
    if not np.all(np.isfinite(rays)):
        return None
    R0 = align_z_to(rays.mean(axis=0))
    local = rays @ R0
    if np.any(local[:, 2] < 0.05):
        return None  # the hint spans more than a hemisphere: not one board
    normalised = (local[:, :2] / local[:, 2:3]).reshape(-1, 1, 2)
    ok, rvec, tvec = cv2.solvePnP(hint_board_m.reshape(-1, 1, 3), normalised, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    if not ok or not np.all(np.isfinite(tvec)):
        return None
    Rb, _ = cv2.Rodrigues(rvec)
    w_m, h_m = board_size_m
    m = VIEW_MARGIN_SQUARES * square_m
    outline = np.array([[-m, -m, 0], [w_m + m, -m, 0], [w_m + m, h_m + m, 0], [-m, h_m + m, 0], [w_m / 2, h_m / 2, 0]])
    in_camera = (outline @ Rb.T + tvec.reshape(3)) @ R0.T
    if np.any((in_camera @ R0)[:, 2] <= 0):
        return None  # a pose with the board behind the hint's own frame: the fit failed
    rotation = align_z_to(in_camera[4])
    in_view = in_camera[:4] @ rotation
    limit = np.tan(np.deg2rad(MAX_HALF_ANGLE_DEG))
    with np.errstate(divide="ignore", invalid="ignore"):
        plane = np.where(in_view[:, 2:3] > 1e-6, in_view[:, :2] / in_view[:, 2:3], np.sign(in_view[:, :2]) * limit)
    lo, hi = np.clip(plane.min(axis=0), -limit, limit), np.clip(plane.max(axis=0), -limit, limit)
    scale = MAGNIFICATION * _frame_px_per_plane_unit(camera, rotation)
    if not np.isfinite(scale) or np.any(hi - lo <= 0):
        return None
    scale = min(scale, MAX_VIEW_SIDE_PX / float(np.max(hi - lo)))
    cells = np.maximum(1, np.ceil((hi - lo) * scale / MAP_STEP_PX).astype(int))
    w, h = int(cells[0] * MAP_STEP_PX), int(cells[1] * MAP_STEP_PX)
    K = np.array([[scale, 0, -lo[0] * scale], [0, scale, -lo[1] * scale], [0, 0, 1]])
    map_x, map_y = _maps(camera, rotation, K, (w, h))
    return LocalView(rotation, K, (w, h), map_x, map_y)


def _frame_px_per_plane_unit(camera: CameraModel, rotation: np.ndarray) -> float:
    """The frame's finest scale around the view's axis: largest singular value of d(frame px)/d(view plane)."""
    eps = 1e-3
    rays = np.array([[0, 0, 1], [eps, 0, 1], [0, eps, 1]], np.float64) @ rotation.T
    px = camera.project(rays)
    J = np.stack([px[1] - px[0], px[2] - px[0]], axis=1) / eps
    return float(np.linalg.svd(J, compute_uv=False)[0])


def _maps(camera: CameraModel, rotation: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The view's remap tables, projected every MAP_STEP_PX pixels and linearly interpolated.

    Coarse sample j sits at fine pixel (j + 0.5) * step - 0.5, where cv2.resize's linear scaling
    puts it, so the fine maps interpolate the samples exactly (edges held constant).
    """
    w, h = size
    step = MAP_STEP_PX
    u = (np.arange(w // step) + 0.5) * step - 0.5
    v = (np.arange(h // step) + 0.5) * step - 0.5
    uu, vv = np.meshgrid(u, v)
    plane = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], axis=-1).reshape(-1, 3)
    px, _inside = seen_in_image(camera, plane @ rotation.T)
    px = np.where(np.isfinite(px), px, _OUTSIDE).reshape(uu.shape + (2,)).astype(np.float32)
    map_x = cv2.resize(px[..., 0], (w, h), interpolation=cv2.INTER_LINEAR)
    map_y = cv2.resize(px[..., 1], (w, h), interpolation=cv2.INTER_LINEAR)
    return map_x, map_y


@dataclass(frozen=True, slots=True)
class Redetection:
    """What a re-detection found, and how: for the caller's accounting and the benchmark."""

    detection: Detection  # the merged detection, frame pixels
    view: LocalView
    found_in_view: int  # corners the detector found in the view
    kept_from_first: int  # corners only the plain detection found, kept (consistent with the view's homography)
    dropped: int  # corners found in the view but dropped (outside the frame, off the homography, refinement ran off)
    mapped_px: np.ndarray  # (N, 2) the view's corners mapped back, before refinement (same order as detection.ids)


def redetect_in_local_view(grey: np.ndarray, camera: CameraModel, detector: CharucoBoardDetector, first: Detection,
                           hint: Detection | None = None, *, refine: bool = False) -> Redetection | None:
    """Re-detect the board on a pinhole view around it; None when that finds no more than `first`.

    Args:
        grey: (H, W) uint8 frame.
        camera: the current lens estimate (the view is only as straight as it is right; the
            corners' positions do not depend on it, see the module docstring).
        detector: the session's detector with the print's variant settled (same board, same
            legacy/inverted handling as the plain detection).
        first: the plain detection of this frame (its corners are merged when consistent).
        hint: where the board is, when not from `first` (e.g. the previous frame's detection).
        refine: refine the corners again in the frame (worse on the far boards this recovers;
            see the module docstring).
    """
    spec = detector.spec
    board = spec.cv_board()
    hint_px, hint_m = hint_points(hint if hint is not None else first, board)
    square_m = spec.square_mm / 1000.0
    view = local_view_of(camera, hint_px, hint_m, (spec.squares_x * square_m, spec.squares_y * square_m), square_m)
    if view is None:
        return None
    found = detector.detect(view.render(grey))
    if found.corner_count < 4:
        return None
    board_xy = found.object_points_m[:, :2].astype(np.float64)
    H, _mask = cv2.findHomography(board_xy, found.corners_px.astype(np.float64), cv2.LMEDS)
    if H is None or H.shape != (3, 3):  # collinear corners: OpenCV returns an empty matrix
        return None
    # The view's corners and the plain ones, both checked against the view's homography.
    first_in_view = view.from_frame(camera, first.corners_px) if first.corner_count else np.zeros((0, 2))
    new_ok = _on_homography(H, board_xy, found.corners_px, square_m)
    first_ok = _on_homography(H, first.object_points_m[:, :2], first_in_view, square_m) if first.corner_count else np.zeros(0, bool)
    mapped = view.to_frame(found.corners_px)
    w, h = camera.image_size
    inside = np.all(np.isfinite(mapped), axis=1) & (mapped[:, 0] >= 0) & (mapped[:, 0] <= w - 1) \
        & (mapped[:, 1] >= 0) & (mapped[:, 1] <= h - 1)
    keep = new_ok & inside
    if refine:
        refined, moved_ok = _refine_in_frame(grey, view, H, found.object_points_m[keep, :2].astype(np.float64), mapped[keep], spec)
    else:
        refined, moved_ok = mapped[keep].astype(np.float32), np.ones(int(keep.sum()), bool)
    new_ids = found.ids[keep][moved_ok]
    new_px = refined[moved_ok]
    new_mapped = mapped[keep][moved_ok]
    old = {int(i): k for k, i in enumerate(first.ids) if first_ok[k]}
    ids = sorted(set(old) | {int(i) for i in new_ids})
    if len(ids) <= first.corner_count:
        return None
    new_at = {int(i): k for k, i in enumerate(new_ids)}
    # For a corner both found, the view's position wins: on the frames re-detected (plain
    # detection short of corners: markers bent and squeezed) the plain positions of such corners
    # were off by 0.37 px at the 95th percentile, the view's by 0.16 px (rendered fisheye, 470 corners).
    corners = np.array([new_px[new_at[i]] if i in new_at else first.corners_px[old[i]] for i in ids], np.float32).reshape(-1, 2)
    mapped_px = np.array([new_mapped[new_at[i]] if i in new_at else first.corners_px[old[i]] for i in ids]).reshape(-1, 2)
    all_corners = np.asarray(board.getChessboardCorners(), np.float32).reshape(-1, 3)
    id_array = np.array(ids, np.int32)
    markers, quads = _merged_markers(first, found, view)
    detection = Detection(corners, id_array, all_corners[id_array], markers, quads)
    return Redetection(detection, view, found.corner_count, len(set(old) - set(new_at)),
                       int(found.corner_count - len(new_ids)), mapped_px)


def _on_homography(H: np.ndarray, board_xy: np.ndarray, view_px: np.ndarray, square_m: float) -> np.ndarray:
    """(N,) bool: each point within CONSISTENCY_SQUARES of a square of where H puts it (NaN: False)."""
    xy = np.asarray(board_xy, np.float64).reshape(-1, 2)
    if xy.shape[0] == 0:
        return np.zeros(0, bool)
    predicted = cv2.perspectiveTransform(xy.reshape(-1, 1, 2), H).reshape(-1, 2)
    # the local size of a square in the view, from H's Jacobian at each point
    dx = cv2.perspectiveTransform((xy + [square_m, 0]).reshape(-1, 1, 2), H).reshape(-1, 2) - predicted
    dy = cv2.perspectiveTransform((xy + [0, square_m]).reshape(-1, 1, 2), H).reshape(-1, 2) - predicted
    square_px = np.sqrt(np.abs(dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0]))
    with np.errstate(invalid="ignore"):
        return np.linalg.norm(np.asarray(view_px, np.float64).reshape(-1, 2) - predicted, axis=1) < CONSISTENCY_SQUARES * square_px


def _refine_in_frame(grey: np.ndarray, view: LocalView, H: np.ndarray, board_xy: np.ndarray, frame_px: np.ndarray,
                     spec) -> tuple[np.ndarray, np.ndarray]:
    """cornerSubPix in the frame, each corner with OpenCV's ChArUco window rule.

    OpenCV sizes a ChArUco corner's window by its distance to the nearest marker corner minus
    2 px, between 1 and 10 (so the window never reaches a marker's edges); the marker corners'
    frame positions come from the view's homography, mapped back through the view's maps.
    Returns the refined (N, 2) float32 positions and (N,) bool: the refinement stayed within
    its window (one that ran further locked onto some other edge).
    """
    n = frame_px.shape[0]
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    gap = (spec.square_mm - spec.marker_mm) / 2000.0  # a marker corner sits this far from the corner along x and y
    offsets = np.array([[gap, gap], [gap, -gap], [-gap, gap], [-gap, -gap]])
    near = (board_xy[:, None, :] + offsets[None]).reshape(-1, 2)
    near_view = cv2.perspectiveTransform(near.reshape(-1, 1, 2), H).reshape(-1, 2)
    near_frame = view.to_frame(near_view).reshape(n, 4, 2)
    distance = np.nanmin(np.linalg.norm(near_frame - frame_px[:, None, :], axis=2), axis=1)
    windows = np.clip(np.nan_to_num(distance - 2.0, nan=1.0).astype(int), 1, 10)
    refined = frame_px.astype(np.float32).copy()
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)  # OpenCV's ArUco defaults (maxIter 30, accuracy 0.01)
    for win in np.unique(windows):
        sel = windows == win
        pts = refined[sel].reshape(-1, 1, 2).copy()
        cv2.cornerSubPix(grey, pts, (int(win), int(win)), (-1, -1), criteria)
        refined[sel] = pts.reshape(-1, 2)
    moved = np.linalg.norm(refined - frame_px, axis=1)
    return refined, moved <= windows


def _merged_markers(first: Detection, found: Detection, view: LocalView) -> tuple[np.ndarray, np.ndarray]:
    """Marker ids and frame-pixel quads of both detections (the view's mapped back)."""
    quads = {int(m): q for m, q in zip(first.marker_ids, first.marker_corners_px, strict=False)}
    for m, q in zip(found.marker_ids, found.marker_corners_px, strict=True):
        if int(m) not in quads:
            back = view.to_frame(q.reshape(4, 2))
            if np.all(np.isfinite(back)):
                quads[int(m)] = back.astype(np.float32)
    ids = np.array(sorted(set(int(m) for m in first.marker_ids) | set(quads)), np.int32)
    have = [m for m in ids if int(m) in quads]
    if len(have) != len(ids):  # a rebuilt detection without quads: keep only ids
        return ids, np.zeros((0, 4, 2), np.float32)
    return ids, np.array([quads[int(m)] for m in ids], np.float32).reshape(-1, 4, 2)
