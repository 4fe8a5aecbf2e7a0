"""Projection uncertainty: Jacobians against finite differences, covariance against OpenCV and
Monte-Carlo, the map's shape over covered and uncovered regions, and the frame-gain score."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibcoach.app.solve import information as I
from calibcoach.app.solve import uncertainty as U
from calibcoach.app.solve.result import View
from calibcoach.drivers.lens import CameraModel

from _synthetic import BOARD, IDS, SIZE, observe, pose_at, random_poses, stacked

LENSES = {
    "pinhole": CameraModel("pinhole", [[900, 0, 645.0], [0, 905, 355.0], [0, 0, 1]], [-0.2, 0.08, 5e-4, -3e-4, -0.01], SIZE),
    "rational": CameraModel(
        "rational", [[560, 0, 642.0], [0, 560, 357.0], [0, 0, 1]], [2.0, 0.5, 3e-4, -2e-4, 0.01, 2.4, 1.1, 0.05], SIZE
    ),
    "fisheye": CameraModel("fisheye", [[460, 0, 641.0], [0, 458, 359.0], [0, 0, 1]], [0.03, -0.01, 0.004, -0.001], SIZE),
}


def perturbed(camera, name, eps):
    """The camera with intrinsic `name` moved by eps."""
    K, D = camera.camera_matrix.copy(), camera.dist_coeffs.copy()
    where = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}
    if name in where:
        K[where[name]] += eps
    else:
        D[I.intrinsic_names(camera.model).index(name) - 4] += eps
    return CameraModel(camera.model, K, D, camera.image_size)


def step(name):
    return 1e-3 if name in ("fx", "fy", "cx", "cy") else 1e-7


def kb_project(camera, points):
    """Independent Kannala-Brandt projection with atan2, valid past 90 deg (OpenCV's is not)."""
    X, Y, Z = points.T
    r = np.hypot(X, Y)
    theta = np.arctan2(r, Z)
    k = camera.dist_coeffs
    theta_d = theta * (1 + k[0] * theta**2 + k[1] * theta**4 + k[2] * theta**6 + k[3] * theta**8)
    return np.stack([camera.fx * theta_d * X / r, camera.fy * theta_d * Y / r], 1) + camera.principal_point


def test_intrinsic_names_follow_opencv_order():
    assert I.intrinsic_names("pinhole") == ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    assert I.intrinsic_names("rational")[8:] == ("k3", "k4", "k5", "k6")
    assert len(I.intrinsic_names("fisheye")) == 8
    with pytest.raises(ValueError, match="model must be one of"):
        I.intrinsic_names("omnidir")


def test_opencv_fisheye_jacobian_columns_are_f_c_k_om_t():
    """cv2.fisheye.projectPoints documents f(2), c(2), k(4), om(3), t(3), alpha(1); check it."""
    cam = LENSES["fisheye"]
    r, t = pose_at(cam, (900, 200), 0.5, 20, -25, 10)
    _, J = cv2.fisheye.projectPoints(BOARD.reshape(1, -1, 3), r.reshape(1, 1, 3), t.reshape(1, 1, 3), cam.camera_matrix, cam.dist_coeffs)
    assert J.shape == (2 * BOARD.shape[0], 15)
    columns = {}
    for name in I.intrinsic_names("fisheye"):
        e = step(name)
        columns[name] = (perturbed(cam, name, e).project(BOARD, r, t) - perturbed(cam, name, -e).project(BOARD, r, t)).reshape(-1) / (2 * e)
    for i in range(6):
        d = np.zeros(6)
        d[i] = 1e-7
        plus = cam.project(BOARD, r + d[:3], t + d[3:])
        minus = cam.project(BOARD, r - d[:3], t - d[3:])
        columns[("om", "t")[i // 3] + str(i % 3)] = (plus - minus).reshape(-1) / 2e-7
    order = [min(columns, key=lambda n: np.abs(columns[n] - J[:, j]).max()) for j in range(14)]
    assert order == ["fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4", "om0", "om1", "om2", "t0", "t1", "t2"]
    for j, name in enumerate(order):
        assert np.abs(columns[name] - J[:, j]).max() < 1e-5 * max(1.0, np.abs(J[:, j]).max())


@pytest.mark.parametrize("model", ["pinhole", "rational", "fisheye"])
def test_view_jacobian_matches_finite_differences(model):
    cam = LENSES[model]
    r, t = pose_at(cam, (400, 500), 0.5, -20, 30, 15)
    J_intr, J_pose = I.view_jacobian(cam, BOARD, r, t)
    assert J_intr.shape == (140, len(I.intrinsic_names(model))) and J_pose.shape == (140, 6)
    for j, name in enumerate(I.intrinsic_names(model)):
        e = step(name)
        fd = (perturbed(cam, name, e).project(BOARD, r, t) - perturbed(cam, name, -e).project(BOARD, r, t)).reshape(-1) / (2 * e)
        assert np.abs(fd - J_intr[:, j]).max() < 1e-5 * max(1.0, np.abs(fd).max()), name
    for i in range(6):
        d = np.zeros(6)
        d[i] = 1e-7
        fd = (cam.project(BOARD, r + d[:3], t + d[3:]) - cam.project(BOARD, r - d[:3], t - d[3:])).reshape(-1) / 2e-7
        assert np.abs(fd - J_pose[:, i]).max() < 1e-5 * max(1.0, np.abs(fd).max()), i


@pytest.mark.parametrize("model", ["pinhole", "rational", "fisheye", "fisheye-200deg"])
def test_projection_jacobian_matches_finite_differences(model):
    cam = LENSES.get(model) or CameraModel("fisheye", [[300, 0, 640.0], [0, 300, 360.0], [0, 0, 1]], [0.02, -0.004, 0, 0], SIZE)
    gx, gy = U.image_grid(SIZE, (9, 5))
    J = U.projection_jacobian(cam, gx, gy, absorb_rotation=False)
    assert J.shape == (5, 9, 2, len(I.intrinsic_names(cam.model)))
    points = cam.unproject(np.stack([c.reshape(-1) for c in np.meshgrid(gx, gy)], 1)) * 10.0
    project = kb_project if cam.model == "fisheye" else (lambda c, p: c.project(p))
    front = points[:, 2] > 0.05
    assert np.abs(project(cam, points[front]) - cam.project(points[front])).max() < 1e-9  # the reference is OpenCV's model
    if model == "fisheye-200deg":
        assert np.degrees(np.arccos(points[:, 2] / 10.0)).max() > 120  # rays past 90 deg are covered
    for j, name in enumerate(I.intrinsic_names(cam.model)):
        e = step(name)
        fd = (project(perturbed(cam, name, e), points) - project(perturbed(cam, name, -e), points)) / (2 * e)
        assert np.abs(fd - J.reshape(-1, 2, J.shape[-1])[:, :, j]).max() < 1e-5 * max(1.0, np.abs(fd).max()), name


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_absorbed_jacobian_is_orthogonal_to_rotations(model):
    """(I - R R^+) M has no component a common rotation of the rays can produce (R by finite differences)."""
    cam = LENSES[model]
    gx, gy = U.image_grid(SIZE, (16, 9))
    M = U.projection_jacobian(cam, gx, gy).reshape(-1, len(I.intrinsic_names(model)))
    points = cam.unproject(np.stack([c.reshape(-1) for c in np.meshgrid(gx, gy)], 1)) * 10.0
    R = np.stack([
        (cam.project(points @ cv2.Rodrigues(w)[0].T) - cam.project(points @ cv2.Rodrigues(-w)[0].T)).reshape(-1) / 2e-7
        for w in np.eye(3) * 1e-7
    ], 1)
    plain = U.projection_jacobian(cam, gx, gy, absorb_rotation=False).reshape(M.shape)
    cos = np.abs(R.T @ M) / (np.linalg.norm(R, axis=0)[:, None] * np.linalg.norm(M, axis=0)[None] + 1e-300)
    assert cos.max() < 1e-6
    assert np.abs(R.T @ plain).max() > 1e3  # the plain operator does have rotation components


def test_absorb_rotation_removes_principal_point_shift_of_narrow_lens():
    cam = CameraModel("pinhole", [[3000, 0, 640.0], [0, 3000, 360.0], [0, 0, 1]], np.zeros(5), SIZE)
    only_cx = np.diag([0, 0, 1.0, 0, 0, 0, 0, 0, 0])
    only_fx = np.diag([1.0, 0, 0, 0, 0, 0, 0, 0, 0])
    plain = U.projection_uncertainty(cam, only_cx, absorb_rotation=False).sigma_px
    assert np.allclose(plain, 1.0)  # a 1 px sigma on cx moves every pixel by 1 px
    assert U.projection_uncertainty(cam, only_cx).sigma_px.max() < 0.05  # a 0.3 deg rotation explains it
    zoom_plain = U.projection_uncertainty(cam, only_fx, absorb_rotation=False).p95_px
    zoom = U.projection_uncertainty(cam, only_fx).p95_px
    assert zoom == pytest.approx(zoom_plain, rel=0.02)  # no rotation looks like a zoom


@pytest.mark.parametrize("model", ["pinhole", "rational"])
def test_covariance_matches_opencv_std_deviations(model):
    """OpenCV inverts the full JtJ; the Schur complement must give the same intrinsic block."""
    cam = LENSES[model]
    rng = np.random.default_rng(5)
    poses = random_poses(cam, 10, rng, distance_m=(0.3, 0.5) if model == "rational" else (0.6, 1.0))
    views = observe(cam, poses, rng)
    obj = [v.object_points_m.astype(np.float32) for v in views]
    img = [v.image_points_px.astype(np.float32) for v in views]
    flags = cv2.CALIB_RATIONAL_MODEL if model == "rational" else 0
    rms, K, D, rvecs, tvecs, std, _, _ = cv2.calibrateCameraExtended(obj, img, SIZE, None, None, flags=flags)
    P = len(I.intrinsic_names(model))
    solved = CameraModel(model, K, D.reshape(-1)[: P - 4], SIZE)
    n = 2 * BOARD.shape[0] * len(views)
    sigma = rms * np.sqrt(n / 2 / (n - P - 6 * len(views)))  # OpenCV's estimate: residual^2 / (dof), per coordinate
    ours = np.sqrt(np.diag(I.intrinsic_covariance(solved, views, np.reshape(rvecs, (-1, 3)), np.reshape(tvecs, (-1, 3)), sigma_px=sigma)))
    theirs = std.reshape(-1)[:P]  # fx fy cx cy, then the distortion vector's order: k1 k2 p1 p2 k3 k4 k5 k6
    np.testing.assert_allclose(ours, theirs, rtol=1e-3)


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_predicted_std_matches_monte_carlo(model):
    """60 re-solves with fresh 0.2 px noise: the empirical std of fx, fy, cx, cy, k1 within 30 % of sigma."""
    cam = LENSES[model]
    rng = np.random.default_rng(0)
    poses = random_poses(cam, 8, rng, distance_m=(0.35, 0.6) if model == "fisheye" else (0.6, 1.0))
    predicted = np.sqrt(np.diag(I.intrinsic_covariance(cam, observe(cam, poses), *stacked(poses), sigma_px=0.2)))
    estimates = []
    for _ in range(60):
        views = observe(cam, poses, rng, noise_px=0.2)
        if model == "fisheye":
            # started from the truth: the Monte-Carlo measures noise, not the solver's basin of attraction
            _, K, D, _, _ = cv2.fisheye.calibrate(
                [v.object_points_m.reshape(1, -1, 3) for v in views], [v.image_points_px.reshape(1, -1, 2) for v in views],
                SIZE, cam.camera_matrix.copy(), cam.dist_coeffs.reshape(4, 1).copy(),
                flags=cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | cv2.CALIB_USE_INTRINSIC_GUESS,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12),
            )
        else:
            obj = [v.object_points_m.astype(np.float32) for v in views]
            img = [v.image_points_px.astype(np.float32) for v in views]
            _, K, D, _, _ = cv2.calibrateCamera(obj, img, SIZE, None, None)
        estimates.append([K[0, 0], K[1, 1], K[0, 2], K[1, 2], D.reshape(-1)[0]])
    ratio = np.std(estimates, axis=0, ddof=1) / predicted[:5]
    assert np.all(np.abs(ratio - 1) < 0.3), ratio  # 60 samples: the std itself is known to ~9 %


def test_rank_deficient_information_gives_huge_finite_variance():
    S = np.diag([4.0, 1.0, 0.0])  # the third parameter is not observed at all
    S[0, 1] = S[1, 0] = 2.0  # and the first two only through their difference: rank 1
    C = I.covariance_from_information(S)
    assert np.all(np.isfinite(C)) and np.all(np.diag(C) > 0)
    assert min(np.diag(C)) > 1e10
    cam = LENSES["pinhole"]
    one = [pose_at(cam, (640, 360), 0.8, 0, 0)]  # one frontal view cannot separate f from distance
    C1 = I.intrinsic_covariance(cam, observe(cam, one), *stacked(one), sigma_px=0.2)
    assert np.all(np.isfinite(C1)) and np.all(np.diag(C1) > 0) and np.sqrt(C1[0, 0]) > 1e3


def test_uncertainty_is_larger_outside_the_covered_region():
    cam = LENSES["pinhole"]
    rng = np.random.default_rng(7)
    poses = random_poses(cam, 10, rng, region=(0.4, 0.6), distance_m=(0.7, 0.9), tilt_deg=40)
    views = observe(cam, poses, rng)
    corners = [v.image_points_px for v in views]
    cov = I.intrinsic_covariance(cam, views, *stacked(poses), sigma_px=0.2)
    umap = U.projection_uncertainty(cam, cov, covered_mask_fn=lambda gx, gy: U.covered_region_mask(SIZE, corners, (gx.size, gy.size)))
    assert umap.sigma_px.shape == (18, 32) and umap.covered.shape == (18, 32)
    assert umap.covered[9, 16] and not umap.covered[0, 0] and not umap.covered[17, 31]
    assert 0.1 < umap.covered.mean() < 0.3  # the board only ever sat around the centre
    inside = np.median(umap.sigma_px[umap.covered])
    outside = np.median(umap.sigma_px[~umap.covered])
    assert inside < 0.5  # ~0.2 px corner noise averaged over 700 corners, plus the f / distance ambiguity
    assert outside > 10 * inside, (inside, outside)
    assert umap.sigma_px[0, 0] > 1000 * inside  # the image corner is pure extrapolation of k1, k2, k3
    assert umap.p95_covered_px < umap.p95_px
    # a whole-image rotation fit would let the unobserved corners drag the centre (hence the covered fit)
    whole = U.projection_uncertainty(cam, cov)
    assert np.median(whole.sigma_px[umap.covered]) > 10 * inside


def test_covered_region_mask_dilates_by_half_a_cell():
    square = np.array([[400.0, 200.0], [880.0, 200.0], [880.0, 520.0], [400.0, 520.0], [640.0, 360.0]])
    mask = U.covered_region_mask(SIZE, [square], (32, 18))  # cells of 40 px: centres at 19.5 + 40 i
    gx, gy = np.meshgrid(*U.image_grid(SIZE, (32, 18)))
    # distance to the rectangle the hull is, at most half a cell (20 px): a rounded box
    dx = np.maximum.reduce([400 - gx, np.zeros_like(gx), gx - 880])
    dy = np.maximum.reduce([200 - gy, np.zeros_like(gy), gy - 520])
    np.testing.assert_array_equal(mask, np.hypot(dx, dy) <= 20)
    assert mask.sum() == 13 * 9 - 1  # the box of centres 419.5..899.5 x 219.5..539.5 less its corner 27.6 px away
    assert not U.covered_region_mask(SIZE, [], (32, 18)).any()


def test_information_gain_prefers_a_tilted_corner_view_to_a_duplicate():
    cam = LENSES["pinhole"]
    rng = np.random.default_rng(11)
    frontal = pose_at(cam, (640, 360), 0.9, 0, 0)
    poses = [frontal, *random_poses(cam, 5, rng, region=(0.35, 0.65), tilt_deg=25)]
    views = observe(cam, poses, rng)
    S = I.marginal_information(cam, views, *stacked(poses))
    corner_pose = pose_at(cam, (1080, 170), 0.7, 30, -30)
    scores = {}
    for label, pose in (("duplicate", frontal), ("corner", corner_pose)):
        image = cam.project(BOARD, *pose) + rng.normal(0, 0.2, (70, 2))
        ok, r, t = cv2.solvePnP(BOARD, image, cam.camera_matrix, cam.opencv_dist())  # the selector's pose
        assert ok
        J_intr, J_pose = I.view_jacobian(cam, BOARD, r, t)
        S_new, drop = I.information_gain(S, J_intr, J_pose)
        W = U.pixel_variance_weight(U.projection_jacobian(cam, *U.image_grid(SIZE, (8, 5))))
        _, drop_px = I.information_gain(S, J_intr, J_pose, weight=W)
        from calibcoach.app.solve.next_view import error_cut

        _, cut_E = error_cut(S, W, J_intr, J_pose)  # what guidance and selection score: the relative cut of E
        scores[label] = (drop, drop_px, cut_E)
        # adding the view one step at a time is exactly the Schur complement of the bigger solve
        full = I.marginal_information(cam, [*views, View(9, "", IDS, image, BOARD)], *stacked([*poses, (r.ravel(), t.ravel())]))
        np.testing.assert_allclose(S_new, full, rtol=1e-9, atol=1e-9 * np.abs(full).max())
    for k in range(3):
        assert 0 <= scores["duplicate"][k] < 0.2
        assert scores["corner"][k] > (0.3 if k < 2 else 0.15)  # E cut = 1 - sqrt(1 - E^2 cut)
        assert scores["corner"][k] > 3 * scores["duplicate"][k], scores


def test_image_grid_defaults_follow_the_aspect():
    gx, gy = U.image_grid((1920, 1080))
    assert (gx.size, gy.size) == (32, 18)
    assert gx[0] == pytest.approx(1920 / 64 - 0.5) and gy[-1] == pytest.approx(1080 - 1080 / 36 - 0.5)
    gx, gy = U.image_grid((640, 480), step_px=40)
    assert (gx.size, gy.size) == (16, 12)
    with pytest.raises(ValueError, match=r"covariance is \(9, 9\)"):
        U.projection_uncertainty(LENSES["pinhole"], np.eye(8))


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_expected_error_and_its_map_match_monte_carlo(model):
    """E and the per-pixel expected error against 60 re-solves with fresh noise, within 20 % both ways.

    The error of each re-solve is measured as a user would: project the truth's rays with the
    re-solved model after the best-fit rotation over the covered region (`projection_difference`).
    """
    from calibcoach.app.solve.compare import projection_difference

    cam = LENSES[model]
    rng = np.random.default_rng(3)
    poses = random_poses(cam, 8, rng, distance_m=(0.35, 0.6) if model == "fisheye" else (0.6, 1.0))
    corners = [v.image_points_px for v in observe(cam, poses)]
    cov = I.intrinsic_covariance(cam, observe(cam, poses), *stacked(poses), sigma_px=0.2)
    umap = U.projection_uncertainty(cam, cov, covered_mask_fn=lambda gx, gy: U.covered_region_mask(SIZE, corners, (gx.size, gy.size)))
    # one computation: the map's E and the trace form candidate scoring uses are the same number
    assert U.expected_error_px(cov, umap.error_weight) == pytest.approx(umap.expected_error_px, rel=1e-9)
    squared = []
    for _ in range(60):
        views = observe(cam, poses, rng, noise_px=0.2)
        obj = [v.object_points_m for v in views]
        img = [v.image_points_px for v in views]
        if model == "fisheye":
            _, K, D, _, _ = cv2.fisheye.calibrate(
                [o.reshape(1, -1, 3) for o in obj], [i.reshape(1, -1, 2) for i in img], SIZE, cam.camera_matrix.copy(),
                cam.dist_coeffs.reshape(4, 1).copy(), flags=cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | cv2.CALIB_USE_INTRINSIC_GUESS,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
        else:
            _, K, D, _, _ = cv2.calibrateCamera([o.astype(np.float32) for o in obj], [i.astype(np.float32) for i in img], SIZE, None, None)
        estimate = CameraModel(model, K, D.reshape(-1)[: 4 if model == "fisheye" else 5], SIZE)
        diff = projection_difference(cam, estimate, grid=(umap.grid_x_px.size, umap.grid_y_px.size), mask=umap.covered)
        squared.append(diff.diff_px**2)
    observed_map = np.sqrt(np.mean(squared, axis=0))  # (GY, GX) RMS error length per grid point
    observed_E = float(np.sqrt(np.mean(observed_map[umap.covered] ** 2)))
    assert 0.8 < observed_E / umap.expected_error_px < 1.2, (observed_E, umap.expected_error_px)
    ratio = observed_map[umap.covered] / umap.error_px[umap.covered]
    assert 0.8 < np.median(ratio) < 1.2 and np.percentile(ratio, 10) > 0.7 and np.percentile(ratio, 90) < 1.3, np.percentile(ratio, [10, 50, 90])


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_weighted_refinement_discounts_noisy_views(model):
    """4 of 18 views at 6x the corner noise: weighting them by inverse variance halves the error."""
    from calibcoach.app.solve.calibrate import reprojection_residuals, solve
    from calibcoach.app.solve.compare import projection_difference
    from calibcoach.app.solve.weighted import view_weights, weighted_refine

    cam = LENSES[model]
    rng = np.random.default_rng(1)
    plain, weighted = [], []
    for _ in range(4):
        poses = random_poses(cam, 18, rng, distance_m=(0.35, 0.6) if model == "fisheye" else (0.6, 1.0))
        views = [View(v.frame_index, "", v.ids, v.image_points_px + rng.normal(0, 0.6 if v.frame_index < 4 else 0.1, (70, 2)),
                      v.object_points_m) for v in observe(cam, poses)]
        raw = solve(views, SIZE, model)
        w = view_weights(reprojection_residuals(raw.camera, views, raw.rvecs, raw.tvecs))
        assert np.all(w[:4] < 0.2) and np.all(w[4:] > 0.5)  # the noisy views are the ones discounted
        refined, _, _ = weighted_refine(raw.camera, views, raw.rvecs, raw.tvecs, w)
        plain.append(projection_difference(cam, raw.camera).rms_px)
        weighted.append(projection_difference(cam, refined).rms_px)
    assert np.median(weighted) < 0.7 * np.median(plain), (plain, weighted)


# A rational model solved on a 104 deg 1080p render whose numerator and denominator vanish together
# near r = 1.465: grid point (row 16, column 0), at the lower-left corner, sits on that 0/0.
_DEGENERATE_RATIONAL = CameraModel(
    "rational",
    np.array([[1081.562981207004, 0.0, 954.8921682265093], [0.0, 1080.7496026010188, 542.9491565592243], [0.0, 0.0, 1.0]]),
    np.array([-0.529811834641253, -0.012583269498551588, 0.00039272776311231655, -0.0002932294154556247,
              0.019742249474090902, -0.17946535790730195, -0.2593887736256844, 0.058685330378585115]),
    (1920, 1080),
)


def test_a_degenerate_point_of_the_model_is_left_out_of_E() -> None:
    cam = _DEGENERATE_RATIONAL
    gx, gy = U.image_grid(cam.image_size)
    everywhere = np.ones((gy.size, gx.size), bool)
    bad = U.degenerate_points(U.projection_jacobian(cam, gx, gy, absorb_rotation=False), everywhere)
    assert np.argwhere(bad).tolist() == [[16, 0]]
    cov = np.diag(np.array([0.09, 0.09, 0.15, 0.2, 0.05, 0.02, 1e-5, 2e-5, 4e-3, 0.05, 6e-3, 0.014]) ** 2)
    umap = U.projection_uncertainty(cam, cov, covered_mask_fn=lambda x, y: everywhere)
    assert not umap.covered[16, 0] and umap.covered.sum() == everywhere.sum() - 1
    # E is what the other points say: the same as with that point never covered
    without = U.projection_uncertainty(cam, cov, covered_mask_fn=lambda x, y: everywhere & ~bad)
    assert umap.expected_error_px == pytest.approx(without.expected_error_px, rel=1e-12)
    assert umap.error_px[16, 0] > 1e3 * np.median(umap.error_px)  # the map still shows it as it is


def test_an_ordinary_model_has_no_degenerate_points() -> None:
    for cam in (CameraModel.from_fov(SIZE, 70.0), CameraModel.from_fov(SIZE, 100.0, "rational"),
                CameraModel.from_fov(SIZE, 150.0, "fisheye")):
        gx, gy = U.image_grid(cam.image_size)
        plain = U.projection_jacobian(cam, gx, gy, absorb_rotation=False)
        assert not U.degenerate_points(plain, np.ones((gy.size, gx.size), bool)).any(), cam.model


@pytest.mark.parametrize("model", list(LENSES))
def test_stacked_projections_are_the_views_projections_in_the_jacobians_rows(model: str) -> None:
    # The weighted refinement takes its residuals from these: each view's corners as the camera
    # projects them, x then y per corner, zero in the padding rows; the Jacobians are the stack's.
    camera = LENSES[model]
    rng = np.random.default_rng(7)
    poses = random_poses(camera, 5, rng)
    views = observe(camera, poses, rng, noise_px=0.0)
    views[1] = View(views[1].frame_index, views[1].frame_name, views[1].ids[:20], views[1].image_points_px[:20],
                    views[1].object_points_m[:20])  # fewer corners than the rest: padded rows
    rvecs, tvecs = [r for r, _ in poses], [t for _, t in poses]
    projected, J_intr, J_pose = I.stacked_projections_and_jacobians(camera, views, np.array(rvecs), np.array(tvecs))
    J_intr_alone, J_pose_alone = I.stacked_view_jacobians(camera, views, np.array(rvecs), np.array(tvecs))
    assert np.array_equal(J_intr, J_intr_alone) and np.array_equal(J_pose, J_pose_alone)
    for k, (v, r, t) in enumerate(zip(views, rvecs, tvecs, strict=True)):
        n = 2 * v.image_points_px.shape[0]
        np.testing.assert_allclose(projected[k, :n], camera.project(v.object_points_m, r, t).reshape(-1), atol=1e-9)
        assert not projected[k, n:].any()
    assert projected.shape == (5, 2 * max(v.image_points_px.shape[0] for v in views))
