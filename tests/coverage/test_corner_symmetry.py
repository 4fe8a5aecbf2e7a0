"""Corners fitted to the checker pattern's point symmetry: closer to the truth than the masked refinement's."""

from __future__ import annotations

import numpy as np
import pytest
from _boards import board_on_axis

from calibcoach.coverage import corner_symmetry
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.corner_refine import refine_on_checker_edges
from calibcoach.coverage.corner_symmetry import MAX_SHIFT_PX, marker_free_squares, refine_by_symmetry
from calibcoach.coverage.detector import CharucoBoardDetector
from calibcoach.drivers.sim import LENSES
from calibcoach.drivers.sim_render import render_board_view

SPEC = BoardSpec()
CAMERA = LENSES["webcam720"]
SQUARE_M, MARKER_M = SPEC.square_mm / 1000.0, SPEC.marker_mm / 1000.0


def _view(tilt_deg: float, distance_m: float, *, noise_dn: float, blur_px: float, seed: int):
    rvec, tvec = board_on_axis(SPEC, tilt_deg, distance_m)
    image = render_board_view(CAMERA, SPEC, rvec, tvec, blur_sigma_px=blur_px, noise_sigma_dn=noise_dn, seed=seed)
    detection = CharucoBoardDetector(SPEC).detect(image)
    assert detection.corner_count >= 20
    return image, detection, CAMERA.project(detection.object_points_m, rvec, tvec)


def _rms(points: np.ndarray, true: np.ndarray) -> float:
    return float(np.sqrt(np.mean((points - true) ** 2)))


@pytest.mark.parametrize(("tilt_deg", "noise_dn"), [(20.0, 2.0), (45.0, 2.0), (30.0, 6.0)])
def test_symmetric_corners_lie_closer_to_the_truth_than_the_masked_ones(tilt_deg: float, noise_dn: float) -> None:
    # Every pixel of the window counts by its own contrast, where the masked window weighs the
    # checker's edges alone and leaves corners of small squares as OpenCV gave them. Measured on
    # these renders (three seeds pooled), masked -> symmetric: 0.025 -> 0.012 px at 20 deg, 0.025 ->
    # 0.015 at 45 deg, 0.045 -> 0.018 at 30 deg with 6 DN of noise.
    masked_sq, symmetric_sq, count = 0.0, 0.0, 0
    for seed in (1, 2, 3):
        image, detection, true = _view(tilt_deg, 0.6, noise_dn=noise_dn, blur_px=0.8, seed=seed)
        blur = 0.8
        masked = refine_on_checker_edges(image, detection.corners_px, detection.object_points_m, SQUARE_M, MARKER_M,
                                         blur_sigma_px=blur)
        fitted = refine_by_symmetry(image, masked, detection.object_points_m, SPEC, blur_sigma_px=blur)
        masked_sq += float(np.sum((masked - true) ** 2))
        symmetric_sq += float(np.sum((fitted - true) ** 2))
        count += true.size
    masked_rms, symmetric_rms = np.sqrt(masked_sq / count), np.sqrt(symmetric_sq / count)
    assert symmetric_rms < 0.75 * masked_rms, (masked_rms, symmetric_rms)


def test_corners_of_fewer_than_six_or_outside_only_keep_their_position() -> None:
    image, detection, _true = _view(20.0, 0.6, noise_dn=1.0, blur_px=0.7, seed=1)
    corners = detection.corners_px.astype(np.float64)
    grid = {tuple(np.rint(p[:2] / SQUARE_M).astype(int)): k for k, p in enumerate(detection.object_points_m)}
    # four corners: too few for the frame's homography, which places every corner's samples
    picked = [grid[(3, 4)], grid[(3, 3)], grid[(3, 5)], grid[(2, 3)]]
    alone = refine_by_symmetry(image, corners[picked], detection.object_points_m[picked], SPEC)
    np.testing.assert_array_equal(alone, corners[picked])
    # `only` leaves the others where they were; the fitted ones move
    only = np.zeros(len(corners), bool)
    only[::3] = True
    out = refine_by_symmetry(image, corners, detection.object_points_m, SPEC, only=only)
    np.testing.assert_array_equal(out[~only], corners[~only])
    assert np.count_nonzero(np.any(out[only] != corners[only], axis=1)) >= 0.8 * only.sum()
    # a corner thrown 2 px off is not pulled back by more than MAX_SHIFT_PX: it stays where it was given
    thrown = corners.copy()
    thrown[10] += (2.0, 0.0)
    moved = refine_by_symmetry(image, thrown, detection.object_points_m, SPEC)
    assert np.linalg.norm(moved[10] - thrown[10]) == 0.0 or np.linalg.norm(moved[10] - thrown[10]) < MAX_SHIFT_PX


def test_corners_whose_neighbours_do_not_bend_the_map_are_fitted_on_the_homography_alone() -> None:
    # Two rows of corners three squares apart: no corner has four neighbours in general position, so
    # none gets the quadratic correction, yet each is fitted through the frame's homography: measured
    # 0.040 -> 0.012 px per axis here (OpenCV's -> fitted). In the replays such corners -- the edge of
    # what a dim or smeared frame detected -- went 0.037-0.159 -> 0.012-0.060 px against the truth
    # (bench/results/homography_alone.md).
    opencv_sq, fitted_sq, count = 0.0, 0.0, 0
    for seed in (1, 2):
        image, detection, true = _view(30.0, 0.6, noise_dn=3.0, blur_px=0.8, seed=seed)
        rows = np.rint(detection.object_points_m[:, 1] / SQUARE_M).astype(int)
        picked = np.flatnonzero(np.isin(rows, (3, 6)))
        assert len(picked) >= 10
        corners = detection.corners_px[picked].astype(np.float64)
        fitted = refine_by_symmetry(image, corners, detection.object_points_m[picked], SPEC, blur_sigma_px=0.8)
        assert np.count_nonzero(np.any(fitted != corners, axis=1)) >= 0.8 * len(picked)
        opencv_sq += float(np.sum((corners - true[picked]) ** 2))
        fitted_sq += float(np.sum((fitted - true[picked]) ** 2))
        count += corners.size
    opencv_rms, fitted_rms = np.sqrt(opencv_sq / count), np.sqrt(fitted_sq / count)
    assert fitted_rms < 0.7 * opencv_rms, (opencv_rms, fitted_rms)


def test_the_c_fit_gives_numpys_corners(monkeypatch: pytest.MonkeyPatch) -> None:
    # The C loop (coverage/_corner_symmetry.c) and NumPy's must agree but for the order of their sums,
    # on a board inside the image and one cut so that windows hang off the image's left edge.
    assert corner_symmetry._fit_in_c is not None, "the C extension coverage/_corner_symmetry.c was not built (pip install -e .)"
    image, detection, _true = _view(40.0, 0.45, noise_dn=1.5, blur_px=0.7, seed=3)
    corners = detection.corners_px.astype(np.float64)
    left = int(np.sort(corners[:, 0])[3]) - 4
    for cut, given in ((image, corners), (image[:, left:], corners - (left, 0))):
        inside = (given >= 0).all(axis=1)
        args = (cut, given[inside], detection.object_points_m[inside], SPEC)
        with_c = refine_by_symmetry(*args, blur_sigma_px=0.7)
        monkeypatch.setattr(corner_symmetry, "_fit_in_c", None)
        with_numpy = refine_by_symmetry(*args, blur_sigma_px=0.7)
        monkeypatch.undo()
        assert np.count_nonzero(np.any(with_numpy != given[inside], axis=1)) >= 0.8 * inside.sum()
        np.testing.assert_allclose(with_c, with_numpy, rtol=0, atol=1e-9)


def test_marker_free_squares_follow_the_pattern() -> None:
    # OpenCV's current pattern leaves the top-left square without a marker; the legacy pattern of a
    # board with an even number of rows puts one there (an odd row count prints the same either way).
    assert marker_free_squares(SPEC)[0, 0] and marker_free_squares(SPEC).sum() == SPEC.squares_x * SPEC.squares_y // 2
    even = BoardSpec(squares_x=5, squares_y=4, square_mm=30.0, marker_mm=22.0, legacy=False)
    legacy = BoardSpec(squares_x=5, squares_y=4, square_mm=30.0, marker_mm=22.0, legacy=True)
    assert marker_free_squares(even)[0, 0] != marker_free_squares(legacy)[0, 0]
