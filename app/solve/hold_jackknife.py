"""The intrinsics' covariance read off the holds themselves: a jackknife that leaves out one hold at a time.

The model covariance (app/solve/information.py) takes the corners' errors as independent, and
`robust.with_look_alikes_weighted` discounts the frames of one hold by how much their residuals
correlate. Yet what the frames of a hold share -- the board's pose, its blur and compression
pattern at that spot, the tracking chain that carries a corner's start from frame to frame -- is
small against each corner's noise (residual correlation 0.00-0.11 on the bench renders) but it
sits in the smooth patterns over the board that the intrinsics are read from, and it does not
average out within the hold. On 21 held-out renders with the smear shown the model's E
understated the true error up to 2.2x (dim renders: E 0.12-0.17 px, error 0.27-0.35 px); the true
error divided by E had an RMS of 1.23 where an honest E gives 1
(bench/results/expected_error_response.md).

So the covariance is also measured from the data's scatter between holds: the solve's score of
each hold (its residuals times the pose-marginalised Jacobian) is what that hold pulls the
intrinsics by; leaving the hold out moves them by (S - S_h)^-1 g_h, S the information of all
views and S_h that hold's share (one Gauss-Newton step, exact for a linear model), and the
covariance is (H - 1) / H times the sum of those moves' outer products (the cluster jackknife,
"CR3" in the econometrics literature). The plain cluster sandwich, S^-1 (sum g_h g_h^T) S^-1,
reads the same scatter off residuals each hold's own pull has shrunk, and with a dozen holds came
out below even the model's E on 14 of 15 of these renders. The jackknife needs no noise
level and no correlation model. On those renders true error / E had an RMS of 0.94 (0.73 on 21
older renders, whose smear under ~4 px was drawn sharp), and the larger of the two Es, which the
final solve reports, 0.88 (worst 1.60x against the model's 2.2x)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibcoach.app.solve.information import (
    covariance_from_information,
    rows_weighted,
    stacked_view_jacobians,
)
from calibcoach.app.solve.result import View
from calibcoach.drivers.lens import CameraModel

# Fewer holds than this and the jackknife's scatter is too few numbers to be read as a covariance
# (E^2 is then a sum of so few squares that its relative standard error passes ~25%), and leaving
# one hold out may leave a direction undetermined: the model covariance stands alone.
MIN_HOLDS = 10
# ... and fewer frames a hold than this on average: what the jackknife sees and the model does not is
# error shared between the frames of a hold. Where holds are single frames (fast swings, photo sets)
# the model's independence holds by construction, and leaving one frame out at a time measures only
# the jackknife's own noise and its pull towards the frames of most leverage (a messy 720p render,
# 46 frames in 25 holds: E 0.093 -> 0.120 px, its whole-image E 0.184 px against the 0.2 px trust
# bound, true error 0.009 px).
MIN_FRAMES_PER_HOLD = 2.0


def hold_jackknife_covariance(camera: CameraModel, views: Sequence[View], rvecs: np.ndarray, tvecs: np.ndarray,
                              residuals_px: Sequence[np.ndarray], holds: Sequence[int]) -> np.ndarray | None:
    """(P, P) covariance of the free intrinsics from the scatter between holds; None with fewer than
    `MIN_HOLDS` holds or `MIN_FRAMES_PER_HOLD` frames a hold.

    Args:
        camera, views, rvecs, tvecs: the solve; each view's rows count by its `information_weight`
            and its corners' `corner_weights` as the weighted solve counted them (not yet
            discounted for look-alikes).
        residuals_px: per view (N_v, 2) observed - projected, at the solution.
        holds: per view the hold (look-alike group) it belongs to.
    """
    labels, hold_of_view = np.unique(np.asarray(holds), return_inverse=True)
    if labels.size < MIN_HOLDS or len(views) < MIN_FRAMES_PER_HOLD * labels.size:
        return None
    J_intr, J_pose = stacked_view_jacobians(camera, views, rvecs, tvecs)  # (V, R, P), (V, R, 6), zero-padded rows
    r = np.zeros(J_intr.shape[:2])
    for k, res in enumerate(residuals_px):
        r[k, : res.size] = np.asarray(res, np.float64).reshape(-1)  # x0, y0, x1, ... as the Jacobian's rows
    J_intr, J_pose, r = rows_weighted(views, J_intr, J_pose, r)  # each row x sqrt(its weight in the solve)
    Jt = np.swapaxes(J_intr, 1, 2)
    B = Jt @ J_pose  # (V, P, 6)
    C_inv = np.linalg.pinv(np.swapaxes(J_pose, 1, 2) @ J_pose, rcond=1e-12, hermitian=True)
    BC = B @ C_inv
    # each view's pose-marginalised information and score
    S_view = Jt @ J_intr - BC @ np.swapaxes(B, 1, 2)
    g_view = np.einsum("vpr,vr->vp", Jt, r) - np.einsum("vpa,va->vp", BC, np.einsum("vra,vr->va", J_pose, r))
    S_hold = np.zeros((labels.size, *S_view.shape[1:]))
    g_hold = np.zeros((labels.size, g_view.shape[1]))
    np.add.at(S_hold, hold_of_view, S_view)
    np.add.at(g_hold, hold_of_view, g_view)
    S = S_hold.sum(axis=0)
    moves = np.einsum("hpq,hq->hp", covariance_from_information(S[None] - S_hold), g_hold)  # leave hold h out
    H = labels.size
    return (H - 1) / H * (moves.T @ moves)
