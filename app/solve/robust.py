"""The final solve: drop outlier frames, then outlier corners, log why, solve again.

A frame is an outlier when its bulk stands far above the median frame's (defocus, motion blur or
a misdetection affects whole frames). Its size is measured by an RMS that leaves out its worst
tenth of corners (`robust_frame_rms_px`), so one or two bad corners leave it unmoved: they are
the corner test's to remove, and only a frame whose bulk is off goes whole. A corner is an outlier when its residual
is far outside the residual distribution of the whole solve (chi-square test with 2 degrees of
freedom on a robust sigma).

Each round tests the frames first; when it drops any, it re-solves and tests again before judging
a single corner, because an outlier frame pulls the solve and the clean corners judged against
that pulled solve would go with it. The corner test then judges every corner of the kept frames
against the latest solve, including those an earlier round set aside, so a corner that fits the
cleaner solve comes back: the loop converges to the corner set consistent with its own final
solve, not to the union of every round's suspicions. Views that stay but are noisier than the
typical one then count by their inverse corner variance in a weighted refinement (`weighted.py`),
and so do the corners the corner refinement could not refine (`unrefined_corner_weights`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from calibcoach.app.solve.calibrate import (
    RawSolution,
    pose_for_view,
    poses_for_views,
    refined_from,
    reprojection_residuals,
    solve,
)
from calibcoach.app.solve.information import intrinsic_covariance, intrinsic_names
from calibcoach.app.solve.result import Calibration, DroppedCorner, DroppedFrame, View
from calibcoach.app.solve.weighted import MIN_WEIGHT, view_weights, weighted_refine
from calibcoach.coverage.detector import MIN_FRAME_CORNERS
from calibcoach.drivers.errors import CalibrationError
from calibcoach.drivers.lens import CameraModel

_UNPOSABLE_TRIES = 6  # frames with fewest corners tried when a fisheye solve cannot start (each try is a solve)
# chi-square with 2 dof: 18.42 is the 99.99% point, so a clean solve drops ~1 corner in 10,000.
_CORNER_CHI2 = 18.42
_CORNER_FLOOR_PX = 0.3  # never call a residual below this an outlier: sub-0.3 px is normal corner noise
# Both frame limits are on the trimmed frame RMS (`robust_frame_rms_px`), which equals the plain
# RMS for a frame of gaussian corner noise -- so the limits mean what they did on the plain RMS --
# but ignores its worst tenth of corners: a few bad corners are the corner test's to remove.
_FRAME_TRIM = 0.1
_FRAME_RATIO = 3.0  # frame RMS over median frame RMS
_FRAME_FLOOR_PX = 0.5  # and above this, so clean sessions with tiny errors keep all frames
# A second solve over every frame (`robust_calibrate`) is taken when it keeps more frames at an RMS
# at most this much above the first's: frames it takes back that fit no worse than the rest raise
# the RMS little (the wide render's 63: 0.0602 -> 0.0599), while frames at fault would raise it.
_READMIT_RMS_RATIO = 1.1


def robust_sigma_px(residuals: Sequence[np.ndarray]) -> float:
    """Per-coordinate noise estimate from residuals (1.4826 * MAD), immune to a few outliers."""
    flat = np.concatenate([r.reshape(-1) for r in residuals]) if residuals else np.zeros(1)
    return float(1.4826 * np.median(np.abs(flat - np.median(flat))))


def robust_frame_rms_px(residuals: np.ndarray) -> float:
    """A frame's RMS from its best 90% of corners, scaled to the full RMS of a frame of gaussian noise.

    Under gaussian corner noise |r|^2 over its mean is exponential, and the mean of its lowest
    1 - t fraction is (1 - t (1 - ln t)) / (1 - t) of the full mean (0.744 at t = 0.1). So for a
    clean frame this is its RMS (sampling scatter 6.3% over 70 corners against the plain RMS's
    5.8%; a median-based RMS scatters 8.5%, which moves frames near the limits across them), while
    up to a tenth of its corners -- 7 of 70 -- can be any distance off without moving it.
    """
    sq = np.sort(np.sum(np.asarray(residuals, dtype=float) ** 2, axis=1))
    n = sq.shape[0]
    if n == 0:
        return 0.0
    m = int(_FRAME_TRIM * n)  # the corners left out; none below 10
    t = m / n
    scale = 1.0 if m == 0 else (1.0 - t * (1.0 - np.log(t))) / (1.0 - t)
    return float(np.sqrt(np.mean(sq[: n - m]) / scale))


def _refit_frame_rms_px(camera: CameraModel, view: View, residuals: np.ndarray) -> float:
    """`robust_frame_rms_px` after re-fitting the frame's pose alone to its best 90% of corners.

    A few corners 10 px off pull their frame's pose in the joint solve, and the pulled pose lifts
    the residuals of all its clean corners (6 of 70 took a frame from 1x to 3.2x the median frame's
    RMS): what leaving them out cannot undo. With the intrinsics held, the pose of the frame's best
    corners shows whether its bulk fits; a refocused lens or misread rows still do not.
    """
    n = len(view.ids)
    plain = robust_frame_rms_px(residuals)
    m = int(_FRAME_TRIM * n)
    if m == 0:
        return plain
    best = np.sort(np.argsort(np.sum(residuals**2, axis=1))[: n - m])
    pose = pose_for_view(camera, _subset(view, ~np.isin(np.arange(n), best)))
    if pose is None:
        return plain
    refit = view.image_points_px - camera.project(view.object_points_m, *pose)
    return min(plain, robust_frame_rms_px(refit))


def _subset(view: View, out: np.ndarray) -> View:
    """`view` without the corners `out` marks."""
    if not out.any():
        return view
    keep = ~out
    per_corner = {name: getattr(view, name)[keep] for name in ("refined_px", "unrefined", "corner_weights")
                  if getattr(view, name) is not None}
    return replace(view, ids=view.ids[keep], image_points_px=view.image_points_px[keep], object_points_m=view.object_points_m[keep],
                   **per_corner)


def unrefined_corner_weights(views: Sequence[View], residuals: Sequence[np.ndarray]) -> list[np.ndarray] | None:
    """Per view (N_v,) weights: 1 for corners the corner refinement refined, w_u for those it left as
    OpenCV gave them (`View.unrefined`); None where no view has both kinds.

    Those corners keep the pull of the markers' edges (coverage/corner_refine.py), and a tracked
    frame's keep part of the frame before's error (app/scan.py): errors the frames of a hold share,
    which more frames do not average out. w_u is their inverse variance against the refined corners
    of the same views: the median over views with three or more of each of (refined mean square
    residual / unrefined), so that a view's own noise (a softer or smeared frame) does not count as
    the kind's. Floored at `weighted.MIN_WEIGHT`, capped at 1. Measured with the masked refinement
    (coverage/corner_refine.py): on careful 720p renders w_u was 0.13-0.22 (19-30% of the corners), on
    dim ones 0.31-0.38. The symmetry fit that replaced it leaves few corners (those without enough
    clean pairs or a converged fit; bench/results/homography_alone.md).
    """
    ratios = []
    for view, res in zip(views, residuals, strict=True):
        mask = view.unrefined
        if mask is None or mask.sum() < 3 or (~mask).sum() < 3:
            continue
        ratios.append(float(np.mean(res[~mask] ** 2)) / max(float(np.mean(res[mask] ** 2)), 1e-24))
    if not ratios:
        return None
    weight = float(np.clip(np.median(ratios), MIN_WEIGHT, 1.0))
    return [np.ones(v.ids.shape[0]) if v.unrefined is None else np.where(v.unrefined, weight, 1.0) for v in views]


def robust_calibrate(
    views: Sequence[View],
    image_size: tuple[int, int],
    model: str,
    *,
    initial: CameraModel | None = None,
    max_rounds: int = 4,
) -> Calibration:
    """Solve, remove outliers, re-solve; returns the final Calibration with what was dropped and why.

    Where whole frames were dropped and some of them fit the intrinsics the kept frames gave (each
    posed under them, `_refitting_frames`), the solve is done once more over every frame from those
    intrinsics (`_robust_once` again), and taken when it keeps more frames at an RMS within
    `_READMIT_RMS_RATIO` of the first. A frame is dropped for misfitting the solve, and a solve in a
    wrong minimum misfits frames that are not at fault: the 8-term rational model's valley has
    several, and on a 104 deg 1080p render (smooth wide s104, 211 frames) both
    OpenCV's start and the capture's own lens led to one at RMS 0.35 px where 4 whole holds (63
    frames, at the image's edges) misfit by 0.65-1.65 px; they were dropped, and the 148 left gave
    0.22 px against the truth, accepted. From the kept frames' solution all 211 fit (RMS 0.060, the
    worst frame 0.093 px): 0.024 px against the truth; posed under the kept frames' intrinsics, the
    63 had fitted at 0.06-0.13 px. Frames dropped for their own fault (blur, a misdetection, another
    focus) misfit those intrinsics too, and then nothing is solved again (a replay pays the second
    solve only where it may help).
    """
    first = _robust_once(views, image_size, model, initial=initial, max_rounds=max_rounds)
    if not _refitting_frames(first, views):
        return first
    try:
        second = _robust_once(views, image_size, model, initial=first.camera, max_rounds=max_rounds)
    except CalibrationError:
        return first
    if len(second.views) > len(first.views) and second.rms_px <= _READMIT_RMS_RATIO * first.rms_px:
        return second
    return first


def _refitting_frames(calibration: Calibration, views: Sequence[View]) -> int:
    """How many of the frames `calibration` dropped whole pass its frame test when each is posed
    under its intrinsics (against the kept frames' median, as `_robust_once` judges)."""
    dropped = {f.frame_index for f in calibration.dropped_frames}
    if not dropped or not calibration.views:
        return 0
    kept = [robust_frame_rms_px(r) for r in calibration.residuals_px]
    limit = max(_FRAME_RATIO * float(np.median(kept)), _FRAME_FLOOR_PX)
    candidates = [v for v in views if v.frame_index in dropped]
    posed = [(v, p) for v, p in zip(candidates, poses_for_views(calibration.camera, candidates), strict=True) if p is not None]
    if not posed:
        return 0
    residuals = reprojection_residuals(calibration.camera, [v for v, _p in posed], np.array([p[0] for _v, p in posed]),
                                       np.array([p[1] for _v, p in posed]))
    return sum(robust_frame_rms_px(r) <= limit for r in residuals)


def _robust_once(
    views: Sequence[View],
    image_size: tuple[int, int],
    model: str,
    *,
    initial: CameraModel | None,
    max_rounds: int,
) -> Calibration:
    """One robust solve from `initial` (see the module docstring)."""
    frames = list(views)  # the frames still in, each with all its corners
    outs = [np.zeros(len(v.ids), dtype=bool) for v in frames]  # per frame: the corners set aside
    norms_out = [np.zeros(len(v.ids)) for v in frames]  # their residuals at the test that set them aside
    dropped_frames: list[DroppedFrame] = []
    dropped_corners: list[DroppedCorner] = []

    def corners_of(i: int) -> list[DroppedCorner]:
        return [DroppedCorner(frames[i].frame_index, int(cid), float(n))
                for cid, n in zip(frames[i].ids[outs[i]], norms_out[i][outs[i]], strict=True)]

    def kept_views() -> list[View]:
        """The kept frames, each with its kept corners: what a round solves."""
        return [_subset(f, o) for f, o in zip(frames, outs, strict=True)]

    def keep_frames(keep: list[bool]) -> None:
        nonlocal frames, outs, norms_out
        frames = [f for f, k in zip(frames, keep, strict=True) if k]
        outs = [o for o, k in zip(outs, keep, strict=True) if k]
        norms_out = [n for n, k in zip(norms_out, keep, strict=True) if k]
        if len(frames) < 3:
            raise CalibrationError(
                f"after removing outliers only {len(frames)} views remain; the frames disagree too much to calibrate "
                "(check that focus was locked and the board is flat)"
            )

    def solve_kept(start: CameraModel | None):
        """Solve the kept frames' kept corners; a fisheye solve that cannot start leaves out the frame that stops it.

        cv2.fisheye.calibrate initialises every view's pose from a homography and asserts on the
        whole solve when one view's is degenerate (seen on a 6-corner view at a 150 deg lens's
        edge). Such a frame is found by leaving out, one at a time, the frames with fewest corners."""
        try:
            return solve(kept_views(), image_size, model, initial=start)
        except CalibrationError as failure:
            if model != "fisheye" or len(frames) <= 4:
                raise
            error = failure
        weakest = sorted(range(len(frames)), key=lambda i: int((~outs[i]).sum()))[:_UNPOSABLE_TRIES]
        for i in weakest:
            rest = [_subset(f, o) for j, (f, o) in enumerate(zip(frames, outs, strict=True)) if j != i]
            try:
                solution = solve(rest, image_size, model, initial=start)
            except CalibrationError:
                continue
            dropped_frames.append(DroppedFrame(frames[i].frame_index, (
                f"the fisheye solve cannot initialise this frame's pose from its {int((~outs[i]).sum())} corners")))
            dropped_corners.extend(corners_of(i))
            keep_frames([j != i for j in range(len(frames))])
            return solution
        raise error

    def resolved(start: RawSolution, kept: list[bool] | None = None) -> RawSolution:
        """The kept frames' kept corners solved again from the round before (`start`, whose frames
        `kept` marks where some were dropped since). A pinhole round starts at its own minimum's
        doorstep, and the Schur-reduced Levenberg-Marquardt of `weighted.py` (unit weights) reaches
        the minimum calibrateCamera does from there (1e-5 px apart on 309 dim 720p views) in 0.14 s
        against 0.35. The rational and fisheye models keep OpenCV's solver: a rational solve's
        valley is nearly flat along its numerator and denominator terms, where the two stopped
        0.1 px apart (16 synthetic views of a 115 deg lens), and a fisheye round has its fallbacks."""
        if model != "pinhole":
            return solve_kept(start.camera)
        if kept is not None:
            start = RawSolution(start.camera, start.rms_px, start.rvecs[kept], start.tvecs[kept])
        refined = refined_from(start.camera, kept_views(), start)
        assert refined is not None  # posed views: every pose is given
        return refined

    raw = solve_kept(initial)
    for _round in range(max_rounds):
        # every corner of every kept frame, those set aside too, against the latest solve
        residuals = reprojection_residuals(raw.camera, frames, raw.rvecs, raw.tvecs)
        norms = [np.linalg.norm(r, axis=1) for r in residuals]
        # 1. whole frames, from five views up (four are the least a solve can cross-check)
        if len(frames) > 4:
            frame_rms = np.array([robust_frame_rms_px(r) for r in residuals])
            median_rms = float(np.median(frame_rms))
            frame_limit = max(_FRAME_RATIO * median_rms, _FRAME_FLOOR_PX)
            for i in np.flatnonzero(frame_rms > frame_limit):  # a suspect: is it its bulk, or a few corners pulling its pose?
                frame_rms[i] = _refit_frame_rms_px(raw.camera, frames[i], residuals[i])
            bad_frames = frame_rms > frame_limit
            if bad_frames.any():
                for i in np.flatnonzero(bad_frames):
                    dropped_frames.append(DroppedFrame(frames[i].frame_index, (
                        f"frame RMS {frame_rms[i]:.2f} px is {frame_rms[i] / max(median_rms, 1e-9):.1f}x the median frame's "
                        f"{median_rms:.2f} px (defocus, motion blur or a misdetection)"
                    )))
                    dropped_corners.extend(corners_of(i))
                good_frames = list(~bad_frames)
                keep_frames(good_frames)
                # the dropped frames pulled this solve: judge no corner against it
                raw = resolved(raw, good_frames)
                continue
        # 2. corners, against a solve no outlier frame pulls; the MAD sigma over all of them
        # (those set aside too) does not shrink as corners are set aside
        sigma = max(robust_sigma_px(residuals), 1e-3)
        corner_limit = max(np.sqrt(_CORNER_CHI2) * sigma, _CORNER_FLOOR_PX)
        new_outs = [n > corner_limit for n in norms]
        if all(np.array_equal(a, b) for a, b in zip(new_outs, outs, strict=True)):
            break
        outs, norms_out = new_outs, norms
        few = [int((~o).sum()) < MIN_FRAME_CORNERS for o in outs]
        frames_kept = None
        if any(few):
            for i in np.flatnonzero(few):
                dropped_frames.append(DroppedFrame(frames[i].frame_index, f"only {int((~outs[i]).sum())} corners left after removing outlier corners"))
                dropped_corners.extend(corners_of(i))
            frames_kept = [not f for f in few]
            keep_frames(frames_kept)
        raw = resolved(raw, frames_kept)
    for i in range(len(frames)):
        dropped_corners.extend(corners_of(i))
    kept = kept_views()
    camera, rvecs, tvecs = raw.camera, raw.rvecs, raw.tvecs
    residuals = reprojection_residuals(camera, kept, rvecs, tvecs)
    weights = view_weights(residuals)
    corner_weights = unrefined_corner_weights(kept, residuals)
    if (np.any(weights < 0.999) or corner_weights is not None) and len(kept) >= 3:
        # views noisier than the typical one, and corners the corner refinement could not refine,
        # count by their inverse corner variance (weighted.py)
        camera, rvecs, tvecs = weighted_refine(camera, kept, rvecs, tvecs, weights, corner_weights=corner_weights)
        kept = [replace(v, information_weight=v.information_weight * float(w),
                        corner_weights=None if corner_weights is None else corner_weights[i])
                for i, (v, w) in enumerate(zip(kept, weights, strict=True))]
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
    """Information weight per frame: a group of k look-alikes whose residuals correlate by rho counts
    as k / (1 + (k - 1) rho) independent frames (the effective number of k equicorrelated
    measurements), shared equally; rho = 0: every frame counts fully.

    Frames of one hold share what their residuals cannot fully show (the pose's own systematic
    corner error), and as k grows their worth tends to 1 / rho frames, not to k. The linear
    1 + (k - 1)(1 - rho) used before counted a hold of 26 frames at rho 0.05 as 25 frames instead
    of 12, so it needed a cap (3 frames a hold), which in turn put E at 3-5x the true error of
    dim 720p renders (0.08-0.16 px true, E 0.34-0.44: refused) and 4x on careful ones.
    """
    sizes = {g: list(groups).count(g) for g in set(groups)}
    return [1.0 / (1.0 + (sizes[g] - 1) * correlation) for g in groups]


def with_look_alikes_weighted(calibration: Calibration, groups: Sequence[int]) -> tuple[Calibration, float]:
    """The calibration with its covariance recomputed, look-alike frames counted for what they add.

    The solve uses every frame; its covariance would treat them all as independent. How much the
    frames of one group share is measured from their residuals (`look_alike_correlation`); each
    then carries `look_alike_weights` as its View.information_weight.

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
    # the noise of a corner of weight 1: each corner's variance is sigma^2 / its weight (weighted.py)
    w = np.concatenate([v.rows_weight() for v in views])
    rms_typical = float(np.sqrt(np.sum(w * np.sum(all_res**2, axis=1)) / max(float(np.sum(w)), 1e-12)))
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
