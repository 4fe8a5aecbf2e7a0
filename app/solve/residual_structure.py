"""Whether the residuals left by a solve are noise, or a pattern fixed to the board or to the image.

Corner noise differs from frame to frame and averages out over poses. Two errors do not, and no
amount of capturing removes them:

- **fixed to the board**: the print is not where the spec says -- not flat, printed unevenly (a
  slipping paper feed), a laminated sheet that crept. The same corner of the board then lands off
  by the same amount (in board millimetres) from every pose, and the lens model absorbs part of
  it (a real 20x20 board of 4 mm squares: 11-12 um from each of three cameras, the same pattern;
  one camera's per-corner means applied to another's board lowered its RMS 3-10% and moved fx by
  up to 0.23%). An even stretch along one side is not seen: the focal lengths absorb it whole.
- **fixed to the image**: the lens model misses the lens (or the sensor reads out in lines while
  the board moves). Residuals at one place in the image then agree whichever corner lands there.

Each test averages the residuals of one pose first (frames of one hold, `look_alike_groups`, are
one pose measured k times; their average is the unit), then compares how far the means of a board
corner (or of an image cell) sit from zero against what the scatter of its poses explains. The
ratio is ~1 for pure noise (an F statistic: the between-pose variance of a mean over n poses is
1/n of the scatter) and grows with a fixed pattern.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from calibcoach.app.solve.result import Calibration, View
from calibcoach.drivers.lens import CameraModel

# A board corner (or image cell) is judged once seen in this many distinct poses: from fewer, its
# mean and its scatter are both too loose to compare (2 poses: one degree of freedom each way).
MIN_POSES = 3
# At least this many places so judged before a verdict: the ratio of K pooled 2-D means scatters
# with a standard deviation of about 1 / sqrt(K) under pure noise. Board corners: 20 (sd 0.22; a
# board of 70 corners seen in a dozen poses judges nearly all). Image cells: 10 (sd 0.32), as a
# capture of ~15 poses puts 3 of them into only 10-20 of the 48 cells (simulated captures).
MIN_CORNERS = 20
MIN_CELLS = 10
# Flagged when the fixed part's variance is at least twice what noise explains: 3-4 standard
# deviations of the ratio above 1, which noise alone does not reach (11 renders of flat boards
# through lenses their model fits: board 0.78-1.13, image 0.68-1.50; bench/residual_patterns.py);
# a real board of 4 mm squares, seen by three cameras, read 3.3-8.1 (11-12 um, the same pattern
# from each camera: bench/real_captures.py).
FIXED_RATIO = 2.0
# ... and when the fixed part is large enough to matter: 0.02 px per coordinate, the smallest error
# target the verdict sets for E (`verdict.ERROR_TARGET_FLOOR_PX`, at 720p). Unlike noise a fixed
# part does not average out over frames, so one under the corner noise still biases the lens; under
# 0.02 px no user would see it. (Flat simulated boards: at most 0.007 px, at ratio ~1.)
FIXED_PX = 0.02
_IMAGE_GRID = (8, 6)  # cells across and down the image: 160 x 120 px at 720p (a lens misfit varies slowly)
_STEP_M = 1e-4  # board step for the local pixel-per-metre Jacobian (0.1 mm: linear at any range)


@dataclass(frozen=True, slots=True)
class FixedPattern:
    """How much of the residual repeats at one place (a board corner, or an image cell)."""

    ratio: float  # variance of the places' means over what the scatter of their poses explains (~1: none)
    rms_px: float  # the repeating part, px per coordinate (noise's share of the means removed)
    places: int  # corners (cells) seen in >= MIN_POSES poses, the ones judged
    least: int  # how many places a verdict needs (MIN_CORNERS, MIN_CELLS)

    @property
    def judged(self) -> bool:
        return self.places >= self.least and np.isfinite(self.ratio)

    @property
    def flagged(self) -> bool:
        return self.judged and self.ratio >= FIXED_RATIO and self.rms_px >= FIXED_PX


@dataclass(frozen=True, slots=True)
class ResidualStructure:
    board: FixedPattern  # residuals repeating at the same board corner, measured in board millimetres
    board_rms_mm: float  # the board's repeating part on the board itself, mm per coordinate
    image: FixedPattern  # residuals repeating at the same place in the image
    # the judged board corners: (K,) ids, (K, 2) where they sit on the board (m), their mean residual there (mm)
    board_corner_ids: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.int32))
    board_corners_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    board_means_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def summary(self) -> dict[str, object]:
        return {
            "board_fixed_ratio": round(self.board.ratio, 3), "board_fixed_px": round(self.board.rms_px, 4),
            "board_fixed_um": round(self.board_rms_mm * 1000.0, 2), "board_corners_judged": self.board.places,
            "board_fixed": self.board.flagged,
            "image_fixed_ratio": round(self.image.ratio, 3), "image_fixed_px": round(self.image.rms_px, 4),
            "image_cells_judged": self.image.places, "image_fixed": self.image.flagged,
            # per judged corner: id and its mean residual on the board, mm (x, y): the print's own error
            "board_corner_residuals_mm": [[int(i), round(float(d[0]), 5), round(float(d[1]), 5)]
                                          for i, d in zip(self.board_corner_ids, self.board_means_mm, strict=True)],
        }


def residual_structure(calibration: Calibration, groups: Sequence[int]) -> ResidualStructure:
    """Test the final solve's residuals for patterns fixed to the board and to the image.

    `groups`: a pose number per view (frames of one hold share one), as `look_alike_groups` gives.
    """
    return residual_patterns(calibration.camera, calibration.views, calibration.rvecs, calibration.tvecs,
                             calibration.residuals_px, groups)


def residual_patterns(camera: CameraModel, views: Sequence[View], rvecs: np.ndarray, tvecs: np.ndarray,
                      residuals_px: Sequence[np.ndarray], groups: Sequence[int]) -> ResidualStructure:
    """`residual_structure` of any solve: its camera, views, poses (V, 3) and residuals (per view (N, 2))."""
    if not views:
        empty = FixedPattern(float("nan"), float("nan"), 0, MIN_CORNERS)
        return ResidualStructure(board=empty, board_rms_mm=float("nan"), image=replace(empty, least=MIN_CELLS))
    on_board, px_per_mm = zip(*(_to_board_mm(camera, v.object_points_m, r, t, res) for v, r, t, res
                                in zip(views, rvecs, tvecs, residuals_px, strict=True)),
                              strict=True)
    poses = np.concatenate([np.full(v.ids.size, g, np.int64) for v, g in zip(views, groups, strict=True)])
    ids = np.concatenate([v.ids for v in views]).astype(np.int64)
    points = np.concatenate([v.image_points_px for v in views])
    width, height = camera.image_size
    gx, gy = _IMAGE_GRID
    cells = (np.clip((points[:, 0] * gx / width).astype(np.int64), 0, gx - 1)
             + gx * np.clip((points[:, 1] * gy / height).astype(np.int64), 0, gy - 1))
    board_mm, corners, means = _fixed_pattern(poses, ids, np.concatenate(on_board), MIN_CORNERS)
    image, _cells, _means = _fixed_pattern(poses, cells, np.concatenate(residuals_px), MIN_CELLS)
    scale = float(np.median(np.concatenate(px_per_mm)))
    seen, first = np.unique(ids, return_index=True)
    where_m = np.concatenate([v.object_points_m[:, :2] for v in views])[first[np.searchsorted(seen, corners)]]
    return ResidualStructure(
        board=replace(board_mm, rms_px=board_mm.rms_px * scale),  # its rms was in board mm until here
        board_rms_mm=board_mm.rms_px, image=image,
        board_corner_ids=corners.astype(np.int32), board_corners_m=where_m.astype(np.float64), board_means_mm=means,
    )


def _to_board_mm(camera: CameraModel, object_points_m: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
                 residuals_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each corner's residual as a displacement on the board (mm), and the local px per mm.

    The displacement d on the board's plane that moves the projection by the residual r solves
    J d = r, J the 2x2 Jacobian of the projection along the board's x and y (by finite steps).
    """
    obj = np.asarray(object_points_m, np.float64)
    n = obj.shape[0]
    at, stepped_x, stepped_y = np.split(camera.project(np.concatenate([obj, obj + [_STEP_M, 0.0, 0.0],
                                                                       obj + [0.0, _STEP_M, 0.0]]), rvec, tvec), [n, 2 * n])
    J = np.stack([stepped_x - at, stepped_y - at], axis=2) / (_STEP_M * 1000.0)  # (N, 2, 2) px per mm; columns: board x, y
    on_board = np.linalg.solve(J, residuals_px[:, :, None])[:, :, 0]
    scale = np.sqrt(np.abs(np.linalg.det(J)))  # px per mm, geometric mean of the two directions
    return on_board, scale


def _fixed_pattern(poses: np.ndarray, places: np.ndarray, values: np.ndarray,
                   least: int) -> tuple[FixedPattern, np.ndarray, np.ndarray]:
    """The F-like ratio and the fixed part's size of per-corner `values` (N, 2) at `places` (N,)
    seen in `poses` (N,); with the places judged (seen in >= MIN_POSES poses) and their mean value."""
    # one pose's frames are averaged into one unit per place (key: pose * stride + place)
    stride = int(places.max()) + 1
    units, unit_of = np.unique(poses * stride + places, return_inverse=True)
    unit_sum = np.zeros((units.size, 2))
    np.add.at(unit_sum, unit_of, values)
    unit_mean = unit_sum / np.bincount(unit_of, minlength=units.size)[:, None]
    unit_place = units % stride
    place_ids, place_of, n = np.unique(unit_place, return_inverse=True, return_counts=True)
    place_sum = np.zeros((place_ids.size, 2))
    np.add.at(place_sum, place_of, unit_mean)
    place_mean = place_sum / n[:, None]
    judged = n >= MIN_POSES
    in_judged = judged[place_of]
    scatter = float(np.sum((unit_mean[in_judged] - place_mean[place_of][in_judged]) ** 2))
    dof = int(2 * np.sum(n[judged] - 1))
    means, counts = place_mean[judged], n[judged].astype(np.float64)
    if not judged.any() or dof == 0:
        return FixedPattern(float("nan"), float("nan"), int(judged.sum()), least), place_ids[judged], means
    noise_var = scatter / dof  # per coordinate, one pose
    squared = np.sum(means**2, axis=1)
    ratio = float(np.sum(counts * squared) / (2 * means.shape[0]) / noise_var) if noise_var > 0 else float("inf")
    # the means' own variance less what noise puts in them (noise_var / n per coordinate)
    fixed_var = float(np.mean(squared / 2.0 - noise_var / counts))
    return FixedPattern(ratio, float(np.sqrt(max(fixed_var, 0.0))), means.shape[0], least), place_ids[judged], means
