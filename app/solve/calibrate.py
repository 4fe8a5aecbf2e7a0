"""One calibration solve per distortion model, on OpenCV's solvers.

- pinhole:  `cv2.calibrateCamera`, 5-parameter Brown-Conrady (skew fixed at 0, as OpenCV does).
- rational: `cv2.calibrateCamera` with `CALIB_RATIONAL_MODEL` (k1..k6, p1, p2); seeded from a
            pinhole solve when none is given, which keeps the extra terms from wandering.
- fisheye:  `cv2.fisheye.calibrate` (Kannala-Brandt). OpenCV's own start (f from a homography)
            asserts in InitExtrinsics on wide views, so the focal length is seeded from a field
            of view guess and extrinsics are recomputed; several seeds are tried and the best kept.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import cv2
import numpy as np

from calibcoach.app.solve.result import View
from calibcoach.app.solve.weighted import weighted_refine
from calibcoach.drivers.errors import CalibrationError
from calibcoach.drivers.lens import CameraModel, rational_like

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
# cv2.fisheye.calibrate stops once an iteration moves f and c by less than eps of their size. At
# 1e-12 that never happens before the 100th iteration, and OpenCV 5.1 re-solves every view's pose
# in each (~60 ms an iteration at 32 views): a 48-frame webcam video's final solve took 50 s. At
# 1e-10 (1e-7 px at f = 900) it stops after ~25, with intrinsics equal to 1e-10 px.
_FISHEYE_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
_FISHEYE_BASIN_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 8, 1e-8)  # OpenCV's part of `_solve_fisheye`
_FISHEYE_OPENCV_VIEWS = 60  # at most this many views go to cv2.fisheye.calibrate in `_solve_fisheye`
_GOOD_ENOUGH_RMS_PX = 1.0  # a start that fits this well is kept without trying the others
_FISHEYE_SEED_HFOV_DEG = (150.0, 120.0, 180.0, 95.0, 210.0)  # tried in this order; the best RMS wins
# Where the reduced bootstrap solves (`solve(..., reduced=True)`) start: Levenberg-Marquardt's
# starting point, not a fitted value. bench/bootstrap_seeds.py swept it over simulated lenses of
# 20-150 deg and the real captures (bench/results/bootstrap_seeds.md): on every lens of 45 deg and
# wider the basin around 70 deg held the best solution (narrowest 50-80 deg on the 70 deg webcam,
# 65-70 on the 115 deg lens), and 150 deg lands for the fisheye model on every lens it is asked of
# (narrowest 60-150; it misses only on lenses of ~25 deg and narrower, where a narrow pinhole fit skips it).
BOOTSTRAP_SEED_HFOV_DEG = {"pinhole": 70.0, "fisheye": 150.0}
# From 70 deg alone the reduced pinhole lands in a wrong basin on narrow lenses (simulated view sets
# of 6-11 views: a 30 deg lens missed on 21 of 45, up to 53% off, at 2-5x the right solution's
# RMS; a 20 deg lens on 31 of 45), while on lenses of 15-45 deg the 35 deg start's basin holds the
# right solution (bench/results/bootstrap_seeds.md). So a reading under 50 deg (every narrow lens,
# right or wrong; no lens of 60 deg or more reads that) is solved again from 35 deg, and that solve
# is kept where it fits clearly better, i.e. is another basin (RMS under 90% of the first; one
# solution reached from two starts differs by far less). Worst f error on careful and sloppy view
# sets: 30 deg lens 53% -> 1.4%, 20 deg 956% -> 4.5%; lenses of 70 deg and wider: the same solve.
_NARROW_READING_DEG = 50.0
_NARROW_SEED_DEG = 35.0
_CLEARLY_BETTER = 0.9


class RawSolution:
    """The bare result of one solver call, before residual analysis."""

    __slots__ = ("camera", "rms_px", "rvecs", "tvecs")

    def __init__(self, camera: CameraModel, rms_px: float, rvecs: np.ndarray, tvecs: np.ndarray) -> None:
        self.camera = camera
        self.rms_px = rms_px
        self.rvecs = rvecs  # (V, 3) float64
        self.tvecs = tvecs  # (V, 3) float64


class ColdPinhole:
    """The pinhole solve of one set of views from OpenCV's own start, made once for every solve that needs it.

    The model choice solves each half of the views with every candidate: the pinhole candidate is
    this solve, and the rational one starts from it (`_starts`). Made lazily, on the first call;
    raises the solve's CalibrationError on every call when it failed.
    """

    def __init__(self, views: Sequence[View], image_size: tuple[int, int]) -> None:
        self.views, self.image_size = views, image_size
        self._made: RawSolution | CalibrationError | None = None

    def __call__(self) -> RawSolution:
        if self._made is None:
            try:
                self._made = _solve_from(self.views, self.image_size, "pinhole", None)
            except CalibrationError as exc:
                self._made = exc
        if isinstance(self._made, CalibrationError):
            raise self._made
        return self._made


def solve(views: Sequence[View], image_size: tuple[int, int], model: str, *, initial: CameraModel | None = None,
          reduced: bool = False, seed_hfov_deg: float | None = None, basin_only: bool = False,
          cold_pinhole: ColdPinhole | None = None) -> RawSolution:
    """Solve intrinsics and per-view poses for `model` from `views` (each with >= 6 corners).

    `reduced` solves a well-conditioned subset for the first frames of a capture: one focal length,
    the principal point held at the image centre and only the first radial terms. A full model on
    five far views fits noise (focal lengths of 3000 px for a 950 px lens were seen), and those
    bootstrap intrinsics steer pose estimates, coverage and frame scoring until the data is richer.
    A reduced solve starts from `seed_hfov_deg` (default `BOOTSTRAP_SEED_HFOV_DEG` of the model;
    bench/bootstrap_seeds.py sweeps it). `basin_only`: a reduced fisheye stops after OpenCV's
    first iterations (`_FISHEYE_BASIN_CRITERIA`), enough to say how well the model can fit (its RMS
    within 0.02% of the converged one on a 90 deg webcam's 6-11 views) at a tenth of the time.

    `cold_pinhole`: the cold pinhole solve of these same `views` where the caller keeps one (it is
    then made once for several solves, with the same result).

    Raises:
        CalibrationError: fewer than 3 views, or the solver failed on this data.
    """
    if len(views) < 3:
        raise CalibrationError(f"a calibration needs at least 3 usable views, got {len(views)}; capture more frames of the board")
    if reduced:
        if basin_only and model == "fisheye":
            return _solve_reduced_from(views, image_size, model, BOOTSTRAP_SEED_HFOV_DEG["fisheye"] if seed_hfov_deg is None
                                       else seed_hfov_deg, fisheye_criteria=_FISHEYE_BASIN_CRITERIA)
        return _solve_reduced(views, image_size, model, seed_hfov_deg)
    if model == "fisheye":
        return _solve_fisheye(views, image_size, initial)
    cold_pinhole = cold_pinhole or ColdPinhole(views, image_size)
    best: RawSolution | None = None
    failure: CalibrationError | None = None
    for start in _starts(model, initial, cold_pinhole):
        try:  # a pinhole from OpenCV's own start is the cold pinhole itself: made once
            sol = cold_pinhole() if model == "pinhole" and start is None else _solve_from(views, image_size, model, start)
        except CalibrationError as exc:
            failure = exc
            continue
        if best is None or sol.rms_px < best.rms_px:
            best = sol
        if best.rms_px < _GOOD_ENOUGH_RMS_PX:
            break
    if best is None:
        assert failure is not None
        raise failure
    return best


def _starts(model: str, initial: CameraModel | None, cold_pinhole: ColdPinhole) -> Iterator[CameraModel | None]:
    """Where a pinhole or rational solve starts, best first: the caller's guess (the incremental
    solve; of a fisheye guess, for the rational model, its `rational_like` twin), then for the
    rational model a pinhole solve, then OpenCV's own initialisation (None).

    `solve` takes a start that fits well and tries no further one; otherwise the lowest RMS wins (a
    few inconsistent views can send one start into a wrong basin). So each start is made only when
    asked for: the pinhole solve behind the rational model's second start costs what the warm
    solve does several times over (263 views of a 104 deg 1080p lens: 1.5 s against 0.3), and a
    warm start from the frame before or the robust solve's last round nearly always fits.
    """
    if initial is not None and initial.model != "fisheye":
        yield initial
    elif initial is not None and model == "rational":
        # A wide lens's capture runs on a fisheye working model; its rational twin over the angles the
        # views reach starts the solve in the basin the pinhole start leads to (104 deg 1080p render,
        # 250 views: the same solution to 1e-7 px in 1.3 s against 2.4 s, the pinhole solve skipped).
        like = rational_like(initial, _largest_view_angle_rad(initial, cold_pinhole.views))
        if like is not None:
            yield like
    if model == "rational":
        try:
            pinhole = cold_pinhole().camera
        except CalibrationError:
            pass
        else:
            yield pinhole
    yield None


def _largest_view_angle_rad(camera: CameraModel, views: Sequence[View]) -> float:
    """The largest angle off `camera`'s axis at which any of `views`' corners is seen, rad."""
    rays = camera.unproject(np.concatenate([v.image_points_px for v in views]))
    return float(np.arccos(np.clip(rays[:, 2], -1.0, 1.0)).max())


def _solve_from(views: Sequence[View], image_size: tuple[int, int], model: str, initial: CameraModel | None) -> RawSolution:
    obj = [np.ascontiguousarray(v.object_points_m, np.float32).reshape(-1, 1, 3) for v in views]
    img = [np.ascontiguousarray(v.image_points_px, np.float32).reshape(-1, 1, 2) for v in views]
    flags = cv2.CALIB_RATIONAL_MODEL if model == "rational" else 0
    K0 = None
    D0 = None
    if initial is not None and initial.model != "fisheye":
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
        K0 = initial.camera_matrix.copy()
        D0 = np.zeros((1, 8 if model == "rational" else 5))
        n = min(D0.size, initial.dist_coeffs.size)
        D0[0, :n] = initial.dist_coeffs[:n]
    try:
        rms, K, D, rvecs, tvecs = cv2.calibrateCamera(obj, img, tuple(image_size), K0, D0, flags=flags, criteria=_CRITERIA)
    except cv2.error as exc:
        raise CalibrationError(f"OpenCV's {model} solve failed on these {len(views)} views ({_short(exc)})") from None
    camera = CameraModel(model, K, np.asarray(D).reshape(-1)[: 8 if model == "rational" else 5], image_size)
    return _checked(RawSolution(camera, float(rms), _stack(rvecs), _stack(tvecs)), len(views))


def _checked(sol: RawSolution, n_views: int) -> RawSolution:
    """Refuse a solve that ran off: non-finite numbers, a negative focal length, a principal point
    far outside the image. OpenCV returns such results without complaint when a few bad views
    pull the optimiser into a wrong basin; passing them on would poison everything downstream."""
    K = sol.camera.camera_matrix
    w, h = sol.camera.image_size
    problems = []
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(sol.camera.dist_coeffs)) and np.isfinite(sol.rms_px)):
        problems.append("non-finite parameters")
    elif K[0, 0] <= 0 or K[1, 1] <= 0 or not 0.5 < K[0, 0] / K[1, 1] < 2.0:
        problems.append(f"focal lengths fx {K[0, 0]:.1f}, fy {K[1, 1]:.1f}")
    elif not (0 < K[0, 2] < w and 0 < K[1, 2] < h):
        problems.append(f"principal point ({K[0, 2]:.0f}, {K[1, 2]:.0f}) outside the image")
    if problems:
        raise CalibrationError(
            f"the {sol.camera.model} solve on {n_views} views diverged ({problems[0]}); some views disagree with the rest"
        )
    return sol


def _solve_reduced(views: Sequence[View], image_size: tuple[int, int], model: str,
                   seed_hfov_deg: float | None = None) -> RawSolution:
    """The bootstrap solve: fx = fy, centred principal point, k1 k2 only (k1 only on the fisheye).

    From `seed_hfov_deg` alone where given; by default from `BOOTSTRAP_SEED_HFOV_DEG`, and a pinhole
    that reads a narrow lens is solved again from `_NARROW_SEED_DEG` (see there).
    """
    kind = "fisheye" if model == "fisheye" else "pinhole"
    if seed_hfov_deg is not None or kind == "fisheye":
        return _solve_reduced_from(views, image_size, model, BOOTSTRAP_SEED_HFOV_DEG[kind] if seed_hfov_deg is None else seed_hfov_deg)
    try:
        first = _solve_reduced_from(views, image_size, model, BOOTSTRAP_SEED_HFOV_DEG[kind])
    except CalibrationError:
        return _solve_reduced_from(views, image_size, model, _NARROW_SEED_DEG)  # raises in turn when it fails too
    if first.camera.field_of_view_deg()[0] >= _NARROW_READING_DEG:
        return first
    try:
        second = _solve_reduced_from(views, image_size, model, _NARROW_SEED_DEG)
    except CalibrationError:
        return first
    return second if second.rms_px < _CLEARLY_BETTER * first.rms_px else first


def _solve_reduced_from(views: Sequence[View], image_size: tuple[int, int], model: str, seed_hfov_deg: float, *,
                        fisheye_criteria: tuple[int, int, float] = _FISHEYE_CRITERIA) -> RawSolution:
    """One reduced solve (see `_solve_reduced`) from a field-of-view guess."""
    kind = "fisheye" if model == "fisheye" else "pinhole"
    seed = CameraModel.from_fov(image_size, seed_hfov_deg, kind)
    if model == "fisheye":
        flags = (cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | cv2.CALIB_USE_INTRINSIC_GUESS
                 | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K4)
        obj = [np.ascontiguousarray(v.object_points_m, np.float64).reshape(1, -1, 3) for v in views]
        img = [np.ascontiguousarray(v.image_points_px, np.float64).reshape(1, -1, 2) for v in views]
        try:
            rms, K, D, rvecs, tvecs = cv2.fisheye.calibrate(obj, img, tuple(image_size), seed.camera_matrix.copy(),
                                                            np.zeros((4, 1)), flags=flags, criteria=fisheye_criteria)
        except cv2.error as exc:
            raise CalibrationError(f"the bootstrap fisheye solve failed ({_short(exc)})") from None
        camera = CameraModel("fisheye", K, np.asarray(D).reshape(-1), image_size)
    else:
        flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_PRINCIPAL_POINT
                 | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3)
        obj = [np.ascontiguousarray(v.object_points_m, np.float32).reshape(-1, 1, 3) for v in views]
        img = [np.ascontiguousarray(v.image_points_px, np.float32).reshape(-1, 1, 2) for v in views]
        try:
            rms, K, D, rvecs, tvecs = cv2.calibrateCamera(obj, img, tuple(image_size), seed.camera_matrix.copy(),
                                                          np.zeros((1, 5)), flags=flags, criteria=_CRITERIA)
        except cv2.error as exc:
            raise CalibrationError(f"the bootstrap solve failed ({_short(exc)})") from None
        camera = CameraModel("pinhole", K, np.asarray(D).reshape(-1)[:5], image_size)
    return _checked(RawSolution(camera, float(rms), _stack(rvecs), _stack(tvecs)), len(views))


def _solve_fisheye(views: Sequence[View], image_size: tuple[int, int], initial: CameraModel | None) -> RawSolution:
    """Kannala-Brandt: OpenCV finds the basin, the Schur-reduced refinement of weighted.py converges.

    cv2.fisheye.calibrate re-solves every view's pose in each of its iterations (OpenCV 5.1: ~2 ms
    a view, so ~1.5 s for 32 views to converge and ~20 s for a final solve of 400). So OpenCV runs
    a few iterations from each start (`_FISHEYE_BASIN_CRITERIA`) on at most `_FISHEYE_OPENCV_VIEWS`
    views spread over the capture, every view is posed under the best start's lens, and intrinsics
    and all poses are refined together by `weighted_refine` with unit weights -- the same least-
    squares problem OpenCV solves, ~1 ms a view an iteration. Where that refinement cannot start
    (a view the start cannot pose) OpenCV solves all views to convergence as before.

    A fisheye `initial` (the session's last solve, a robust round's previous one) is refined from
    directly, and kept when it fits as well as a good start must (`_GOOD_ENOUGH_RMS_PX`): it is in
    the basin already, and the refinement lands where the basin search's would (to ~1e-8 px on the
    fisheye renders: same decisions, same verdicts), without OpenCV's ~0.35 s on 60 views. That took
    a 150 deg replay's parent process from 10.8 to 9.2 s of CPU (replay ratio 0.90 -> 0.72).
    """
    if initial is not None and initial.model == "fisheye":
        warm = refined_from(initial, views, None)
        if warm is not None and warm.rms_px < _GOOD_ENOUGH_RMS_PX:
            try:
                return _checked(warm, len(views))
            except CalibrationError:
                pass  # ran off: search the basin as from a cold start
    step = max(len(views) / _FISHEYE_OPENCV_VIEWS, 1.0)
    spread = [views[int(i * step)] for i in range(min(len(views), _FISHEYE_OPENCV_VIEWS))]
    start = _solve_fisheye_opencv(spread, image_size, initial, criteria=_FISHEYE_BASIN_CRITERIA)
    refined = refined_from(start.camera, views, start if len(spread) == len(views) else None)
    if refined is None:
        return _solve_fisheye_opencv(views, image_size, initial, criteria=_FISHEYE_CRITERIA)
    return _checked(refined, len(views))


def refined_from(camera: CameraModel, views: Sequence[View], posed: RawSolution | None) -> RawSolution | None:
    """Intrinsics and every pose refined together from `camera` (`posed`: its solve of these very views,
    poses included), unchecked, by the Schur-reduced Levenberg-Marquardt of weighted.py at unit weights
    (the fisheye's solve here, the robust solve's later pinhole rounds); None when `camera` cannot
    pose some view."""
    if posed is not None:
        rvecs, tvecs = posed.rvecs, posed.tvecs
    else:
        poses = poses_for_views(camera, views)
        if any(pose is None for pose in poses):
            return None
        rvecs = np.array([pose[0] for pose in poses])  # type: ignore[index]
        tvecs = np.array([pose[1] for pose in poses])  # type: ignore[index]
    camera, rvecs, tvecs = weighted_refine(camera, views, rvecs, tvecs, np.ones(len(views)), iterations=50)
    residuals = np.concatenate(reprojection_residuals(camera, views, rvecs, tvecs))
    rms = float(np.sqrt(np.mean(np.sum(residuals**2, axis=1))))
    return RawSolution(camera, rms, rvecs, tvecs)


def _solve_fisheye_opencv(views: Sequence[View], image_size: tuple[int, int], initial: CameraModel | None, *,
                          criteria: tuple[int, int, float]) -> RawSolution:
    obj = [np.ascontiguousarray(v.object_points_m, np.float64).reshape(1, -1, 3) for v in views]
    img = [np.ascontiguousarray(v.image_points_px, np.float64).reshape(1, -1, 2) for v in views]
    flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | cv2.CALIB_USE_INTRINSIC_GUESS
    best: RawSolution | None = None
    failures: list[str] = []
    for number, seed in enumerate(_fisheye_seeds(views, image_size, initial)):
        try:
            rms, K, D, rvecs, tvecs = cv2.fisheye.calibrate(
                obj, img, tuple(image_size), seed.camera_matrix.copy(), seed.dist_coeffs.reshape(4, 1).copy(),
                flags=flags, criteria=criteria,
            )
        except cv2.error as exc:
            failures.append(_short(exc))
            continue
        if not np.all(np.isfinite(K)) or not np.all(np.isfinite(D)) or K[0, 0] <= 0:
            failures.append("non-finite result")
            continue
        try:
            sol = _checked(RawSolution(CameraModel("fisheye", K, np.asarray(D).reshape(-1), image_size), float(rms),
                                       _stack(rvecs), _stack(tvecs)), len(views))
        except CalibrationError as exc:
            failures.append(str(exc))
            continue
        if best is None or sol.rms_px < best.rms_px:
            best = sol
        if best.rms_px < 1.0 and number == 0:
            break  # the first seed converged well: the others only cost time (and are never built)
    if best is None:
        raise CalibrationError(
            f"the fisheye (Kannala-Brandt) solve failed from every start ({'; '.join(sorted(set(failures)))}); "
            "check the board settings, or try --model rational"
        )
    return best


def _fisheye_seeds(views: Sequence[View], image_size: tuple[int, int], initial: CameraModel | None) -> Iterator[CameraModel]:
    """Starts for cv2.fisheye.calibrate, best first, each built only when asked for: the caller's
    fisheye guess, then a narrow lens's pinhole solve (equidistant ~ pinhole near the axis), then
    field-of-view guesses. Lazily, because a warm start that converges ends the search, and the
    pinhole solve it would otherwise pay for costs as much as the fisheye basin search itself."""
    if initial is not None and initial.model == "fisheye":
        yield initial
    try:
        pinhole = solve(views, image_size, "pinhole").camera
    except CalibrationError:
        pinhole = None
    if pinhole is not None and pinhole.field_of_view_deg()[0] < 100.0:
        yield CameraModel("fisheye", pinhole.camera_matrix, np.zeros(4), image_size)
    for fov in _FISHEYE_SEED_HFOV_DEG:
        yield CameraModel.from_fov(image_size, fov, "fisheye")


def reprojection_residuals(camera: CameraModel, views: Sequence[View], rvecs: np.ndarray, tvecs: np.ndarray) -> list[np.ndarray]:
    """Per view (N_v, 2) float64 residuals, observed minus projected, in pixels."""
    return [v.image_points_px - camera.project(v.object_points_m, rvecs[i], tvecs[i]) for i, v in enumerate(views)]


def pose_for_view(camera: CameraModel, view: View) -> tuple[np.ndarray, np.ndarray] | None:
    """T_cam_board for one view with fixed intrinsics (held-out evaluation), or None when it fails.

    Works for every model by unprojecting the corners to normalised coordinates first, so the
    fisheye needs no special PnP.
    """
    return poses_for_views(camera, [view])[0]


def poses_for_views(camera: CameraModel, views: Sequence[View]) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """`pose_for_view` of each view, the corners of all of them unprojected in one batch."""
    if not views:
        return []
    bounds = np.cumsum([0, *(v.image_points_px.shape[0] for v in views)])
    rays_all = camera.unproject(np.concatenate([v.image_points_px for v in views]))
    poses: list[tuple[np.ndarray, np.ndarray] | None] = []
    for view, a, b in zip(views, bounds[:-1], bounds[1:], strict=True):
        rays = rays_all[a:b]
        if np.any(rays[:, 2] <= 1e-6):
            poses.append(None)
            continue
        normalised = (rays[:, :2] / rays[:, 2:3]).reshape(-1, 1, 2)
        ok, rvec, tvec = cv2.solvePnP(view.object_points_m.reshape(-1, 1, 3), normalised, np.eye(3), None, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            poses.append(None)
            continue
        rvec, tvec = cv2.solvePnPRefineLM(
            view.object_points_m.reshape(-1, 1, 3), view.image_points_px.reshape(-1, 1, 2).astype(np.float64),
            camera.camera_matrix, camera.opencv_dist(), rvec, tvec,
        ) if camera.model != "fisheye" else (rvec, tvec)
        poses.append((rvec.reshape(3), tvec.reshape(3)))
    return poses


def _stack(vectors: Sequence[np.ndarray]) -> np.ndarray:
    return np.asarray([np.asarray(v, np.float64).reshape(3) for v in vectors], np.float64).reshape(-1, 3)


def _short(exc: cv2.error) -> str:
    text = str(exc).strip().splitlines()
    return text[-1].strip() if text else "OpenCV error"
