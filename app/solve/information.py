"""What the frames tell about the intrinsics: Jacobians, the pose-reduced information, its covariance.

Each view's Jacobian (OpenCV's `projectPoints` derivatives) gives the information the frames hold
about the intrinsics; every board pose is marginalised out of it by a Schur complement, one 6 x 6
block per view, and its inverse scaled by the corner noise is the intrinsics' covariance, which
app/solve/uncertainty.py pushes through the projection of the image. The same reduced information
scores a candidate view by how much it would cut that covariance (`information_gain`, the next-pose
ranking of app/solve/next_view.py).

Rows of every Jacobian are ordered as OpenCV's: corner i of a view gives rows 2i (u) and 2i + 1 (v).
Columns follow `intrinsic_names(model)`; skew is fixed at 0 in every model.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from calibcoach.app.solve.result import View
from calibcoach.drivers.lens import MODELS, CameraModel

_EIGEN_FLOOR = 1e-12  # relative floor on the scaled information's eigenvalues: unobserved -> huge variance

_NAMES = {
    "pinhole": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"),
    "rational": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "fisheye": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}


def intrinsic_names(model: str) -> tuple[str, ...]:
    """Names of the free intrinsics of `model`, in Jacobian column order (OpenCV's order).

    Example:
        >>> intrinsic_names("fisheye")
        ('fx', 'fy', 'cx', 'cy', 'k1', 'k2', 'k3', 'k4')
    """
    if model not in _NAMES:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    return _NAMES[model]


# --- the solve's Jacobian and covariance -----------------------------------------------------


def view_jacobian(camera: CameraModel, object_points_m: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobian of one view's projected corners w.r.t. the intrinsics and the view's pose.

    Args:
        camera: the model the Jacobian is taken at.
        object_points_m: (N, 3) float board-frame corners, metres.
        rvec: (3,) Rodrigues vector of T_cam_board.
        tvec: (3,) translation of T_cam_board, metres.

    Returns:
        J_intrinsics (2N, P) float64 px per parameter unit and J_pose (2N, 6) float64 (rvec then tvec).
    """
    _projected, J_intr, J_pose = _projection_and_jacobian(camera, object_points_m, rvec, tvec)
    return J_intr, J_pose


def _projection_and_jacobian(camera: CameraModel, object_points_m: np.ndarray, rvec: np.ndarray,
                             tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`view_jacobian` with the projected corners (N, 2) OpenCV computed alongside, first."""
    obj = np.ascontiguousarray(object_points_m, np.float64).reshape(-1, 3)
    r, t = np.asarray(rvec, np.float64).reshape(3), np.asarray(tvec, np.float64).reshape(3)
    if camera.model == "fisheye":
        # Columns f(2), c(2), k(4), om(3), t(3), alpha(1), as documented; checked against finite
        # differences in tests/app/test_uncertainty.py. alpha (skew) is fixed, so it is dropped.
        K, D = camera.camera_matrix, camera.dist_coeffs
        projected, J = cv2.fisheye.projectPoints(obj.reshape(1, -1, 3), r.reshape(1, 1, 3), t.reshape(1, 1, 3), K, D)
        return projected.reshape(-1, 2), J[:, :8].copy(), J[:, 8:14].copy()
    projected, J = cv2.projectPoints(obj, r, t, camera.camera_matrix, camera.opencv_dist())
    return projected.reshape(-1, 2), J[:, 6 : 6 + len(intrinsic_names(camera.model))].copy(), J[:, :6].copy()


def solve_jacobian(camera: CameraModel, views: Sequence[View], rvecs: np.ndarray, tvecs: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """The solve's Jacobian: intrinsic columns shared by every view, pose columns per view.

    Args:
        camera: the solved model.
        views: V views; view v has N_v corners.
        rvecs: (V, 3) float64 T_cam_board Rodrigues vectors.
        tvecs: (V, 3) float64 T_cam_board translations, metres.

    Returns:
        J_intrinsics (2N, P) float64 with N = sum N_v (views stacked in order) and a list of V
        J_pose arrays (2N_v, 6) float64.
    """
    rv, tv = (np.asarray(a, np.float64).reshape(-1, 3) for a in (rvecs, tvecs))
    if not len(views) == rv.shape[0] == tv.shape[0]:
        raise ValueError(f"expected one pose per view; got {len(views)} views, {rv.shape[0]} rvecs, {tv.shape[0]} tvecs")
    parts = [view_jacobian(camera, v.object_points_m, rv[i], tv[i]) for i, v in enumerate(views)]
    J_intr = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, len(intrinsic_names(camera.model))))
    return J_intr, [p[1] for p in parts]


def schur_update(information: np.ndarray, J_intr: np.ndarray, J_pose: np.ndarray) -> np.ndarray:
    """Add one view to a marginal information matrix: S + A_v - B_v C_v^-1 B_v^T.

    Each view's pose is its own, so marginalising views one by one is exact.

    Args:
        information: (P, P) float64 current S (unit noise).
        J_intr: (2n, P) float64 the view's intrinsic Jacobian.
        J_pose: (2n, 6) float64 the view's pose Jacobian.

    Returns:
        (P, P) float64 the new S.
    """
    return schur_updates(information, [(J_intr, J_pose)])[0]


def schur_updates(information: np.ndarray, jacobians: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """`schur_update` of one S with each of K views on its own: (K, P, P), the pseudo-inverses batched."""
    P = information.shape[0]
    if not jacobians:
        return np.zeros((0, P, P))
    A = np.stack([J_intr.T @ J_intr for J_intr, _ in jacobians])  # (K, P, P)
    B = np.stack([J_intr.T @ J_pose for J_intr, J_pose in jacobians])  # (K, P, 6)
    C = np.stack([J_pose.T @ J_pose for _, J_pose in jacobians])  # (K, 6, 6)
    # pinv: a view with < 3 corners has a singular pose block; its rows then add only what they fix.
    S = information + A - B @ np.linalg.pinv(C, rcond=1e-12, hermitian=True) @ np.swapaxes(B, -1, -2)
    return 0.5 * (S + np.swapaxes(S, -1, -2))


def stacked_view_jacobians(camera: CameraModel, views: Sequence[View], rvecs: np.ndarray,
                           tvecs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every view's `view_jacobian` in one padded stack: J_intr (V, R, P) and J_pose (V, R, 6), R the
    most rows a view has; a view's rows beyond its own 2N are zero (they add nothing to a normal
    equation), so all views' normal equations form and reduce in batches.

    Raises:
        ValueError: unless there is one pose per view.
    """
    _projected, J_intr, J_pose = stacked_projections_and_jacobians(camera, views, rvecs, tvecs)
    return J_intr, J_pose


def stacked_projections_and_jacobians(camera: CameraModel, views: Sequence[View], rvecs: np.ndarray,
                                      tvecs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`stacked_view_jacobians` with the projected corners in the same padded rows first: (V, R)
    as x0, y0, x1, y1, ... (zero beyond a view's 2N), what OpenCV computed with the Jacobian."""
    rv, tv = (np.asarray(a, np.float64).reshape(-1, 3) for a in (rvecs, tvecs))
    if len(views) != rv.shape[0] or len(views) != tv.shape[0]:
        raise ValueError(f"expected one pose per view; got {len(views)} views, {rv.shape[0]} rvecs, {tv.shape[0]} tvecs")
    P = len(intrinsic_names(camera.model))
    rows = 2 * max((v.object_points_m.shape[0] for v in views), default=0)
    projected = np.zeros((len(views), rows))
    J_intr, J_pose = np.zeros((len(views), rows, P)), np.zeros((len(views), rows, 6))
    for k, (v, r, t) in enumerate(zip(views, rv, tv, strict=True)):
        px, Ji, Jp = _projection_and_jacobian(camera, v.object_points_m, r, t)
        projected[k, : px.size], J_intr[k, : Ji.shape[0]], J_pose[k, : Jp.shape[0]] = px.reshape(-1), Ji, Jp
    return projected, J_intr, J_pose


def padded_rows(per_corner: Sequence[np.ndarray], rows: int) -> np.ndarray:
    """(V, rows): each view's (N_v,) per-corner values on the corner's two rows (x, y), zero beyond
    its 2 N_v rows, as the stacked Jacobians pad them."""
    out = np.zeros((len(per_corner), rows))
    for k, values in enumerate(per_corner):
        out[k, : 2 * len(values)] = np.repeat(values, 2)
    return out


def rows_weighted(views: Sequence[View], *stacks: np.ndarray) -> tuple[np.ndarray, ...]:
    """Zero-padded (V, R, ...) Jacobian or residual stacks with each corner's two rows x sqrt(its
    weight): a view counting for w of an independent one (`information_weight`), times its corners'
    own weights (`View.corner_weights`)."""
    scale = padded_rows([np.sqrt(v.rows_weight()) for v in views], stacks[0].shape[1])
    return tuple(s * scale.reshape(scale.shape + (1,) * (s.ndim - 2)) for s in stacks)


def marginal_information(camera: CameraModel, views: Sequence[View], rvecs: np.ndarray, tvecs: np.ndarray) -> np.ndarray:
    """S = A - sum_v B_v C_v^-1 B_v^T, the intrinsics' information with all poses marginalised.

    Args:
        camera, views, rvecs, tvecs: as for `solve_jacobian`; each view's rows are weighted by its
            `information_weight` (look-alikes of one hold share one view's worth) and its corners'
            `corner_weights`.

    Returns:
        (P, P) float64 information for unit pixel noise (per coordinate).
    """
    P = len(intrinsic_names(camera.model))
    J_intr, J_pose = stacked_view_jacobians(camera, views, rvecs, tvecs)  # one pose per view, or ValueError
    if not views:
        return np.zeros((P, P))
    J_intr, J_pose = rows_weighted(views, J_intr, J_pose)
    A = J_intr.reshape(-1, P).T @ J_intr.reshape(-1, P)
    B = np.swapaxes(J_intr, 1, 2) @ J_pose  # (V, P, 6)
    C = np.swapaxes(J_pose, 1, 2) @ J_pose  # (V, 6, 6)
    # pinv: a view with < 3 corners has a singular pose block; its rows then add only what they fix.
    S = A - np.einsum("vpa,vqa->pq", B @ np.linalg.pinv(C, rcond=1e-12, hermitian=True), B)
    return 0.5 * (S + S.T)


def covariance_from_information(information: np.ndarray) -> np.ndarray:
    """(P, P) S -> S^-1 that stays finite and positive when S is rank deficient.

    Parameters are first scaled to unit diagonal (fx in px and k3 differ by 1e6 in scale, so a floor
    on raw eigenvalues would clip real directions); scaled eigenvalues below 1e-12 of the largest are
    raised to it, which turns an unobserved direction into a huge variance instead of NaN or < 0.
    """
    S = np.asarray(information, np.float64)  # (P, P), or a stack (..., P, P) inverted one by one
    d = np.sqrt(np.clip(np.diagonal(S, axis1=-2, axis2=-1), 0, None))
    d = np.where(d > 0, d, 1.0)  # an unobserved parameter keeps scale 1 and gets the floor below
    w, V = np.linalg.eigh(S / d[..., :, None] / d[..., None, :])
    w = np.maximum(w, np.maximum(w.max(axis=-1, keepdims=True), 1e-300) * _EIGEN_FLOOR)
    inv = (V / w[..., None, :]) @ np.swapaxes(V, -1, -2)
    return inv / d[..., :, None] / d[..., None, :]


def intrinsic_covariance(camera: CameraModel, views: Sequence[View], rvecs: np.ndarray, tvecs: np.ndarray, *, sigma_px: float) -> np.ndarray:
    """Covariance of the free intrinsics with every pose marginalised: sigma^2 S^-1.

    Args:
        camera, views, rvecs, tvecs: the solve, as for `solve_jacobian`.
        sigma_px: corner noise per coordinate: OpenCV's RMS (per corner) / sqrt(2), times
            sqrt(2N / (2N - P - 6V)) for the fitted parameters, or a robust estimate.

    Returns:
        (P, P) float64 in the units of `intrinsic_names(camera.model)`.
    """
    return sigma_px**2 * covariance_from_information(marginal_information(camera, views, rvecs, tvecs))


# --- is a candidate view worth keeping? -------------------------------------------------------


def information_gain(information: np.ndarray, J_intr: np.ndarray, J_pose: np.ndarray, *, weight: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """New information and the relative drop of trace(S^-1) (or trace(W S^-1)) if the view is added.

    Args:
        information: (P, P) float64 current S (`marginal_information`).
        J_intr: (2n, P) float64 the candidate's intrinsic Jacobian (`view_jacobian`, pose from PnP).
        J_pose: (2n, 6) float64 the candidate's pose Jacobian.
        weight: optional (P, P) `pixel_variance_weight`; None scores the plain trace.

    Returns:
        (P, P) float64 new S, and the drop in [0, 1] (0: the view adds nothing).
    """
    S_new = schur_update(information, J_intr, J_pose)
    W = np.eye(S_new.shape[0]) if weight is None else weight
    before = float(np.sum(W * covariance_from_information(information)))  # trace(W C), W and C symmetric
    after = float(np.sum(W * covariance_from_information(S_new)))
    return S_new, max(0.0, 1.0 - after / before) if before > 0 else 0.0
