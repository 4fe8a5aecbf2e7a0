"""CameraModel: projection round trips for every model, field of view, resize and crop rules."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibcoach.drivers.lens import CameraModel, rational_like

LENSES = {
    "pinhole": CameraModel("pinhole", [[900, 0, 641.3], [0, 901, 357.9], [0, 0, 1]], [-0.12, 0.08, 0.001, -0.0007, -0.02], (1280, 720)),
    "rational": CameraModel("rational", [[420, 0, 640], [0, 420, 360], [0, 0, 1]], [0.6, 0.1, 0.0005, 0.0003, 0.002, 0.95, 0.2, 0.01], (1280, 720)),
    "fisheye": CameraModel("fisheye", [[489, 0, 640], [0, 489, 360], [0, 0, 1]], [0.02, -0.01, 0.002, -0.0005], (1280, 720)),
}


@pytest.mark.parametrize("name", sorted(LENSES))
def test_unproject_then_project_returns_every_pixel(name: str) -> None:
    camera = LENSES[name]
    px = np.random.default_rng(1).uniform([0, 0], [1279, 719], size=(5000, 2))
    back = camera.project(camera.unproject(px))
    assert np.max(np.abs(back - px)) < 1e-6


def test_unproject_beats_opencv_on_a_strong_real_lens() -> None:
    # The caliscope webcam's published solve (k1 -0.38): OpenCV's fixed-point undistortPoints
    # (default 5 iterations) misses pixels near the corner by a pixel or more; the bisection +
    # Newton inverse is exact wherever the model is invertible.
    camera = CameraModel("pinhole", [[877.47, 0, 624.05], [0, 878.88, 383.24], [0, 0, 1]],
                         [-0.3793, 0.1345, 0.0005, -0.0071, -0.0447], (1280, 720))
    px = np.array([[100.0, 80.0], [200.0, 100.0], [640.0, 360.0]])
    ours = camera.project(camera.unproject(px))
    cv = cv2.undistortPoints(px.reshape(-1, 1, 2), camera.camera_matrix, camera.opencv_dist()).reshape(-1, 2)
    theirs = camera.project(np.concatenate([cv, np.ones((3, 1))], axis=1))
    assert np.max(np.abs(ours - px)) < 1e-6
    assert np.max(np.abs(theirs - px)) > 1.0


def test_fisheye_unprojects_beyond_ninety_degrees() -> None:
    camera = CameraModel("fisheye", [[300, 0, 640], [0, 300, 360], [0, 0, 1]], [0, 0, 0, 0], (1280, 720))
    ray = camera.unproject(np.array([[1279.0, 360.0]]))[0]
    assert np.degrees(np.arccos(ray[2])) == pytest.approx(np.degrees((1279 - 640) / 300), abs=1e-6)
    assert ray[2] < 0  # 122 deg off axis: behind the image plane, still a valid fisheye ray


def test_the_fisheye_newton_inverse_finds_the_bisections_angle() -> None:
    # Newton steps inside the bisection's bracket, and plain bisection, on 200 random Kannala-Brandt
    # profiles: the same angle wherever the profile rises; past its fold, the fold's angle.
    from calibcoach.drivers.lens import _fisheye_theta_d, _fisheye_theta_d_slope, _fold_of, _invert_monotonic

    rng = np.random.default_rng(7)
    for _ in range(200):
        D = rng.normal(0.0, [0.05, 0.02, 0.01, 0.005])
        fold = _fold_of("fisheye", tuple(D))
        top = float(_fisheye_theta_d(D, np.array(fold)))
        targets = np.concatenate([[0.0], rng.uniform(0.0, 0.999 * top, 300), [1.5 * top]])
        bisected = _invert_monotonic(lambda t, D=D: _fisheye_theta_d(D, t), targets, fold)
        newton = _invert_monotonic(lambda t, D=D: _fisheye_theta_d(D, t), targets, fold,
                                   slope=lambda t, D=D: _fisheye_theta_d_slope(D, t))
        assert np.max(np.abs(newton - bisected)) < 1e-13
        assert np.max(np.abs(_fisheye_theta_d(D, newton[:-1]) - targets[:-1])) < 1e-14 * max(top, 1.0)


def test_field_of_view_from_fov_guess_round_trips() -> None:
    for model in ("pinhole", "fisheye"):
        camera = CameraModel.from_fov((1280, 720), 100.0, model)
        assert camera.field_of_view_deg()[0] == pytest.approx(100.0, abs=0.2)


def test_resize_scales_focal_lengths_and_keeps_distortion() -> None:
    camera = LENSES["pinhole"]
    half = camera.resized((640, 360))
    assert half.fx == pytest.approx(camera.fx / 2)
    assert half.fy == pytest.approx(camera.fy / 2)
    # pixel centres: (c + 0.5) * s - 0.5
    assert half.principal_point[0] == pytest.approx((641.3 + 0.5) / 2 - 0.5)
    np.testing.assert_array_equal(half.dist_coeffs, camera.dist_coeffs)
    # the same ray lands on the resized pixel grid consistently
    ray = np.array([[0.3, -0.2, 1.0]])
    full_px = camera.project(ray)[0]
    assert half.project(ray)[0] == pytest.approx((full_px + 0.5) / 2 - 0.5)


def test_resize_refuses_a_change_of_aspect_ratio() -> None:
    with pytest.raises(ValueError, match="aspect ratio"):
        LENSES["pinhole"].resized((640, 480))


def test_crop_shifts_the_principal_point_only() -> None:
    camera = LENSES["rational"]
    crop = camera.cropped(100, 60, 1080, 600)
    assert crop.principal_point == pytest.approx((540.0, 300.0))
    assert crop.fx == camera.fx
    np.testing.assert_array_equal(crop.dist_coeffs, camera.dist_coeffs)
    with pytest.raises(ValueError, match="does not fit"):
        camera.cropped(300, 0, 1080, 720)


@pytest.mark.parametrize("model", ["pinhole", "rational", "fisheye"])
def test_many_points_project_as_opencv_projects_them(model: str) -> None:
    """Large batches take the NumPy path (OpenCV's bindings always compute the Jacobian); it must be OpenCV's formula."""
    rng = np.random.default_rng(7)
    coeffs = {"pinhole": 5, "rational": 8, "fisheye": 4}[model]
    for _ in range(20):
        K = np.array([[rng.uniform(300, 1500), 0.0, rng.uniform(300, 900)], [0.0, rng.uniform(300, 1500), rng.uniform(200, 600)],
                      [0.0, 0.0, 1.0]])
        camera = CameraModel(model, K, rng.normal(0.0, 0.1, coeffs), (1280, 720))
        points = rng.normal(0.0, 0.5, (300, 3)) + [0.0, 0.0, 2.0]
        rvec, tvec = rng.normal(0.0, 0.4, 3), rng.normal(0.0, 0.2, 3)
        if model == "fisheye":
            expected, _ = cv2.fisheye.projectPoints(points.reshape(1, -1, 3), rvec.reshape(1, 1, 3), tvec.reshape(1, 1, 3),
                                                    K, camera.dist_coeffs)
        else:
            expected, _ = cv2.projectPoints(points, rvec, tvec, K, camera.opencv_dist())
        got = camera.project(points, rvec, tvec)
        assert got.shape == (300, 2)
        np.testing.assert_allclose(got, expected.reshape(-1, 2), rtol=1e-11, atol=1e-9)
        # and the few-point path (OpenCV itself) agrees with the batch
        np.testing.assert_allclose(camera.project(points[:5], rvec, tvec), got[:5], rtol=1e-11, atol=1e-9)


@pytest.mark.parametrize("fisheye", [LENSES["fisheye"], CameraModel("fisheye", [[700, 0, 960], [0, 700, 540], [0, 0, 1]],
                                                                     [0.05, -0.02, 0.004, -0.0005], (1920, 1080))])
def test_a_fisheyes_rational_twin_images_its_rays_where_it_does(fisheye: CameraModel) -> None:
    # The start a wide lens's rational solve takes from the capture's fisheye model (calibrate._starts).
    twin = rational_like(fisheye, np.radians(60.0))
    assert twin is not None and twin.model == "rational"
    np.testing.assert_array_equal(twin.camera_matrix, fisheye.camera_matrix)
    rng = np.random.default_rng(4)
    theta, phi = rng.uniform(0, np.radians(60.0), 2000), rng.uniform(0, 2 * np.pi, 2000)
    rays = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)
    assert np.abs(twin.project(rays) - fisheye.project(rays)).max() < 0.05  # px
    with pytest.raises(ValueError, match="converts a fisheye"):
        rational_like(LENSES["rational"], 1.0)
