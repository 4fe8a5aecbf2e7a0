"""The camera model: intrinsics plus one of three distortion models, with project/unproject.

It sits in the bottom layer because every layer needs it: the simulated camera renders through it,
the coverage map estimates board poses with it, the solver produces it and the outputs write it.

Models (OpenCV's conventions; pixel (0, 0) is the centre of the top-left pixel):
- "pinhole":  5-parameter Brown-Conrady (k1, k2, p1, p2, k3), ordinary lenses.
- "rational": 8-parameter rational model (k1, k2, p1, p2, k3, k4, k5, k6), beyond ~90 deg field of view.
- "fisheye":  Kannala-Brandt (k1..k4 on theta), `cv2.fisheye`, 120 deg and beyond.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

MODELS = ("pinhole", "rational", "fisheye")
COEFF_COUNT = {"pinhole": 5, "rational": 8, "fisheye": 4}
ROS_DISTORTION_NAME = {"pinhole": "plumb_bob", "rational": "rational_polynomial", "fisheye": "equidistant"}
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True, slots=True)
class CameraModel:
    """Intrinsics of one camera at one resolution."""

    model: str  # "pinhole" | "rational" | "fisheye"
    camera_matrix: np.ndarray  # (3, 3) float64, fx fy in pixels, cx cy in pixels
    dist_coeffs: np.ndarray  # (5,) pinhole, (8,) rational, (4,) fisheye; float64
    image_size: tuple[int, int]  # (width, height) pixels

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {self.model!r}")
        K = np.asarray(self.camera_matrix, np.float64).reshape(3, 3)
        D = np.asarray(self.dist_coeffs, np.float64).reshape(-1)
        n = COEFF_COUNT[self.model]
        if D.size < n:
            D = np.concatenate([D, np.zeros(n - D.size)])
        elif D.size > n:
            if np.any(D[n:] != 0):
                raise ValueError(f"{self.model} model takes {n} distortion coefficients, got {D.size} with non-zero extras")
            D = D[:n]
        object.__setattr__(self, "camera_matrix", K)
        object.__setattr__(self, "dist_coeffs", D)
        object.__setattr__(self, "image_size", (int(self.image_size[0]), int(self.image_size[1])))

    # --- construction -------------------------------------------------------------------------
    @staticmethod
    def from_fov(image_size: tuple[int, int], hfov_deg: float, model: str = "pinhole") -> CameraModel:
        """A distortion-free guess from a horizontal field of view (bootstraps pose estimates)."""
        w, h = image_size
        if model == "fisheye":
            f = (w / 2.0) / np.deg2rad(hfov_deg / 2.0)  # equidistant: r = f * theta
        else:
            f = (w / 2.0) / np.tan(np.deg2rad(min(hfov_deg, 170.0) / 2.0))
        K = np.array([[f, 0, (w - 1) / 2.0], [0, f, (h - 1) / 2.0], [0, 0, 1]], np.float64)
        return CameraModel(model, K, np.zeros(COEFF_COUNT[model]), image_size)

    # --- geometry -----------------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.camera_matrix[0, 0])

    @property
    def fy(self) -> float:
        return float(self.camera_matrix[1, 1])

    @property
    def principal_point(self) -> tuple[float, float]:
        return float(self.camera_matrix[0, 2]), float(self.camera_matrix[1, 2])

    def opencv_dist(self) -> np.ndarray:
        """Distortion as OpenCV's non-fisheye calls want it: (1, 5) or (1, 8)."""
        return self.dist_coeffs.reshape(1, -1)

    def project(self, points_cam: np.ndarray, rvec: np.ndarray | None = None, tvec: np.ndarray | None = None) -> np.ndarray:
        """Project (N, 3) points (camera frame, or board frame with rvec/tvec) to (N, 2) float64 pixels."""
        pts = np.asarray(points_cam, np.float64).reshape(-1, 3)
        r = np.zeros(3) if rvec is None else np.asarray(rvec, np.float64).reshape(3)
        t = np.zeros(3) if tvec is None else np.asarray(tvec, np.float64).reshape(3)
        if pts.shape[0] == 0:
            return np.zeros((0, 2))
        if pts.shape[0] >= _NUMPY_PROJECTION_FROM:
            return _project_numpy(self, pts, r, t)
        if self.model == "fisheye":
            out, _ = cv2.fisheye.projectPoints(pts.reshape(1, -1, 3), r.reshape(1, 1, 3), t.reshape(1, 1, 3), self.camera_matrix, self.dist_coeffs)
        else:
            out, _ = cv2.projectPoints(pts, r, t, self.camera_matrix, self.opencv_dist())
        return out.reshape(-1, 2)

    def unproject(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) unit rays in the camera frame (z forward).

        OpenCV's fixed-point `undistortPoints` diverges near the corners of strongly distorted
        lenses (a real 93 deg webcam, k1 = -0.38, misses its own corner by 144 px), so this inverts
        the radial profile on its monotonic branch (`_invert_monotonic`: by bisection, by Newton
        steps inside the bisection's bracket for the fisheye, which always takes this path) and
        polishes with Newton steps on the full model (tangential terms included). OpenCV's answer is still tried first and kept
        when it reprojects to within a micropixel: this runs on every frame's corners, and the
        C++ path is ~10x cheaper than the Python bisection for the pixels where it converges.
        """
        px = np.asarray(pixels, np.float64).reshape(-1, 2)
        if px.shape[0] == 0:
            return np.zeros((0, 3))
        if self.model != "fisheye":
            xy = cv2.undistortPoints(px.reshape(-1, 1, 2), self.camera_matrix, self.opencv_dist(),
                                     criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)
            rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
            with np.errstate(invalid="ignore", over="ignore"):
                missed = ~(np.all(np.isfinite(rays), axis=1) & np.all(np.abs(self.project(rays) - px) < 1e-6, axis=1))
            if missed.any():  # only the pixels OpenCV did not reach take the slow path
                rays[missed] = self._unproject_by_inversion(px[missed])
            return rays / np.linalg.norm(rays, axis=1, keepdims=True)
        return self._unproject_by_inversion(px)

    def _unproject_by_inversion(self, px: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) unit rays by inverting the radial profile (see `unproject`)."""
        K = self.camera_matrix
        yn = (px[:, 1] - K[1, 2]) / K[1, 1]
        xn = (px[:, 0] - K[0, 2] - K[0, 1] * yn) / K[0, 0]
        target = np.stack([xn, yn], axis=1)
        if self.model == "fisheye":
            D = self.dist_coeffs
            theta_fold = _fold_of("fisheye", tuple(D))
            theta = _invert_monotonic(lambda t: _fisheye_theta_d(D, t), np.hypot(xn, yn), theta_fold,
                                      slope=lambda t: _fisheye_theta_d_slope(D, t))
            r_d = np.hypot(xn, yn)
            scale = np.divide(np.sin(theta), r_d, out=np.ones_like(r_d), where=r_d > 1e-12)
            rays = np.stack([xn * scale, yn * scale, np.cos(theta)], axis=1)
            return rays / np.linalg.norm(rays, axis=1, keepdims=True)
        D = self.dist_coeffs
        r_fold = _fold_of(self.model, tuple(D))
        r_d = np.hypot(xn, yn)
        r_u = _invert_monotonic(lambda r: r * _radial_gain(D, r), r_d, r_fold)
        xy = target * np.divide(r_u, r_d, out=np.ones_like(r_d), where=r_d > 1e-12)[:, None]
        # Pixels beyond the fold cannot be reached by the model at all (an over-fitted k3 does that
        # inside the image); they keep the fold's radius instead of sending Newton to infinity.
        reachable = r_d <= r_fold * _radial_gain(D, np.array(r_fold)) + 1e-12
        xy = np.where(reachable[:, None], self._polish(D, xy, target), xy)
        rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    @staticmethod
    def _polish(D: np.ndarray, xy: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Newton steps on the full distortion model (tangential included) from a radial solution."""
        for _ in range(8):  # Newton on the full model; tangential terms are small, so few steps suffice
            f0 = _distort(D, xy) - target
            eps = 1e-7
            jx = (_distort(D, xy + [eps, 0]) - _distort(D, xy - [eps, 0])) / (2 * eps)
            jy = (_distort(D, xy + [0, eps]) - _distort(D, xy - [0, eps])) / (2 * eps)
            det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            dx = (jy[:, 1] * f0[:, 0] - jy[:, 0] * f0[:, 1]) / det
            dy = (-jx[:, 1] * f0[:, 0] + jx[:, 0] * f0[:, 1]) / det
            step = np.stack([dx, dy], axis=1)
            step = np.where(np.isfinite(step), step, 0.0)
            xy = xy - np.clip(step, -0.1, 0.1)
            if np.max(np.abs(f0)) < 1e-14:
                break
        return xy

    def field_of_view_deg(self) -> tuple[float, float]:
        """(horizontal, vertical) field of view through the image's edge midpoints, degrees."""
        w, h = self.image_size
        cx, cy = self.principal_point
        edges = np.array([[-0.5, cy], [w - 0.5, cy], [cx, -0.5], [cx, h - 0.5]])
        rays = self.unproject(edges)
        angles = np.degrees(np.arccos(np.clip(rays[:, 2], -1, 1)))
        return float(angles[0] + angles[1]), float(angles[2] + angles[3])

    # --- resolution changes -------------------------------------------------------------------
    def resized(self, new_size: tuple[int, int]) -> CameraModel:
        """The same lens after a uniform resize of the whole image to `new_size` (width, height).

        fx, fy scale by the factor; the principal point scales about the image's outer corner, i.e.
        (c + 0.5) * s - 0.5, because pixel (0, 0) is a pixel's centre (cv2.resize maps areas the
        same way). Distortion coefficients live in normalised coordinates and do not change.
        """
        w, h = self.image_size
        sx, sy = new_size[0] / w, new_size[1] / h
        if abs(sx - sy) > 1e-3 * max(sx, sy):
            raise ValueError(
                f"resizing {w}x{h} to {new_size[0]}x{new_size[1]} changes the aspect ratio (x {sx:.4f}, y {sy:.4f}); "
                "crop first (--crop) so that the resize is uniform"
            )
        K = self.camera_matrix.copy()
        K[0, 0] *= sx
        K[1, 1] *= sy
        K[0, 1] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return CameraModel(self.model, K, self.dist_coeffs.copy(), (int(new_size[0]), int(new_size[1])))

    def cropped(self, x: int, y: int, width: int, height: int) -> CameraModel:
        """The same lens seen through a crop whose top-left pixel is (x, y): the principal point shifts."""
        w, h = self.image_size
        if x < 0 or y < 0 or width <= 0 or height <= 0 or x + width > w or y + height > h:
            raise ValueError(f"crop {x},{y},{width},{height} does not fit inside the {w}x{h} image")
        K = self.camera_matrix.copy()
        K[0, 2] -= x
        K[1, 2] -= y
        return CameraModel(self.model, K, self.dist_coeffs.copy(), (int(width), int(height)))


# --- distortion math in numpy (vectorised, used by unproject) -----------------------------------



# From this many points on, `CameraModel.project` evaluates OpenCV's projection formulas in NumPy:
# the Python bindings of cv2.projectPoints and cv2.fisheye.projectPoints always compute the
# Jacobian (2N x 14-18 doubles), ~0.5 us a point, 9x what the projection itself costs; the
# candidate poses project ~170,000 points at a time. Below it the binding's fixed cost is lower.
# Both agree to ~1e-13 px (tests/drivers/test_lens.py).
_NUMPY_PROJECTION_FROM = 64


def _project_numpy(camera: CameraModel, pts: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(N, 2) pixels by the formulas of OpenCV's projectPoints (calib3d) and fisheye::projectPoints.

    As OpenCV does: a point at z == 0 is divided by 1, and the skew of the camera matrix is ignored
    (the bindings' fisheye `alpha` defaults to 0).
    """
    if np.any(rvec):
        pts = pts @ cv2.Rodrigues(rvec)[0].T
    if np.any(tvec):
        pts = pts + tvec
    z = pts[:, 2]
    inv_z = np.divide(1.0, z, out=np.ones_like(z), where=z != 0)
    x, y = pts[:, 0] * inv_z, pts[:, 1] * inv_z
    K, D = camera.camera_matrix, camera.dist_coeffs
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    r2 = x * x + y * y
    if camera.model == "fisheye":
        r = np.sqrt(r2)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (D[0] + t2 * (D[1] + t2 * (D[2] + t2 * D[3]))))
        scale = np.divide(theta_d, r, out=np.ones_like(r), where=r > 1e-8)
        xd, yd = x * scale, y * scale
        return np.stack([fx * xd + cx, fy * yd + cy], axis=1)
    k1, k2, p1, p2, k3 = D[:5]
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    if camera.model == "rational":
        k4, k5, k6 = D[5:8]
        radial = radial / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xy = x * y
    xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
    return np.stack([fx * xd + cx, fy * yd + cy], axis=1)

def _radial_gain(D: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Brown-Conrady / rational radial factor at undistorted normalised radius r."""
    r2 = r * r
    k = np.zeros(8)
    k[: D.size] = D
    num = 1 + k[0] * r2 + k[1] * r2**2 + k[4] * r2**3
    den = 1 + k[5] * r2 + k[6] * r2**2 + k[7] * r2**3
    return num / den


def _distort(D: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N, 2) undistorted normalised -> distorted normalised coordinates (OpenCV's formulas)."""
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    g = _radial_gain(D, np.sqrt(r2))
    p1, p2 = D[2], D[3]
    xd = x * g + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * g + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def _fisheye_theta_d(D: np.ndarray, theta: np.ndarray) -> np.ndarray:
    t2 = theta * theta
    return theta * (1 + D[0] * t2 + D[1] * t2**2 + D[2] * t2**3 + D[3] * t2**4)


def _fisheye_theta_d_slope(D: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """d theta_d / d theta of `_fisheye_theta_d`."""
    t2 = theta * theta
    return 1 + 3 * D[0] * t2 + 5 * D[1] * t2**2 + 7 * D[2] * t2**3 + 9 * D[3] * t2**4


def radial_fold(camera: CameraModel) -> float:
    """Where `camera`'s radial profile stops increasing: beyond it the model folds back on itself.

    For the fisheye the off-axis angle theta (rad, may pass pi / 2); for the others the undistorted
    normalised radius r = |(x, y)| / z. Points beyond it are not imaged where `project` puts them.
    """
    return _fold_of(camera.model, tuple(camera.dist_coeffs))


@functools.lru_cache(maxsize=64)
def _fold_of(model: str, dist: tuple[float, ...]) -> float:
    """The fold of a model's radial profile, cached: unproject runs per frame with the same lens."""
    D = np.asarray(dist)
    if model == "fisheye":
        return _fold_radius(lambda t: _fisheye_theta_d(D, t), np.pi * 0.999)
    return _fold_radius(lambda r: r * _radial_gain(D, r))


def _fold_radius(profile, r_max: float = 20.0) -> float:
    """Where a radial profile stops increasing (beyond it the lens model folds back on itself)."""
    r = np.linspace(0.0, r_max, 4001)
    values = profile(r)
    falling = np.nonzero(np.diff(values) <= 0)[0]
    return float(r[falling[0]]) if falling.size else r_max


def _invert_monotonic(profile, targets: np.ndarray, upper: float, slope=None) -> np.ndarray:
    """Solve profile(x) = target for x in [0, upper] (profile increasing there).

    By bisection to 2^-48 of the bracket (far below a nanopixel); where `slope` (the profile's
    derivative) is given, by Newton steps kept inside the same bracket instead, a step that would
    leave it bisecting: the same root to ~1e-14 in ~6 steps instead of 48. A fisheye's every
    unprojection runs this (pose estimates, local views: 743 calls on a 150 deg replay took 2.1 s).
    """
    lo = np.zeros_like(targets)
    hi = np.full_like(targets, upper)
    if slope is None:
        for _ in range(48):
            mid = 0.5 * (lo + hi)
            below = profile(mid) < targets
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
        return 0.5 * (lo + hi)
    x = np.clip(targets, 0.0, upper)
    beyond = profile(hi) <= targets  # past the fold: bisection's answer is the bracket's end
    lo = np.where(beyond, upper, lo)
    x = np.where(beyond, upper, x)
    tolerance = upper * 2.0**-48
    for _ in range(64):
        value = profile(x) - targets
        below = value < 0
        lo = np.where(below, x, lo)
        hi = np.where(below, hi, x)
        derivative = slope(x)
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = x - value / derivative
        inside = (derivative > 0) & (newton >= lo) & (newton <= hi)
        step = np.where(inside, newton, 0.5 * (lo + hi))
        done = np.abs(step - x) <= tolerance
        x = step
        if done.all():
            break
    return x


# A rational profile fitted to a fisheye's is a start for a rational solve, not a model: past this
# off-axis angle tan(theta) grows without bound and no rational term follows the fisheye there.
_RATIONAL_FIT_MAX_ANGLE_RAD = np.deg2rad(75.0)


def rational_like(camera: CameraModel, max_angle_rad: float) -> CameraModel | None:
    """A rational model with `camera`'s matrix and a fisheye `camera`'s radial profile out to `max_angle_rad` off axis.

    Both models put a ray at the angle theta off axis at the distance f * rho * tan(theta) from the
    principal point: the fisheye's rho = theta_d / tan(theta), the rational's (1 + k1 r^2 + k2 r^4 +
    k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6) at r = tan(theta). Multiplied by the denominator the
    match is linear in k1..k6, and is solved by least squares over the angles, each row weighted
    by r (its pixel lever). None when the fit has a pole or a fold inside the range (no usable start).
    """
    if camera.model != "fisheye":
        raise ValueError(f"rational_like converts a fisheye model, got {camera.model!r}")
    top = float(np.clip(max_angle_rad, np.deg2rad(5.0), _RATIONAL_FIT_MAX_ANGLE_RAD))
    theta = np.linspace(top / 200.0, top, 200)
    r = np.tan(theta)
    rho = _fisheye_theta_d(camera.dist_coeffs, theta) / r
    r2 = r * r
    design = np.stack([r2, r2**2, r2**3, -rho * r2, -rho * r2**2, -rho * r2**3], axis=1) * r[:, None]
    k, *_ = np.linalg.lstsq(design, (rho - 1.0) * r, rcond=None)
    dist = np.array([k[0], k[1], 0.0, 0.0, k[2], k[3], k[4], k[5]])
    if not np.all(np.isfinite(dist)) or np.any(1 + k[3] * r2 + k[4] * r2**2 + k[5] * r2**3 <= 0):
        return None
    rational = CameraModel("rational", camera.camera_matrix, dist, camera.image_size)
    if _fold_of("rational", tuple(dist)) <= r[-1]:
        return None
    return rational
