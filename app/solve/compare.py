"""How differently two camera models project: mrcal's `projection_diff` on OpenCV's models.

Two calibrations of one lens never agree on the camera frame exactly: a small rotation of it is
indistinguishable from a shift of the principal point for a narrow lens, and any extrinsic
calibration absorbs it. So the models are compared after the one rotation that best maps the rays
of `a` into `b`'s projection. This scores a calibration against the lens truth (tests, benchmarks)
and compares two solves of the same camera (cross-validation: odd against even frames).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibcoach.app.solve.result import UncertaintyMap
from calibcoach.app.solve.uncertainty import DEFAULT_DISTANCE_M, image_grid
from calibcoach.drivers.lens import CameraModel

_ROUND_TRIP_RAD = 1e-6  # a ray b projects must come back from b.unproject within this angle
_GAUSS_NEWTON_STEPS = 10  # the fit starts at the identity and is nearly linear: 2-3 steps converge


@dataclass(frozen=True, slots=True)
class DifferenceMap:
    """Per grid point: how far b projects the ray a sees there, after the fitted rotation."""

    grid_x_px: np.ndarray  # (GX,) float64 pixel x of grid columns (in a's image)
    grid_y_px: np.ndarray  # (GY,) float64 pixel y of grid rows
    diff_px: np.ndarray  # (GY, GX) float64 distance between a's pixel and b's projection; NaN where excluded
    valid: np.ndarray  # (GY, GX) bool rays b can project (and project back), inside the mask
    rotation: np.ndarray  # (3,) float64 Rodrigues vector of the fitted rotation (a's frame -> b's); 0 without fit
    rms_px: float  # over valid points
    p95_px: float
    max_px: float


@dataclass(frozen=True, slots=True)
class CrossValidation:
    """Observed difference of two solves against the difference their uncertainties predict."""

    difference: DifferenceMap
    predicted_px: np.ndarray  # (GY, GX) float64 sqrt(sigma_a^2 + sigma_b^2), 1 sigma worst direction
    ratio: np.ndarray  # (GY, GX) float64 diff_px / predicted_px; NaN where excluded
    ratio_p95: float  # 95th percentile of ratio over the compared points: >> 1 means the model cannot fit
    diff_p95_px: float
    predicted_p95_px: float


def projection_difference(
    a: CameraModel,
    b: CameraModel,
    *,
    grid: tuple[int, int] | None = None,
    mask: np.ndarray | None = None,
    fit_rotation: bool = True,
    distance_m: float | None = None,
) -> DifferenceMap:
    """Unproject a grid of `a`'s pixels, rotate (best fit), project with `b`, measure the distance.

    Args:
        a: the reference model (its grid and image).
        b: the model compared; same image size.
        grid: (GX, GY) counts; default 32 columns and rows scaled to the aspect.
        mask: (GY, GX) bool points to fit and score (e.g. the covered region); default all.
        fit_rotation: fit the rotation by Gauss-Newton on the pixel differences (a 3-vector).
        distance_m: where the points sit on a's rays (default 10 m). Only a rotation is fitted and
            a projection depends on a point's direction only, so the result does not depend on it.

    Returns:
        DifferenceMap; points whose rays b cannot project (behind it, past its fold) are excluded.

    Example:
        >>> cam = CameraModel.from_fov((640, 480), 60.0)
        >>> projection_difference(cam, cam).max_px < 1e-9
        True
    """
    if tuple(a.image_size) != tuple(b.image_size):
        raise ValueError(f"models must share an image size to be compared, got {a.image_size} and {b.image_size}")
    gx, gy = image_grid(a.image_size, grid)
    return _difference_on_grid(a, b, gx, gy, mask=mask, fit_rotation=fit_rotation, distance_m=distance_m)


def cross_validation_difference(
    a: CameraModel, b: CameraModel, uncertainty_a: UncertaintyMap, uncertainty_b: UncertaintyMap
) -> CrossValidation:
    """Two solves of one camera (e.g. odd and even frames): is their difference what noise predicts?

    The two solves use disjoint frames, so their errors are independent and the predicted 1-sigma
    of the difference is sqrt(sigma_a^2 + sigma_b^2) per point. The difference is a 2-D distance and
    sigma the worst direction, so a ratio up to ~2-3 is noise; well above it the model cannot fit
    the lens, whatever the RMS says. Points covered in both maps are compared (all when none are).

    Args:
        a, b: the two solved models.
        uncertainty_a, uncertainty_b: their maps on the same grid (`projection_uncertainty`, with
            the default `absorb_rotation=True` to match the rotation fitted here).

    Returns:
        CrossValidation with ratio_p95 the 95th percentile of difference / predicted.
    """
    ua, ub = uncertainty_a, uncertainty_b
    if not (np.array_equal(ua.grid_x_px, ub.grid_x_px) and np.array_equal(ua.grid_y_px, ub.grid_y_px)):
        raise ValueError("the two uncertainty maps must share one grid; build them with the same grid counts")
    if tuple(a.image_size) != tuple(b.image_size):
        raise ValueError(f"models must share an image size to be compared, got {a.image_size} and {b.image_size}")
    both = ua.covered & ub.covered
    mask = both if both.any() else np.ones_like(both)
    diff = _difference_on_grid(a, b, ua.grid_x_px, ua.grid_y_px, mask=mask, fit_rotation=True, distance_m=None)
    predicted = np.sqrt(ua.sigma_px**2 + ub.sigma_px**2)
    ratio = np.where(diff.valid, diff.diff_px / np.maximum(predicted, 1e-12), np.nan)
    return CrossValidation(
        difference=diff,
        predicted_px=predicted,
        ratio=ratio,
        ratio_p95=_p95(ratio[diff.valid]),
        diff_p95_px=diff.p95_px,
        predicted_p95_px=_p95(predicted[diff.valid]),
    )


def _difference_on_grid(
    a: CameraModel,
    b: CameraModel,
    gx: np.ndarray,
    gy: np.ndarray,
    *,
    mask: np.ndarray | None,
    fit_rotation: bool,
    distance_m: float | None,
) -> DifferenceMap:
    shape = (gy.size, gx.size)
    keep = np.ones(shape, bool) if mask is None else np.asarray(mask, bool)
    if keep.shape != shape:
        raise ValueError(f"mask must be {shape} bool (GY, GX), got {keep.shape}")
    q = np.stack([c.reshape(-1) for c in np.meshgrid(gx, gy)], axis=1)  # (G, 2)
    d = DEFAULT_DISTANCE_M if distance_m is None else float(distance_m)
    points = a.unproject(q) * d  # (G, 3)
    ok = _projectable(b, points) & keep.reshape(-1)
    omega = np.zeros(3)
    if fit_rotation and ok.sum() >= 2:
        for _ in range(_GAUSS_NEWTON_STEPS):
            proj, J_rot = _project_rotated(b, points[ok], omega)
            r = (proj - q[ok]).reshape(-1)
            step = np.linalg.lstsq(J_rot, -r, rcond=None)[0]
            omega = omega + step
            if np.linalg.norm(step) < 1e-12:
                break
        # a rotation that turns rays past b's edge excludes them too
        rotated = points @ cv2.Rodrigues(omega)[0].T
        ok &= _projectable(b, rotated)
    else:
        rotated = points
    diff = np.full(q.shape[0], np.nan)
    if ok.any():
        diff[ok] = np.linalg.norm(b.project(rotated[ok]) - q[ok], axis=1)
    values = diff[ok]
    return DifferenceMap(
        grid_x_px=np.asarray(gx, np.float64),
        grid_y_px=np.asarray(gy, np.float64),
        diff_px=diff.reshape(shape),
        valid=ok.reshape(shape),
        rotation=omega,
        rms_px=float(np.sqrt(np.mean(values**2))) if values.size else float("nan"),
        p95_px=_p95(values),
        max_px=float(values.max()) if values.size else float("nan"),
    )


def _projectable(b: CameraModel, points: np.ndarray) -> np.ndarray:
    """(G,) bool: b projects the point to a finite pixel that unprojects back to the same ray.

    The round trip rejects what b cannot represent: rays behind a pinhole or past 90 deg for
    OpenCV's fisheye projection, and rays past the fold of an over-fitted radial polynomial.
    """
    ok = np.zeros(points.shape[0], bool)
    front = points[:, 2] > 1e-9 * np.linalg.norm(points, axis=1)  # OpenCV divides by z in every model
    if not front.any():
        return ok
    px = b.project(points[front])
    finite = np.all(np.isfinite(px), axis=1)
    back = np.zeros((px.shape[0], 3))
    back[finite] = b.unproject(px[finite])
    unit = points[front] / np.linalg.norm(points[front], axis=1, keepdims=True)
    angle = np.linalg.norm(np.cross(back, unit), axis=1)
    ok[np.nonzero(front)[0]] = finite & (angle < _ROUND_TRIP_RAD) & (np.sum(back * unit, axis=1) > 0)
    return ok


def _project_rotated(b: CameraModel, points: np.ndarray, omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """b's projection of R(omega) p, (n, 2), and its Jacobian w.r.t. omega, (2n, 3)."""
    zero = np.zeros(3)
    if b.model == "fisheye":
        proj, J = cv2.fisheye.projectPoints(
            points.reshape(1, -1, 3), omega.reshape(1, 1, 3), zero.reshape(1, 1, 3), b.camera_matrix, b.dist_coeffs
        )
        return proj.reshape(-1, 2), J[:, 8:11]
    proj, J = cv2.projectPoints(points, omega, zero, b.camera_matrix, b.opencv_dist())
    return proj.reshape(-1, 2), J[:, :3]


def _p95(values: np.ndarray) -> float:
    return float(np.percentile(values, 95)) if values.size else float("nan")
