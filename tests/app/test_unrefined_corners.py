"""Corners the masked refinement could not refine count by their own variance in the final solve.

`View.as_refined` marks the corners `refine_on_checker_edges` left as OpenCV gave them; the robust
solve measures their residuals against the refined corners of the same views and weighs them by
the ratio (`robust.unrefined_corner_weights`) in its weighted refinement, and the information and
noise estimate count them the same way. Synthetic views of the webcam (`_synthetic.py`) with a
quarter of each view's corners carrying what an unrefined corner carries on the renders -- more
noise and a pull the views share -- show the weights and where they take the solve.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from calibcoach.app.solve import information as I
from calibcoach.app.solve import uncertainty as U
from calibcoach.app.solve.calibrate import solve
from calibcoach.app.solve.compare import projection_difference
from calibcoach.app.solve.result import View
from calibcoach.app.solve.robust import robust_calibrate, unrefined_corner_weights
from calibcoach.app.solve.weighted import MIN_WEIGHT, weighted_refine
from calibcoach.drivers.sim import LENSES

from _synthetic import IDS, SIZE, observe, random_poses, stacked

CAMERA = LENSES["webcam720"]
GRID = (32, 18)
PULL_PX = 0.1  # what the quarter's corners carry: a pull the views share ...
EXTRA_NOISE_PX = 0.06  # ... and more noise


def _views_with_pulled_quarter(seed: int, *, marked: bool) -> tuple[list[View], np.ndarray]:
    """30 views at 0.03 px noise whose last quarter of corners (the board's far rows) are pulled
    `PULL_PX` away from the image centre and carry `EXTRA_NOISE_PX` more noise; `marked`: as_refined says so."""
    rng = np.random.default_rng(seed)
    poses = random_poses(CAMERA, 30, rng, region=(0.1, 0.9), distance_m=(0.4, 0.7), tilt_deg=40)
    views = observe(CAMERA, poses, rng, noise_px=0.03)
    quarter = np.arange(IDS.size) >= 0.75 * IDS.size
    centre = np.array([(SIZE[0] - 1) / 2.0, (SIZE[1] - 1) / 2.0])
    out = []
    for view in views:
        px = view.image_points_px.copy()
        away = px[quarter] - centre
        px[quarter] += PULL_PX * away / np.linalg.norm(away, axis=1, keepdims=True) + rng.normal(0.0, EXTRA_NOISE_PX, away.shape)
        if not marked:
            out.append(replace(view, image_points_px=px))
            continue
        # as the refinement returns it: its own corner where it refined one (OpenCV's, 0.01 px off,
        # went in), OpenCV's corner bit for bit where it did not
        opencv = px.copy()
        opencv[~quarter] += 0.01
        out.append(replace(view, image_points_px=opencv, refined_px=px).as_refined())
    mask = U.covered_region_mask(SIZE, [v.image_points_px for v in out], GRID)
    return out, mask


def test_as_refined_marks_the_corners_the_refinement_left_alone() -> None:
    px = np.array([[10.0, 20.0], [30.0, 40.0], [50.0, 60.0]])
    refined = px.copy()
    refined[1] += [0.05, -0.02]
    view = View(0, "", np.arange(3, dtype=np.int32), px, np.zeros((3, 3)), refined_px=refined).as_refined()
    assert view.unrefined.tolist() == [True, False, True]
    assert np.array_equal(view.image_points_px, refined) and view.refined_px is None
    assert View(0, "", np.arange(3, dtype=np.int32), px, np.zeros((3, 3))).as_refined().unrefined is None  # nothing refined


def test_the_unrefined_corners_weight_is_their_variance_against_the_refined_ones() -> None:
    ids = np.arange(8, dtype=np.int32)
    unrefined = np.array([True] * 4 + [False] * 4)
    views = [View(k, "", ids, np.zeros((8, 2)), np.zeros((8, 3)), unrefined=unrefined) for k in range(3)]
    # unrefined corners 2x the refined ones' residual in every view: a quarter of the weight
    residuals = [np.vstack([np.full((4, 2), 0.2 * s), np.full((4, 2), 0.1 * s)]) for s in (1.0, 2.0, 3.0)]
    weights = unrefined_corner_weights(views, residuals)
    assert weights is not None and np.allclose(weights[0], [0.25] * 4 + [1.0] * 4)
    far = [np.vstack([np.full((4, 2), 1.0), np.full((4, 2), 0.1)])] * 3
    assert np.allclose(unrefined_corner_weights(views, far)[1][:4], MIN_WEIGHT)  # floored
    assert unrefined_corner_weights([replace(v, unrefined=None) for v in views], residuals) is None  # none marked
    one_kind = [replace(v, unrefined=np.ones(8, bool)) for v in views]
    assert unrefined_corner_weights(one_kind, residuals) is None  # no view to compare within


def test_a_corner_of_weight_zero_adds_no_information() -> None:
    rng = np.random.default_rng(3)
    poses = random_poses(CAMERA, 6, rng, region=(0.2, 0.8), distance_m=(0.5, 0.6), tilt_deg=30)
    views = observe(CAMERA, poses)
    rvecs, tvecs = stacked(poses)
    keep = np.arange(IDS.size) % 3 != 0
    weighted = [replace(v, corner_weights=keep.astype(float)) for v in views]
    dropped = [replace(v, ids=v.ids[keep], image_points_px=v.image_points_px[keep], object_points_m=v.object_points_m[keep])
               for v in views]
    assert np.allclose(I.marginal_information(CAMERA, weighted, rvecs, tvecs), I.marginal_information(CAMERA, dropped, rvecs, tvecs),
                       rtol=1e-9, atol=1e-9)
    assert np.allclose(I.marginal_information(CAMERA, [replace(v, corner_weights=np.ones(IDS.size)) for v in views], rvecs, tvecs),
                       I.marginal_information(CAMERA, views, rvecs, tvecs))


def test_a_corner_of_weight_zero_leaves_the_weighted_refinement_to_the_others() -> None:
    views, mask = _views_with_pulled_quarter(12, marked=True)
    quarter = views[0].unrefined
    start = solve(views, SIZE, "pinhole")
    others = [replace(v, ids=v.ids[~quarter], image_points_px=v.image_points_px[~quarter],
                      object_points_m=v.object_points_m[~quarter], unrefined=None) for v in views]
    alone = solve(others, SIZE, "pinhole").camera
    zero, _r, _t = weighted_refine(start.camera, views, start.rvecs, start.tvecs, np.ones(len(views)),
                                   corner_weights=[np.where(quarter, 0.0, 1.0)] * len(views))
    assert projection_difference(alone, zero, grid=GRID, mask=mask).rms_px < 1e-4  # both converged
    full, _r, _t = weighted_refine(start.camera, views, start.rvecs, start.tvecs, np.ones(len(views)),
                                   corner_weights=[np.ones(IDS.size)] * len(views))
    assert projection_difference(start.camera, full, grid=GRID, mask=mask).rms_px < 1e-4  # unit weights: OpenCV's solve


def test_the_robust_solve_weighs_the_marked_corners_by_their_variance() -> None:
    """The marked quarter (0.1 px pull shared by the views, 0.06 px more noise) counts ~a quarter
    and the solve moves towards what the refined corners alone give; unmarked, it counts fully."""
    solved, reference = {}, None
    for marked in (False, True):
        views, mask = _views_with_pulled_quarter(12, marked=marked)
        calibration = robust_calibrate(views, SIZE, "pinhole")
        solved[marked] = calibration.camera
        if marked:
            quarter = views[0].unrefined
            weights = np.concatenate([v.corner_weights[v.unrefined] for v in calibration.views])
            assert 0.15 < float(np.median(weights)) < 0.35  # (0.03 / ~0.065)^2: their residuals against the others'
            reference = robust_calibrate([replace(v, ids=v.ids[~quarter], image_points_px=v.image_points_px[~quarter],
                                                  object_points_m=v.object_points_m[~quarter], unrefined=None) for v in views],
                                         SIZE, "pinhole").camera
        else:
            assert all(v.corner_weights is None for v in calibration.views)
    off = {m: projection_difference(reference, c, grid=GRID, mask=mask).rms_px for m, c in solved.items()}
    assert off[True] < 0.8 * off[False], off
