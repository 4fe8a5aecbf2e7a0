"""The calibration session: one frame in, one decision out; the same for live cameras and replay.

`CalibrationSession.process(frame, detection)` runs pose estimation, the selector's gates and
coverage bookkeeping, solves incrementally as frames are accepted, and says when the stop rule is
met (coverage complete AND projection uncertainty below target). `finish()` runs the final robust
solve, chooses the model, maps the uncertainty and judges the result. Detection is done by the
caller (the replay runner detects ahead on worker threads; a live loop on the newest frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from calibcoach.app.solve.calibrate import pose_for_view, solve
from calibcoach.app.solve.model_choice import choose_model
from calibcoach.app.solve.result import Calibration, ModelChoice, UncertaintyMap, Verdict, View
from calibcoach.app.solve.robust import noise_sigma_px, robust_calibrate
from calibcoach.app.solve.uncertainty import (
    covariance_from_information,
    covered_region_mask,
    image_grid,
    information_gain,
    intrinsic_names,
    marginal_information,
    pixel_variance_weight,
    projection_jacobian,
    projection_sigma,
    projection_uncertainty,
    view_jacobian,
)
from calibcoach.app.solve.verdict import judge, uncertainty_target_px
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import Detection, diagnose_board_mismatch
from calibcoach.coverage.grid import CoverageMap, CoverageRequirements
from calibcoach.coverage.guidance import Guidance, next_guidance
from calibcoach.coverage.pose import BoardPose, estimate_pose
from calibcoach.coverage.select import (
    Decision,
    FrameSelector,
    SelectorSettings,
    board_motion_px,
    edge_blur_px,
)
from calibcoach.drivers.base import Frame
from calibcoach.drivers.errors import CalibrationError
from calibcoach.drivers.lens import MODELS, CameraModel

MIN_VIEWS_FOR_INCREMENTAL_SOLVE = 6
FULL_MODEL_VIEWS = 12  # below this the incremental solve uses the reduced bootstrap model
MIN_VIEWS_TO_STOP = 15  # never stop on fewer frames, however good they look
_SAMPLE_FRAMES_FOR_DIAGNOSIS = 6
_CHOICE_PER_BUDGET_FRAME = 1.5  # usable frames per budget frame below which a replay reads more
_MIN_FILL_GAIN = 0.002  # a reserve frame must cut the mean pixel variance by 0.2% to be worth solving with


def _view_of(frame: Frame, detection: Detection) -> View:
    return View(frame.index, frame.name, detection.ids.copy(), detection.corners_px.astype(np.float64),
                detection.object_points_m.astype(np.float64))


@dataclass(frozen=True, slots=True)
class SessionSettings:
    model: str = "auto"  # "auto" | "pinhole" | "rational" | "fisheye"
    selector: SelectorSettings = field(default_factory=SelectorSettings)
    hfov_guess_deg: float = 70.0  # bootstrap intrinsics for pose estimates before the first solve
    stop_when_done: bool = True
    uncertainty_target_px: float | None = None  # stop rule's p95 target; None = 0.05 px at 720p, scaled with the diagonal
    coverage: CoverageRequirements = field(default_factory=CoverageRequirements)
    use_motion_gate: bool = True  # off for folders of independent photos


@dataclass(frozen=True, slots=True)
class Progress:
    frames_seen: int
    frames_accepted: int
    coverage: float  # 0..1
    uncertainty_p95_px: float | None  # over the covered region; None before the first incremental solve
    uncertainty_target_px: float
    rejections: dict[str, int]
    done: bool


@dataclass(frozen=True, slots=True)
class FrameOutcome:
    frame_index: int
    frame_name: str
    detection: Detection
    pose: BoardPose | None
    decision: Decision
    blur_px: float | None
    motion_px_s: float | None
    guidance: Guidance
    progress: Progress
    camera: CameraModel  # the intrinsics the pose was estimated with (the bootstrap guess before any solve)
    coverage: CoverageMap  # the session's live map (shared, not a copy: read it before the next frame)


@dataclass(frozen=True, slots=True)
class SessionResult:
    calibration: Calibration
    model_choice: ModelChoice
    uncertainty: UncertaintyMap
    verdict: Verdict
    coverage: CoverageMap  # rebuilt from the final solve's poses
    board: BoardSpec  # with the print's legacy/inverted settled
    rejections: dict[str, int]
    frames_seen: int
    check_image: np.ndarray | None  # one accepted frame, for the undistortion check picture


class CalibrationSession:
    """Feeds frames through selection and incremental solving; see the module docstring."""

    def __init__(self, board: BoardSpec, image_size: tuple[int, int], settings: SessionSettings | None = None) -> None:
        # OpenCV's internal threads sum in a varying order, so calibrateCamera differs in the 9th digit
        # from run to run, and those digits tip frame decisions. calibcoach parallelises detection
        # itself; single-threaded OpenCV makes a replay reproduce a live session exactly.
        cv2.setNumThreads(1)
        self.settings = settings or SessionSettings()
        if self.settings.model not in ("auto", *MODELS):
            raise CalibrationError(f"unknown model {self.settings.model!r}; pass --model auto, pinhole, rational or fisheye")
        self.board = board
        self.image_size = image_size
        self.selector = FrameSelector(image_size, squares_x=board.squares_x, settings=self.settings.selector,
                                      coverage=CoverageMap(image_size, self.settings.coverage))
        self.views: list[View] = []
        self.camera = CameraModel.from_fov(image_size, self.settings.hfov_guess_deg)
        self.working_model = "pinhole" if self.settings.model == "auto" else self.settings.model
        self.uncertainty: UncertaintyMap | None = None
        self._information: np.ndarray | None = None  # (P, P) intrinsics' information, unit noise, poses marginalised
        self._pixel_weight: np.ndarray | None = None  # (P, P) turns a covariance into mean pixel variance
        self.target_px = self.settings.uncertainty_target_px or uncertainty_target_px(image_size)
        self.frames_seen = 0
        self._previous: tuple[Detection, int] | tuple[None, None] = (None, None)
        self._check_image: tuple[int, np.ndarray] | None = None
        self._samples: list[np.ndarray] = []  # a few frames kept for diagnosing a wrong board
        self._reserve: list[tuple[View, float]] = []  # usable frames not taken at the time, with their quality weight
        self.budget_fill: tuple[int, int] = (0, 0)  # (frames added at the end, candidates they came from)
        self._done = False
        self.accepting = True  # a live session turns this off when the focus drifts

    # --- per frame ------------------------------------------------------------------------------
    @property
    def done(self) -> bool:
        return self._done

    def short_of_choice(self, unread_repeats: int = 0) -> bool:
        """Too few usable frames for the final solve to choose its budget from (a hurried capture).

        The final solve takes the accepted frames and fills the budget from the reserve by
        information; with fewer than 1.5x the budget to choose from, any more usable frame helps.
        `unread_repeats`: usable frames a sparse replay passed over as repeats of a held board,
        which count as choice the capture offered.
        """
        usable = len(self.views) + len(self._reserve) + unread_repeats
        return usable < _CHOICE_PER_BUDGET_FRAME * self.settings.selector.max_frames

    def process(self, frame: Frame, detection: Detection, *, following: tuple[Detection, int] | None = None) -> FrameOutcome:
        """Decide about one frame (already detected) and update coverage and the incremental solve.

        `following` is the next frame's (detection, timestamp_ns) when the caller can look one
        frame ahead (replay always can): the board must then be still on both sides of the frame,
        which catches the first frame of a move, whose smear the backward difference cannot see.
        """
        if frame.image_size != self.image_size:
            decision = Decision(False, "no board", f"frame is {frame.image_size[0]}x{frame.image_size[1]}, session is "
                                f"{self.image_size[0]}x{self.image_size[1]}")
            return self._outcome(frame, detection, None, decision, None, None)
        self.frames_seen += 1
        if len(self._samples) < _SAMPLE_FRAMES_FOR_DIAGNOSIS and detection.corner_count == 0 and self.frames_seen % 5 == 1:
            self._samples.append(frame.grey())
        motion = self._motion_px_s(frame, detection, following)
        previous = self._previous[0]
        just_appeared = self.settings.use_motion_gate and previous is not None and previous.corner_count < 4
        self._previous = (detection, frame.timestamp_ns)
        pose = estimate_pose(detection, self.camera) if detection.corner_count >= self.settings.selector.min_corners else None
        gated = self.selector.gate(detection)
        if gated is None and not self.accepting:
            gated = Decision(False, "focus drift", "acceptance stopped: the lens moved since focus was locked", quality=0.0)
        blur = None
        if gated is None:
            blur = edge_blur_px(frame.grey(), detection.corners_px)
            decision, contribution = self.selector.decide(
                frame.index, detection, pose, motion_px_s=motion, blur_px=blur,
                uncertainty_gain=lambda: self._uncertainty_gain(detection, pose),
                just_appeared=just_appeared,
            )
        else:
            decision, contribution = gated, None
        self.selector.record(decision)
        if not decision.accepted and decision.quality > 0.05:
            self._reserve.append((_view_of(frame, detection), decision.quality))  # usable later: see _fill_budget
        if decision.accepted and contribution is not None:
            self.selector.commit(frame.index, detection, pose, contribution, blur_px=blur)
            self.views.append(_view_of(frame, detection))
            if self._check_image is None or detection.corner_count > self._check_image[0]:
                self._check_image = (detection.corner_count, frame.image)
            self._incremental_solve()
        return self._outcome(frame, detection, pose, decision, blur, motion)

    def _motion_px_s(self, frame: Frame, detection: Detection, following: tuple[Detection, int] | None) -> float | None:
        """Corner speed around this frame, px/s: the larger of the backward and forward differences."""
        if not self.settings.use_motion_gate:
            return None
        speeds = []
        for neighbour in (self._previous, following):
            if neighbour is None or neighbour[0] is None:
                continue
            other, t_other = neighbour
            moved = board_motion_px(other, detection)
            dt_s = abs(frame.timestamp_ns - t_other) / 1e9
            if moved is not None and dt_s > 0:
                speeds.append(moved / dt_s)
        return max(speeds) if speeds else None

    def _uncertainty_gain(self, detection: Detection, pose: BoardPose | None) -> float:
        """Relative drop of the mean pixel variance if this frame joined the solve (0 before any solve)."""
        if self._information is None or pose is None:
            return 0.0
        J_intr, J_pose = view_jacobian(self.camera, detection.object_points_m, pose.rvec, pose.tvec)
        if not (np.all(np.isfinite(J_intr)) and np.all(np.isfinite(J_pose))):
            return 0.0  # a pose the current model cannot project (an early, poor solve): no evidence either way
        try:
            _, drop = information_gain(self._information, J_intr, J_pose, weight=self._pixel_weight)
        except np.linalg.LinAlgError:
            return 0.0
        return drop

    def _incremental_solve(self) -> None:
        if len(self.views) < MIN_VIEWS_FOR_INCREMENTAL_SOLVE:
            return
        reduced = len(self.views) < FULL_MODEL_VIEWS
        try:
            raw = solve(self.views, self.image_size, self.working_model, reduced=reduced,
                        initial=self.camera if self.camera.model == self.working_model else None)
        except CalibrationError:
            return
        if self.settings.model == "auto" and self.working_model == "pinhole" and raw.camera.field_of_view_deg()[0] > 110.0:
            self.working_model = "fisheye"  # a pinhole model cannot follow this lens even for guidance
            try:
                raw = solve(self.views, self.image_size, "fisheye", reduced=reduced)
            except CalibrationError:
                return
        self.camera = raw.camera
        n_points = sum(v.ids.size for v in self.views)
        sigma = noise_sigma_px(raw.rms_px, n_points=n_points, n_params=len(intrinsic_names(raw.camera.model)), n_views=len(self.views))
        sigma = max(sigma, 0.05)  # floor: early solves fit their few frames too well
        self._information = marginal_information(raw.camera, self.views, raw.rvecs, raw.tvecs)
        gx, gy = image_grid(self.image_size, (16, 9))
        covered = covered_region_mask(self.image_size, [v.image_points_px for v in self.views], (gx.size, gy.size))
        # the rotation any extrinsic absorbs is fitted where the board was seen (see uncertainty.py)
        J = projection_jacobian(raw.camera, gx, gy, fit_mask=covered if covered.any() else None)
        self._pixel_weight = pixel_variance_weight(J)
        covariance = sigma**2 * covariance_from_information(self._information)
        self.uncertainty = UncertaintyMap(gx, gy, projection_sigma(J, covariance), covered)
        if (
            self.settings.stop_when_done
            and len(self.views) >= MIN_VIEWS_TO_STOP
            and self.selector.coverage.is_complete()
            and self.uncertainty.p95_covered_px <= self.target_px
        ):
            self._done = True

    def progress(self) -> Progress:
        return Progress(
            frames_seen=self.frames_seen,
            frames_accepted=len(self.views),
            coverage=self.selector.coverage.completeness(),
            uncertainty_p95_px=None if self.uncertainty is None else self.uncertainty.p95_covered_px,
            uncertainty_target_px=self.target_px,
            rejections={k: v for k, v in self.selector.counts.items() if k != "accepted" and v},
            done=self._done,
        )

    def _outcome(self, frame: Frame, detection: Detection, pose: BoardPose | None, decision: Decision,
                 blur: float | None, motion: float | None) -> FrameOutcome:
        return FrameOutcome(frame.index, frame.name, detection, pose, decision, blur, motion,
                            next_guidance(self.selector.coverage), self.progress(), self.camera, self.selector.coverage)

    # --- the end --------------------------------------------------------------------------------
    def finish(self) -> SessionResult:
        """Final robust solve, model choice, uncertainty map and verdict."""
        if len(self.views) < 3 and len(self.views) + len(self._reserve) >= 3:
            # Too few distinct frames (a frontal-only capture, say): solve with the look-alikes anyway,
            # so the verdict can say what is wrong with the data instead of refusing to look.
            step = max(1, len(self._reserve) // 8)
            taken = self._reserve[::step][: self.settings.selector.max_frames]
            self.views = sorted(self.views + [v for v, _q in taken], key=lambda v: v.frame_index)
            self._reserve = [r for r in self._reserve if not any(r is t for t in taken)]
        if len(self.views) < 3:
            raise self._not_enough_views_error()
        self._fill_budget()
        if self.settings.model == "auto":
            choice = choose_model(self.views, self.image_size)
        else:
            choice = ModelChoice(self.settings.model, {}, f"{self.settings.model} model requested with --model")
        initial = self.camera if self.camera.model == choice.chosen else None
        calibration = robust_calibrate(self.views, self.image_size, choice.chosen, initial=initial)
        corner_sets = [v.image_points_px for v in calibration.views]
        grid = (32, 18) if self.image_size[0] >= self.image_size[1] else (18, 32)
        uncertainty = projection_uncertainty(
            calibration.camera, calibration.intrinsic_covariance, grid=grid,
            covered_mask_fn=lambda gx, gy: covered_region_mask(self.image_size, corner_sets, (gx.size, gy.size)),
        )
        coverage = self._final_coverage(calibration)
        verdict = judge(
            calibration,
            coverage_completeness=coverage.completeness(),
            coverage_missing=coverage.summary()["missing"],  # type: ignore[arg-type]
            uncertainty=uncertainty,
            image_size=self.image_size,
        )
        return SessionResult(
            calibration=calibration,
            model_choice=choice,
            uncertainty=uncertainty,
            verdict=verdict,
            coverage=coverage,
            board=self.board,
            rejections=dict(self.selector.counts),
            frames_seen=self.frames_seen,
            check_image=None if self._check_image is None else self._check_image[1],
        )

    def _fill_budget(self) -> None:
        """Spend the unused frame budget on the reserve frames that shrink the uncertainty most.

        During capture a frame must beat an average kept frame to be accepted, which keeps the
        guidance honest; but a solve on 60 well-chosen frames beats one on 30, so before the final
        solve the free budget is filled greedily by information gain (each pick updates the
        information matrix, so look-alikes of what is already in lose their value at once).
        """
        budget = self.settings.selector.max_frames - len(self.views)
        if budget <= 0 or not self._reserve:
            return
        if self._information is None:  # fewer frames than the incremental solve waits for
            try:
                raw = solve(self.views, self.image_size, self.working_model)
            except CalibrationError:
                return
            self.camera = raw.camera
            self._information = marginal_information(raw.camera, self.views, raw.rvecs, raw.tvecs)
        candidates: list[tuple[View, np.ndarray, np.ndarray]] = []
        for view, quality in self._reserve:
            pose = pose_for_view(self.camera, view)
            if pose is not None:
                # a frame of quality q counts as if its corner noise were sigma / sqrt(q)
                J_intr, J_pose = (np.sqrt(quality) * J for J in view_jacobian(self.camera, view.object_points_m, *pose))
                if np.all(np.isfinite(J_intr)) and np.all(np.isfinite(J_pose)):
                    candidates.append((view, J_intr, J_pose))
        information = self._information
        added: list[View] = []
        while candidates and len(added) < budget:
            gains = [information_gain(information, Ji, Jp, weight=self._pixel_weight) for _v, Ji, Jp in candidates]
            best = int(np.argmax([g for _S, g in gains]))
            if gains[best][1] < _MIN_FILL_GAIN:
                break
            information = gains[best][0]
            added.append(candidates.pop(best)[0])
        self.budget_fill = (len(added), len(self._reserve))
        self.views = sorted(self.views + added, key=lambda v: v.frame_index)

    def _final_coverage(self, calibration: Calibration) -> CoverageMap:
        """The coverage map again, with tilts and distances from the final solve's poses."""
        coverage = CoverageMap(self.image_size, self.selector.coverage.requirements)
        for view in calibration.views:
            det = Detection(view.image_points_px.astype(np.float32), view.ids, view.object_points_m.astype(np.float32), np.zeros(0, np.int32))
            pose = estimate_pose(det, calibration.camera)
            coverage.add(coverage.contribution(det, pose), pose.footprint if pose else None)
        return coverage

    def _not_enough_views_error(self) -> CalibrationError:
        counts = {k: v for k, v in self.selector.counts.items() if v and k != "accepted"}
        breakdown = ", ".join(f"{v} {k}" for k, v in sorted(counts.items(), key=lambda kv: -kv[1])) or "no frames at all"
        if self.frames_seen and counts.get("no board", 0) == self.frames_seen:
            mismatch = diagnose_board_mismatch(self.board, self._samples)
            if mismatch is not None:
                return mismatch  # type: ignore[return-value]
            return CalibrationError(
                f"no board corners were found in any of the {self.frames_seen} frames, and no ArUco markers of any "
                f"dictionary either; check that the images show the board ({self.board.describe()}), in focus and lit "
                "(a plain chessboard has no markers: print a ChArUco board with `calibcoach board --out board.pdf`)"
            )
        return CalibrationError(
            f"only {len(self.views)} of {self.frames_seen} frames were usable ({breakdown}); a calibration needs at least 3 "
            "(and about 20 diverse ones to be trustworthy): capture the board still, close enough for >= 6 corners"
        )
