"""The end of a calibration session: the final robust solve, model choice, uncertainty and verdict.

`SessionFinish.finish()` is what `CalibrationSession` (app/session.py) runs once capture ends:
it spends the unused frame budget on reserve frames (poses of their own first, then the repeats
of every hold), chooses the lens model on the live budget's frames, solves robustly on all of
them, counts each hold's look-alike frames for what they add to the covariance, maps the expected
projection error and judges the result. It is a mixin: the state it reads (kept views, reserve,
selector, incremental intrinsics) is the session's own.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from calibcoach.app.session_types import SessionResult
from calibcoach.app.solve.calibrate import solve
from calibcoach.app.solve.hold_jackknife import hold_jackknife_covariance
from calibcoach.app.solve.information import marginal_information
from calibcoach.app.solve.model_choice import choose_model, likely_model
from calibcoach.app.solve.next_view import fill_from_reserve
from calibcoach.app.solve.residual_structure import residual_structure
from calibcoach.app.solve.result import Calibration, ExpectedErrors, ModelChoice, View
from calibcoach.app.solve.robust import noise_sigma_px, robust_calibrate, with_look_alikes_weighted
from calibcoach.app.solve.uncertainty import covered_region_mask, expected_error_px, projection_uncertainty
from calibcoach.app.solve.verdict import error_target_px, judge, smeared_capture_advice
from calibcoach.coverage.board_diagnosis import diagnose_board_mismatch
from calibcoach.coverage.candidates import ranges_for
from calibcoach.coverage.corner_symmetry import refine_by_symmetry
from calibcoach.coverage.detector import Detection
from calibcoach.coverage.grid import CoverageMap
from calibcoach.coverage.pose import estimate_pose, estimate_poses
from calibcoach.coverage.select import AcceptedView, LookAlikeTable, accepted_view, look_alike_groups
from calibcoach.coverage.sharpness import EdgeBlur, edge_blur
from calibcoach.drivers.base import Frame
from calibcoach.drivers.errors import BoardError, CalibrationError
from calibcoach.drivers.lens import CameraModel

# Fewer kept frames than this and the live session has not solved yet (app/session.py solves from here on).
MIN_VIEWS_FOR_INCREMENTAL_SOLVE = 6
# The final solve takes the masked corners below this horizontal field of view (`refines_corners`):
# the method's boundary between ordinary lenses (5-term Brown-Conrady) and wide ones, whose
# checker edges curve over the half square the refinement spans.
ORDINARY_LENS_FOV_DEG = 90.0
# The capture's own lens names the likely model before the model choice does (`finish`) only when
# this much wider or narrower would name the same: its field of view and the model choice's
# estimate, from other solves of other views, differ by a few degrees (see the bench note in
# bench/results/replay_speed.md); a guess that misses costs a solve's CPU, never its result.
_FOV_GUESS_MARGIN_DEG = 5.0

if TYPE_CHECKING:
    from calibcoach.app.session_types import SessionSettings
    from calibcoach.coverage.board import BoardSpec
    from calibcoach.coverage.exposure import ExposureReading, SmearLedger
    from calibcoach.coverage.pose import BoardPose
    from calibcoach.coverage.select import FrameSelector
    from calibcoach.coverage.virtual_view import BoardGeometry


def view_detection(view: View) -> Detection:
    """The detection a stored view was made from (without its markers)."""
    return Detection(view.image_points_px.astype(np.float32), view.ids, view.object_points_m.astype(np.float32),
                     np.zeros(0, np.int32))


def frame_view(frame: Frame, detection: Detection, board: BoardSpec, *, refine: bool = True,
               edges: EdgeBlur | None = None, blur_px: float | None = None) -> View:
    """A detected frame as the solver takes it, with its corners also fitted to the pattern's point
    symmetry (`refine`).

    `edges`: the frame's edge widths where already measured, or `blur_px` their blurrier family's
    (`EdgeBlur.blur_px`: a held board's, measured on another frame of the hold); the refinement's
    mask keeps clear of the markers' edges by twice that width. Neither: measured here.
    """
    corners = detection.corners_px.astype(np.float64)
    refined = None
    if refine:
        grey = frame.grey()
        blur = edges.blur_px if edges is not None else blur_px
        if blur is None:
            blur = edge_blur(grey, corners, detection.object_points_m).blur_px
        blur = blur if np.isfinite(blur) else None
        # every corner (of a frame with 6 or more) fitted to the pattern's point symmetry
        # (coverage/corner_symmetry.py), from OpenCV's corners: refining them on the checker's edges first
        # (coverage/corner_refine.py, which the symmetry fit replaced) gave the same error against the
        # truth over 63 renders (1.00x) for ~0.7 ms more a frame
        refined = refine_by_symmetry(grey, corners, detection.object_points_m, board, blur_sigma_px=blur)
    return View(frame.index, frame.name, detection.ids.copy(), corners, detection.object_points_m.astype(np.float64),
                timestamp_ns=int(frame.timestamp_ns), refined_px=refined)




class SessionFinish:
    """`finish()` and its steps, mixed into `CalibrationSession`, whose state they use."""

    # the session's state that the final solve reads (set in CalibrationSession.__init__)
    settings: SessionSettings
    board: BoardSpec
    image_size: tuple[int, int]
    geometry: BoardGeometry
    camera: CameraModel
    selector: FrameSelector
    views: list[View]
    working_model: str
    frames_seen: int
    stop_reason: str
    focus_drift: str | None
    drifted_ranges: list[tuple[int, int | None]]
    look_alike_correlation: float
    budget_fill: tuple[int, int]
    _reserve: list[tuple[View, float]]
    _repeats: list[View]
    _information: np.ndarray | None
    _error_weight: np.ndarray | None
    _check_image: tuple[int, Frame] | None
    _samples: list[np.ndarray]
    board_mismatch: BoardError | None
    _final_poses: tuple[CameraModel, dict[int, BoardPose | None]] | None = None  # see _poses_under
    smear: SmearLedger
    exposure: ExposureReading | None = None  # as the final solve read it (`_leave_out_smeared`)
    smeared_left_out: int = 0  # usable frames the final solve left out as smeared

    @property
    def refines_corners(self) -> bool:
        """Whether the final solve takes the refined corners (`SessionSettings.corners`): on an ordinary lens only.

        Measured for the masked refinement (coverage/corner_refine.py) that the symmetry fit replaced:
        it solves cornerSubPix's equations over half a square, assuming the checker's
        edges straight through the corner; through a wide or fisheye lens they curve over that
        span, and the curvature pulls outer corners outward: on a 150 deg lens by 0.019 px on
        average at 450-600 px from the centre (OpenCV's corners 0.008), on a 104 deg one by 0.017 px
        beyond 750 px (0.006), a radial pattern the distortion model takes up. Paired on the same
        code (bench/heldout.py renders): fisheye s101/s103/s104 0.023/0.015/0.006 -> 0.031/0.045/0.047
        px (s104 above the plain recipe's 0.027), s102 better; the 104 deg lens s103 0.014 -> 0.064,
        s101 better (0.053 -> 0.026). Solving the same equations in the board's plane through the
        local map removed the radial pull but coupled each corner to its neighbours' detections
        (the map's curvature is fitted to them) and was worse on every lens. So the masked corners
        are taken where the method's 5-term model suffices, a field of view under 90 deg (where they
        helped most: careful 720p renders 0.063/0.078 -> 0.033/0.022 px), and not through a fisheye.
        The symmetry fit (coverage/corner_symmetry.py) was measured under 90 deg only; a crossing of
        two edges stays point-symmetric through a wide lens to first order, so it may suit those
        lenses too (not measured: the wide and fisheye renders still solve OpenCV's corners).
        """
        return self._refines_views and self.camera.field_of_view_deg()[0] < ORDINARY_LENS_FOV_DEG

    @property
    def _refines_views(self) -> bool:
        """Whether views are refined as they are made (cheap; the final solve may still not take them)."""
        return self.settings.corners == "masked" and self.working_model != "fisheye"

    def _drifted(self, frame_index: int) -> bool:
        """Taken at a drifted focus (see `CalibrationSession.stop_accepting`)."""
        return any(start <= frame_index and (end is None or frame_index < end) for start, end in self.drifted_ranges)

    def _pose(self, detection: Detection) -> BoardPose | None:
        return estimate_pose(detection, self.camera, self.geometry.centre_m)

    def finish(self, on_stage: Callable[[str], None] | None = None) -> SessionResult:
        """Final robust solve, model choice, uncertainty map and verdict.

        `on_stage(name)` is told as each stage begins ("frame budget", "model choice", "robust solve",
        "uncertainty", "verdict": `progress.SOLVE_STAGES`), for a progress bar.
        """
        stage = on_stage or (lambda _name: None)
        self._leave_out_smeared()
        if self.drifted_ranges:  # taken at another focus: another camera
            self.views = [v for v in self.views if not self._drifted(v.frame_index)]
            self._reserve = [(v, q) for v, q in self._reserve if not self._drifted(v.frame_index)]
        if len(self.views) < 3 and len(self.views) + len(self._reserve) >= 3:
            # Too few distinct frames (a frontal-only capture, say): solve with the look-alikes anyway,
            # so the verdict can say what is wrong with the data instead of refusing to look.
            step = max(1, len(self._reserve) // 8)
            taken = self._reserve[::step][: self.settings.selector.max_frames]
            self.views = sorted(self.views + [v for v, _q in taken], key=lambda v: v.frame_index)
            self._reserve = [r for r in self._reserve if not any(r is t for t in taken)]
        if len(self.views) < 3:
            raise self._not_enough_views_error()
        stage("frame budget")
        kept_live = list(self.views)
        self._fill_budget()
        if self.refines_corners:
            kept_live = [v.as_refined() for v in kept_live]
            self.views = [v.as_refined() for v in self.views]
            self._repeats = [v.as_refined() for v in self._repeats]
        stage("model choice")
        distinct = self.views
        offered_views = sorted(self.views + self._repeats, key=lambda v: v.frame_index)
        budget = max(0, self.settings.selector.max_frames - len(self.views))
        choice_views = sorted(self.views + self._repeats[:budget], key=lambda v: v.frame_index)
        self.views, self._repeats = offered_views, []

        def solve_with(views: Sequence[View], model: str) -> Calibration:
            # the capture's own lens as the start (a fisheye one, of a wide lens, for a rational solve too: calibrate._starts)
            warm = self.camera.model == model or (model == "rational" and self.camera.model == "fisheye")
            return robust_calibrate(views, self.image_size, model, initial=self.camera if warm else None)

        # The robust solve of the likeliest model starts as soon as a field of view names it and
        # runs beside the model choice's cross-validation (OpenCV releases the GIL): its inputs do
        # not depend on the choice, so the result is the same as solving after it. The capture's
        # own lens names it first, unless its field of view lies within a few degrees of a
        # boundary between models (the model choice's field-of-view solves take 0.1-0.5 s before
        # they name one); where the model choice names another, that one starts beside it. Where
        # another model is chosen, a solve started is left to finish unread and the chosen one
        # solved here.
        ahead: dict[str, Future[Calibration]] = {}  # the likely model -> its solve
        pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="solve-ahead")

        def start(model: str) -> None:
            if model not in ahead:
                ahead[model] = pool.submit(solve_with, offered_views, model)

        try:
            if self.settings.model == "auto":
                live_fov = self.camera.field_of_view_deg()[0]
                guesses = {likely_model(fov, len(choice_views)) for fov in (live_fov - _FOV_GUESS_MARGIN_DEG,
                                                                          live_fov + _FOV_GUESS_MARGIN_DEG)}
                if np.isfinite(live_fov) and len(guesses) == 1:
                    start(guesses.pop())
                # On the frames the budget of the live selection holds (distinct poses, then repeats of every
                # pose alike up to `max_frames`), as before repeats could fill 400: on the distinct poses
                # alone (~20 at a wide lens) the 8-term rational overfits its halves and a 104 deg rational
                # lens was solved as a fisheye 0.7 px off on 2 of 5 renders; on all 400 the halves share poses.
                choice = choose_model(choice_views, self.image_size, on_likely=start, warm=self.camera)
            else:
                choice = ModelChoice(self.settings.model, {}, f"{self.settings.model} model requested with --model")
            stage("robust solve")
            # cv2.fisheye.calibrate re-initialises every view's pose at each step and asserts when one turns
            # degenerate (robust.solve_kept leaves out one such frame, not several); among hundreds of
            # frames that happened on 1 of 5 fisheye renders. Then the distinct poses alone, then the frames
            # kept live (which the incremental solves took), are solved instead.
            offered = len(self.views)
            fallbacks = [v for v in (distinct, kept_live) if 3 <= len(v) < len(self.views)]
            started = ahead.get(choice.chosen)
            while True:
                try:
                    solved = started.result() if started is not None else solve_with(self.views, choice.chosen)
                    break
                except CalibrationError:
                    if not fallbacks:
                        raise
                    started, self.views = None, fallbacks.pop(0)
        finally:
            pool.shutdown(wait=False, cancel_futures=True)
        groups = self._look_alike_groups(solved.views, solved.camera)
        calibration = self._with_look_alikes_weighted(solved, groups)
        structure = residual_structure(calibration, groups)
        corner_sets = [v.image_points_px for v in calibration.views]
        # the same map, grid and covered region as the live E (`_update_after_accept`), on the final solve
        stage("uncertainty")
        uncertainty = projection_uncertainty(
            calibration.camera, calibration.intrinsic_covariance,
            covered_mask_fn=lambda gx, gy: covered_region_mask(self.image_size, corner_sets, (gx.size, gy.size)),
        )
        # E is the larger of the model's and the one the scatter between holds measures (app/solve/hold_jackknife.py):
        # the model cannot see error a hold's frames share, and the jackknife of a dozen holds is noisy either way
        between_holds = hold_jackknife_covariance(solved.camera, solved.views, solved.rvecs, solved.tvecs,
                                                  solved.residuals_px, groups)
        expected = ExpectedErrors(uncertainty.expected_error_px)
        if between_holds is not None:
            expected = ExpectedErrors(uncertainty.expected_error_px, expected_error_px(between_holds, uncertainty.error_weight),
                                      len(set(groups)))
            if expected.between_holds_wins:
                calibration = replace(calibration, intrinsic_covariance=between_holds)
                covered = uncertainty.covered  # the same region: only the covariance changed
                uncertainty = projection_uncertainty(calibration.camera, between_holds, covered_mask_fn=lambda gx, gy: covered)
        stage("verdict")
        coverage = self._final_coverage(calibration)
        reachable_error = uncertainty.expected_error_where(coverage.reachable_at(uncertainty.grid_x_px, uncertainty.grid_y_px))
        noise = noise_sigma_px(calibration.rms_px, n_points=calibration.corner_count,
                               n_params=len(calibration.intrinsic_names), n_views=len(calibration.views))
        verdict = judge(
            calibration,
            coverage_completeness=coverage.completeness(),
            coverage_missing=coverage.summary()["missing"],  # type: ignore[arg-type]
            uncertainty=uncertainty,
            image_size=self.image_size,
            noise_px=noise,
            target_px=self.settings.error_target_px,
            structure=structure,
            reachable_error_px=reachable_error,
        )
        if len(self.views) < offered:
            verdict = replace(verdict, reasons=(*verdict.reasons, f"OpenCV's {choice.chosen} solve could not start with all "
                              f"{offered} usable frames; solved on {len(self.views)} of them instead."))
        exposure = "" if self.exposure is None else self.exposure.describe()
        advice = None if verdict.trusted else smeared_capture_advice(self.selector.counts, exposure)
        if advice is not None:
            verdict = replace(verdict, reasons=(*verdict.reasons, advice))
        if expected.between_holds_wins:
            verdict = replace(verdict, reasons=(*verdict.reasons, f"E is read from the scatter between the capture's {expected.holds} "
                              f"holds ({expected.between_holds_px:.3f} px); the corner noise alone predicts {expected.from_model_px:.3f} px: "
                              "the frames of a hold share part of their corners' error, which more frames of the same holds do not average out."))
        if self.focus_drift is not None:
            verdict = replace(verdict, reasons=(*verdict.reasons, f"Focus drifted ({self.focus_drift}): frames taken after "
                              "it were left out; lock focus at the recorded value and continue with --resume to add more."))
        return SessionResult(
            calibration=calibration,
            model_choice=choice,
            uncertainty=uncertainty,
            verdict=verdict,
            coverage=coverage,
            board=self.board,
            rejections=dict(self.selector.counts),
            frames_seen=self.frames_seen,
            check_image=None if self._check_image is None else self._check_image[1].colour(),
            noise_px=noise,
            target_px=self.settings.error_target_px or error_target_px(noise, self.image_size),
            stop_reason=self.stop_reason,
            residual_structure=structure,
            reachable_error_px=reachable_error,
            smeared_left_out=self.smeared_left_out,
            exposure=exposure,
            expected_errors=expected,
        )

    def _leave_out_smeared(self) -> None:
        """Frames whose fastest corner moved more than `SelectorSettings.max_solve_smear_px` within the
        exposure, as read off the whole capture (coverage/exposure.py), never enter the final solve.

        During the capture each frame was judged by its own edges, which show a smear of 2 px only
        faintly on a noisy frame; by the end the capture's moving frames have shown the exposure,
        and each frame's speed across it is known from its neighbours.
        """
        indices = [v.frame_index for v in self.views] + [v.frame_index for v, _q in self._reserve]
        smeared, self.exposure = self.smear.smeared(indices, self.settings.selector.max_solve_smear_px)
        if smeared:
            self.views = [v for v in self.views if v.frame_index not in smeared]
            self._reserve = [(v, q) for v, q in self._reserve if v.frame_index not in smeared]
        self.smeared_left_out = len(smeared)

    def _fill_budget(self) -> None:
        """Spend the unused frame budget on distinct reserve frames that shrink the uncertainty most.

        During capture a frame must cut E by half what the guidance's target would, which keeps the
        guidance honest; frames the live selection passed over that show a pose of their own (not a
        look-alike of a kept or added frame) still help the final solve, greedily by information
        gain (`next_view.fill_from_reserve`).
        """
        budget = max(self.settings.solve_frames, self.settings.selector.max_frames) - len(self.views)
        if budget <= 0 or not self._reserve:
            return
        if self._information is None or len(self.views) < MIN_VIEWS_FOR_INCREMENTAL_SOLVE:  # no solve yet
            try:
                raw = solve(self.views, self.image_size, self.working_model)
            except CalibrationError:
                return
            self.camera = raw.camera
            self._information = marginal_information(raw.camera, self.views, raw.rvecs, raw.tvecs)
        offered = [*self.views, *(v for v, _q in self._reserve)]
        row = {id(view): i for i, view in enumerate(offered)}
        table = LookAlikeTable(self._looks(offered, self.camera), self.settings.selector, float(np.hypot(*self.image_size)))

        def alike(a: View, b: View) -> bool:
            return table(row[id(a)], row[id(b)])

        distinct, repeats = fill_from_reserve(self.camera, self._information, self._error_weight, self._reserve, budget,
                                              alike=alike, kept=self.views)
        self.budget_fill = (len(distinct) + len(repeats), len(self._reserve))
        self.views = sorted(self.views + distinct, key=lambda v: v.frame_index)
        self._repeats = repeats

    def _look_alike_groups(self, views: Sequence[View], camera: CameraModel) -> list[int]:
        """Group number per view: frames showing the board at nearly the same place, size and tilt."""
        return look_alike_groups(self._looks(views, camera), self.settings.selector, float(np.hypot(*self.image_size)))

    def _looks(self, views: Sequence[View], camera: CameraModel) -> list[AcceptedView | None]:
        """What the look-alike test compares of each view, posed under `camera` (None: no pose)."""
        return [None if pose is None else accepted_view(view.frame_index, view_detection(view), pose)
                for view, pose in zip(views, self._poses_under(views, camera), strict=True)]

    def _poses_under(self, views: Sequence[View], camera: CameraModel) -> list[BoardPose | None]:
        """Each view's board pose under `camera`, kept for the next call with the same camera (the
        look-alike groups and the final coverage both ask it of the final solve's hundreds of views)."""
        known = self._final_poses if self._final_poses is not None and self._final_poses[0] is camera else (camera, {})
        self._final_poses = known
        new = [view for view in views if view.frame_index not in known[1]]
        for view, pose in zip(new, estimate_poses([view_detection(v) for v in new], camera, self.geometry.centre_m), strict=True):
            known[1][view.frame_index] = pose
        return [known[1][view.frame_index] for view in views]

    def _with_look_alikes_weighted(self, calibration: Calibration, groups: list[int]) -> Calibration:
        """The final covariance with each hold's look-alike frames counted for what they add.

        See `robust.with_look_alikes_weighted`; `groups` are the selector's look-alike test
        on the final solve's poses (`_look_alike_groups`).
        """
        weighted, self.look_alike_correlation = with_look_alikes_weighted(calibration, groups)
        return weighted

    def _final_coverage(self, calibration: Calibration) -> CoverageMap:
        """The coverage map again, with tilts and ranges from the final solve's intrinsics."""
        live = self.selector.coverage
        coverage = CoverageMap(self.image_size, live.requirements, ranges=ranges_for(calibration.camera, self.geometry),
                               reachable=live.reachable)
        for view, pose in zip(calibration.views, self._poses_under(calibration.views, calibration.camera), strict=True):
            coverage.add(coverage.contribution(view_detection(view), pose), pose.footprint if pose else None)
        return coverage

    def _not_enough_views_error(self) -> CalibrationError:
        counts = {k: v for k, v in self.selector.counts.items() if v and k != "accepted"}
        breakdown = ", ".join(f"{v} {k}" for k, v in sorted(counts.items(), key=lambda kv: -kv[1])) or (
            "none rejected: the source held too few frames" if self.frames_seen else "no frames at all")
        if self.frames_seen and counts.get("no board", 0) == self.frames_seen:
            # the live board watch's finding where it named one (1-2 s of detection not spent twice)
            mismatch = self.board_mismatch or diagnose_board_mismatch(self.board, self._samples)
            if mismatch is not None:
                return mismatch  # type: ignore[return-value]
            return CalibrationError(
                f"no board corners were found in any of the {self.frames_seen} frames, and at most a stray ArUco marker "
                f"or two of any dictionary; check that the images show the board ({self.board.describe()}), in focus and lit "
                "(a plain chessboard has no markers: print a ChArUco board with `calibcoach board --out board.pdf`)"
            )
        return CalibrationError(
            f"only {len(self.views)} of {self.frames_seen} frames were usable ({breakdown}); a calibration needs at least 3 "
            f"(and about 20 diverse ones to be trustworthy): capture the board still, close enough for >= {self.settings.selector.min_corners} corners"
        )
