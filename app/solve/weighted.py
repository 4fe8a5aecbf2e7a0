"""A weighted refinement of a solved calibration: each view counts by the inverse of its corner variance.

OpenCV's solvers weight every corner alike. Corners are not alike: a steep view at the image edge,
a softer frame or a pose whose print or light is poor has corner errors several times those of a
frontal sharp view (on the closed-loop simulator one hold's corners were 0.13 px off where the
median view's were 0.04), and at equal weight those errors pull the intrinsics. Starting from
OpenCV's solution, this runs Levenberg-Marquardt on intrinsics and poses together, every view's
rows scaled by sqrt(w_v), w_v = (sigma_typical / sigma_v)^2 from its own residuals (never above 1:
a view is trusted at most as much as a typical one, so no single view can take over). The normal
equations are reduced to the intrinsics by the same Schur complement the uncertainty uses, one
6 x 6 pose block per view, so it stays cheap for 60 views. Corners can carry weights of their own
on top of their view's (`corner_weights`): the corners the corner refinement could not refine
count by their measured variance against the refined ones (`robust.unrefined_corner_weights`).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from calibcoach.app.solve.information import intrinsic_names, padded_rows, stacked_projections_and_jacobians
from calibcoach.app.solve.result import View
from calibcoach.drivers.lens import CameraModel

MIN_WEIGHT = 0.1  # a view at 3x the typical corner noise or worse counts a tenth


def view_weights(residuals: Sequence[np.ndarray]) -> np.ndarray:
    """(V,) inverse-variance weights from each view's residuals, relative to the median view, capped at 1."""
    sigma = np.array([float(np.sqrt(np.mean(r**2))) if r.size else np.inf for r in residuals])
    typical = float(np.median(sigma[np.isfinite(sigma)])) if np.isfinite(sigma).any() else 1.0
    return np.clip((typical / np.maximum(sigma, 1e-12)) ** 2, MIN_WEIGHT, 1.0)


def camera_from_vector(camera: CameraModel, p: np.ndarray) -> CameraModel:
    """The camera with its free intrinsics (`intrinsic_names` order) replaced by `p` (P,)."""
    K = camera.camera_matrix.copy()
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = p[:4]
    return CameraModel(camera.model, K, np.asarray(p[4:], np.float64), camera.image_size)


def vector_of(camera: CameraModel) -> np.ndarray:
    K = camera.camera_matrix
    return np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera.dist_coeffs[: len(intrinsic_names(camera.model)) - 4]])


def weighted_refine(camera: CameraModel, views: Sequence[View], rvecs: np.ndarray, tvecs: np.ndarray,
                    weights: np.ndarray, *, corner_weights: Sequence[np.ndarray] | None = None,
                    iterations: int = 15) -> tuple[CameraModel, np.ndarray, np.ndarray]:
    """Minimise sum_v w_v sum_i c_vi |r_vi|^2 over intrinsics and poses from a solved start (LM, Schur-reduced).

    Each view's Jacobian comes from OpenCV with its projections, which the residuals take
    (`stacked_projections_and_jacobians`); the normal equations of all views are then formed and
    reduced in batches (views padded to the largest corner count with zero rows), ~3x faster than
    view by view for a final solve's hundreds of views.

    Args:
        camera: the start (OpenCV's solution).
        views: V views; rvecs, tvecs: (V, 3) their poses.
        weights: (V,) per-view weights (`view_weights`).
        corner_weights: per view (N_v,) weights of its corners on top of the view's (None: all 1).

    Returns:
        (camera, rvecs (V, 3), tvecs (V, 3)); the start itself when no step lowers the cost.
    """
    p = vector_of(camera)
    rv, tv = np.array(rvecs, np.float64).reshape(-1, 3), np.array(tvecs, np.float64).reshape(-1, 3)
    w = np.asarray(weights, np.float64)
    P, V = p.size, len(views)
    counts = np.array([v.image_points_px.shape[0] for v in views])
    rows = 2 * int(counts.max()) if V else 0
    observed = np.concatenate([v.image_points_px for v in views]) if V else np.zeros((0, 2))
    board = np.concatenate([v.object_points_m for v in views]).astype(np.float64) if V else np.zeros((0, 3))
    owner = np.repeat(np.arange(V), counts)
    # each corner's weight: its view's times its own
    corner_w = [w[k] * (1.0 if corner_weights is None else np.asarray(corner_weights[k], np.float64)) * np.ones(n)
                for k, n in enumerate(counts)]
    point_w = np.concatenate(corner_w) if V else np.zeros(0)
    row_w = padded_rows(corner_w, rows)

    def cost(cam: CameraModel, r: np.ndarray, t: np.ndarray) -> float:
        R = np.stack([cv2.Rodrigues(ri)[0] for ri in r]) if V else np.zeros((0, 3, 3))
        in_camera = np.einsum("mij,mj->mi", R[owner], board) + t[owner]
        return float(np.sum(point_w * np.sum((observed - cam.project(in_camera)) ** 2, axis=1)))

    lam = 1e-3
    current = cost(camera, rv, tv)
    observed_rows = np.zeros((V, rows))  # each view's corners, padded as the stacked Jacobians are
    for k, v in enumerate(views):
        observed_rows[k, : 2 * v.image_points_px.shape[0]] = v.image_points_px.reshape(-1)
    for _ in range(iterations):
        cam = camera_from_vector(camera, p)
        # the residuals from the projections OpenCV makes with the Jacobian (one call a view, not two)
        projected, J_intr, J_pose = stacked_projections_and_jacobians(cam, views, rv, tv)
        res = observed_rows - projected
        J_intr_w, J_pose_w = J_intr * row_w[:, :, None], J_pose * row_w[:, :, None]
        U = J_intr_w.reshape(-1, P).T @ J_intr.reshape(-1, P)
        W = np.swapaxes(J_intr_w, 1, 2) @ J_pose  # (V, P, 6)
        C = np.swapaxes(J_pose_w, 1, 2) @ J_pose  # (V, 6, 6)
        e_i = J_intr_w.reshape(-1, P).T @ res.reshape(-1)
        e_p = np.einsum("vnq,vn->vq", J_pose_w, res)
        C = C + lam * (C * np.eye(6) + 1e-12 * np.eye(6))
        try:
            C_inv = np.linalg.inv(C)
        except np.linalg.LinAlgError:
            break
        W_C_inv = W @ C_inv  # (V, P, 6)
        S = U - np.einsum("vpa,vqa->pq", W_C_inv, W)
        g = e_i - np.einsum("vpa,va->p", W_C_inv, e_p)
        S = S + lam * np.diag(np.diag(S) + 1e-12)
        try:
            dp = np.linalg.solve(S, g)
        except np.linalg.LinAlgError:
            break
        d_pose = np.einsum("vab,vb->va", C_inv, e_p - np.einsum("vpa,p->va", W, dp))
        p_new, rv_new, tv_new = p + dp, rv + d_pose[:, :3], tv + d_pose[:, 3:]
        cam_new = camera_from_vector(camera, p_new)
        new = cost(cam_new, rv_new, tv_new) if np.all(np.isfinite(p_new)) else np.inf
        if new < current:
            p, rv, tv = p_new, rv_new, tv_new
            lam = max(lam / 10, 1e-9)
            done = (current - new) < 1e-10 * max(current, 1e-12)
            current = new
            if done:
                break
        else:
            lam *= 10
            if lam > 1e6:
                break
    return camera_from_vector(camera, p), rv, tv
