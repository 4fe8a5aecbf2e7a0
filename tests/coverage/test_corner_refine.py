"""Corners refined on the checker's edges with the markers masked: closer to the truth than OpenCV's."""

from __future__ import annotations

import numpy as np
import pytest
from _boards import board_on_axis

from calibcoach.coverage import corner_refine
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.corner_refine import MAX_SHIFT_PX, refine_on_checker_edges
from calibcoach.coverage.detector import CharucoBoardDetector
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.sim import LENSES
from calibcoach.drivers.sim_render import render_board_view

SPEC = BoardSpec()
CAMERA = LENSES["webcam720"]
SQUARE_M, MARKER_M = SPEC.square_mm / 1000.0, SPEC.marker_mm / 1000.0


def _errors(tilt_deg: float, distance_m: float, *, noise_dn: float = 1.0, supersample: int = 2,
            camera=CAMERA) -> tuple[float, float, np.ndarray, np.ndarray]:
    rvec, tvec = board_on_axis(SPEC, tilt_deg, distance_m)
    image = render_board_view(camera, SPEC, rvec, tvec, blur_sigma_px=0.6, noise_sigma_dn=noise_dn, seed=1,
                              supersample=supersample)
    detection = CharucoBoardDetector(SPEC).detect(image)
    assert detection.corner_count >= 20
    true = camera.project(detection.object_points_m, rvec, tvec)
    refined = refine_on_checker_edges(image, detection.corners_px, detection.object_points_m, SQUARE_M, MARKER_M)
    rms = lambda points: float(np.sqrt(np.mean((points - true) ** 2)))  # noqa: E731
    return rms(detection.corners_px), rms(refined), detection.corners_px, refined


@pytest.mark.parametrize("tilt_deg", [40.0, 55.0])
def test_tilted_board_corners_move_closer_to_the_truth(tilt_deg: float) -> None:
    # Under a steep tilt the two markers' edges that OpenCV's window takes in pull unequally; the
    # masked window sees the checker's edges alone. Measured: 0.041 -> 0.035 px at 40 deg, 0.056 -> 0.032 at 55.
    detected, refined, _, _ = _errors(tilt_deg, 0.45)
    assert refined < 0.9 * detected, (detected, refined)


def test_frontal_board_corners_lose_the_pixel_locking() -> None:
    # Frontal, noise-free, finely supersampled, a distortion-free lens: what is left of OpenCV's error
    # is its bilinear resampling of sharp edges, a pull with each edge's sub-pixel phase; gradients
    # taken at the pixels remove most of it (measured 0.046 -> 0.023 px).
    pinhole = CameraModel("pinhole", CAMERA.camera_matrix, np.zeros(5), CAMERA.image_size)
    detected, refined, corners, moved = _errors(0.0, 0.6, noise_dn=0.0, supersample=8, camera=pinhole)
    assert refined < 0.7 * detected, (detected, refined)
    assert np.abs(moved - corners).max() < MAX_SHIFT_PX


def test_a_board_too_blurred_for_its_squares_keeps_opencvs_corners() -> None:
    # Squares of ~40 px put the markers' edges 5.4 px from the checker's; at an edge width of 1.5 px
    # (what edge_blur reads on a soft frame) the mask would leave the checker's edge less than two
    # widths each side: no mask separates them, so the corners are left as detected.
    rvec, tvec = board_on_axis(SPEC, 20.0, 0.7)
    image = render_board_view(CAMERA, SPEC, rvec, tvec, blur_sigma_px=1.0, seed=1)
    detection = CharucoBoardDetector(SPEC).detect(image)
    assert detection.corner_count >= 20
    out = refine_on_checker_edges(image, detection.corners_px, detection.object_points_m, SQUARE_M, MARKER_M,
                                  blur_sigma_px=1.5)
    np.testing.assert_array_equal(out, detection.corners_px.astype(np.float64))


def test_corners_without_a_local_homography_keep_their_position() -> None:
    rvec, tvec = board_on_axis(SPEC, 20.0, 0.6)
    image = render_board_view(CAMERA, SPEC, rvec, tvec, blur_sigma_px=0.6, seed=1)
    detection = CharucoBoardDetector(SPEC).detect(image)
    # a corner, the two above and below it and one diagonal: four points, three on a line, from which
    # no homography follows; none of the four has four neighbours in general position
    grid = {tuple(np.rint(p[:2] / SQUARE_M).astype(int)): k for k, p in enumerate(detection.object_points_m)}
    picked = [grid[(3, 4)], grid[(3, 3)], grid[(3, 5)], grid[(2, 3)]]
    alone = refine_on_checker_edges(image, detection.corners_px[picked], detection.object_points_m[picked], SQUARE_M, MARKER_M)
    np.testing.assert_array_equal(alone, detection.corners_px[picked].astype(np.float64))
    # with a fifth off the line the centre corner has its homography and moves
    picked.append(grid[(4, 5)])
    five = refine_on_checker_edges(image, detection.corners_px[picked], detection.object_points_m[picked], SQUARE_M, MARKER_M)
    assert np.any(five[0] != detection.corners_px[picked[0]])
    # and a corner thrown 2 px off is not dragged back by more than MAX_SHIFT_PX: it stays where it was given
    thrown = detection.corners_px.astype(np.float64).copy()
    thrown[10] += (2.0, 0.0)
    out = refine_on_checker_edges(image, thrown, detection.object_points_m, SQUARE_M, MARKER_M)
    np.testing.assert_array_equal(out[10], thrown[10])



def test_the_c_window_sums_give_numpys_corners(monkeypatch: pytest.MonkeyPatch) -> None:
    # The C pass (coverage/_checker_edges.c) and the NumPy one must agree to the float32 rounding of
    # their weights, on a board inside the image and cut so that windows hang off the image's left
    # and bottom edges (whose outermost rows and columns have no gradient in either).
    assert corner_refine._moments_in_c is not None, "the C extension coverage/_checker_edges.c was not built (pip install -e .)"
    rvec, tvec = board_on_axis(SPEC, 40.0, 0.45)
    image = render_board_view(CAMERA, SPEC, rvec, tvec, blur_sigma_px=0.7, noise_sigma_dn=1.5, seed=3)
    detection = CharucoBoardDetector(SPEC).detect(image)
    assert detection.corner_count >= 20
    corners = detection.corners_px.astype(np.float64)
    left = int(np.sort(corners[:, 0])[3]) - 4  # a few corners 4 px or less from the cut, some left of it
    bottom = int(np.sort(corners[:, 1])[-4]) + 3
    cuts = [(image, corners, None), (image[:, left:], corners - (left, 0), 0.9), (image[:bottom], corners, 0.6)]
    for cut, given, blur_px in cuts:
        inside = (given >= 0).all(axis=1) & (given < cut.shape[::-1]).all(axis=1)
        args = (cut, given[inside], detection.object_points_m[inside], SQUARE_M, MARKER_M)
        with_c = refine_on_checker_edges(*args, blur_sigma_px=blur_px)
        monkeypatch.setattr(corner_refine, "_moments_in_c", None)
        with_numpy = refine_on_checker_edges(*args, blur_sigma_px=blur_px)
        monkeypatch.undo()
        moved = np.any(with_numpy != given[inside], axis=1)
        assert np.count_nonzero(moved) >= 0.5 * inside.sum()
        if cut is not image:  # windows over the cut were solved
            to_edge = np.minimum(given[inside], np.array(cut.shape[::-1]) - 1 - given[inside]).min(axis=1)
            assert np.any(moved & (to_edge < 5)), to_edge[moved].min()
        np.testing.assert_allclose(with_c, with_numpy, rtol=0, atol=1e-6)
