"""Pictures a person reads after a run: where the board was seen, how the residuals and the
uncertainty spread over the image, and whether the undistorted image looks straight.

Drawn with OpenCV only (no plotting library in the dependencies). Every function returns a BGR
uint8 picture at least 1000 px wide with a title, axes in pixels, a legend and, for heat maps, a
colour bar with numbers; `save_png` writes one. The bar charts live in `charts.py` and are
re-exported here, so the pipeline imports every picture from this module.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from calibcoach.app.outputs.charts import bars_picture, per_frame_error_picture
from calibcoach.app.outputs.drawing import (
    BAD,
    GOOD,
    HATCH,
    INK,
    TITLE_H,
    ImagePanel,
    colour_bar,
    colourise,
    fit_panel,
    fmt,
    hatch,
    legend,
    new_canvas,
    pixel_frame,
    put_text,
    text_width,
)
from calibcoach.app.outputs.files import atomic_write_bytes
from calibcoach.app.solve.residual_structure import ResidualStructure
from calibcoach.app.solve.result import UncertaintyMap
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.errors import CalibcoachError
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.png_fast import encode_png

__all__ = [
    "bars_picture",
    "board_pattern_picture",
    "board_residual_picture",
    "coverage_picture",
    "per_frame_error_picture",
    "residual_map_picture",
    "save_png",
    "uncertainty_picture",
    "undistort_for_check",
    "undistorted_check_picture",
]
FADE = 0.3  # heat colours blended 30 % towards white, so dark outlines and arrows stay visible on them
_LEFT = 90  # room for the y pixel ticks and label


def save_png(path: str | Path, img: np.ndarray) -> Path:
    """Write `img` (BGR or grey uint8) as PNG (atomically, creating folders); returns the path.

    ISA-L's deflate (`png_fast.encode_png`) rather than OpenCV's encoder: a replay's eight pictures
    took 87 ms of CPU to encode in OpenCV 5.1 and 27 ms this way, for files 25-75% of the size
    (the charts' flat colours compress better with every row Sub-filtered), at the end of every run.
    """
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise CalibcoachError(f"cannot write a {img.shape} {img.dtype} picture to {path}: pictures are BGR or grey uint8")
    return atomic_write_bytes(path, encode_png(img))


def _canvas_for(panel: ImagePanel, title: str, subtitle: str, *, legend_rows: int = 1) -> np.ndarray:
    w, h = panel.size
    return new_canvas(max(1000, panel.x + w + 170), panel.y + h + 60 + 30 * legend_rows, title, subtitle)


def _cell_grid(img: np.ndarray, panel: ImagePanel, values: np.ndarray, vmax: float, empty: np.ndarray, *, label_cells: bool) -> None:
    """Fill each grid cell with its value's colour; `empty` cells are hatched instead."""
    rows, cols = values.shape
    for r in range(rows):
        for c in range(cols):
            x0, y0, x1, y1 = panel.cell_rect(r, c, rows, cols)
            if empty[r, c]:
                hatch(img, x0, y0, x1, y1)
            else:
                colour = tuple(int(v) for v in colourise(values[r, c], 0, vmax, fade=FADE))
                cv2.rectangle(img, (x0, y0), (x1, y1), colour, -1)
            if label_cells and x1 - x0 >= 40:
                value = float(values[r, c])
                text = fmt(value) if value > 0 else "none"
                dark = not empty[r, c] and value < 0.35 * vmax  # the lower third of viridis is dark
                colour = HATCH if empty[r, c] else ((255, 255, 255) if dark else INK)
                put_text(img, text, ((x0 + x1) / 2, (y0 + y1) / 2), scale=0.55, align="centre", valign="middle",
                         color=colour, thickness=2)


def coverage_picture(
    image_size: tuple[int, int],
    corner_sets: Sequence[np.ndarray],
    region_counts: np.ndarray,
    *,
    title: str = "Coverage: where the board's corners were seen",
    required: float | None = None,
) -> np.ndarray:
    """The image area as a heat map of the region cells, with each accepted view's corner hull.

    Args:
        image_size: (width, height) pixels.
        corner_sets: per accepted view, (N, 2) corner pixels; each view's convex hull is outlined.
        region_counts: (GY, GX) per-cell weight (corner observations) over a grid covering the image.
        required: cells below this are hatched as missing; default: only cells with nothing.

    Returns:
        (H, W, 3) uint8 BGR picture, W >= 1000.
    """
    counts = np.asarray(region_counts, np.float64)
    if counts.ndim != 2:
        raise ValueError(f"region_counts must be (rows, cols), got shape {counts.shape}")
    missing = counts < required if required is not None else counts <= 0
    n_corners = int(sum(np.asarray(s).reshape(-1, 2).shape[0] for s in corner_sets))
    subtitle = (
        f"{len(corner_sets)} accepted views, {n_corners} corners; {int(missing.sum())} of {missing.size} "
        f"cells {'below ' + fmt(required) if required is not None else 'without corners'}"
    )
    panel = fit_panel(image_size, _LEFT, TITLE_H + 20)
    img = _canvas_for(panel, title, subtitle)
    vmax = max(float(counts.max()), 1e-9)
    _cell_grid(img, panel, counts, vmax, missing, label_cells=True)
    overlay = img.copy()
    for corners in corner_sets:
        pts = panel.to_display(np.asarray(corners).reshape(-1, 2))
        if pts.shape[0] >= 3:
            hull = cv2.convexHull(np.round(pts).astype(np.int32))
            cv2.polylines(overlay, [hull], True, INK, 1, cv2.LINE_AA)
    cv2.addWeighted(overlay, 0.6, img, 0.4, 0, dst=img)
    pixel_frame(img, panel)
    w, h = panel.size
    colour_bar(img, panel.x + w + 40, panel.y + 30, h - 40, 0.0, vmax, label="corners / cell", fade=FADE)
    missing_label = f"below {fmt(required)} (missing)" if required is not None else "no corners seen"
    legend(img, panel.x, img.shape[0] - 18, [("box", tuple(int(v) for v in colourise(0.6, 0, 1, fade=FADE)), "corners seen in the cell"),
                                              ("hatch", HATCH, missing_label), ("line", INK, "outline of one accepted view")])
    return img


def _nice_factor(raw: float) -> float:
    """Largest 1/2/5 x 10^k not above `raw` (at least 1e-3)."""
    if not np.isfinite(raw) or raw <= 0:
        return 1.0
    power = 10.0 ** np.floor(np.log10(raw))
    return float(max(m * power for m in (1, 2, 5) if m * power <= raw))


def residual_map_picture(
    image_size: tuple[int, int],
    points_px: np.ndarray,
    residuals_px: np.ndarray,
    *,
    grid: tuple[int, int] = (16, 9),
    title: str = "Reprojection residuals across the image",
) -> np.ndarray:
    """Per-cell mean residual length as a heat map, with every residual drawn as an exaggerated arrow.

    A good calibration shows short arrows pointing every which way; arrows that line up (radially
    at the edges, or one way in a corner) show a distortion the model did not capture.

    Args:
        image_size: (width, height) pixels.
        points_px: (M, 2) corner positions in pixels.
        residuals_px: (M, 2) observed - projected, pixels.
        grid: (columns, rows) of the heat map.

    Returns:
        (H, W, 3) uint8 BGR picture, W >= 1000.
    """
    pts = np.asarray(points_px, np.float64).reshape(-1, 2)
    res = np.asarray(residuals_px, np.float64).reshape(-1, 2)
    if pts.shape != res.shape:
        raise ValueError(f"points_px {pts.shape} and residuals_px {res.shape} must have the same shape")
    gx, gy = int(grid[0]), int(grid[1])
    w_img, h_img = image_size
    mag = np.hypot(res[:, 0], res[:, 1])
    col = np.clip(((pts[:, 0] + 0.5) / w_img * gx).astype(int), 0, gx - 1)
    row = np.clip(((pts[:, 1] + 0.5) / h_img * gy).astype(int), 0, gy - 1)
    sums, counts = np.zeros((gy, gx)), np.zeros((gy, gx))
    np.add.at(sums, (row, col), mag)
    np.add.at(counts, (row, col), 1)
    means = np.divide(sums, counts, out=np.zeros_like(sums), where=counts > 0)
    rms = float(np.sqrt(np.mean(mag**2))) if mag.size else 0.0
    subtitle = f"{mag.size} corners; RMS {fmt(rms)} px, median {fmt(float(np.median(mag)) if mag.size else 0.0)} px, max {fmt(float(mag.max()) if mag.size else 0.0)} px"
    panel = fit_panel(image_size, _LEFT, TITLE_H + 20)
    img = _canvas_for(panel, title, subtitle, legend_rows=2)
    vmax = max(float(means.max()), 1e-6)
    _cell_grid(img, panel, means, vmax, counts == 0, label_cells=False)
    cell_px = min(panel.size[0] / gx, panel.size[1] / gy)
    p95 = float(np.percentile(mag, 95)) if mag.size else 0.0
    factor = _nice_factor(0.5 * cell_px / (p95 * panel.scale)) if p95 > 0 else 1.0
    step = max(1, mag.size // 4000)  # beyond ~4000 arrows the map turns into a texture
    w, h = panel.size
    area = img[panel.y : panel.y + h, panel.x : panel.x + w]  # a view: arrows are clipped to the image area
    starts = panel.to_display(pts[::step]) - [panel.x, panel.y]
    ends = starts + res[::step] * factor * panel.scale
    for (x0, y0), (x1, y1) in zip(np.round(starts).astype(int), np.round(ends).astype(int), strict=True):
        if (x1 - x0) ** 2 + (y1 - y0) ** 2 > 64:
            cv2.arrowedLine(area, (x0, y0), (x1, y1), INK, 1, cv2.LINE_AA, tipLength=0.25)
        else:
            cv2.line(area, (x0, y0), (x1, y1), INK, 1, cv2.LINE_AA)
    pixel_frame(img, panel)
    colour_bar(img, panel.x + w + 40, panel.y + 30, h - 40, 0.0, vmax, label="mean |residual| [px]", fade=FADE)
    sample = _nice_factor(70 / (factor * panel.scale))
    length = int(round(sample * factor * panel.scale))
    y_legend = img.shape[0] - 48
    cv2.arrowedLine(img, (panel.x, y_legend - 5), (panel.x + length, y_legend - 5), INK, 2, cv2.LINE_AA, tipLength=0.2)
    shown = "" if step == 1 else f" (every {step}th of {mag.size} shown)"
    how = f"exaggerated {fmt(factor)}x" if factor > 1 else f"drawn at {fmt(factor)}x"
    put_text(img, f"= {fmt(sample)} px residual: arrows are {how}{shown}", (panel.x + length + 12, y_legend), scale=0.5)
    legend(img, panel.x, img.shape[0] - 14, [("hatch", HATCH, "no corners in the cell"), ("line", INK, "residual (observed - projected), from the corner")])
    return img


def board_residual_picture(corners_m: np.ndarray, means_mm: np.ndarray, board_size_m: tuple[float, float], square_m: float,
                           *, flagged: bool, summary: str) -> np.ndarray:
    """Each board corner's residual averaged over the poses that saw it, as an exaggerated arrow on the board.

    Noise averages out over poses, so a good board shows short arrows every which way; long arrows
    that agree in a region (or swirl, or grow towards an edge) are the board itself off its spec:
    not flat, or printed unevenly (`residual_structure.py`).

    Args:
        corners_m: (K, 2) the corners' (x, y) on the board, metres.
        means_mm: (K, 2) their mean residual on the board, millimetres.
        board_size_m: (width, height) of the board's squares area, metres.
        square_m: the square side, metres (the checker drawn underneath).
        flagged: draw the arrows in red (the pattern was called out).
        summary: the subtitle (the pattern's size against noise).

    Returns:
        (H, W, 3) uint8 BGR picture, W >= 1000.
    """
    corners = np.asarray(corners_m, np.float64).reshape(-1, 2)
    means = np.asarray(means_mm, np.float64).reshape(-1, 2)
    width_m, height_m = board_size_m
    scale = min(760.0 / width_m, 560.0 / height_m)  # display px per metre
    x0, y0 = 60, TITLE_H + 30
    img = new_canvas(1000, int(y0 + height_m * scale + 80), "Residuals on the board, averaged over poses", summary)
    columns, rows = int(round(width_m / square_m)), int(round(height_m / square_m))
    for r in range(rows):
        for c in range(columns):
            if (r + c) % 2 == 0:
                p0 = (int(x0 + c * square_m * scale), int(y0 + r * square_m * scale))
                p1 = (int(x0 + (c + 1) * square_m * scale), int(y0 + (r + 1) * square_m * scale))
                cv2.rectangle(img, p0, p1, (228, 228, 228), -1)
    cv2.rectangle(img, (x0, y0), (int(x0 + width_m * scale), int(y0 + height_m * scale)), INK, 1)
    lengths = np.hypot(means[:, 0], means[:, 1])
    p95 = float(np.percentile(lengths, 95)) if lengths.size else 0.0
    factor = _nice_factor(0.9 * square_m / (p95 * 1e-3)) if p95 > 0 else 1.0  # the longest arrows about a square
    colour = BAD if flagged else INK
    for (x, y), (dx, dy) in zip(corners, means, strict=True):
        start = (int(round(x0 + x * scale)), int(round(y0 + y * scale)))
        end = (int(round(start[0] + dx * 1e-3 * factor * scale)), int(round(start[1] + dy * 1e-3 * factor * scale)))
        cv2.circle(img, start, 2, colour, -1, cv2.LINE_AA)
        cv2.arrowedLine(img, start, end, colour, 2 if flagged else 1, cv2.LINE_AA, tipLength=0.25)
    sample_mm = _nice_factor(70 / (factor * 1e-3 * scale))
    length = int(round(sample_mm * 1e-3 * factor * scale))
    y_legend = img.shape[0] - 30
    cv2.arrowedLine(img, (x0, y_legend - 5), (x0 + length, y_legend - 5), colour, 2, cv2.LINE_AA, tipLength=0.2)
    put_text(img, f"= {fmt(sample_mm * 1000)} um on the board (arrows exaggerated {fmt(factor)}x); {len(corners)} corners "
             "seen in 3 or more poses", (x0 + length + 12, y_legend), scale=0.5)
    return img


def board_pattern_picture(structure: ResidualStructure, board: BoardSpec) -> np.ndarray:
    """`board_residual_picture` of a solve's `residual_structure` on its board."""
    side_m = board.square_mm * 1e-3
    verdict = "the board is off its spec" if structure.board.flagged else "within what noise explains"
    return board_residual_picture(
        structure.board_corners_m, structure.board_means_mm, (board.squares_x * side_m, board.squares_y * side_m), side_m,
        flagged=structure.board.flagged,
        summary=f"fixed part {fmt(structure.board_rms_mm * 1000)} um ({fmt(structure.board.rms_px)} px) per coordinate, "
                f"{fmt(structure.board.ratio)}x the variance noise leaves; {verdict}")


def _grid_coordinates(values_px: np.ndarray, grid_px: np.ndarray) -> np.ndarray:
    """Fractional grid indices of pixel positions (clamped at the ends: nearest extrapolation)."""
    return np.interp(values_px, grid_px, np.arange(grid_px.size)).astype(np.float32)


def uncertainty_picture(
    map: UncertaintyMap,  # shadows the builtin on purpose: the name the pipeline's brief fixed
    *,
    target_px: float,
    image_size: tuple[int, int] | None = None,
    title: str = "Expected projection error (RMS length of the error, px)",
) -> np.ndarray:
    """Heat map of the expected projection error, with the region the board covered outlined.

    The map is sqrt(trace(J Sigma J^T)) per grid point; the headline is E, its RMS over the
    covered region, against the stop rule's target. The colour scale runs to max(3 x target, 2 x E) so the interesting range keeps its
    contrast; values beyond are drawn at the top colour (the bar says ">="). Without `image_size`
    the image extent is taken as symmetric around the grid (grid_x.max() + grid_x.min() + 1 wide),
    which holds both for grids through the edge pixels and for cell-centred grids.

    Returns:
        (H, W, 3) uint8 BGR picture, W >= 1000.
    """
    sigma = np.asarray(map.error_px, np.float64)
    gx_px, gy_px = np.asarray(map.grid_x_px, np.float64), np.asarray(map.grid_y_px, np.float64)
    if sigma.shape != (gy_px.size, gx_px.size) or map.covered.shape != sigma.shape:
        raise ValueError(f"sigma_px {sigma.shape} / covered {map.covered.shape} do not match the grid ({gy_px.size}, {gx_px.size})")
    if image_size is None:
        image_size = (int(round(gx_px.max() + gx_px.min() + 1)), int(round(gy_px.max() + gy_px.min() + 1)))
    E, p95_all, worst = map.expected_error_px, float(np.percentile(sigma, 95)), float(sigma.max())
    met = E <= target_px
    subtitle = f"E over the covered region {fmt(E)} px (target {fmt(target_px)} px); p95 over the whole image {fmt(p95_all)} px; max {fmt(worst)} px"
    panel = fit_panel(image_size, _LEFT, TITLE_H + 20)
    img = _canvas_for(panel, title, subtitle)
    w, h = panel.size
    xs = (np.arange(w) + 0.5) / panel.scale - 0.5
    ys = (np.arange(h) + 0.5) / panel.scale - 0.5
    map_x, map_y = np.meshgrid(_grid_coordinates(xs, gx_px), _grid_coordinates(ys, gy_px))
    dense = cv2.remap(sigma.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR)
    vmax = max(min(worst, max(3 * target_px, 2 * E)), 1e-9)
    img[panel.y : panel.y + h, panel.x : panel.x + w] = colourise(dense, 0.0, vmax, fade=FADE)
    covered = cv2.remap(map.covered.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR) >= 0.5
    contours, _ = cv2.findContours(covered.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    for contour in contours:
        shifted = contour + np.array([panel.x, panel.y])
        cv2.polylines(img, [shifted], True, (255, 255, 255), 4, cv2.LINE_AA)
        cv2.polylines(img, [shifted], True, INK, 2, cv2.LINE_AA)
    box = f"E = {fmt(E)} px ({'meets' if met else 'misses'} the {fmt(target_px)} px target)"
    cv2.rectangle(img, (panel.x + 10, panel.y + 10), (panel.x + 30 + text_width(box, 0.6, 2), panel.y + 44), (255, 255, 255), -1)
    put_text(img, box, (panel.x + 20, panel.y + 27), scale=0.6, thickness=2, valign="middle", color=GOOD if met else (40, 40, 200))
    pixel_frame(img, panel)
    colour_bar(img, panel.x + w + 40, panel.y + 30, h - 40, 0.0, vmax, label="error [px]", fade=FADE,
               open_top=worst > vmax, marks=((target_px, "target"),))
    legend(img, panel.x, img.shape[0] - 18, [("line", INK, "region the board was seen in (outside it the model is extrapolated)")])
    return img


def undistort_for_check(image: np.ndarray, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """Undistort `image` keeping about half of the invalid border (alpha / balance 0.5).

    Pinhole and rational use `getOptimalNewCameraMatrix(alpha=0.5)`; fisheye uses
    `cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(balance=0.5)`. An image whose size
    differs from the camera's by a uniform resize is handled with `CameraModel.resized`.

    Returns:
        (undistorted image of the input's shape and dtype, (3, 3) float64 camera matrix of it).
    """
    h, w = image.shape[:2]
    if (w, h) != camera.image_size:
        try:
            camera = camera.resized((w, h))
        except ValueError as exc:
            raise CalibcoachError(f"the check image is {w}x{h} but the camera is {camera.image_size}: {exc}") from None
    K, D = camera.camera_matrix, camera.dist_coeffs
    if camera.model == "fisheye":
        new_k = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(K, D.reshape(4, 1), (w, h), np.eye(3), balance=0.5)
        map1, map2 = cv2.fisheye.initUndistortRectifyMap(K, D.reshape(4, 1), np.eye(3), new_k, (w, h), cv2.CV_16SC2)
    else:
        new_k, _ = cv2.getOptimalNewCameraMatrix(K, camera.opencv_dist(), (w, h), 0.5, (w, h))
        map1, map2 = cv2.initUndistortRectifyMap(K, camera.opencv_dist(), None, new_k, (w, h), cv2.CV_16SC2)
    out = cv2.remap(image, map1, map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return out, np.asarray(new_k, np.float64)


def undistorted_check_picture(image: np.ndarray, camera: CameraModel, *, title: str = "Undistortion check") -> np.ndarray:
    """The captured image and its undistorted version side by side, both under straight guide lines.

    Lines that are straight in the world (door frames, shelves, the board's edges) should follow
    the magenta guides in the right panel; in the left one they bend by the lens's distortion.

    Args:
        image: (H, W) grey or (H, W, 3) BGR uint8 image from the calibrated camera.

    Returns:
        (H', W', 3) uint8 BGR picture, W' >= 1000.
    """
    img_in = np.asarray(image)
    if img_in.ndim == 2:
        img_in = cv2.cvtColor(img_in, cv2.COLOR_GRAY2BGR)
    if img_in.ndim != 3 or img_in.shape[2] != 3:
        raise ValueError(f"image must be (H, W) or (H, W, 3), got {np.asarray(image).shape}")
    img_in = img_in.astype(np.uint8)
    undistorted, new_k = undistort_for_check(img_in, camera)
    h, w = img_in.shape[:2]
    scale = min(760 / w, 620 / h)
    pw, ph = int(round(w * scale)), int(round(h * scale))
    top = TITLE_H + 50
    k = camera.camera_matrix
    subtitle = (
        f"{camera.model} model: fx {fmt(k[0, 0])}, fy {fmt(k[1, 1])}, cx {fmt(k[0, 2])}, cy {fmt(k[1, 2])} px; "
        f"distortion [{', '.join(f'{d:.4g}' for d in camera.dist_coeffs)}]"
    )
    out = new_canvas(max(1000, 2 * pw + 120), top + ph + 70, title, subtitle)
    labels = ("original (as captured)", "undistorted, " + ("balance" if camera.model == "fisheye" else "alpha") + " 0.5")
    for i, (picture, label) in enumerate(zip((img_in, undistorted), labels, strict=True)):
        x = 40 + i * (pw + 40)
        tile = cv2.resize(picture, (pw, ph), interpolation=cv2.INTER_AREA)
        guides = tile.copy()
        for gx in np.linspace(0, pw - 1, 9)[1:-1]:
            cv2.line(guides, (int(gx), 0), (int(gx), ph - 1), (255, 0, 255), 1, cv2.LINE_AA)
        for gy in np.linspace(0, ph - 1, 7)[1:-1]:
            cv2.line(guides, (0, int(gy)), (pw - 1, int(gy)), (255, 0, 255), 1, cv2.LINE_AA)
        out[top : top + ph, x : x + pw] = cv2.addWeighted(guides, 0.75, tile, 0.25, 0)
        cv2.rectangle(out, (x - 1, top - 1), (x + pw, top + ph), INK, 1)
        put_text(out, label, (x, top - 12), scale=0.6, thickness=2)
    put_text(out, f"new camera matrix of the undistorted view: fx {fmt(new_k[0, 0])}, fy {fmt(new_k[1, 1])}, "
             f"cx {fmt(new_k[0, 2])}, cy {fmt(new_k[1, 2])} px", (40, top + ph + 28), scale=0.5)
    legend(out, 40, top + ph + 56, [("line", (255, 0, 255), "straight guide lines: straight edges in the scene should follow them on the right")])
    return out
