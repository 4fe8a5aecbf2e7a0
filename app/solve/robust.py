"""The final solve: drop outlier corners and outlier frames, log why, solve again.

A corner is an outlier when its residual is far outside the residual distribution of the whole
solve (chi-square test with 2 degrees of freedom on a robust sigma). A frame is an outlier when its
RMS stands far above the median frame's (defocus, motion blur or a misdetection affects whole
frames). Each round removes what it finds and re-solves, until nothing more is dropped. Views
that stay but are noisier than the typical one then count by their inverse corner variance in a
weighted refinement (`weighted.py`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from calibcoach.app.solve.calibrate import reprojection_residuals, solve
from calibcoach.app.solve.result import Calibration, DroppedCorner, DroppedFrame, View
from calibcoach.app.solve.uncertainty import intrinsic_covariance, intrinsic_names
from calibcoach.app.solve.weighted import view_weights, weighted_refine
from calibcoach.drivers.errors import CalibrationError
from calibcoach.drivers.lens import CameraModel

MIN_CORNERS = 6
# chi-square with 2 dof: 18.42 is the 99.99% point, so a clean solve drops ~1 corner in 10,000.
_CORNER_CHI2 = 18.42
_CORNER_FLOOR_PX = 0.3  # never call a residual below this an outlier: sub-0.3 px is normal corner noise
_FRAME_RATIO = 3.0  # frame RMS over median frame RMS
_FRAME_FLOOR_PX = 0.5  # and above this, so clean sessions with tiny errors keep all frames


def robust_sigma_px(residuals: Sequence[np.ndarray]) -> float:
    """Per-coordinate noise estimate from residuals (1.4826 * MAD), immune to a few outliers."""
    flat = np.concatenate([r.reshape(-1) for r in residuals]) if residuals else np.zeros(1)
    return float(1.4826 * np.median(np.abs(flat - np.median(flat))))


def robust_calibrate(
    views: Sequence[View],
    image_size: tuple[int, int],
    model: str,
    *,
    initial: CameraModel | None = None,
    max_rounds: int = 4,
) -> Calibration:
    """Solve, remove outliers, re-solve; returns the final Calibration with what was dropped and why."""
    kept = list(views)
    dropped_frames: list[DroppedFrame] = []
    dropped_corners: list[DroppedCorner] = []
    raw = solve(kept, image_size, model, initial=initial)
    for _round in range(max_rounds):
        residuals = reprojection_residuals(raw.camera, kept, raw.rvecs, raw.tvecs)
        sigma = max(robust_sigma_px(residuals), 1e-3)
        corner_limit = max(np.sqrt(_CORNER_CHI2) * sigma, _CORNER_FLOOR_PX)
        view_rms = np.array([np.sqrt(np.mean(np.sum(r**2, axis=1))) for r in residuals])
        frame_limit = max(_FRAME_RATIO * float(np.median(view_rms)), _FRAME_FLOOR_PX)
        changed = False
        next_views: list[View] = []
        for view, res, rms in zip(kept, residuals, view_rms, strict=True):
            if rms > frame_limit and len(kept) > 4:
                dropped_frames.append(DroppedFrame(view.frame_index, (
                    f"frame RMS {rms:.2f} px is {rms / max(np.median(view_rms), 1e-9):.1f}x the median frame's "
                    f"{np.median(view_rms):.2f} px (defocus, motion blur or a misdetection)"
                )))
                changed = True
                continue
            norms = np.linalg.norm(res, axis=1)
            bad = norms > corner_limit
            if bad.any():
                changed = True
                for cid, n in zip(view.ids[bad], norms[bad], strict=True):
                    dropped_corners.append(DroppedCorner(view.frame_index, int(cid), float(n)))
                good = ~bad
                if good.sum() < MIN_CORNERS:
                    dropped_frames.append(DroppedFrame(view.frame_index, f"only {int(good.sum())} corners left after removing outlier corners"))
                    continue
                view = replace(view, ids=view.ids[good], image_points_px=view.image_points_px[good], object_points_m=view.object_points_m[good])
            next_views.append(view)
        if not changed:
            break
        if len(next_views) < 3:
            raise CalibrationError(
                f"after removing outliers only {len(next_views)} views remain; the frames disagree too much to calibrate "
                "(check that focus was locked and the board is flat)"
            )
        kept = next_views
        raw = solve(kept, image_size, model, initial=raw.camera)
    camera, rvecs, tvecs = raw.camera, raw.rvecs, raw.tvecs
    weights = view_weights(reprojection_residuals(camera, kept, rvecs, tvecs))
    if np.any(weights < 0.999) and len(kept) >= 3:
        # views noisier than the typical one count by their inverse corner variance (weighted.py)
        camera, rvecs, tvecs = weighted_refine(camera, kept, rvecs, tvecs, weights)
        kept = [replace(v, information_weight=v.information_weight * float(w)) for v, w in zip(kept, weights, strict=True)]
    return build_calibration(camera, kept, rvecs, tvecs, dropped_frames, dropped_corners)


def look_alike_correlation(views: Sequence[View], residuals: Sequence[np.ndarray], groups: Sequence[int]) -> float:
    """How much of their residuals look-alike frames share: 0 = independent, 1 = the same error.

    For consecutive frames of one group (one hold of the board), the residuals of the corners both
    show are correlated as vectors: rho = sum(r_i . r_j) / sqrt(sum |r_i|^2 sum |r_j|^2). What is
    shared -- blur, aliasing, the print or the light at that spot, a model that does not fit there
    -- does not average out by taking more frames of the same pose, and the covariance must not
    pretend it does. Returns 0 when no group has two frames.
    """
    by_group: dict[int, list[int]] = {}
    for i, g in enumerate(groups):
        by_group.setdefault(g, []).append(i)
    num = den_a = den_b = 0.0
    for members in by_group.values():
        for a, b in zip(members, members[1:], strict=False):
            _, ia, ib = np.intersect1d(views[a].ids, views[b].ids, return_indices=True)
            ra, rb = residuals[a][ia], residuals[b][ib]
            num += float(np.sum(ra * rb))
            den_a += float(np.sum(ra * ra))
            den_b += float(np.sum(rb * rb))
    if den_a <= 0 or den_b <= 0:
        return 0.0
    return float(np.clip(num / np.sqrt(den_a * den_b), 0.0, 1.0))


def look_alike_weights(groups: Sequence[int], correlation: float) -> list[float]:
    """Information weight per frame: a group of k look-alikes with residual correlation rho counts
    as 1 + (k - 1)(1 - rho) independent frames, shared equally (rho = 0: every frame counts fully)."""
    sizes = {g: list(groups).count(g) for g in set(groups)}
    return [(1.0 + (sizes[g] - 1) * (1.0 - correlation)) / sizes[g] for g in groups]


def with_look_alikes_weighted(calibration: Calibration, groups: Sequence[int]) -> tuple[Calibration, float]:
    """The calibration with its covariance recomputed, look-alike frames counted for what they add.

    The solve uses every frame; its covariance would treat them all as independent. How much the
    frames of one group share is measured from their residuals (`look_alike_correlation`); each
    then carries `look_alike_weights` as its View.information_weight. Measured on the closed-loop
    simulator at 1x supersampling: counting look-alikes as independent put the true error at
    1.5-2x E; weighted, 1.0-1.3x.

    Returns:
        (calibration, residual correlation rho); unchanged with rho 0 when no two frames look alike.
    """
    if len(set(groups)) == len(groups):
        return calibration, 0.0
    rho = look_alike_correlation(calibration.views, calibration.residuals_px, groups)
    views = tuple(replace(v, information_weight=v.information_weight * w)
                  for v, w in zip(calibration.views, look_alike_weights(groups, rho), strict=True))
    rebuilt = build_calibration(calibration.camera, views, calibration.rvecs, calibration.tvecs,
                                calibration.dropped_frames, calibration.dropped_corners)
    return rebuilt, rho


def noise_sigma_px(rms_px: float, *, n_points: int, n_params: int, n_views: int) -> float:
    """Per-coordinate corner noise from a solve's RMS (per point), corrected for the fitted parameters.

    The residuals of a least-squares fit are smaller than the noise by the degrees of freedom the
    fit used: sigma^2 = RMS^2 * 2N / (2N - P - 6V) per coordinate pair, halved per coordinate.
    """
    dof = 2 * n_points - n_params - 6 * n_views
    scale = np.sqrt(2 * n_points / dof) if dof > 0 else 1.0
    return float(rms_px / np.sqrt(2.0) * scale)


def build_calibration(
    camera: CameraModel,
    views: Sequence[View],
    rvecs: np.ndarray,
    tvecs: np.ndarray,
    dropped_frames: Sequence[DroppedFrame] = (),
    dropped_corners: Sequence[DroppedCorner] = (),
) -> Calibration:
    """Residuals, per-view RMS and the intrinsics' covariance for a solved model."""
    residuals = reprojection_residuals(camera, views, rvecs, tvecs)
    all_res = np.concatenate(residuals)
    rms = float(np.sqrt(np.mean(np.sum(all_res**2, axis=1))))
    view_rms = np.array([np.sqrt(np.mean(np.sum(r**2, axis=1))) for r in residuals])
    # the noise of a view of weight 1: each view's variance is sigma^2 / its weight (weighted.py)
    w = np.array([v.information_weight for v in views])
    rms_typical = float(np.sqrt(np.sum(w * np.array([np.sum(r**2) for r in residuals]))
                                / max(float(np.sum(w * np.array([r.shape[0] for r in residuals]))), 1e-12)))
    sigma = noise_sigma_px(rms_typical, n_points=all_res.shape[0], n_params=len(intrinsic_names(camera.model)), n_views=len(views))
    covariance = intrinsic_covariance(camera, views, rvecs, tvecs, sigma_px=sigma)
    return Calibration(
        camera=camera,
        rms_px=rms,
        views=tuple(views),
        rvecs=rvecs,
        tvecs=tvecs,
        residuals_px=tuple(residuals),
        per_view_rms_px=view_rms,
        intrinsic_names=intrinsic_names(camera.model),
        intrinsic_covariance=covariance,
        dropped_frames=tuple(dropped_frames),
        dropped_corners=tuple(dropped_corners),
    )
