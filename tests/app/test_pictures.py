"""Report pictures: sizes, that the data shows up in them, and that the undistortion straightens lines."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from calibcoach.app.outputs import pictures
from calibcoach.app.outputs.drawing import BAD, FONT, GOOD, INK, NEUTRAL, colourise, nice_ticks
from calibcoach.app.outputs.pictures import (
    FADE,
    bars_picture,
    board_residual_picture,
    coverage_picture,
    per_frame_error_picture,
    residual_map_picture,
    save_png,
    uncertainty_picture,
    undistort_for_check,
    undistorted_check_picture,
)
from calibcoach.app.solve.result import UncertaintyMap
from calibcoach.drivers.errors import CalibcoachError
from calibcoach.drivers.lens import CameraModel

SIZE = (1280, 720)
K = np.array([[900.0, 0, 639.5], [0, 900.0, 359.5], [0, 0, 1]])


def count_colour(img: np.ndarray, bgr) -> int:
    """Pixels exactly of colour `bgr`."""
    return int(np.all(img == np.asarray(bgr, np.uint8).reshape(-1), axis=2).sum())


def count_reddish(img: np.ndarray) -> int:
    """Pixels of the hatching's red (anti-aliased shades included): red well above green and blue."""
    b, g, r = (img[..., i].astype(int) for i in range(3))
    return int(((r - g > 60) & (r - b > 60)).sum())


def heat(value: float, vmax: float) -> tuple[int, int, int]:
    return tuple(int(v) for v in colourise(value, 0, vmax, fade=FADE))


def assert_picture(img: np.ndarray) -> None:
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert img.shape[1] >= 1000
    assert 0 < (img < 250).mean() < 0.95  # neither blank nor filled


def test_coverage_cells_are_coloured_by_count_and_missing_cells_hatched() -> None:
    counts = np.array([[0.0, 40.0], [10.0, 20.0]])
    img = coverage_picture(SIZE, [], counts, title="coverage")
    assert_picture(img)
    cell_area = (SIZE[0] / 2) * (SIZE[1] / 2) * (1100 / 1280) ** 2  # the panel is 1100 px wide
    assert count_colour(img, heat(40, 40)) > 0.8 * cell_area  # the full cell in the top colour
    assert count_colour(img, heat(20, 40)) > 0.8 * cell_area
    assert heat(40, 40) != heat(0, 40)
    filled = coverage_picture(SIZE, [], np.array([[5.0, 40.0], [10.0, 20.0]]), title="coverage")
    assert count_reddish(img) > count_reddish(filled) + 3000  # the empty cell's hatching
    assert count_colour(filled, heat(5, 40)) > 0.8 * cell_area  # ... which now has a colour


def test_coverage_required_hatches_thin_cells_and_hulls_are_drawn() -> None:
    counts = np.array([[5.0, 40.0], [10.0, 20.0]])
    plain = coverage_picture(SIZE, [], counts, title="coverage")
    thin = coverage_picture(SIZE, [], counts, title="coverage", required=12)  # 5 and 10 are below 12
    assert count_reddish(thin) > count_reddish(plain) + 6000
    square = np.array([[200.0, 100.0], [1000.0, 100.0], [1000.0, 600.0], [200.0, 600.0], [600.0, 350.0]])
    outlined = coverage_picture(SIZE, [square], counts, title="coverage")
    assert outlined.shape == plain.shape
    assert 1000 < np.any(outlined != plain, axis=2).sum() < 20000  # a thin outline, not a fill


def test_bars_are_green_when_enough_and_red_when_not() -> None:
    enough = bars_picture([("tilt", ["a", "b", "c"], [1.0, 2.0, 1.5]), ("distance", ["far", "mid"], [3.0, 1.0])], title="t")
    short = bars_picture([("tilt", ["a", "b", "c"], [1.0, 0.5, 0.25]), ("distance", ["far", "mid"], [3.0, 0.75])], title="t")
    assert_picture(enough)
    legend_swatch = 23 * 17
    assert count_colour(enough, BAD) <= legend_swatch  # only the legend's red box
    assert count_colour(short, BAD) > 10 * legend_swatch
    assert count_colour(enough, GOOD) > count_colour(short, GOOD)
    single = bars_picture([("tilt x", ["<-45°", "±15°", ">45°"], [0.0, 1.0, 2.0])], title="one group")
    assert single.shape[1] >= 1000
    with pytest.raises(ValueError, match="has 2 labels but 3 values"):
        bars_picture([("g", ["a", "b"], [1, 2, 3])], title="t")


def test_residual_map_colours_cells_by_mean_length_and_draws_arrows() -> None:
    pts = np.array([[100.0, 100.0]] * 20 + [[1200.0, 650.0]] * 20)
    res = np.array([[1.0, 0.0]] * 20 + [[0.0, 0.25]] * 20)
    img = residual_map_picture(SIZE, pts, res, grid=(4, 3))
    assert_picture(img)
    cell_area = (1100 / 4) * (1100 * 720 / 1280 / 3)
    assert count_colour(img, heat(1.0, 1.0)) > 0.5 * cell_area  # the cell with 1 px residuals, top of the scale
    assert count_colour(img, heat(0.25, 1.0)) > 0.5 * cell_area
    assert count_reddish(img) > 10000  # the ten cells without corners are hatched
    still = residual_map_picture(SIZE, pts, np.zeros_like(res), grid=(4, 3))
    assert np.any(still != img)
    with pytest.raises(ValueError, match="must have the same shape"):
        residual_map_picture(SIZE, pts, res[:5])


def test_board_residuals_are_arrows_on_the_board_red_when_the_board_is_off_its_spec() -> None:
    grid = np.stack(np.meshgrid(np.arange(1, 8), np.arange(1, 11)), axis=-1).reshape(-1, 2) * 0.03  # 70 corners, m
    means = np.where(grid[:, :1] > 0.12, [[0.05, 0.0]], [[-0.05, 0.0]])  # the right half stretched: mm
    flagged = board_residual_picture(grid, means, (0.24, 0.33), 0.03, flagged=True, summary="off its spec")
    assert_picture(flagged)
    red = np.all(flagged == BAD, axis=2)
    assert red.sum() > 70 * 20  # 70 arrows of ~a square's length, drawn 2 px wide
    # each arrow starts at its corner and points its way: stretched outwards the arrows reach further
    # out on both sides than the same arrows pointing inwards
    inwards = board_residual_picture(grid, -means, (0.24, 0.33), 0.03, flagged=True, summary="off its spec")
    out_x = np.nonzero(red[:-60].any(axis=0))[0]  # above the legend's arrow
    in_x = np.nonzero(np.all(inwards[:-60] == BAD, axis=2).any(axis=0))[0]
    assert out_x.min() < in_x.min() - 30 and out_x.max() > in_x.max() + 30
    calm = board_residual_picture(grid, means, (0.24, 0.33), 0.03, flagged=False, summary="noise")
    assert not np.any(np.all(calm == BAD, axis=2))
    assert np.all(calm == INK, axis=2).sum() > 70 * 8


def test_per_frame_error_marks_dropped_and_above_threshold_frames() -> None:
    rms = np.array([0.3, 0.4, 2.5, 0.35, 1.9, 0.3])
    base = per_frame_error_picture([str(i) for i in range(6)], rms, threshold_px=None)
    marked = per_frame_error_picture([f"f{i}.png" for i in range(6)], rms, dropped={2}, threshold_px=1.0)
    assert_picture(marked)
    assert count_colour(marked, NEUTRAL) > count_colour(base, NEUTRAL) + 5000  # the grey dropped bar
    assert count_colour(marked, BAD) > count_colour(base, BAD) + 5000  # frame 4 is above 1 px and kept
    wide = per_frame_error_picture([str(i) for i in range(150)], np.full(150, 0.3))
    assert wide.shape[1] > marked.shape[1] and wide.shape[1] <= 2400
    with pytest.raises(ValueError, match="3 frame labels for 6 RMS values"):
        per_frame_error_picture(["a", "b", "c"], rms)


def _uncertainty(level: float) -> UncertaintyMap:
    gx, gy = np.linspace(0, SIZE[0] - 1, 9), np.linspace(0, SIZE[1] - 1, 5)
    sigma = np.full((5, 9), level)
    sigma[0, :] = sigma[-1, :] = 3 * level
    covered = np.zeros((5, 9), bool)
    covered[1:4, 2:7] = True
    return UncertaintyMap(gx, gy, sigma, covered, error_px=sigma, error_weight=np.eye(2))


def test_uncertainty_picture_writes_the_verdict_on_the_expected_error() -> None:
    met = uncertainty_picture(_uncertainty(0.05), target_px=0.1)
    missed = uncertainty_picture(_uncertainty(0.2), target_px=0.1)
    assert_picture(met)
    assert count_colour(met, GOOD) > 100 and count_colour(missed, GOOD) == 0  # green "meets the target"
    assert count_colour(missed, (40, 40, 200)) > 100 and count_colour(met, (40, 40, 200)) == 0
    vmax = max(min(0.15, max(0.3, 0.1)), 1e-9)  # the documented scale: max(3 x target, 2 x E), capped at the max
    assert count_colour(met, heat(0.05, vmax)) > 20000  # the flat centre in its colour
    sized = uncertainty_picture(_uncertainty(0.05), target_px=0.1, image_size=SIZE)
    assert sized.shape == met.shape  # the grid runs through the edge pixels, so the inferred size is SIZE


def test_nice_ticks_cover_the_range_with_round_steps() -> None:
    assert nice_ticks(0, 264) == [0, 50, 100, 150, 200, 250]
    assert nice_ticks(0, 1080) == [0, 200, 400, 600, 800, 1000]
    assert nice_ticks(0, 1.25, 5) == [0.0, 0.25, 0.5, 0.75, 1.0, 1.25]


# --- undistortion -------------------------------------------------------------------------------


def _seen_through(camera: CameraModel, ideal_f: float) -> np.ndarray:
    """A white image with black horizontal lines every 120 px of an ideal pinhole, as `camera` sees it."""
    w, h = camera.image_size
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = camera.unproject(np.stack([u.ravel(), v.ravel()], axis=1))
    z = np.maximum(rays[:, 2], 1e-6)
    y_ideal = (ideal_f * rays[:, 1] / z + (h - 1) / 2).reshape(h, w)
    return np.where(np.abs((y_ideal + 60) % 120 - 60) < 2.5, 0, 255).astype(np.uint8)


def _trace_line(img: np.ndarray, y_near: float, x_from: int, x_to: int) -> np.ndarray:
    """y (px) of the dark line closest to `y_near` at the image centre, followed column by column."""
    rows = np.arange(img.shape[0])

    def centre_at(x: int, y: float) -> float | None:
        dark = rows[(img[:, x] < 128) & (np.abs(rows - y) < 8)]
        return float(dark.mean()) if dark.size else None

    mid = img.shape[1] // 2
    dark = rows[img[:, mid] < 128]
    y0 = float(dark[np.argmin(np.abs(dark - y_near))])
    found = {mid: centre_at(mid, y0)}
    for columns in (range(mid + 1, x_to), range(mid - 1, x_from - 1, -1)):
        y = found[mid]
        for x in columns:
            y_next = centre_at(x, y)
            if y_next is None:
                break
            found[x], y = y_next, y_next
    return np.array([found[x] for x in sorted(found)])


@pytest.mark.parametrize(
    ("model", "f", "dist", "ideal_f"),
    [("pinhole", 900.0, [-0.3, 0.1, 0.0, 0.0, -0.02], 900.0), ("fisheye", 700.0, [0.05, -0.01, 0.002, 0.0], 600.0)],
)
def test_undistortion_straightens_lines_the_lens_bends(model: str, f: float, dist: list[float], ideal_f: float) -> None:
    camera = CameraModel(model, np.array([[f, 0, 639.5], [0, f, 359.5], [0, 0, 1]]), np.array(dist), SIZE)
    bent = _seen_through(camera, ideal_f)
    straight, new_k = undistort_for_check(bent, camera)
    assert straight.shape == bent.shape and new_k.shape == (3, 3)
    bowed = _trace_line(bent, 150, 200, 1080)
    assert bowed.size == 880 and np.ptp(bowed) > 8.0  # the lens bows the line by many pixels
    line = _trace_line(straight, 150, 420, 860)
    assert line.size == 440 and np.ptp(line) < 1.5  # straight again in the undistorted view
    picture = undistorted_check_picture(bent, camera)
    assert_picture(picture)
    b, g, r = (picture[..., i].astype(int) for i in range(3))
    magenta = int(((b > 150) & (r > 150) & (g < 100)).sum())
    assert magenta > 2 * (6 * 560 + 4 * 760)  # 7 vertical and 5 horizontal guides over each of the two panels


def test_undistort_adapts_to_a_uniformly_resized_image_and_refuses_other_sizes() -> None:
    camera = CameraModel("pinhole", K, np.array([-0.2, 0.05, 0, 0, 0]), SIZE)
    half = np.full((360, 640), 128, np.uint8)
    out, new_k = undistort_for_check(half, camera)
    assert out.shape == (360, 640) and 200 < new_k[0, 0] < 500  # the half-size camera's focal length
    with pytest.raises(CalibcoachError, match="changes the aspect ratio"):
        undistort_for_check(np.zeros((480, 640), np.uint8), camera)


def test_save_png_writes_a_readable_file(tmp_path: Path) -> None:
    img = np.zeros((20, 30, 3), np.uint8)
    cv2.putText(img, "x", (5, 15), FONT, 0.5, (0, 255, 0), 1)
    path = save_png(tmp_path / "sub" / "p.png", img)
    np.testing.assert_array_equal(cv2.imread(str(path)), img)
    assert pictures.__all__ == sorted(pictures.__all__)
