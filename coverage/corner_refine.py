"""ChArUco corners refined on the checker's own edges, with the markers' edges masked out.

OpenCV refines a ChArUco corner with `cornerSubPix` over a window that stops 2 px short of the
nearest *marker corner*: it still takes in stretches of the edges of the markers that sit in the
two white squares around the corner. Their gradients pull the corner; on a frontal board the two
pulls cancel, under perspective they do not, and the leftover is a smooth per-view pattern over
the board (0.015 px rms on the careful bench renders) that is the same in sign across views, so
averaging frames does not remove it: it carried the whole 0.07 px error of two of five renders
(bench/corner_masking.py, bench/results/corner_masking.md). cornerSubPix also resamples its
window bilinearly, which pulls a sharp edge toward or away from the pixel centres with its
sub-pixel phase (up to 0.04 px on noise-free renders).

`refine_on_checker_edges` solves cornerSubPix's equations again (each pixel's gradient is normal
to the line from the corner through it), on the gradients at the pixels themselves, over a
window of half a square, weighting out the pixels that the local image-to-board map puts inside
a marker's span, less a margin of twice the edges' blur: only the four checker edges meeting at
the corner pull it. The map is a quadratic fitted to the corner's detected grid neighbours: a
homography (straight lines) put the masks of a 115 deg lens's outer corners a fraction of a pixel
off, enough to leave the markers' blurred edges in on one side, and the guided wide-lens capture
calibrated 10x worse than with OpenCV's corners; the quadratic follows the lens's curvature over
a square (that capture: 0.005 px against the truth, OpenCV's corners 0.022). All corners of a
frame are solved together: ~0.9 ms a 720p frame with the window sums in C (coverage/_checker_edges.c),
~2.8 ms in NumPy (216 frames of four renders).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np

try:  # built by `pip install` where a C compiler is present (pyproject ext-modules, optional)
    from calibcoach.coverage._checker_edges import moments as _moments_in_c
except ImportError:  # pragma: no cover - no compiler at install: the NumPy path, the same numbers
    _moments_in_c = None

# The mask keeps this many blur widths (gaussian sigma, as sharpness.edge_blur reads it) clear of
# a marker's edge, where the edge's squared gradient is under 2% of its peak; and it needs as many
# again between its own border and the checker's edge for that edge's profile. Where a square is
# too small or too soft for both (a far or blurred board), the corner is left as OpenCV gave it.
# Over 24 renders of tilted boards at four blurs (0.5-1.4 px), margin and band of 2 sigma each
# gave the lowest corner error of 2-3.5 and 2-2.5 sigma; every setting beat OpenCV's corners.
BLUR_MARGIN_SIGMAS = 2.0
BAND_SIGMAS = 2.0
MIN_BLUR_MARGIN_PX = 1.5  # where the blur is not known: 2 sigma of a sharp webcam edge (0.7 px)
# Window: half a square each way from the corner (the next corner is a square away), at most this
# many pixels: past it the pixels are far from the corner and add little but cost.
MAX_HALF_WINDOW_PX = 14
MIN_HALF_WINDOW_PX = 3
# Gaussian weight over the window, sigma in squares: as cornerSubPix, the pixels near the corner count most.
WEIGHT_SIGMA_SQUARES = 0.3
_WEIGHT_EXPONENT = np.float32(-0.5 / WEIGHT_SIGMA_SQUARES ** 2)
GRADIENT_KSIZE = 3  # Sobel: central differences, smoothed across over 3 pixels (the C pass has this kernel built in)
_GRADIENT_SCALE = 1.0 / 8.0
# A refined corner more than this far from OpenCV's is a failure of the mask or the fit, not a
# correction (the bias removed is hundredths of a pixel): the detected position is kept.
MAX_SHIFT_PX = 0.5

# Ridge on the local map's quadratic terms (offsets normalised to ~1 neighbour spacing): far below
# what nine points determine, enough to hold them at zero where the neighbours lie on two lines.
QUADRATIC_RIDGE = 1e-3
NEIGHBOUR_OFFSETS = np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], np.int64)  # (9, 2), (0, 0) at 4


def _general_position_table() -> np.ndarray:
    """(512,) bool by bitmask of present neighbours: whether four of them have no three on a line.

    The 3x3 neighbourhood of a corner at the board's border or beside undetected corners often
    has four points three of which lie on a line (the border and one more); a local map fitted to
    them folds the window (corners moved 0.4 px off on renders), so such corners are left alone.
    """
    at = NEIGHBOUR_OFFSETS.tolist()

    def on_a_line(a: int, b: int, c: int) -> bool:
        (xa, ya), (xb, yb), (xc, yc) = at[a], at[b], at[c]
        return (xb - xa) * (yc - ya) - (xc - xa) * (yb - ya) == 0

    quads = [q for q in itertools.combinations(range(9), 4) if not any(on_a_line(*t) for t in itertools.combinations(q, 3))]
    quad_masks = np.array([sum(1 << i for i in q) for q in quads])
    masks = np.arange(512)[:, None]
    return ((masks & quad_masks[None]) == quad_masks[None]).any(axis=1)  # (a loop over the 512 took 45 ms at import)


_GENERAL_POSITION = _general_position_table()


def refine_on_checker_edges(grey: np.ndarray, corners_px: np.ndarray, object_points_m: np.ndarray, square_m: float,
                            marker_m: float, *, blur_sigma_px: float | None = None) -> np.ndarray:
    """(N, 2) float64 corners refined on the checker edges alone, from OpenCV's (N, 2) detections.

    `object_points_m`: (N, 2 or 3) the same corners on the board; `blur_sigma_px`: the frame's
    edge blur (gaussian sigma, `sharpness.EdgeBlur.blur_px`), which widens the margin left
    around the markers. Corners without four grid neighbours in general position detected, in
    squares too small for the mask at this blur, or whose refinement fails, keep their position.
    """
    corners = np.asarray(corners_px, np.float64).reshape(-1, 2)
    out = corners.copy()
    if len(corners) < 4:
        return out
    grid = board_grid(object_points_m, square_m)
    coef, scale, axis_all, valid = _local_quadratic_maps(corners, grid)
    if not valid.any():
        return out
    fitted = axis_all[valid]  # (px per square along the board's u and v) of every corner with a map
    # one window size for the frame, from every corner with a map (what decides a corner's window
    # must not depend on which others are solved)
    half = int(np.clip(np.ceil(0.5 * fitted.max()), MIN_HALF_WINDOW_PX, MAX_HALF_WINDOW_PX))
    border_squares = (square_m - marker_m) / 2.0 / square_m
    margin_px = max(MIN_BLUR_MARGIN_PX, BLUR_MARGIN_SIGMAS * (blur_sigma_px or 0.0))
    # the checker edge's own profile needs room between the mask and the edge (+-BAND_SIGMAS sigma):
    # corners without it are left as detected, and not solved
    band_px = border_squares * axis_all.min(axis=1) - margin_px
    roomy = valid & (band_px >= BAND_SIGMAS * max(blur_sigma_px or 0.0, MIN_BLUR_MARGIN_PX / BLUR_MARGIN_SIGMAS))
    if not roomy.any():
        return out
    index = np.flatnonzero(roomy)
    start = corners[index]
    window = _Windows(
        coef=np.ascontiguousarray(coef[index], np.float32),  # float32: a 720p frame's windows are ~40k pixels
        inv_scale=(1.0 / scale[index]).astype(np.float32),
        # a marker's span starts `border_squares` from the corner along each axis; its edge's blur reaches margin_px further in
        marker_edges=np.ascontiguousarray(border_squares - margin_px / axis_all[index]),
    )
    refined, solved = _solve_on_pixels(grey, start, half, window)
    keep = solved & (np.linalg.norm(refined - start, axis=1) < MAX_SHIFT_PX)
    out[index[keep]] = refined[keep]
    return out


def board_grid(object_points_m: np.ndarray, square_m: float) -> np.ndarray:
    """(N, 2) int64 each corner's (column, row) on the board's grid, from its (N, 2 or 3) board position."""
    points = np.asarray(object_points_m, np.float64)
    return np.rint(points.reshape(len(points), -1)[:, :2] / square_m).astype(np.int64)


def grid_neighbours(grid: np.ndarray) -> np.ndarray:
    """(N, 9) int64: the index of each corner's 3 x 3 grid neighbours (in `NEIGHBOUR_OFFSETS`' order, the
    corner itself at 4) among the (N, 2) `grid` positions, -1 where that neighbour was not detected."""
    lo = grid.min(axis=0) - 1
    shape = grid.max(axis=0) - lo + 2
    lookup = np.full((shape[0], shape[1]), -1, np.int64)
    lookup[grid[:, 0] - lo[0], grid[:, 1] - lo[1]] = np.arange(len(grid))
    cells = grid[:, None, :] - lo + NEIGHBOUR_OFFSETS[None]
    return lookup[cells[..., 0], cells[..., 1]]


def in_general_position(present: np.ndarray) -> np.ndarray:
    """(N,) bool from (N, 9) which neighbours are present: whether four of them have no three on a line."""
    return _GENERAL_POSITION[(present * (1 << np.arange(9))).sum(axis=1)]


def _local_quadratic_maps(corners: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Image offset (px from the corner, over `scale`) -> board offset (squares), a quadratic per corner.

    Returns (N, 2, 6) coefficients of 1, x, y, x^2, xy, y^2, (N,) scale, (N, 2) px per square
    along u and v at the corner, and (N,) whether fitted. Least squares on the corner and its
    detected 8-neighbours; a small ridge on the quadratic terms leaves them at zero where the
    neighbours do not determine them (a border row), so the map falls back to affine there.
    """
    members = grid_neighbours(grid)
    present = members >= 0
    xy = np.where(present[..., None], corners[np.maximum(members, 0)] - corners[:, None, :], 0.0)
    scale = np.maximum(np.sqrt((xy ** 2).sum(axis=2).sum(axis=1) / np.maximum(present.sum(axis=1) - 1, 1)), 1e-6)
    x, y = xy[..., 0] / scale[:, None], xy[..., 1] / scale[:, None]
    A = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=2) * present[..., None]  # (N, 9, 6)
    b = NEIGHBOUR_OFFSETS[None].astype(np.float64) * present[..., None]  # (N, 9, 2)
    ridge = np.diag([0.0, 0.0, 0.0, QUADRATIC_RIDGE, QUADRATIC_RIDGE, QUADRATIC_RIDGE])
    coef = np.linalg.solve(A.transpose(0, 2, 1) @ A + ridge + 1e-12 * np.eye(6), A.transpose(0, 2, 1) @ b)  # (N, 6, 2)
    coef = coef.transpose(0, 2, 1)  # (N, 2, 6)
    # d(u, v)/d(x, y) at the corner, in px: its inverse's columns are the image steps of one square along u and v
    jac = coef[:, :, 1:3] / scale[:, None, None]
    det = np.linalg.det(jac)
    valid = in_general_position(present) & (np.abs(det) > 1e-12) & np.isfinite(coef).all(axis=(1, 2))
    steps = np.linalg.inv(np.where(valid[:, None, None], jac, np.eye(2)))
    axis_px = np.linalg.norm(steps, axis=1)  # (N, 2)
    return coef, scale, axis_px, valid


@dataclass(frozen=True, slots=True)
class _Windows:
    """What weighs each corner's window pixels: the local map, and where the markers' spans begin."""

    coef: np.ndarray  # (M, 2, 6) float32: board offset (u, v) in squares, quadratic in the pixel offset times inv_scale
    inv_scale: np.ndarray  # (M,) float32
    marker_edges: np.ndarray  # (M, 2) float64: |u| and |v| both beyond these is inside a marker's span

    def weights(self, rel: np.ndarray) -> np.ndarray:
        """(M, P) weight of the pixels at `rel` (M, P, 2) px from each corner: gaussian in board units,
        zero in a marker's span or beyond half a square."""
        x, y = rel[..., 0] * self.inv_scale[:, None], rel[..., 1] * self.inv_scale[:, None]
        terms = (x, y, x * x, x * y, y * y)
        c = self.coef
        u = c[:, 0, 0:1] + sum(c[:, 0, k + 1:k + 2] * t for k, t in enumerate(terms))
        v = c[:, 1, 0:1] + sum(c[:, 1, k + 1:k + 2] * t for k, t in enumerate(terms))
        in_marker = (np.abs(u) > self.marker_edges[:, 0:1]) & (np.abs(v) > self.marker_edges[:, 1:2])
        inside = (np.abs(u) <= 0.5) & (np.abs(v) <= 0.5)
        return np.exp((u * u + v * v) * _WEIGHT_EXPONENT) * (inside & ~in_marker)


def _solve_on_pixels(grey: np.ndarray, start: np.ndarray, half: int, window: _Windows) -> tuple[np.ndarray, np.ndarray]:
    """cornerSubPix's equations solved once for all windows: q = (sum w g g^T)^-1 sum w g g^T p.

    Unlike cornerSubPix, which resamples its window bilinearly around each new estimate and
    iterates, the gradients are taken at the pixels themselves (p their true positions), with
    the weights centred on OpenCV's corner: linear interpolation of an edge as sharp as a
    webcam's (sigma ~0.7 px) is not symmetric about the edge, which pulls the estimate by up to
    0.04 px with the edge's sub-pixel phase ("pixel locking": noise-free frontal renders, 0.030 ->
    0.023 px rms). The weights are smooth in the window but for the mask, whose edge a tenth of a
    pixel does not move: re-centring them on the solution and solving again changed the corners'
    error by under 0.0002 px on 24 renders of tilted boards.

    The sums come from the C pass (`_checker_edges.moments`) where it was built, else from NumPy;
    the two give the same corners to ~1e-7 px (their float32 weights' exp may differ in the last bit).
    """
    centre = np.rint(start).astype(np.int64)
    if _moments_in_c is not None and grey.dtype == np.uint8 and grey.ndim == 2:
        image = np.ascontiguousarray(grey)
        sums = np.empty((len(start), 5), np.float64)
        _moments_in_c(image, image.shape[0], image.shape[1], half, np.ascontiguousarray(centre),
                      np.ascontiguousarray(centre - start, np.float32), window.coef, window.inv_scale,
                      window.marker_edges, float(_WEIGHT_EXPONENT), sums)
        a, b, c, r1, r2 = sums.T
    else:
        a, b, c, r1, r2 = _moments_in_numpy(grey, start, centre, half, window)
    det = a * c - b * b
    solved = det > 1e-9 * np.maximum(a + c, 1e-12) ** 2
    safe = np.where(solved, det, 1.0)
    q = start + np.stack([(c * r1 - b * r2) / safe, (a * r2 - b * r1) / safe], axis=1) * solved[:, None]
    return q, solved


def _moments_in_numpy(grey: np.ndarray, start: np.ndarray, centre: np.ndarray, half: int,
                      window: _Windows) -> tuple[np.ndarray, ...]:
    """(a, b, c, r1, r2), each (M,) float64: sum w gx^2, w gx gy, w gy^2 and the right-hand sides, per window."""
    height, width = grey.shape[:2]
    size = 2 * half + 1
    ys, xs = np.mgrid[-half:half + 1, -half:half + 1]
    offsets = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float32)  # (P, 2), row by row
    x0, y0 = max(int(centre[:, 0].min()) - half - 1, 0), max(int(centre[:, 1].min()) - half - 1, 0)
    x1, y1 = min(int(centre[:, 0].max()) + half + 2, width), min(int(centre[:, 1].max()) + half + 2, height)
    crop = grey[y0:y1, x0:x1].astype(np.float32)
    # each window's gradients cut straight out of the crop's (zero-padded, so windows may hang off
    # the image; the image's outermost rows and columns, whose differences run off it, weigh nothing)
    gradients = []
    for dx, dy in ((1, 0), (0, 1)):
        grad = cv2.Sobel(crop, cv2.CV_32F, dx, dy, ksize=GRADIENT_KSIZE, scale=_GRADIENT_SCALE)
        for edge, at in ((y0 == 0, (0, slice(None))), (y1 == height, (-1, slice(None))),
                         (x0 == 0, (slice(None), 0)), (x1 == width, (slice(None), -1))):
            if edge:
                grad[at] = 0.0
        padded = cv2.copyMakeBorder(grad, half, half, half, half, cv2.BORDER_CONSTANT, value=0.0)
        windows = np.lib.stride_tricks.sliding_window_view(padded, (size, size))
        gradients.append(windows[centre[:, 1] - y0, centre[:, 0] - x0].reshape(len(start), -1))
    gx, gy = gradients
    rel = (centre - start).astype(np.float32)[:, None, :] + offsets[None]  # each pixel's position from OpenCV's corner
    w = window.weights(rel)
    wgx, wgy = w * gx, w * gy
    gxx, gxy, gyy = wgx * gx, wgx * gy, wgy * gy
    # float64 sums: ~800 terms a window
    return (gxx.sum(axis=1, dtype=np.float64), gxy.sum(axis=1, dtype=np.float64), gyy.sum(axis=1, dtype=np.float64),
            (gxx * rel[..., 0] + gxy * rel[..., 1]).sum(axis=1, dtype=np.float64),
            (gxy * rel[..., 0] + gyy * rel[..., 1]).sum(axis=1, dtype=np.float64))
