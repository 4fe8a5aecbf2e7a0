"""How far off a pixel's ray can be: projection uncertainty from an OpenCV solve (mrcal's idea).

A reprojection RMS only says the model fits the frames it saw. Here the covariance of the
intrinsics with every board pose marginalised out (app/solve/information.py) is pushed through the
projection of a grid of image points. Following mrcal, the part of an intrinsic perturbation that
a small common rotation of the camera frame explains is removed: any extrinsic calibration done
later absorbs it, so it is not an error a user would ever see.

Columns of every Jacobian follow `intrinsic_names(model)`; skew is fixed at 0 in every model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2
import numpy as np

from calibcoach.app.solve.information import intrinsic_names
from calibcoach.app.solve.result import UncertaintyMap
from calibcoach.drivers.lens import CameraModel

DEFAULT_GRID_X = 32  # grid columns; rows follow the image's aspect (18 for 16:9), as mrcal's maps
DEFAULT_DISTANCE_M = 10.0  # "far": beyond any board distance, mrcal's working-distance idea


# --- projection uncertainty over the image ---------------------------------------------------


def image_grid(image_size: tuple[int, int], grid: tuple[int, int] | None = None, *, step_px: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates of grid cell centres, (GX,) and (GY,) float64.

    Default: 32 columns and rows scaled to the aspect; `step_px` picks the counts from a cell size.

    Example:
        >>> gx, gy = image_grid((1280, 720))
        >>> gx.size, gy.size, float(gx[0]), float(gy[-1])
        (32, 18, 19.5, 699.5)
    """
    w, h = image_size
    if grid is None:
        if step_px is not None:
            grid = (max(2, round(w / step_px)), max(2, round(h / step_px)))
        else:  # 32 x 18 for 16:9
            grid = (DEFAULT_GRID_X, max(2, round(DEFAULT_GRID_X * h / w)))
    gx, gy = int(grid[0]), int(grid[1])
    if gx < 1 or gy < 1:
        raise ValueError(f"grid must have at least 1x1 cells, got {grid}")
    return (np.arange(gx) + 0.5) * w / gx - 0.5, (np.arange(gy) + 0.5) * h / gy - 0.5


def projection_jacobian(
    camera: CameraModel, grid_x_px: np.ndarray, grid_y_px: np.ndarray, *,
    distance_m: float | None = None, absorb_rotation: bool = True, fit_mask: np.ndarray | None = None,
) -> np.ndarray:
    """d(pixel)/d(intrinsics) of the point seen at each grid pixel, optionally rotation-free.

    With `absorb_rotation`, the perturbation operator M (2G, P) becomes M - R R_f^+ M_f, R (2G, 3)
    being the pixel motion of a small common rotation of all rays and _f the rows in `fit_mask`: the
    rotation fitted there (least squares) is removed everywhere. Fit where the board was seen: an
    unobserved k3 moves the corners by 1000s of px, which would drag a whole-image fit and spoil the
    centre (mrcal's projection_diff fits in a focus region for the same reason). This is the
    infinite-distance form of mrcal's reference-frame fit; it needs no board poses.

    Args:
        camera: the model.
        grid_x_px: (GX,) float pixel x of grid columns.
        grid_y_px: (GY,) float pixel y of grid rows.
        distance_m: where the point sits on its ray (default 10 m). An intrinsic change moves the
            projection of a camera-frame point through its direction only, and only a rotation is
            absorbed, so the result does not depend on it; it is kept for mrcal's interface.
        absorb_rotation: remove the part of each perturbation a common rotation explains.
        fit_mask: (GY, GX) bool grid points the rotation is fitted on; None or < 2 points: all.

    Returns:
        (GY, GX, 2, P) float64 px per parameter unit.
    """
    J_intr, J_rot = _grid_jacobians(camera, grid_x_px, grid_y_px, distance_m=distance_m)
    return _rotation_absorbed(J_intr, J_rot, fit_mask) if absorb_rotation else J_intr


def _grid_jacobians(camera: CameraModel, grid_x_px: np.ndarray, grid_y_px: np.ndarray, *,
                    distance_m: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(GY, GX, 2, P) d(pixel)/d(intrinsics) and (GY, GX, 2, 3) d(pixel)/d(rotation) of the point seen
    at each grid pixel (see `projection_jacobian`)."""
    gx, gy = np.meshgrid(np.asarray(grid_x_px, np.float64), np.asarray(grid_y_px, np.float64))
    rays = camera.unproject(np.stack([gx.reshape(-1), gy.reshape(-1)], axis=1))  # (G, 3) unit
    if camera.model == "fisheye":
        # OpenCV's fisheye projection divides by z, so rays beyond 90 deg need the numpy form.
        J_intr, J_rot = _kannala_brandt_jacobian(camera, rays)
    else:
        d = DEFAULT_DISTANCE_M if distance_m is None else float(distance_m)
        P = len(intrinsic_names(camera.model))
        # At the identity pose the rvec columns are the pixel motion of a small rotation of the ray.
        _, J = cv2.projectPoints(rays * d, np.zeros(3), np.zeros(3), camera.camera_matrix, camera.opencv_dist())
        J_intr, J_rot = J[:, 6 : 6 + P], J[:, :3]
    return J_intr.reshape(gy.shape[0], gy.shape[1], 2, -1), J_rot.reshape(gy.shape[0], gy.shape[1], 2, 3)


def _rotation_absorbed(J_intr: np.ndarray, J_rot: np.ndarray, fit_mask: np.ndarray | None) -> np.ndarray:
    """`J_intr` less the part a common rotation, fitted on `fit_mask`'s points, explains (see `projection_jacobian`)."""
    M = J_intr.reshape(-1, J_intr.shape[-1])  # (2G, P), rows u0, v0, u1, ...
    R = J_rot.reshape(-1, 3)
    points = J_intr.shape[0] * J_intr.shape[1]
    rows = np.repeat(np.ones(points, bool) if fit_mask is None else np.asarray(fit_mask, bool).reshape(-1), 2)
    rows = rows if rows.sum() >= 4 else np.ones_like(rows)
    Rf, Mf = R[rows], M[rows]
    M = M - R @ (np.linalg.pinv(Rf.T @ Rf, hermitian=True) @ (Rf.T @ Mf))  # R_f^+ M_f via the 3x3 normal matrix
    return M.reshape(J_intr.shape)


def projection_sigma(jacobian: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Worst-direction 1-sigma: sqrt of the largest eigenvalue of J Sigma J^T per point.

    Args:
        jacobian: (..., 2, P) float64 from `projection_jacobian`.
        covariance: (P, P) float64 intrinsic covariance.

    Returns:
        (...) float64 pixels.
    """
    V = np.einsum("...ip,pq,...jq->...ij", jacobian, covariance, jacobian)
    a, b, c = V[..., 0, 0], V[..., 0, 1], V[..., 1, 1]
    largest = 0.5 * (a + c) + np.sqrt(0.25 * (a - c) ** 2 + b * b)  # closed form for a 2x2
    return np.sqrt(np.clip(largest, 0, None))


def projection_uncertainty(
    camera: CameraModel, covariance: np.ndarray, *, grid_step_px: float | None = None, grid: tuple[int, int] | None = None,
    distance_m: float | None = None, covered_mask_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    absorb_rotation: bool = True,
) -> UncertaintyMap:
    """The map a user reads: per grid pixel, how far its projection can be off (1 sigma, px).

    Args:
        camera: the solved model.
        covariance: (P, P) float64 from `intrinsic_covariance`.
        grid_step_px: cell size in pixels (ignored when `grid` is given).
        grid: (GX, GY) counts; default 32 columns and rows scaled to the aspect.
        distance_m: see `projection_jacobian` (default 10 m; no effect on the result).
        covered_mask_fn: (grid_x (GX,), grid_y (GY,)) -> (GY, GX) bool where the board was seen,
            e.g. `lambda gx, gy: covered_region_mask(size, corners, (gx.size, gy.size))`.
            Without it nothing is marked covered (and `p95_covered_px` falls back to the whole map).
        absorb_rotation: see `projection_jacobian`; the rotation is fitted on the covered points
            (on the whole grid when none are covered).

    Returns:
        UncertaintyMap with sigma_px (GY, GX).
    """
    P = len(intrinsic_names(camera.model))
    cov = np.asarray(covariance, np.float64)
    if cov.shape != (P, P):
        raise ValueError(f"a {camera.model} covariance is ({P}, {P}) over {intrinsic_names(camera.model)}, got {cov.shape}")
    gx, gy = image_grid(camera.image_size, grid, step_px=grid_step_px)
    covered = np.zeros((gy.size, gx.size), bool) if covered_mask_fn is None else np.asarray(covered_mask_fn(gx, gy), bool)
    if covered.shape != (gy.size, gx.size):
        raise ValueError(f"covered_mask_fn must return ({gy.size}, {gx.size}) bool, got {covered.shape}")
    J_intr, J_rot = _grid_jacobians(camera, gx, gy, distance_m=distance_m)
    if covered.any():
        covered = covered & ~degenerate_points(J_intr, covered)
    fit = covered if covered.any() else None
    J = _rotation_absorbed(J_intr, J_rot, fit) if absorb_rotation else J_intr
    weight = pixel_variance_weight(J[covered] if covered.any() else J)
    return UncertaintyMap(grid_x_px=gx, grid_y_px=gy, sigma_px=projection_sigma(J, cov), covered=covered,
                          error_px=projection_error_rms(J, cov), error_weight=weight)


# A grid point whose projection moves this many times more per unit of intrinsics than the
# covered region's median is where the fitted model's parametrization degenerates, not where the
# lens is uncertain: a rational model whose numerator and denominator vanish together (0/0 at
# r = 1.465 on a 104 deg render) gives one covered corner point 45,000x the median. Its
# J Sigma J^T is then a cancellation of huge terms, and in the rotation fit it outweighs every
# other point: that capture's E read 8.2 px where its true error was 0.027 px, and 0.057 px
# without the point. Across the held-out renders' solves the largest honest ratio was 141 (a
# rational model's far corner); pinhole ~5, fisheye ~30.
DEGENERATE_JACOBIAN_RATIO = 1e4


def degenerate_points(jacobian: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """(GY, GX) bool: covered grid points whose `jacobian` ((GY, GX, 2, P), `projection_jacobian`
    without the rotation absorbed) is `DEGENERATE_JACOBIAN_RATIO` times the covered median or more
    (left out of E and of the rotation fit; see the constant)."""
    norms = np.linalg.norm(jacobian, axis=(-2, -1))
    with np.errstate(invalid="ignore"):
        return covered & ~(norms <= DEGENERATE_JACOBIAN_RATIO * np.median(norms[covered]))


def projection_error_rms(jacobian: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Expected length of the projection error, sqrt(trace(J Sigma J^T)) per point (px).

    The RMS of the 2-D error vector's length, i.e. the root of the sum of both directions'
    variances: what a user comparing projected and true pixels would measure on average.

    Args:
        jacobian: (..., 2, P) float64 from `projection_jacobian`.
        covariance: (P, P) float64 intrinsic covariance.

    Returns:
        (...) float64 pixels.
    """
    V = np.einsum("...ip,pq,...iq->...", jacobian, covariance, jacobian)
    return np.sqrt(np.clip(V, 0, None))


def expected_error_px(covariance: np.ndarray, weight: np.ndarray) -> float:
    """E = sqrt(trace(W Sigma)): the RMS over the weight's region of the expected projection error.

    With W = `pixel_variance_weight` of the covered grid points this equals
    sqrt(mean(projection_error_rms^2)) over them, exactly; the same number is reached by the
    uncertainty map (`UncertaintyMap.expected_error_px`) and by candidate scoring, which only
    swaps the covariance.
    """
    return float(np.sqrt(max(float(np.sum(np.asarray(weight) * np.asarray(covariance))), 0.0)))


def covered_region_mask(image_size: tuple[int, int], corner_sets: Sequence[np.ndarray], grid: tuple[int, int] | None = None) -> np.ndarray:
    """Grid points inside the union of each view's corner hull, dilated by half a grid cell.

    Args:
        image_size: (width, height) pixels.
        corner_sets: per view (N_v, 2) float detected corners, pixels.
        grid: (GX, GY) counts, as for `image_grid`.

    Returns:
        (GY, GX) bool.
    """
    gx, gy = image_grid(image_size, grid)
    pts = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 2)
    radius = 0.5 * max(image_size[0] / gx.size, image_size[1] / gy.size)
    mask = np.zeros(pts.shape[0], bool)
    for corners in corner_sets:
        c = np.asarray(corners, np.float32).reshape(-1, 2)
        if not c.shape[0]:
            continue
        # only points no view covered yet (a final solve has hundreds of views) and within reach of
        # this one's bounding box: the hull test of the rest could not come out true
        low, high = c.min(axis=0) - radius, c.max(axis=0) + radius
        todo = np.flatnonzero(~mask & np.all((pts >= low) & (pts <= high), axis=1))
        if todo.size:
            hull = cv2.convexHull(c).reshape(-1, 2).astype(np.float64)
            mask[todo] = _distance_to_convex(pts[todo], hull) <= radius
    return mask.reshape(gy.size, gx.size)


def _distance_to_convex(pts: np.ndarray, hull: np.ndarray) -> np.ndarray:
    """(G,) distance from (G, 2) points to a convex polygon (H, 2) given in hull order; 0 inside."""
    a, b = hull, np.roll(hull, -1, axis=0)
    e = b - a  # (H, 2)
    rel = pts[:, None, :] - a[None]  # (G, H, 2)
    t = np.clip(np.einsum("ghk,hk->gh", rel, e) / np.maximum((e * e).sum(1), 1e-12), 0, 1)
    dist = np.linalg.norm(rel - t[..., None] * e[None], axis=2).min(axis=1)
    if hull.shape[0] >= 3:
        cross = e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0]
        inside = np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)
        dist = np.where(inside, 0.0, dist)
    return dist


def _kannala_brandt_jacobian(camera: CameraModel, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(G, 3) unit rays -> d(pixel)/d(intrinsics) (G, 2, 8) and d(pixel)/d(rotation) (G, 2, 3).

    theta = atan2(r, z) holds beyond 90 deg, where OpenCV's atan(r / z) does not. Near the axis
    theta / r -> 1 / z and the terms carrying 1 / r^2 vanish as X^2, so both have safe limits.
    """
    X, Y, Z = rays[:, 0], rays[:, 1], rays[:, 2]
    (k1, k2, k3, k4), fx, fy = camera.dist_coeffs, camera.fx, camera.fy
    r = np.hypot(X, Y)
    small, theta = r < 1e-12, np.arctan2(r, Z)
    safe_r, t2 = np.where(small, 1.0, r), theta * theta
    h = np.where(small, 1.0 / np.where(small, Z, 1.0), theta / safe_r)  # theta / r
    g = h * (1 + k1 * t2 + k2 * t2**2 + k3 * t2**3 + k4 * t2**4)  # theta_d / r
    xd, yd = g * X, g * Y
    one, zero = np.ones_like(X), np.zeros_like(X)
    du = [xd, zero, one, zero] + [fx * X * h * t2**i for i in (1, 2, 3, 4)]
    dv = [zero, yd, zero, one] + [fy * Y * h * t2**i for i in (1, 2, 3, 4)]
    J_intr = np.stack([np.stack(du, axis=1), np.stack(dv, axis=1)], axis=1)
    s = r * r + Z * Z
    dtheta_d = 1 + 3 * k1 * t2 + 5 * k2 * t2**2 + 7 * k3 * t2**3 + 9 * k4 * t2**4
    c = np.where(small, 0.0, (dtheta_d * Z / s - g) / (safe_r * safe_r))  # dg/dX = X c, dg/dY = Y c
    dxd = np.stack([g + X * X * c, X * Y * c, -X * dtheta_d / s], axis=1)  # (G, 3)
    dyd = np.stack([X * Y * c, g + Y * Y * c, -Y * dtheta_d / s], axis=1)
    dq_dp = np.stack([fx * dxd, fy * dyd], axis=1)  # (G, 2, 3)
    # p -> p + w x p, so dp/dw = -[p]x
    dp_dw = np.stack([np.stack([zero, Z, -Y], 1), np.stack([-Z, zero, X], 1), np.stack([Y, -X, zero], 1)], axis=1)
    return J_intr, dq_dp @ dp_dw


def pixel_variance_weight(jacobian: np.ndarray) -> np.ndarray:
    """W (P, P) with trace(W Sigma) = mean over the grid of trace(J_q Sigma J_q^T), in px^2.

    Plain trace(S^-1) adds px^2 (fx) to unitless^2 (k3); weighting by W scores a covariance by the
    pixel variance it causes, which is what the user sees.

    Args:
        jacobian: (..., 2, P) float64 `projection_jacobian` on a coarse grid (8x5 suffices), with
            fit_mask = the covered region once there is one.
    """
    M = jacobian.reshape(-1, jacobian.shape[-1])
    return M.T @ M / (M.shape[0] // 2)
