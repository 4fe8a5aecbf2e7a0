"""ChArUco corners refined by the checker pattern's point symmetry about each corner.

Within half a square a checker corner is two straight edges crossing (a homography keeps lines
straight), and the image turned half a turn about the crossing is the same image: a point up and
right of it has the grey of the point as far down and left, blur included. So the corner is
where the image agrees with itself reflected through it: for sample offsets d about a pixel
apart over the window, the corner c minimises sum (I(c + d) - I(c - d))^2 (the image interpolated
bilinearly), by Gauss-Newton on c alone. Every pixel of the window counts by the contrast it
carries, and the estimator needs no room between the markers and the checker's edges, which the
masked refinement does. It is the estimator the accurate-calibration literature uses for
checkerboards (Schops et al., "Why having 10,000 parameters in your camera model is better than
twelve", CVPR 2020, there over a pattern symmetric on the board with its homography fitted too).

The offsets d come from board offsets through the corner's board-to-image map (the frame's
homography, bent by a quadratic through its grid neighbours where they determine one), which
also says which samples lie in a marker's span (not symmetric: left out, with the masked
refinement's blur margin) and sets the window: half a square, at most
`corner_refine.MAX_HALF_WINDOW_PX`. The final solve's corners are OpenCV's fitted so
(`session_finish.frame_view`), every corner of a frame with 6 or more. Against the truth, on
still frames of 720p renders, the corners' error per axis went 0.028 -> 0.018 px (careful) and
0.089-0.097 -> 0.058-0.068 (dim) from the masked refinement's (coverage/corner_refine.py, which it
replaced in the final solve: run before it, that one changed nothing, 1.00x over 63 renders); the
replays' error over 63 renders halved (bench/results/corner_symmetry.md).

The fit, and the samples it makes from each corner's map, are in C where it was built
(coverage/_corner_symmetry.c), else NumPy (`_pairs`, `_fit_in_numpy`: the same numbers to ~1e-12
px, several times slower).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.corner_refine import (
    BLUR_MARGIN_SIGMAS,
    MAX_HALF_WINDOW_PX,
    MIN_BLUR_MARGIN_PX,
    NEIGHBOUR_OFFSETS,
    QUADRATIC_RIDGE,
    board_grid,
    grid_neighbours,
    in_general_position,
)

try:  # built by `pip install` where a C compiler is present (pyproject ext-modules, optional)
    from calibcoach.coverage._corner_symmetry import fit as _fit_in_c
except ImportError:  # pragma: no cover - no compiler at install: the NumPy path, the same numbers
    _fit_in_c = None

# Pairs sampled a pixel apart in the image (at the corner's scale): the pixels are the information;
# half a pixel apart gave the same corners (careful and dim renders) at four times the cost.
SAMPLE_STEP_PX = 1.0
MIN_PAIRS = 24  # fewer clean pairs (a far board, a corner at the image's edge): left as it was
MAX_ITERATIONS = 10
CONVERGED_PX = 1e-3
# A corner fitted further than this from its start (OpenCV's corner, in the pipeline) is a failure of
# the map or the symmetry (a corner half off the image, a reflection), not a correction: left as it was.
MAX_SHIFT_PX = 0.5

# Sample grid in steps: (i + 0.5, j + 0.5), j >= 0 (the upper half-plane; each sample's partner is
# its reflection through the corner), within the largest window
_RADIUS_STEPS = int(np.ceil(MAX_HALF_WINDOW_PX / SAMPLE_STEP_PX))
_I, _J = np.meshgrid(np.arange(-_RADIUS_STEPS, _RADIUS_STEPS) + 0.5, np.arange(0, _RADIUS_STEPS) + 0.5)
_TEMPLATE = np.stack([_I.ravel(), _J.ravel()], axis=1)
_TEMPLATE = _TEMPLATE[np.hypot(_TEMPLATE[:, 0], _TEMPLATE[:, 1]) <= _RADIUS_STEPS]  # (P, 2), P = 308
_TEMPLATE_RADIUS = np.hypot(_TEMPLATE[:, 0], _TEMPLATE[:, 1])


@lru_cache(maxsize=16)
def marker_free_squares(spec: BoardSpec) -> np.ndarray:
    """(squares_x, squares_y) bool: which squares of the board hold no marker (the settled pattern's)."""
    board = spec.cv_board(legacy=bool(spec.legacy))
    square_m = spec.square_mm / 1000.0
    free = np.ones((spec.squares_x, spec.squares_y), bool)
    for corners in board.getObjPoints():
        centre = np.asarray(corners, np.float64).reshape(-1, 3)[:, :2].mean(axis=0)
        x, y = np.floor(centre / square_m).astype(int)
        free[x, y] = False
    return free


def refine_by_symmetry(grey: np.ndarray, corners_px: np.ndarray, object_points_m: np.ndarray, spec: BoardSpec,
                       *, blur_sigma_px: float | None = None, only: np.ndarray | None = None) -> np.ndarray:
    """(N, 2) float64 corners fitted to the pattern's point symmetry, from (N, 2) starts.

    `object_points_m`: (N, 2 or 3) the same corners on the board; `blur_sigma_px`: the frame's edge
    blur, which widens the margin kept clear of the markers; `only`: (N,) bool, the corners to fit
    (the rest, every corner of a frame with fewer than 6 or no homography, and corners without
    enough clean pairs or a converged fit, keep their position).
    """
    corners = np.asarray(corners_px, np.float64).reshape(-1, 2)
    out = corners.copy()
    n = len(corners)
    if n < 4 or grey.ndim != 2:
        return out
    grid = board_grid(object_points_m, spec.square_mm / 1000.0)
    homography, correction = _board_to_image_maps(corners, grid)
    if homography is None:
        return out
    index = np.arange(n) if only is None else np.flatnonzero(np.asarray(only, bool))
    if index.size == 0:
        return out
    geometry = _pair_geometry(homography, grid[index], spec, blur_sigma_px)
    fitted, iterations = _fit(grey, corners[index], homography, grid[index], correction[index], geometry)
    keep = (iterations > 0) & (np.linalg.norm(fitted - corners[index], axis=1) < MAX_SHIFT_PX)
    out[index[keep]] = fitted[keep]
    return out


def _board_to_image_maps(corners: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """Each corner's board-to-image map: the frame's homography (all its corners, least squares),
    corrected by a quadratic fitted to its detected 8-neighbours' departures from it where four of
    them are in general position, else the homography alone.

    The map places the samples and their masks (which squares hold markers, how far the border
    reaches): a tilted board's perspective bends a square's image by ~2 px per square^2 (a 45 deg
    tilt at 0.5 m, 720p). The homography carries the perspective; the neighbours' quadratic adds
    the lens's bending where they determine it (a small ridge holds it at zero along a border row,
    where the homography's alone is taken). Corners whose neighbours do not determine it (the edge
    of what was detected: the image's border, markers lost in a dim or smeared frame) were first
    left as OpenCV gave them: 4% of the corners in a careful 720p replay's final solve, 12% in a
    dim one's, 23% in a messy one's, at 3-5x the fitted corners' error. With the homography alone
    they are fitted as well (the pairs are reflections in the image, so the map only sets the
    window and the masks): against the truth, 0.136 -> 0.046 px per axis on a dim 720p render,
    0.048 -> 0.015 careful, 0.037-0.071 -> 0.012-0.025 messy (bench/results/homography_alone.md).

    Returns the homography (None when it cannot be fitted) and the (N, 2, 5) correction's x, y,
    x^2, xy, y^2 terms per image axis (zero where the neighbours do not determine it).
    """
    n = len(corners)
    if n < 6:
        return None, np.zeros((n, 2, 5))
    board = grid.astype(np.float64)
    homography, _ = cv2.findHomography(board, corners, 0)
    if homography is None or not np.isfinite(homography).all():
        return None, np.zeros((n, 2, 5))
    members = grid_neighbours(grid)
    present = members >= 0
    predicted = _offsets_under(homography, board, NEIGHBOUR_OFFSETS.astype(np.float64)[None])  # (N, 9, 2)
    seen = np.where(present[..., None], corners[np.maximum(members, 0)] - corners[:, None, :], 0.0)
    departures = np.where(present[..., None], seen - predicted, 0.0)
    u, v = (NEIGHBOUR_OFFSETS[:, 0].astype(np.float64), NEIGHBOUR_OFFSETS[:, 1].astype(np.float64))
    design = np.stack([np.ones(9), u, v, u * u, u * v, v * v], axis=1)[None] * present[..., None]  # (N, 9, 6)
    ridge = np.diag([0.0, 0.0, 0.0, QUADRATIC_RIDGE, QUADRATIC_RIDGE, QUADRATIC_RIDGE])
    normal = design.transpose(0, 2, 1) @ design + ridge + 1e-12 * np.eye(6)
    coef = np.linalg.solve(normal, design.transpose(0, 2, 1) @ departures)  # (N, 6, 2)
    correction = coef[:, 1:6, :].transpose(0, 2, 1)  # (N, 2, 5): the constant is the corner's own offset, dropped
    determined = in_general_position(present) & np.isfinite(coef).all(axis=(1, 2))
    return homography, np.where(determined[:, None, None], correction, 0.0)


def _offsets_under(homography: np.ndarray, board: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(M, P, 2) image offsets H(g + p) - H(g) of board offsets `offsets` (M or 1, P, 2) from each corner's `board` (M, 2)."""
    (h00, h01, h02), (h10, h11, h12), (h20, h21, h22) = homography
    gx, gy = board[:, 0:1], board[:, 1:2]
    ax, ay = gx + offsets[..., 0], gy + offsets[..., 1]  # (M, P), written out: matmul over a 2-vector is slower
    w, w0 = h20 * ax + h21 * ay + h22, h20 * gx + h21 * gy + h22
    out = np.empty(ax.shape + (2,))
    out[..., 0] = (h00 * ax + h01 * ay + h02) / w - (h00 * gx + h01 * gy + h02) / w0
    out[..., 1] = (h10 * ax + h11 * ay + h12) / w - (h10 * gx + h11 * gy + h12) / w0
    return out


def _pair_geometry(homography: np.ndarray, grid: np.ndarray, spec: BoardSpec,
                   blur_sigma_px: float | None) -> tuple[np.ndarray, ...]:
    """Per corner (each (M,) float64): the sample step, the window's half-width and the squares'
    marker-free border (all in squares), and whether the squares left and right of it in the
    template's row (1.0) hold no marker: what `_pairs` (and the C fit) make each corner's samples from.

    The step is a pixel at the corner's scale; the window half a square, at most `MAX_HALF_WINDOW_PX`;
    the border, the marker-free margin of a square less the blur margin (`corner_refine`'s).
    """
    board = grid.astype(np.float64)
    axes = _offsets_under(homography, board, np.array([[[1e-3, 0.0], [0.0, 1e-3]]])) / 1e-3  # (M, 2 board axes, 2)
    px_per_square = np.sqrt(np.abs(axes[:, 0, 0] * axes[:, 1, 1] - axes[:, 0, 1] * axes[:, 1, 0]))  # (M,)
    step = SAMPLE_STEP_PX / px_per_square
    half = np.minimum(0.5, MAX_HALF_WINDOW_PX / px_per_square)
    margin_px = max(MIN_BLUR_MARGIN_PX, BLUR_MARGIN_SIGMAS * (blur_sigma_px or 0.0))
    border = (spec.square_mm - spec.marker_mm) / 2.0 / spec.square_mm - margin_px / px_per_square
    # the corner at grid (i, j) sits between squares i - 1 and i, j - 1 and j; the template's samples
    # have v > 0, so a sample's square is (i - [u < 0], j), its reflection's the one opposite (alike)
    free = marker_free_squares(spec)
    right = free[np.clip(grid[:, 0], 0, free.shape[0] - 1), np.clip(grid[:, 1], 0, free.shape[1] - 1)]
    left = free[np.clip(grid[:, 0] - 1, 0, free.shape[0] - 1), np.clip(grid[:, 1], 0, free.shape[1] - 1)]
    return step, half, border, left.astype(np.float64), right.astype(np.float64)


def _pairs(homography: np.ndarray, correction: np.ndarray, grid: np.ndarray,
           geometry: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Each corner's samples: image offsets (M, P, 2) d of board offsets p, each paired with its
    reflection -d through the corner, and (M, P) weights (1 or 0). The C fit makes the same per corner.

    p runs over `_TEMPLATE` scaled to a pixel apart at the corner's scale, within half a square and
    `MAX_HALF_WINDOW_PX`; a pair counts where p lies in a marker-free square (then the reflection
    does too: the squares opposite each other at a corner are alike) or within the marker-free
    border of its square less the blur margin (`corner_refine`'s; the reflection lands within a
    fiftieth of a square of -p on the board, well inside that margin).

    The partner is the reflection in the image, not the image of -p: within half a square the
    corner is two straight lines crossing (a homography keeps lines straight), which the image's
    own half-turn maps onto themselves whatever the perspective, and so does the blur. The image
    of -p lies nearer to or further from the edges than d by the perspective's change of scale
    across the window (a few percent at a steep tilt), and within the blur that changes its grey:
    pairs of images of +p and -p gave 1.17x the error against the truth over the 63 renders of
    bench/results/corner_symmetry.md (35 of 63 worse).
    """
    step, half, border, left, right = geometry
    u = _TEMPLATE[None, :, 0] * step[:, None]  # (M, P) board offsets in squares
    v = _TEMPLATE[None, :, 1] * step[:, None]
    marker_free = np.where(_TEMPLATE[None, :, 0] < 0, left[:, None] != 0.0, right[:, None] != 0.0)
    in_border = np.minimum(np.abs(u), v) <= border[:, None]
    within = _TEMPLATE_RADIUS[None] * step[:, None] <= half[:, None]
    weights = (within & (marker_free | in_border)).astype(np.float64)
    plus = _offsets_under(homography, grid.astype(np.float64), np.stack([u, v], axis=2))
    for axis in (0, 1):
        c = correction[:, axis]
        plus[..., axis] += c[:, 0:1] * u + c[:, 1:2] * v + c[:, 2:3] * u * u + c[:, 3:4] * u * v + c[:, 4:5] * v * v
    return plus, weights


def _fit(grey: np.ndarray, starts: np.ndarray, homography: np.ndarray, grid: np.ndarray, correction: np.ndarray,
         geometry: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on each corner's symmetry cost: (M, 2) corners and (M,) steps taken (0: fewer
    than `MIN_PAIRS` samples count, not fitted; -1: no converged fit)."""
    if _fit_in_c is not None and grey.dtype == np.uint8:
        image = np.ascontiguousarray(grey)
        out = np.empty_like(starts)
        iterations = np.empty(len(starts), np.int32)
        step, half, border, left, right = (np.ascontiguousarray(a, np.float64) for a in geometry)
        _fit_in_c(image, image.shape[0], image.shape[1], len(starts), len(_TEMPLATE), np.ascontiguousarray(starts),
                  np.ascontiguousarray(homography, np.float64), np.ascontiguousarray(grid, np.float64),
                  np.ascontiguousarray(correction, np.float64), step, half, border, left, right, _TEMPLATE,
                  _TEMPLATE_RADIUS, MIN_PAIRS, MAX_ITERATIONS, CONVERGED_PX, out, iterations)
        return out, iterations
    dp, weights = _pairs(homography, correction, grid, geometry)
    enough = weights.sum(axis=1) >= MIN_PAIRS
    fitted, iterations = starts.copy(), np.zeros(len(starts), np.int32)
    fitted[enough], iterations[enough] = _fit_in_numpy(grey, starts[enough], dp[enough], weights[enough])
    return fitted, iterations


def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
    """Value, d/dx, d/dy of the bilinear interpolation of `image` at (x, y), and where the cell is inside."""
    height, width = image.shape
    fx0, fy0 = np.floor(x), np.floor(y)
    inside = (fx0 >= 0) & (fy0 >= 0) & (fx0 < width - 1) & (fy0 < height - 1)
    x0 = np.where(inside, fx0, 0).astype(np.int64)
    y0 = np.where(inside, fy0, 0).astype(np.int64)
    fx, fy = x - fx0, y - fy0
    a, b = image[y0, x0], image[y0, x0 + 1]
    c, d = image[y0 + 1, x0], image[y0 + 1, x0 + 1]
    value = ((a * (1.0 - fx)) * (1.0 - fy) + (b * fx) * (1.0 - fy)) + ((c * (1.0 - fx)) * fy + (d * fx) * fy)
    return value, (1.0 - fy) * (b - a) + fy * (d - c), (1.0 - fx) * (c - a) + fx * (d - b), inside


def _fit_in_numpy(grey: np.ndarray, starts: np.ndarray, dp: np.ndarray,
                  weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`_corner_symmetry.fit`'s loop in NumPy: every corner steps together, each until its own step is
    small, each sample `dp` paired with its reflection `-dp` through the corner."""
    image = np.asarray(grey, np.float64)
    corners = starts.copy()
    iterations = np.full(len(starts), -1, np.int32)
    active = np.ones(len(starts), bool)
    for it in range(1, MAX_ITERATIONS + 1):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        c = corners[idx][:, None, :]
        vp, gxp, gyp, ip = _bilinear(image, c[..., 0] + dp[idx, :, 0], c[..., 1] + dp[idx, :, 1])
        vm, gxm, gym, im = _bilinear(image, c[..., 0] + -dp[idx, :, 0], c[..., 1] + -dp[idx, :, 1])
        w = np.where(ip & im, weights[idx], 0.0)
        r, jx, jy = vp - vm, gxp - gxm, gyp - gym
        wjx, wjy = w * jx, w * jy
        sxx, sxy, syy = (wjx * jx).sum(axis=1), (wjx * jy).sum(axis=1), (wjy * jy).sum(axis=1)
        sxr, syr = (wjx * r).sum(axis=1), (wjy * r).sum(axis=1)
        det = sxx * syy - sxy * sxy
        solvable = det > 1e-12 * (sxx + syy) * (sxx + syy)
        safe = np.where(solvable, det, 1.0)
        step = np.stack([-(syy * sxr - sxy * syr) / safe, -(sxx * syr - sxy * sxr) / safe], axis=1)
        corners[idx[solvable]] += step[solvable]
        converged = solvable & (np.hypot(step[:, 0], step[:, 1]) < CONVERGED_PX)
        iterations[idx[converged]] = it
        active[idx[converged | ~solvable]] = False
    return corners, iterations
