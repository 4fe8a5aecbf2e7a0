"""Poses a person can hold and calibcoach can register: the candidates next-best-pose guidance picks from.

A candidate is said the way a person thinks of it: where in the image the board's centre goes,
how far away it is (range from the camera to the board's centre), and which way it is tilted
against the line of sight. Positions span the image on a 5 x 3 grid (boards near the border
run partly out of view on purpose: the corners that stay are where distortion is strongest);
tilts are frontal, 30 deg and 50 deg towards each of the four edges (the method asks for 30-60);
ranges are near, mid and far.

Ranges come from the board and the current intrinsics, so they mean the same on every lens:
far is where a frontal board spans ~38% of the image height (never beyond 90% of the range at
which its markers stop being readable), mid ~52%, near ~72%. A candidate is kept only when its
virtual view (`virtual_view.py`) shows at least `MIN_TARGET_CORNERS` detectable corners, every
board corner stays `MIN_RANGE_M` in front of the lens, and its tilt is at most 50 deg.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calibcoach.coverage.detector import MIN_FRAME_CORNERS
from calibcoach.coverage.virtual_view import BoardGeometry, VirtualView, virtual_views
from calibcoach.drivers.geometry import align_z_to, pose_matrix, poses_facing_pixel
from calibcoach.drivers.lens import CameraModel

POSITIONS_X = (0.1, 0.3, 0.5, 0.7, 0.9)  # board centre, share of the image width
POSITIONS_Y = (0.12, 0.5, 0.88)  # and of its height
TILTS_DEG = ((0.0, 0.0), (30.0, 0.0), (-30.0, 0.0), (0.0, 30.0), (0.0, -30.0),
             (50.0, 0.0), (-50.0, 0.0), (0.0, 50.0), (0.0, -50.0))  # (tilt_x, tilt_y)
HEIGHT_SHARE = {"far": 0.38, "mid": 0.52, "near": 0.72}  # frontal board height over image height
RANGE_NAMES = ("near", "mid", "far")
MIN_TARGET_CORNERS = 16  # ~a quarter of the default board: a partial view that still pins its pose
# ... for a smaller board a quarter of it, never under the method's 6 a frame needs to count: a
# fixed 16 left a 4 x 5 board (12 corners) without a single candidate, so without guidance.
MIN_RANGE_M = 0.12  # no board corner closer to the lens than this (a hand, a focus limit)
_READABLE_SHARE = 0.9  # far stays within 90% of the range where frontal markers become unreadable


@dataclass(frozen=True, slots=True)
class Ranges:
    """Representative ranges (m) of near, mid and far, and the limits between them."""

    near_m: float
    mid_m: float
    far_m: float

    @property
    def near_max_m(self) -> float:
        return float(np.sqrt(self.near_m * self.mid_m))

    @property
    def far_min_m(self) -> float:
        return float(np.sqrt(self.mid_m * self.far_m))

    def cell(self, range_m: float) -> str:
        """'near', 'mid' or 'far' for a board centre `range_m` from the camera."""
        return "near" if range_m <= self.near_max_m else "far" if range_m >= self.far_min_m else "mid"

    def of(self, name: str) -> float:
        return {"near": self.near_m, "mid": self.mid_m, "far": self.far_m}[name]


def ranges_for(camera: CameraModel, board: BoardGeometry) -> Ranges:
    """Near, mid and far for this board on this lens (focal length at the image centre)."""
    f = 0.5 * (camera.fx + camera.fy)
    h = camera.image_size[1]
    share_range = {name: board.height_m * f / (share * h) for name, share in HEIGHT_SHARE.items()}
    readable = board.marker_m * f / board.min_marker_px  # frontal markers at the centre shrink to the limit here
    far = min(share_range["far"], _READABLE_SHARE * readable)
    mid = min(share_range["mid"], 0.8 * far)
    near = min(share_range["near"], 0.8 * mid)
    return Ranges(near_m=float(near), mid_m=float(mid), far_m=float(far))


@dataclass(frozen=True, slots=True)
class CandidatePose:
    """One pose to ask for, in a person's terms and as the board pose that realises it."""

    key: tuple[int, int, int, str]  # (position x index, position y index, tilt index, range name): stable identity
    centre_px: tuple[float, float]  # where the board's centre should show
    range_m: float  # camera to board centre
    range_name: str
    tilt_x_deg: float  # top edge away = positive
    tilt_y_deg: float  # right edge away = positive
    view: VirtualView  # the pose (rvec, tvec) and the corners it would give


def candidate_poses(camera: CameraModel, board: BoardGeometry, ranges: Ranges) -> list[CandidatePose]:
    """Every candidate pose that a person can hold and the detector would register (see module docstring)."""
    w, h = camera.image_size
    centres = np.array([[fx * w, fy * h] for fy in POSITIONS_Y for fx in POSITIONS_X])
    rays = camera.unproject(centres)
    distances = [ranges.of(name) for name in RANGE_NAMES]
    placed = []  # (key, centre, range, name, tilt_x, tilt_y, rvec, tvec) of the poses that keep clear of the lens
    for k, (centre, ray) in enumerate(zip(centres, rays, strict=True)):
        ix, iy = k % len(POSITIONS_X), k // len(POSITIONS_X)
        aligned = align_z_to(ray)  # one line of sight for the nine tilts
        for it, (tx, ty) in enumerate(TILTS_DEG):
            # one orientation for the three ranges: a rebuild of the 720p lens's grid 64 -> 51 ms, same poses
            rvec, tvecs = poses_facing_pixel(ray, board.centre_m, distances, tilt_x_deg=tx, tilt_y_deg=ty, aligned=aligned)
            outline_turned = board.outline_m @ pose_matrix(rvec).T
            for name, rng, tvec in zip(RANGE_NAMES, distances, tvecs, strict=True):
                if np.min((outline_turned + tvec)[:, 2]) < MIN_RANGE_M:
                    continue
                placed.append(((ix, iy, it, name), centre, rng, name, tx, ty, rvec.copy(), tvec))
    views = virtual_views(camera, board, [(p[6], p[7]) for p in placed])
    need = target_corners(len(board.corners_m))
    return [CandidatePose(key, (float(centre[0]), float(centre[1])), float(rng), name, float(tx), float(ty), view)
            for (key, centre, rng, name, tx, ty, _r, _t), view in zip(placed, views, strict=True)
            if view.corner_count >= need]


def target_corners(board_corners: int) -> int:
    """Detectable corners a candidate's view must show: MIN_TARGET_CORNERS, or a quarter of a smaller board.

    Example:
        >>> target_corners(70), target_corners(361), target_corners(12), target_corners(35)
        (16, 16, 6, 8)
    """
    return max(MIN_FRAME_CORNERS, min(MIN_TARGET_CORNERS, board_corners // 4))


def cell_index(px: np.ndarray, extent_px: float, cells: int) -> np.ndarray:
    """The region cell (0 .. cells-1) each pixel coordinate along one image axis falls in; outside the image, the nearest."""
    return np.clip((np.asarray(px, np.float64) / extent_px * cells).astype(int), 0, cells - 1)


def region_cell_counts(point_sets: Sequence[np.ndarray], image_size: tuple[int, int],
                       grid_shape: tuple[int, int]) -> np.ndarray:
    """(K, rows, cols) int: how many of each of K sets of (N, 2) pixels fall in each region cell,
    counted for all sets in one bincount (candidates and kept frames are counted by hundreds)."""
    rows, cols = grid_shape
    w, h = image_size
    if not point_sets:
        return np.zeros((0, rows, cols), np.intp)
    px = np.concatenate([np.asarray(p, np.float64).reshape(-1, 2) for p in point_sets])
    owner = np.repeat(np.arange(len(point_sets)), [np.asarray(p).reshape(-1, 2).shape[0] for p in point_sets])
    r, c = cell_index(px[:, 1], h, rows), cell_index(px[:, 0], w, cols)
    counts = np.bincount(owner * rows * cols + r * cols + c, minlength=len(point_sets) * rows * cols)
    return counts.reshape(len(point_sets), rows, cols)


# A region cell asks for 10 corner observations (`CoverageRequirements`), a seventh of the default
# board's 70 corners; a cell counts as reachable when one candidate pose puts that share of its
# board there. Asking a small board for the default board's 10 at once asked caliscope's 4 x 5 board
# (12 corners) for 83% of itself in one cell: no cell was reachable, the region axis stayed at zero
# and no capture of it could ever be trusted. Its requirement itself (10 observations, over frames)
# is unchanged.
REACHABLE_SHARE_OF_BOARD = 1 / 7
MIN_CORNERS_TO_REACH = 2


def corners_to_reach(requirement: int, board_corners: int) -> int:
    """Corners one candidate must put in a region cell for the cell to be reachable (see REACHABLE_SHARE_OF_BOARD).

    Example:
        >>> corners_to_reach(10, 70), corners_to_reach(10, 361), corners_to_reach(10, 12), corners_to_reach(10, 24)
        (10, 10, 2, 3)
    """
    return max(MIN_CORNERS_TO_REACH, min(requirement, int(board_corners * REACHABLE_SHARE_OF_BOARD + 1e-9)))


def reachable_cells(candidates: Sequence[CandidatePose], image_size: tuple[int, int], grid_shape: tuple[int, int],
                    need: int) -> np.ndarray:
    """(rows, cols) bool: region cells into which some candidate puts at least `need` detectable corners
    (`corners_to_reach`).

    These are the cells a board can be seen in on this lens: a fisheye's black corners, or image
    corners beyond ~85 deg where no board can be read, are not among them.
    """
    if not candidates:
        return np.zeros(grid_shape, bool)
    counts = region_cell_counts([cand.view.image_points_px for cand in candidates], image_size, grid_shape)
    return counts.max(axis=0) >= need  # most corners one candidate puts in a cell


def lens_moved_px(a: CameraModel, b: CameraModel) -> float:
    """Largest pixel shift between two models over a 9 x 5 grid of a's image (inf on a model change)."""
    if a.model != b.model:
        return float("inf")
    w, h = a.image_size
    grid = np.stack(np.meshgrid(np.linspace(0.05, 0.95, 9) * w, np.linspace(0.05, 0.95, 5) * h), -1).reshape(-1, 2)
    moved = b.project(a.unproject(grid)) - grid
    return float(np.max(np.linalg.norm(moved, axis=1))) if np.all(np.isfinite(moved)) else float("inf")
