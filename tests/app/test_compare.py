"""Comparing camera models: mrcal's projection_diff and the odd/even cross-validation check."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibcoach.app.solve import information as I
from calibcoach.app.solve import uncertainty as U
from calibcoach.app.solve.compare import cross_validation_difference, projection_difference
from calibcoach.app.solve.result import View
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.lens import CameraModel

SIZE = (1280, 720)
BOARD = BoardSpec().corner_points_m()  # (70, 3) the default 8x11 board
IDS = np.arange(BOARD.shape[0], dtype=np.int32)
PINHOLE = CameraModel("pinhole", [[900, 0, 645.0], [0, 905, 355.0], [0, 0, 1]], [-0.2, 0.08, 5e-4, -3e-4, -0.01], SIZE)
# a 128 x 75 deg lens (HFOV x VFOV) the 5-term model cannot follow to the edges
WIDE = CameraModel("rational", [[560, 0, 642.0], [0, 560, 357.0], [0, 0, 1]], [2.0, 0.5, 3e-4, -2e-4, 0.01, 2.4, 1.1, 0.05], SIZE)
FISHEYE = CameraModel("fisheye", [[460, 0, 641.0], [0, 458, 359.0], [0, 0, 1]], [0.03, -0.01, 0.004, -0.001], SIZE)


def shifted(camera, dcx=0.0, dfx=0.0):
    K = camera.camera_matrix.copy()
    K[0, 2] += dcx
    K[0, 0] += dfx
    return CameraModel(camera.model, K, camera.dist_coeffs, camera.image_size)


@pytest.mark.parametrize("camera", [PINHOLE, WIDE, FISHEYE], ids=["pinhole", "rational", "fisheye"])
def test_a_model_matches_itself(camera):
    diff = projection_difference(camera, camera)
    assert diff.diff_px.shape == (18, 32) and diff.valid.all()
    assert diff.max_px < 1e-6 and np.abs(diff.rotation).max() < 1e-9
    assert projection_difference(camera, camera, fit_rotation=False).max_px < 1e-6


def test_a_principal_point_shift_of_a_narrow_lens_is_a_rotation():
    narrow = CameraModel("pinhole", [[2000, 0, 640.0], [0, 2000, 360.0], [0, 0, 1]], np.zeros(5), SIZE)
    other = shifted(narrow, dcx=2.0)
    plain = projection_difference(narrow, other, fit_rotation=False)
    assert plain.rms_px == pytest.approx(2.0, abs=1e-6) and plain.max_px == pytest.approx(2.0, abs=1e-6)
    fitted = projection_difference(narrow, other)
    # what is left is second order: about 2 px * tan^2(field angle), 0.2 px at the left and right edges
    assert fitted.max_px < 0.2 and fitted.rms_px < 0.1
    # b sees every ray 2 px further right; turning the rays by about -2/2000 rad about y (towards -x)
    # undoes it; the least-squares angle is 3 % smaller because edge rays move more per radian
    assert fitted.rotation == pytest.approx([0.0, -1e-3, 0.0], abs=5e-5)
    # a focal length change is no rotation: the fit cannot remove it
    zoom = projection_difference(narrow, shifted(narrow, dfx=4.0))
    assert zoom.max_px > 1.0 and zoom.max_px == pytest.approx(projection_difference(narrow, shifted(narrow, dfx=4.0), fit_rotation=False).max_px, rel=0.02)


def test_distance_and_mask():
    other = shifted(PINHOLE, dcx=3.0, dfx=5.0)
    far = projection_difference(PINHOLE, other)
    near = projection_difference(PINHOLE, other, distance_m=0.5)
    np.testing.assert_allclose(near.diff_px, far.diff_px, atol=1e-9)  # only the ray direction matters
    centre = np.zeros((18, 32), bool)
    centre[6:12, 10:22] = True
    masked = projection_difference(PINHOLE, other, mask=centre)
    assert masked.valid.sum() == centre.sum() and np.isnan(masked.diff_px[0, 0])
    assert masked.max_px < far.max_px
    with pytest.raises(ValueError, match="share an image size"):
        projection_difference(PINHOLE, PINHOLE.resized((640, 360)))
    with pytest.raises(ValueError, match=r"mask must be \(18, 32\)"):
        projection_difference(PINHOLE, other, mask=np.ones((5, 5), bool))


def test_rays_the_other_model_cannot_project_are_excluded():
    wide_fisheye = CameraModel("fisheye", [[300, 0, 640.0], [0, 300, 360.0], [0, 0, 1]], [0.02, -0.004, 0, 0], SIZE)
    pinhole = CameraModel("pinhole", [[300, 0, 640.0], [0, 300, 360.0], [0, 0, 1]], np.zeros(5), SIZE)
    diff = projection_difference(wide_fisheye, pinhole, fit_rotation=False)
    gx, gy = U.image_grid(SIZE)
    rays = wide_fisheye.unproject(np.stack([c.reshape(-1) for c in np.meshgrid(gx, gy)], 1))
    behind = (rays[:, 2] <= 0).reshape(18, 32)
    assert behind.sum() > 20  # the fisheye sees past 90 deg in the image corners
    assert not diff.valid[behind].any() and diff.valid[9, 16]
    assert np.isfinite(diff.diff_px[diff.valid]).all() and np.isnan(diff.diff_px[~diff.valid]).all()
    assert diff.diff_px[9, 16] < 0.5 and diff.max_px > 100  # same centre, very different periphery


def _views(camera, n, rng):
    """n noisy (0.2 px) views of the board, corners all inside the image, spread over it."""
    w, h = camera.image_size
    views = []
    while len(views) < n:
        pixel = rng.uniform([0.15 * w, 0.15 * h], [0.85 * w, 0.85 * h])
        tilt = np.radians(rng.uniform(-40, 40, 2))
        R = cv2.Rodrigues(np.array([tilt[0], 0.0, 0.0]))[0] @ cv2.Rodrigues(np.array([0.0, tilt[1], 0.0]))[0]
        t = camera.unproject(pixel.reshape(1, 2))[0] * rng.uniform(0.3, 0.5) - R @ BOARD.mean(axis=0)
        px = camera.project(BOARD, cv2.Rodrigues(R)[0], t)
        if np.all((px >= 5) & (px <= [w - 6, h - 6])):
            views.append(View(len(views), "", IDS, px + rng.normal(0, 0.2, px.shape), BOARD))
    return views


def _solve(views, model):
    """OpenCV solve, covariance with OpenCV's noise estimate, and the map with its covered region."""
    obj = [v.object_points_m.astype(np.float32) for v in views]
    img = [v.image_points_px.astype(np.float32) for v in views]
    flags = cv2.CALIB_RATIONAL_MODEL if model == "rational" else 0
    rms, K, D, rvecs, tvecs = cv2.calibrateCamera(obj, img, SIZE, None, None, flags=flags)
    P = len(I.intrinsic_names(model))
    camera = CameraModel(model, K, D.reshape(-1)[: P - 4], SIZE)
    n = 2 * BOARD.shape[0] * len(views)
    sigma = rms * np.sqrt(n / 2 / (n - P - 6 * len(views)))
    cov = I.intrinsic_covariance(camera, views, np.reshape(rvecs, (-1, 3)), np.reshape(tvecs, (-1, 3)), sigma_px=sigma)
    corners = [v.image_points_px for v in views]
    umap = U.projection_uncertainty(camera, cov, covered_mask_fn=lambda gx, gy: U.covered_region_mask(SIZE, corners, (gx.size, gy.size)))
    return camera, umap


def test_cross_validation_flags_a_model_that_cannot_fit_the_lens():
    views = _views(WIDE, 24, np.random.default_rng(3))
    ratios = {}
    for model in ("pinhole", "rational"):
        a, ua = _solve(views[0::2], model)
        b, ub = _solve(views[1::2], model)
        cv = cross_validation_difference(a, b, ua, ub)
        assert cv.ratio.shape == (18, 32) and cv.difference.valid.sum() == (ua.covered & ub.covered).sum()
        assert cv.predicted_p95_px > 0 and cv.diff_p95_px > 0
        ratios[model] = cv.ratio_p95
        if model == "rational":
            truth = projection_difference(a, WIDE, mask=ua.covered)
            assert truth.p95_px < 3 * ua.p95_covered_px  # the predicted uncertainty is the right size
    assert ratios["rational"] < 2.0  # difference within noise: the model fits
    assert ratios["pinhole"] > 3.0 and ratios["pinhole"] > 4 * ratios["rational"], ratios
