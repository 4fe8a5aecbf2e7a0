"""Choosing the distortion model: the field of view proposes, held-out residuals decide.

Each candidate model is solved on the odd views and scored on the even views (and the other way
round): intrinsics fixed, only the board pose fitted per held-out view. A model with too many
parameters for the data fits its own half well and the other half badly; a model too simple for
the lens fits neither. The simplest candidate within a small margin of the best held-out error
wins, "simplest" ordered by the field of view (the method: Brown-Conrady for ordinary lenses,
rational beyond ~90 deg, Kannala-Brandt beyond 120 deg).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from calibcoach.app.solve.calibrate import ColdPinhole, poses_for_views, reprojection_residuals, solve
from calibcoach.app.solve.result import ModelChoice, View
from calibcoach.drivers.errors import CalibrationError
from calibcoach.drivers.lens import CameraModel

MIN_VIEWS_FOR_CROSS_VALIDATION = 8
_MARGIN = 1.05  # a more complex model must beat the simpler one's held-out error by more than 5 %
_MARGIN_PX = 0.005
_NARROW_DEG = 80.0  # below this a pinhole solve sees the lens right and fisheye is never the answer
_PINHOLE_FITS_PX = 1.0  # a pinhole solve this close says the lens is no fisheye
# Two halves of one capture see one lens with the same corner noise: their held-out RMS differ by
# the sampling of ~30 views each (tens of percent). One half's 1.5x the other's says a solve stopped
# in a wrong minimum (the wide render's: 0.26 against 0.056), and the halves are solved again from
# each other's solution (`choose_model`).
_HALVES_DISAGREE = 1.5


def held_out_rms(camera: CameraModel, views: Sequence[View]) -> float:
    """Typical RMS reprojection error of `views` with the intrinsics fixed and only poses fitted.

    The per-view RMS values are combined as an RMS over the best 90% of the views, so that a
    motion-blurred frame or two (which the final robust solve drops anyway) do not decide the model.
    """
    per_view = []
    for view, pose in zip(views, poses_for_views(camera, views), strict=True):
        if pose is None:
            per_view.append(float("inf"))
            continue
        # poses_for_views refines pinhole and rational poses by OpenCV's LM already (a Gauss-Newton
        # pass after it moved the held-out RMS by 1e-7 of itself, for a third of the time); a
        # fisheye pose comes from PnP on undistorted rays and is refined here
        rvec, tvec = _refine_pose(camera, view, *pose) if camera.model == "fisheye" else pose
        res = view.image_points_px - camera.project(view.object_points_m, rvec, tvec)
        per_view.append(float(np.mean(np.sum(res**2, axis=1))))
    if not per_view:
        return float("inf")
    kept = np.sort(per_view)[: max(1, int(np.ceil(0.9 * len(per_view))))]
    return float(np.sqrt(np.mean(kept)))


def _solve_half(views: Sequence[View], image_size: tuple[int, int], model: str, warm: CameraModel | None = None,
                cold_pinhole: ColdPinhole | None = None) -> CameraModel:
    """Solve one half, drop its clearly inconsistent views (3x the median view RMS) and solve again.

    `cold_pinhole`: the half's pinhole solve from OpenCV's start, kept across the candidates (the
    pinhole candidate's first solve, and the rational one's start: `calibrate.solve`)."""
    raw = solve(views, image_size, model, initial=_warm_for(model, warm), cold_pinhole=cold_pinhole)
    res = reprojection_residuals(raw.camera, views, raw.rvecs, raw.tvecs)
    view_rms = np.array([np.sqrt(np.mean(np.sum(r**2, axis=1))) for r in res])
    keep = view_rms <= max(3.0 * float(np.median(view_rms)), 0.5)
    if keep.all() or keep.sum() < 3:
        return raw.camera
    return solve([v for v, k in zip(views, keep, strict=True) if k], image_size, model, initial=raw.camera).camera


def _better_of(camera: CameraModel, other: CameraModel, views: Sequence[View], image_size: tuple[int, int],
               model: str) -> CameraModel:
    """`camera`, or the solve of `views` from `other` where that fits `views` better (`held_out_rms`)."""
    try:
        alternative = solve(views, image_size, model, initial=other).camera
    except CalibrationError:
        return camera
    return alternative if held_out_rms(alternative, views) < held_out_rms(camera, views) else camera


def _refine_pose(camera: CameraModel, view: View, rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on the pose alone (works for every model through projectPoints' Jacobian)."""
    for _ in range(10):
        if camera.model == "fisheye":
            proj, J = cv2.fisheye.projectPoints(
                view.object_points_m.reshape(1, -1, 3), rvec.reshape(1, 1, 3), tvec.reshape(1, 1, 3),
                camera.camera_matrix, camera.dist_coeffs,
            )
            Jp = J[:, 8:14]  # fisheye Jacobian columns: f(2), c(2), k(4), om(3), T(3), alpha(1)
        else:
            proj, J = cv2.projectPoints(view.object_points_m, rvec, tvec, camera.camera_matrix, camera.opencv_dist())
            Jp = J[:, :6]
        r = (view.image_points_px - proj.reshape(-1, 2)).reshape(-1)
        step, *_ = np.linalg.lstsq(Jp, r, rcond=None)
        rvec, tvec = rvec + step[:3], tvec + step[3:]
        if np.max(np.abs(step)) < 1e-10:
            break
    return rvec, tvec


def pinhole_sees_narrow_lens(pinhole_rms_px: float, hfov_deg: float) -> bool:
    """A pinhole solve that fits within a pixel and sees a field under 80 deg: the lens is no fisheye.

    On a fisheye the pinhole model either misses by pixels or, fitting the centre, reads a wide
    field (a 150 deg render's six-view reduced pinhole: 0.39 px but 123 deg; another: 1.5 px);
    a fisheye solve of a narrow lens that a pinhole fits can only agree with it.
    """
    return pinhole_rms_px < _PINHOLE_FITS_PX and hfov_deg < _NARROW_DEG


def likely_model(hfov_deg: float, n_views: int) -> str:
    """The model `choose_model` most likely picks for views of a lens this wide: the simplest
    candidate, which wins whenever it is within the margin of the best (too few views to
    cross-validate: the field of view's own choice)."""
    return _by_field_of_view(hfov_deg) if n_views < MIN_VIEWS_FOR_CROSS_VALIDATION else candidate_order(hfov_deg)[0]


def _by_field_of_view(hfov_deg: float) -> str:
    """The choice where there is too little to cross-validate (fewer parameters are safer on little data)."""
    return "fisheye" if hfov_deg >= 120.0 else "pinhole"


def candidate_order(hfov_deg: float) -> list[str]:
    """Candidates, simplest first for this field of view.

    Below ~80 deg Kannala-Brandt is not a candidate: no lens that narrow needs it, and its
    cross-validation costs more than the rest of the model choice together.
    """
    if hfov_deg >= 120.0:
        return ["fisheye", "rational"]
    if hfov_deg >= 90.0:
        return ["rational", "fisheye", "pinhole"]
    if hfov_deg >= _NARROW_DEG:
        return ["pinhole", "rational", "fisheye"]
    return ["pinhole", "rational"]


def _warm_for(model: str, warm: CameraModel | None) -> CameraModel | None:
    """The warm start a `model` solve takes: a fisheye one only (see `choose_model`)."""
    return warm if warm is not None and model == "fisheye" and warm.model == "fisheye" else None


def choose_model(views: Sequence[View], image_size: tuple[int, int], *,
                 on_likely: Callable[[str], None] | None = None, warm: CameraModel | None = None) -> ModelChoice:
    """Pick a model for `views` by field of view and odd/even cross-validation.

    `on_likely(model)` is told, once the field of view is known and before the cross-validation,
    the model most likely chosen (the simplest candidate for that field of view, which wins
    whenever it is within the margin of the best), so that its solve can start alongside.
    `warm`: the session's last fisheye solve, from which the fisheye solves here start (they then
    skip OpenCV's basin search, ~0.4 s each, and land where it would: calibrate._solve_fisheye);
    other models always start cold, as their scores are compared against it.
    """
    hfov = estimate_hfov_deg(views, image_size, warm=warm)
    order = candidate_order(hfov)
    few = len(views) < MIN_VIEWS_FOR_CROSS_VALIDATION
    by_field_of_view = _by_field_of_view(hfov)
    if on_likely is not None:
        on_likely(likely_model(hfov, len(views)))
    if few:
        chosen = by_field_of_view
        return ModelChoice(chosen, {}, (
            f"only {len(views)} views: too few to cross-validate, so the {chosen} model was taken from the "
            f"~{hfov:.0f} deg field of view (fewer parameters are safer on little data)"
        ))
    odd, even = list(views[1::2]), list(views[0::2])
    scores: dict[str, float] = {}
    # The two halves solve on two threads (OpenCV releases the GIL; each solve is single-threaded,
    # so the numbers are the same as one after the other).
    cold_pinholes = [ColdPinhole(half, image_size) for half in (odd, even)]  # each made once, by the first candidate that needs it
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="model-choice") as pool:
        for model in order:
            halves = [pool.submit(_solve_half, half, image_size, model, warm, cold)
                      for half, cold in zip((odd, even), cold_pinholes, strict=True)]
            try:
                a, b = (h.result() for h in halves)
            except CalibrationError:
                scores[model] = float("inf")
                continue
            ea, eb = held_out_rms(a, even), held_out_rms(b, odd)
            if model == "rational" and max(ea, eb) > _HALVES_DISAGREE * min(ea, eb):
                # The rational model's valley has several minima (`robust.robust_calibrate`): where
                # the halves disagree, each is solved again from the other's solution, and the one
                # that fits its own half better taken. On a 104 deg render's `--every-frame` replay
                # (smooth wide s104) the odd half's own solve stopped at RMS 0.28 px (held out 0.26)
                # where the even half's gave 0.06, and the fisheye model was chosen for a rational
                # lens: 0.70 px against the truth, refused; from the even half's, 0.06 and 0.056.
                a, b = (h.result() for h in [pool.submit(_better_of, a, b, half, image_size, model)
                                             for (a, b), half in (((a, b), odd), ((b, a), even))])
                ea, eb = held_out_rms(a, even), held_out_rms(b, odd)
            scores[model] = float(np.sqrt(0.5 * (ea * ea + eb * eb)))
    best = min(scores.values())
    if not np.isfinite(best):
        raise CalibrationError("no distortion model could be solved on these views; capture more, more varied frames")
    for model in order:
        if scores[model] <= best * _MARGIN + _MARGIN_PX:
            others = ", ".join(f"{m} {s:.3f} px" for m, s in scores.items())
            return ModelChoice(model, scores, (
                f"~{hfov:.0f} deg horizontal field of view; held-out RMS (solve on odd frames, test on even and back): "
                f"{others}; {model} is the simplest within 5% of the best"
            ))
    raise AssertionError("unreachable: the best model is within its own margin")


def estimate_hfov_deg(views: Sequence[View], image_size: tuple[int, int], *, warm: CameraModel | None = None) -> float:
    """Horizontal field of view from quick pinhole and fisheye solves, whichever fits better.

    A pinhole solve is reliable for narrow lenses and fails on fisheyes; an equidistant solve
    follows wide lenses; the lower RMS tells which one saw the lens right. `warm`: see `choose_model`;
    a pinhole `warm` starts the pinhole solve too, since this solve is read for its field of view,
    not scored against another (`solve` still tries OpenCV's own start where the warm one fits worse
    than a pixel): 0.03 s instead of 0.09 on a careful 720p replay's 60 views, the same solution.
    """
    best: tuple[float, float] | None = None
    for model in ("pinhole", "fisheye"):
        start = warm if model == "pinhole" and warm is not None and warm.model == "pinhole" else _warm_for(model, warm)
        try:
            raw = solve(views, image_size, model, initial=start)
        except CalibrationError:
            continue
        hfov = raw.camera.field_of_view_deg()[0]
        if np.isfinite(hfov) and 1.0 < hfov < 250.0 and (best is None or raw.rms_px < best[0]):
            best = (raw.rms_px, hfov)
        if model == "pinhole" and best is not None and pinhole_sees_narrow_lens(*best):
            break  # the fisheye solve could only agree
    return 70.0 if best is None else best[1]
