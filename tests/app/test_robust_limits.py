"""The robust solve's limits, each on both sides: the corner floor, the frame ratio and floor, the
smallest view and session that lose frames, and the exact sigma behind the reported covariance."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_robust import CAMERA, session, swapped_rows  # its synthetic sessions (tests/app is on pythonpath)

from calibcoach.app.solve import information as I
from calibcoach.app.solve.calibrate import pose_for_view, reprojection_residuals, solve
from calibcoach.app.solve.result import View
from calibcoach.app.solve.robust import (
    _refit_frame_rms_px,
    build_calibration,
    look_alike_correlation,
    noise_sigma_px,
    robust_calibrate,
    robust_frame_rms_px,
    robust_sigma_px,
)
from calibcoach.drivers.errors import CalibrationError
from calibcoach.drivers.sim import LENSES

from _synthetic import BOARD, IDS, SIZE, observe, random_poses, stacked


def test_a_one_pixel_outlier_in_a_low_noise_session_is_dropped_but_not_below_the_floor() -> None:
    """0.03 px noise: the chi-square limit is 0.13 px, the floor 0.3 px decides."""
    rng, _poses, views, _mask = session(20, 0.03, n=8)
    px = views[2].image_points_px.copy()
    px[30] += [1.0, 0.0]  # dropped: above the 0.3 px floor
    px[40] += [0.0, 0.2]  # kept: 7 sigma, but below the floor
    views[2] = replace(views[2], image_points_px=px)
    cal = robust_calibrate(views, SIZE, "pinhole")
    assert [(c.frame_index, c.corner_id) for c in cal.dropped_corners] == [(2, 30)]
    assert cal.dropped_frames == ()


@pytest.mark.parametrize(("noise", "dropped"), [(0.45, True), (0.33, False)])
def test_the_frame_floor(noise: float, dropped: bool) -> None:
    """0.1 px sessions: a view at RMS 0.64 px (> 0.5 px floor) goes, one at 0.47 px stays."""
    rng, _poses, views, _mask = session(21, 0.1, n=10)
    views[4] = replace(views[4], image_points_px=views[4].image_points_px + rng.normal(0, np.sqrt(noise**2 - 0.01), (70, 2)))
    cal = robust_calibrate(views, SIZE, "pinhole")
    assert ([f.frame_index for f in cal.dropped_frames] == [4]) is dropped


@pytest.mark.parametrize(("noise", "dropped"), [(1.25, True), (0.9, False)])
def test_the_frame_ratio(noise: float, dropped: bool) -> None:
    """0.3 px sessions (median view RMS 0.42 px): a view at 3.8x the median goes, one at 2.8x stays."""
    rng, _poses, views, _mask = session(22, 0.3, n=10)
    views[4] = replace(views[4], image_points_px=views[4].image_points_px + rng.normal(0, np.sqrt(noise**2 - 0.09), (70, 2)))
    cal = robust_calibrate(views, SIZE, "pinhole")
    assert (4 in [f.frame_index for f in cal.dropped_frames]) is dropped
    assert len(cal.dropped_frames) <= 1


def test_five_views_do_lose_a_frame() -> None:
    rng, poses, views, _mask = session(23, 0.2, n=5)
    views[2] = swapped_rows(views[2], 1, 6)
    cal = robust_calibrate(views, SIZE, "pinhole")
    assert [f.frame_index for f in cal.dropped_frames] == [2] and cal.dropped_frames[0].reason.startswith("frame RMS")


def test_the_covariance_is_built_on_the_dof_corrected_weighted_sigma() -> None:
    """Exactly: sigma = noise_sigma_px(typical RMS) with all corners, all views, the model's parameters."""
    rng = np.random.default_rng(24)
    poses = random_poses(CAMERA, 6, rng)
    views = observe(CAMERA, poses, rng, noise_px=0.2)
    rvecs, tvecs = stacked(poses)
    cal = build_calibration(CAMERA, views, rvecs, tvecs)
    sigma = noise_sigma_px(cal.rms_px, n_points=6 * 70, n_params=9, n_views=6)
    assert sigma == pytest.approx(cal.rms_px / np.sqrt(2) * np.sqrt(840 / (840 - 9 - 36)))
    np.testing.assert_allclose(cal.intrinsic_covariance, I.intrinsic_covariance(CAMERA, views, rvecs, tvecs, sigma_px=sigma),
                               rtol=1e-9)
    # weighted views: the typical RMS is sum(w r^2) / sum(w n), and each view enters the covariance at its weight
    w = [1.0, 1.0, 0.25, 1.0, 0.5, 1.0]
    weighted = [replace(v, information_weight=wi) for v, wi in zip(views, w, strict=True)]
    cal_w = build_calibration(CAMERA, weighted, rvecs, tvecs)
    res = [v.image_points_px - CAMERA.project(v.object_points_m, r, t) for v, r, t in zip(views, rvecs, tvecs, strict=True)]
    typical = np.sqrt(sum(wi * np.sum(r**2) for wi, r in zip(w, res, strict=True)) / (70 * sum(w)))
    sigma_w = noise_sigma_px(typical, n_points=420, n_params=9, n_views=6)
    np.testing.assert_allclose(cal_w.intrinsic_covariance,
                               I.intrinsic_covariance(CAMERA, weighted, rvecs, tvecs, sigma_px=sigma_w), rtol=1e-9)
    assert cal_w.rms_px == cal.rms_px  # the reported RMS stays the plain one


def test_noise_sigma_with_one_degree_of_freedom() -> None:
    assert noise_sigma_px(1.0, n_points=8, n_params=9, n_views=1) == pytest.approx(np.sqrt(16) / np.sqrt(2))  # dof = 1


def test_look_alike_correlation_of_small_or_empty_residuals() -> None:
    rng = np.random.default_rng(25)
    views = observe(CAMERA, random_poses(CAMERA, 3, rng))
    small = rng.normal(0, 0.05, (70, 2))  # sum of squares ~0.35: the measure has no scale
    assert look_alike_correlation(views, [small, small.copy(), small], [0, 0, 1]) == pytest.approx(1.0)
    other = rng.normal(0, 0.05, (70, 2))
    half = 0.5 * small + 0.5 * other
    expected = np.sum(small * half) / np.sqrt(np.sum(small**2) * np.sum(half**2))
    assert look_alike_correlation(views, [small, half, small], [0, 0, 1]) == pytest.approx(expected)
    zero = np.zeros((70, 2))
    assert look_alike_correlation(views, [zero, small, small], [0, 0, 1]) == 0.0  # one frame without residuals
    assert look_alike_correlation(views, [small, zero, small], [0, 0, 1]) == 0.0


def test_the_trimmed_frame_rms() -> None:
    """The frame statistic: a gaussian frame's RMS, unmoved by its worst tenth of corners, moved by more."""
    rng = np.random.default_rng(26)
    frames = [rng.normal(0, 0.3, (70, 2)) for _ in range(2000)]
    ratio = np.array([robust_frame_rms_px(r) / np.sqrt(np.mean(np.sum(r**2, axis=1))) for r in frames])
    assert np.mean(ratio) == pytest.approx(1.0, abs=0.01) and np.std(ratio) < 0.05  # the plain RMS, unbiased
    r = frames[0].copy()
    r[:7] += 50.0  # 7 of 70 corners 70 px off: left out, and the 63 clean ones taken for the best 90%
    plain_63 = np.sqrt(np.mean(np.sum(frames[0][7:] ** 2, axis=1)))
    assert robust_frame_rms_px(r) == pytest.approx(plain_63 / np.sqrt(0.74416), rel=1e-4)  # 1.16x: never more
    r[7] += 50.0  # the eighth is counted
    assert robust_frame_rms_px(r) > 5.0
    few = rng.normal(0, 0.3, (9, 2))  # under 10 corners none is left out: the plain RMS
    assert robust_frame_rms_px(few) == pytest.approx(np.sqrt(np.mean(np.sum(few**2, axis=1))))
    assert robust_frame_rms_px(np.zeros((0, 2))) == 0.0


@pytest.mark.parametrize(("bad", "frame_dropped"), [(6, False), (12, True)])
def test_bad_corners_go_as_corners_up_to_a_tenth_of_the_frame(bad: int, frame_dropped: bool) -> None:
    """0.2 px session, one frame with `bad` corners 10 px off: 6 of 70 go as corners and the frame
    stays with its other 64; 12 of 70 are the frame's bulk being off, and it goes whole."""
    rng, _poses, views, _mask = session(27, 0.2, n=10)
    idx = rng.choice(70, bad, replace=False)
    px = views[5].image_points_px.copy()
    angles = rng.uniform(0, 2 * np.pi, bad)
    px[idx] += 10.0 * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    views[5] = replace(views[5], image_points_px=px)
    cal = robust_calibrate(views, SIZE, "pinhole")
    assert ([f.frame_index for f in cal.dropped_frames] == [5]) is frame_dropped
    if not frame_dropped:
        assert cal.dropped_frames == ()
        assert {(c.frame_index, c.corner_id) for c in cal.dropped_corners} == {(5, int(i)) for i in idx}
        assert cal.corner_count == 10 * 70 - bad


def test_a_view_of_six_clean_corners_stays() -> None:
    """Six corners are enough (the selector's minimum too): when another view's outlier corner goes,
    a clean six-corner view is kept whole, not dropped as "too few left"."""
    rng, _poses, views, _mask = session(3, 0.2, n=4)
    keep = np.isin(views[1].ids, [0, 1, 2, 7, 8, 9])  # two rows of three
    views[1] = replace(views[1], ids=views[1].ids[keep], image_points_px=views[1].image_points_px[keep],
                       object_points_m=views[1].object_points_m[keep])
    px = views[0].image_points_px.copy()
    px[20] += [6.0, 0.0]
    views[0] = replace(views[0], image_points_px=px)
    cal = robust_calibrate(views, SIZE, "pinhole")
    assert cal.dropped_frames == ()
    assert [(c.frame_index, c.corner_id) for c in cal.dropped_corners] == [(0, 20)]
    assert [len(v.ids) for v in cal.views] == [69, 6, 70, 70]


def test_three_views_still_get_the_weighted_refinement() -> None:
    """The smallest solve (three views) weights a noisier view down like any other."""
    rng, _poses, views, _mask = session(30, 0.2, n=3)
    views[1] = replace(views[1], image_points_px=views[1].image_points_px + rng.normal(0, 0.5, (70, 2)))
    cal = robust_calibrate(views, SIZE, "pinhole")
    weights = [v.information_weight for v in cal.views]
    assert weights[0] == weights[2] == 1.0 and 0.1 < weights[1] < 0.5  # (0.2 / 0.54)^2 ~ 0.15-0.2


@pytest.mark.parametrize(("offset_px", "dropped"), [(0.88, True), (0.85, False)])
def test_the_corner_limit_is_the_chi_square_99_99_point(offset_px: float, dropped: bool) -> None:
    """A corner whose residual in the first solve is 4.35 robust sigmas out goes (sqrt(18.42) = 4.29:
    1 clean corner in 10,000 beyond it); one at 4.2 sigmas stays."""
    rng, poses, views, _mask = session(41, 0.2, n=10)
    px = views[3].image_points_px.copy()
    px[33] = CAMERA.project(BOARD[33:34], *poses[3])[0] + [offset_px, 0.0]
    views[3] = replace(views[3], image_points_px=px)
    raw = solve(views, SIZE, "pinhole")
    res = reprojection_residuals(raw.camera, views, raw.rvecs, raw.tvecs)
    sigmas = float(np.linalg.norm(res[3][33])) / robust_sigma_px(res)
    assert (4.30 < sigmas < 4.40) if dropped else (4.15 < sigmas < 4.28), sigmas
    cal = robust_calibrate(views, SIZE, "pinhole")
    assert [(c.frame_index, c.corner_id) for c in cal.dropped_corners] == ([(3, 33)] if dropped else [])


def test_a_suspect_frame_is_judged_by_the_pose_of_its_best_corners() -> None:
    """7 of 70 corners 10 px off pull the frame's pose: its trimmed RMS at that pose is 2x the noise,
    re-fitted to its best 63 corners it is the noise's. Under 10 corners none is left out: no re-fit."""
    rng = np.random.default_rng(40)
    view = observe(CAMERA, random_poses(CAMERA, 1, rng, region=(0.3, 0.7), distance_m=(0.5, 0.7)), rng, noise_px=0.2)[0]
    px = view.image_points_px.copy()
    angles = rng.uniform(0, 2 * np.pi, 7)
    px[rng.choice(70, 7, replace=False)] += 10.0 * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    view = replace(view, image_points_px=px)
    res = view.image_points_px - CAMERA.project(view.object_points_m, *pose_for_view(CAMERA, view))
    assert robust_frame_rms_px(res) > 0.5  # 2x the noise
    assert _refit_frame_rms_px(CAMERA, view, res) == pytest.approx(0.2 * np.sqrt(2), rel=0.15)
    nine = replace(view, ids=view.ids[:9], image_points_px=px[:9], object_points_m=view.object_points_m[:9])
    assert _refit_frame_rms_px(CAMERA, nine, res[:9]) == robust_frame_rms_px(res[:9])


@pytest.mark.parametrize(("good", "survives"), [(4, True), (3, False)])
def test_an_unposable_fisheye_view_is_left_out_only_from_five_frames(good: int, survives: bool) -> None:
    """Leaving a frame out to let the fisheye solve start needs four frames to remain."""
    camera = LENSES["fisheye150"]
    rng = np.random.default_rng(0)
    views = observe(camera, random_poses(camera, good, rng, region=(0.05, 0.95), distance_m=(0.25, 0.5), tilt_deg=40,
                                         max_off_axis_deg=80), rng)
    r, t = random_poses(camera, 1, np.random.default_rng(5), region=(0.3, 0.7), distance_m=(0.3, 0.4), tilt_deg=20,
                        max_off_axis_deg=80)[0]
    row = np.arange(6)  # one board row: six collinear corners, no homography
    line = View(99, "", IDS[row], camera.project(BOARD[row], r, t), BOARD[row])
    if survives:
        cal = robust_calibrate([*views, line], camera.image_size, "fisheye")
        assert [d.frame_index for d in cal.dropped_frames] == [99] and len(cal.views) == good
    else:
        with pytest.raises(CalibrationError, match="fisheye"):
            robust_calibrate([*views, line], camera.image_size, "fisheye")
