"""The calibration session: one frame in, one decision out; the same for live cameras and replay.

`CalibrationSession.process(frame, detection)` runs pose estimation, the selector's gates and
coverage bookkeeping; after each accepted frame it solves incrementally, re-reads the coverage
with the new intrinsics, recomputes the expected projection error E, re-ranks the candidate poses
for the guide (the next-best pose) and checks the stop rule: coverage complete and E at its
target, or diminishing returns, or the frame budget full. `finish()` (app/session_finish.py) runs
the final robust solve, chooses the model, maps the uncertainty and judges the result. Detection is done by the caller
(`calibcoach.Assistant`, which the replay and live loops use, looks one frame ahead).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from calibcoach.app.guide import Guide
from calibcoach.app.session_finish import (
    MIN_VIEWS_FOR_INCREMENTAL_SOLVE,
    SessionFinish,
    frame_view,
    view_detection,
)
from calibcoach.app.session_types import FrameOutcome, Progress, SessionSettings, lens_guess
from calibcoach.app.session_types import SessionResult as SessionResult  # re-exported: what finish() returns
from calibcoach.app.solve.calibrate import poses_for_views, reprojection_residuals
from calibcoach.app.solve.information import (
    covariance_from_information,
    intrinsic_names,
    marginal_information,
    view_jacobian,
)
from calibcoach.app.solve.next_view import RankedPose, error_cut, rank_poses
from calibcoach.app.solve.residual_structure import residual_patterns
from calibcoach.app.solve.result import UncertaintyMap, View
from calibcoach.app.solve.robust import noise_sigma_px
from calibcoach.app.solve.uncertainty import covered_region_mask, projection_uncertainty
from calibcoach.app.solve.verdict import error_target_px
from calibcoach.app.solve.working_model import live_solve
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.candidates import (
    CandidatePose,
    candidate_poses,
    corners_to_reach,
    lens_moved_px,
    ranges_for,
    reachable_cells,
)
from calibcoach.coverage.detector import Detection
from calibcoach.coverage.exposure import SmearLedger, velocities_across, worst_corner_speed_px_s
from calibcoach.coverage.grid import CoverageMap, region_grid_shape
from calibcoach.coverage.pose import BoardPose
from calibcoach.coverage.select import (
    Decision,
    FrameSelector,
    board_speed_px_s,
)
from calibcoach.coverage.sharpness import EdgeBlur, edge_blur
from calibcoach.coverage.virtual_view import BoardGeometry
from calibcoach.drivers.base import Frame
from calibcoach.drivers.errors import BoardError, CalibrationError
from calibcoach.drivers.geometry import pose_matrix
from calibcoach.drivers.lens import MODELS, CameraModel

FULL_MODEL_VIEWS = 12  # below this the incremental solve uses the reduced bootstrap model
MIN_VIEWS_TO_STOP = 15  # never stop on fewer frames: the model choice cross-validates two halves of >= 8
# Diminishing returns: stop once the best pose calibcoach could ask for would cut E by less than
# this. E falls about as 1 / sqrt(frames), so at a 3% cut per pose ten more poses (~20 s of a
# person's time) would buy less than a quarter; pose_calib stops each parameter at < 10% per frame.
# On the closed-loop simulator this came after 20-35 diverse frames, within about a minute.
DIMINISHING_CUT = 0.03
ACCEPT_SHARE = 0.5  # a frame without new coverage is kept when it cuts E by half what the best target would
MIN_ACCEPT_CUT = 0.005  # and by at least 0.5%
_SAMPLE_FRAMES_FOR_DIAGNOSIS = 6


# The candidate poses are rebuilt when the lens moved by more than this share of the image diagonal
# (at least _LENS_MOVED_MIN_PX) since they were built. Ranking projects the candidates through the
# current lens (their Jacobians, so what each would cut E by, are always current); only where their
# corners land (visible or not, which region cell) comes from the lens they were built with, and
# region cells are a sixth of the image wide: a shift of 1% of the diagonal (15 px at 720p) moves a
# handful of corners across a cell border. A fixed 2 px rebuilt them after most solves of a narrow
# lens seen in the middle only (pycamset's 25 deg cameras: the image corners, where nothing pins the
# distortion, moved 4-47 px from solve to solve), 0.38 s a time for a 20 x 20 board.
_LENS_MOVED_SHARE = 0.01
_LENS_MOVED_MIN_PX = 2.0

# Judged frames whose edge blur a replay's holds may borrow: a hold is settled as soon as the judged
# frame after it is, so only the last few are ever asked for; a live session runs for hours.
_JUDGED_BLUR_KEPT = 256


class CalibrationSession(SessionFinish):
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
        self.geometry = BoardGeometry.of(board)
        self.camera = lens_guess(image_size, self.settings.hfov_guess_deg)  # until the first solve
        self.selector = FrameSelector(image_size, squares_x=board.squares_x, settings=self.settings.selector,
                                      coverage=CoverageMap(image_size, self.settings.coverage,
                                                           ranges=ranges_for(self.camera, self.geometry)))
        self.views: list[View] = []
        self.working_model = "pinhole" if self.settings.model == "auto" else self.settings.model
        self.uncertainty: UncertaintyMap | None = None
        self._information: np.ndarray | None = None  # (P, P) intrinsics' information, unit noise, poses marginalised
        self._error_weight: np.ndarray | None = None  # (P, P) W: E^2 = sigma^2 trace(W S^-1) over the covered region
        self.noise_px: float | None = None  # corner noise per coordinate from the latest incremental solve
        self.frames_seen = 0
        self._previous: tuple[Detection, int] | None = None  # (detection, timestamp_ns) of the frame processed last
        # frame index -> (before, after): its neighbours in the footage, where a replay saw them (`note_neighbours`)
        self._neighbours: dict[int, tuple[tuple[Detection, int] | None, tuple[Detection, int] | None]] = {}
        self._check_image: tuple[int, Frame] | None = None
        self._samples: list[np.ndarray] = []  # a few frames kept for diagnosing a wrong board
        self.board_mismatch: BoardError | None = None  # ... or what the capture's board watch found (app/board_watch.py)
        self._reserve: list[tuple[View, float]] = []  # usable frames not taken at the time, with their quality weight
        # frame index -> `EdgeBlur.blur_px` of the last frames whose edges were measured (`hold_blur_px`)
        self._judged_blur: dict[int, float] = {}
        self._repeats: list[View] = []  # the final solve's repeats of held poses, added after the model choice
        self.budget_fill: tuple[int, int] = (0, 0)  # (frames added at the end, candidates they came from)
        self._candidates: list[CandidatePose] = []
        self._candidates_camera: CameraModel | None = None  # the intrinsics the candidates were built with
        self.guide = Guide(image_size, self.geometry.centre_m)
        self.stop_reason = ""
        self._recent: list[str] = []  # decisions of the last frames that showed a usable board
        self._board_hint = ""  # said while the incremental solve finds the board off its spec (`_check_board`)
        self._board_checked_at = 0  # views kept at the last check
        self.look_alike_correlation = 0.0  # residual correlation of look-alike frames in the final solve
        self._done = False
        self.focus_drift: str | None = None  # what moved, in words (app/focus_watch.py)
        # [start, end) frame indices taken at a drifted focus: left out of the final solve (end None: to the end)
        self.drifted_ranges: list[tuple[int, int | None]] = []
        self.smear = SmearLedger()  # each usable frame's corner speed and the exposure read off the frames
        self._refresh_lens()
        self._rank()

    # --- per frame ------------------------------------------------------------------------------
    @property
    def done(self) -> bool:
        return self._done

    @property
    def target_px(self) -> float | None:
        """The stop rule's target for E (px): given in the settings, else from the measured corner noise."""
        if self.settings.error_target_px is not None:
            return self.settings.error_target_px
        return None if self.noise_px is None else error_target_px(self.noise_px, self.image_size)

    @property
    def detection_lens(self) -> CameraModel:
        """The lens estimate to re-detect frames with (coverage/redetect.py): the latest solve, or
        before it the field-of-view guess (`SessionSettings.hfov_guess_deg`, --fov)."""
        return self.camera

    def add_held_repeats(self, repeats: Sequence[tuple[Frame, Detection]], *, usable: bool,
                         blur_px: Sequence[float | None] | None = None,
                         corner_speeds_px_s: Sequence[float | None] | None = None) -> None:
        """Frames a replay tracked through a hold instead of detecting them (app/scan.py).

        `usable`: the session judged a fully detected frame of the same hold usable (sharp, enough
        corners, not collinear), and each repeat was tracked as still on both sides. Such repeats
        join the reserve, from which the final solve takes them to average each pose's corner noise
        (`_fill_budget`); otherwise they are only counted as seen. `blur_px`: each repeat's edge blur
        where already known (`hold_blur_px`, or its own from `sharp_edges`), for the masked corners'
        margin; None entries are measured on the repeat's image. `corner_speeds_px_s`: each repeat's
        fastest corner's speed across it, by which the final solve judges its smear (`SmearLedger`).
        """
        for i, (frame, detection) in enumerate(repeats):
            self.frames_seen += 1
            if usable and detection.corner_count >= self.settings.selector.min_corners and not self._drifted(frame.index):
                self._reserve.append((self._view(frame, detection, blur_px=None if blur_px is None else blur_px[i]), 1.0))
                self.smear.record(frame.index, None if corner_speeds_px_s is None else corner_speeds_px_s[i])

    def hold_blur_px(self, frame_indices: Sequence[int | None]) -> float | None:
        """The edge blur measured on the first of `frame_indices` (a hold's judged frames) that had it measured.

        A held board's tracked frames show it at the judged frame's pose, a pixel or two away, with
        the same lens blur; and a repeat whose stillness is in doubt is measured on its own
        (`sharp_edges`). Measuring each repeat again took ~40% of a replay's session CPU (the
        masked corners only need the blur for the margin they keep from the markers' edges).
        """
        return next((self._judged_blur[i] for i in frame_indices if i is not None and i in self._judged_blur), None)

    def sharp_edges(self, frame: Frame, detection: Detection, *, motion_px_s: float | None) -> EdgeBlur | None:
        """A tracked frame's edge widths when its own image passes the selector's smear and blur tests
        (`FrameSelector.unsharp`), else None.

        `motion_px_s`: the board's median corner speed into and out of the frame (only a hint,
        as for detected frames, and ignored where the source has no motion gate: photo folders).
        """
        edges = edge_blur(frame.grey(), detection.corners_px, detection.object_points_m)
        self.selector.note_sharpness(edges)
        motion = motion_px_s if self.settings.use_motion_gate else None
        return edges if self.selector.unsharp(motion_px_s=motion, blur_px=edges.sharp_px, edges=edges) is None else None

    def process(self, frame: Frame, detection: Detection, *, following: tuple[Detection, int] | None = None,
                in_transit: bool = False) -> FrameOutcome:
        """Decide about one frame (already detected) and update coverage and the incremental solve.

        `in_transit`: the replay's scan saw the scene change fast into and out of this frame of
        footage (app/scan.py); such a frame is rejected as moving whatever its edges say.

        `following` is the next frame's (detection, timestamp_ns) when the caller can look one
        frame ahead (replay always can): the board's speed at the frame is then measured across it
        (`_motion_px_s`), which sees the first frame of a move, whose smear the backward
        difference cannot, and a swing's turn, which moves before and after but not at the frame.
        """
        if frame.image_size != self.image_size:
            decision = Decision(False, "no board", f"frame is {frame.image_size[0]}x{frame.image_size[1]}, session is "
                                f"{self.image_size[0]}x{self.image_size[1]}")
            return self._outcome(frame, detection, None, decision, None, None)
        self.frames_seen += 1
        if len(self._samples) < _SAMPLE_FRAMES_FOR_DIAGNOSIS and detection.corner_count == 0 and self.frames_seen % 5 == 1:
            self._samples.append(frame.grey())
        here = (detection, frame.timestamp_ns)
        before, after = self._neighbours.pop(frame.index, (self._previous, following))
        velocities = velocities_across(here, before, after)
        motion = self._motion_px_s(here, before, after, velocities)
        self.smear.saw(frame.index, frame.timestamp_ns)
        just_appeared = self.settings.use_motion_gate and self._previous is not None and self._previous[0].corner_count < 4
        self._previous = here
        pose = self._pose(detection) if detection.corner_count >= self.settings.selector.min_corners else None
        gated = self.selector.gate(detection)
        if gated is None and in_transit:
            gated = Decision(False, "moving", "in transit: the scene changed fast before and after it", quality=0.0)
        if gated is None and self._drifted(frame.index):
            gated = Decision(False, "focus drift", "acceptance stopped: the lens moved since focus was locked", quality=0.0)
        if gated is None and self._done:
            gated = Decision(False, "frame limit", f"capture complete ({self.stop_reason})", quality=0.0)
        blur, edges = None, None
        if gated is None:
            edges = edge_blur(frame.grey(), detection.corners_px, detection.object_points_m)
            blur = edges.sharp_px
            self.smear.reader.add(edges, velocities)
            self._judged_blur[frame.index] = edges.blur_px
            if len(self._judged_blur) > _JUDGED_BLUR_KEPT:
                del self._judged_blur[next(iter(self._judged_blur))]  # the oldest: its holds have been settled
            best = self.guide.best
            needed = max(MIN_ACCEPT_CUT, ACCEPT_SHARE * (best.error_cut if best is not None else 0.0))
            decision, contribution = self.selector.decide(
                frame.index, detection, pose, motion_px_s=motion, blur_px=blur, edges=edges,
                uncertainty_gain=lambda: self._error_cut(detection, pose), uncertainty_needed=needed,
                just_appeared=just_appeared,
            )
        else:
            decision, contribution = gated, None
        self.selector.record(decision)
        if decision.accepted or decision.quality >= 1.0:  # may enter the final solve, unless it smeared (`finish`)
            self.smear.record(frame.index, worst_corner_speed_px_s(velocities))
        if not decision.accepted and decision.quality >= 1.0:
            self._reserve.append((self._view(frame, detection, edges), decision.quality))  # usable later: see _fill_budget
        if decision.accepted and contribution is not None:
            self.selector.commit(frame.index, detection, pose, contribution, blur_px=blur)
            self.views.append(self._view(frame, detection, edges))
            if self._check_image is None or detection.corner_count > self._check_image[0]:
                self._check_image = (detection.corner_count, frame)  # its colour is decoded for the picture at the end
            self._update_after_accept()
        self.guide.observe(frame.timestamp_ns, pose, accepted=len(self.views))
        return self._outcome(frame, detection, pose, decision, blur, motion)

    def _view(self, frame: Frame, detection: Detection, edges: EdgeBlur | None = None, *, blur_px: float | None = None) -> View:
        """The frame as the solver takes it, its corners also refined on the checker's edges unless --corners
        opencv or a fisheye working model (`SessionFinish._refines_views`)."""
        return frame_view(frame, detection, self.board, refine=self._refines_views, edges=edges, blur_px=blur_px)

    def _motion_px_s(self, here: tuple[Detection, int], before: tuple[Detection, int] | None,
                     after: tuple[Detection, int] | None, velocities: np.ndarray | None) -> float | None:
        """Corner speed at this frame, px/s: the median of its corners' `velocities` (across it from
        the frame before to the one after where both show the board, else one-sided:
        `velocities_across`), else, where those do not tell (the board jumped more than a
        neighbour's limit, or shares too few corners), the median corner move across or the
        larger one-sided one; None: unknown. Each (detection, timestamp_ns) of `here` and the
        neighbours `before` and `after` (None: not seen).

        The neighbours are the frames either side of this one in the footage: those judged before
        and after it live, those a replay saw around it where it judges only some
        (`note_neighbours`), since the frames it judged may lie a hold or a skipped transit away,
        across which a swing read 2-3x its speed at the frame (a messy 720p render: 176-291 px/s,
        and a frame between two skipped ones 2000 px/s, where the neighbours gave 62-87; sharp
        frames were rejected as in transit that `--every-frame` kept).

        An exposure centred on the frame's time smears by its speed there times the exposure, and
        the central difference estimates that speed to second order. The larger of the backward and
        forward differences (used before) read a board at the turn of a swing -- still for an
        instant, moving before and after -- as moving fast: on a messy 720p render (MJPG video)
        it rejected 17 of the 43 frames whose corners moved less than 1.5 px in the exposure by the
        truth, and the capture was refused. At the start of a move (still before, moving after)
        the central difference is half the forward one, as the exposure's second half smears and
        its first does not. Rolling-shutter skew grows with the same speed, which the transit veto
        (`SelectorSettings.transit_speed_px_s`) still bounds.
        """
        if not self.settings.use_motion_gate:
            return None
        if velocities is not None:
            return float(np.median(np.linalg.norm(velocities, axis=1)))
        if before is not None and after is not None:
            across = board_speed_px_s(*before, *after)
            if across is not None:
                return across
        speeds = [board_speed_px_s(*other, *here) for other in (before, after) if other is not None]
        known = [v for v in speeds if v is not None]
        return max(known) if known else None

    def note_neighbours(self, index: int, before: tuple[Detection, int] | None, after: tuple[Detection, int] | None) -> None:
        """The frames either side of frame `index` in the footage ((detection, timestamp_ns); None: not
        seen, e.g. skipped in transit), from a replay that judges only some frames: its speed and
        smear are measured across them rather than across the frames judged before and after it."""
        self._neighbours[index] = (before, after)
        if len(self._neighbours) > 64:  # noted for frames never judged (a replay cut short): the oldest go
            del self._neighbours[next(iter(self._neighbours))]

    def _error_cut(self, detection: Detection, pose: BoardPose | None) -> float:
        """Relative cut of E if this frame joined (0 when there is nothing to compare with yet)."""
        if self._information is None or self._error_weight is None or pose is None \
                or len(self.views) < MIN_VIEWS_FOR_INCREMENTAL_SOLVE:
            return 0.0  # before the first solve the full model's information is rank deficient: coverage decides
        J_intr, J_pose = view_jacobian(self.camera, detection.object_points_m, pose.rvec, pose.tvec)
        if not (np.all(np.isfinite(J_intr)) and np.all(np.isfinite(J_pose))):
            return 0.0  # a pose the current model cannot project (an early, poor solve): no evidence either way
        try:
            return error_cut(self._information, self._error_weight, J_intr, J_pose)[1]
        except np.linalg.LinAlgError:
            return 0.0

    # --- after a frame is accepted ----------------------------------------------------------------
    def _update_after_accept(self) -> None:
        """Solve, re-read the coverage with the new intrinsics, re-rank the next poses, check the stop rule."""
        rvecs_tvecs = self._incremental_solve()
        if rvecs_tvecs is None:  # no solve yet: the poses the bootstrap intrinsics give
            poses = poses_for_views(self.camera, self.views)
            if any(p is None for p in poses):
                return
            rvecs = np.array([p[0] for p in poses])  # type: ignore[index]
            tvecs = np.array([p[1] for p in poses])  # type: ignore[index]
        else:
            rvecs, tvecs = rvecs_tvecs
            self._check_board(rvecs, tvecs)
        self._refresh_lens()
        self._information = marginal_information(self.camera, self.views, rvecs, tvecs)
        covariance = (self.noise_px or 1.0) ** 2 * covariance_from_information(self._information)
        corner_sets = [v.image_points_px for v in self.views]
        self.uncertainty = projection_uncertainty(
            self.camera, covariance,
            covered_mask_fn=lambda gx, gy: covered_region_mask(self.image_size, corner_sets, (gx.size, gy.size)),
        )
        self._error_weight = self.uncertainty.error_weight
        self._rank()
        self._check_stop()

    def _incremental_solve(self) -> tuple[np.ndarray, np.ndarray] | None:
        if len(self.views) < MIN_VIEWS_FOR_INCREMENTAL_SOLVE:
            return None
        try:
            raw, self.working_model = live_solve(self.views, self.image_size, self.working_model,
                                                 reduced=len(self.views) < FULL_MODEL_VIEWS, may_switch=self.settings.model == "auto",
                                                 initial=self.camera)
        except CalibrationError:
            return None
        if raw is None:
            return None
        self.camera = raw.camera
        n_points = sum(v.ids.size for v in self.views)
        self.noise_px = noise_sigma_px(raw.rms_px, n_points=n_points, n_params=len(intrinsic_names(raw.camera.model)),
                                       n_views=len(self.views))
        return raw.rvecs, raw.tvecs

    def _check_board(self, rvecs: np.ndarray, tvecs: np.ndarray) -> None:
        """Tell the person early when the board is off its spec (`residual_structure`): no capture fixes it.

        Checked on the full model's solves, each time the kept views have grown by a quarter (at 12,
        15, 19, 24, ... views: ~1-5 ms each). Frames kept live are never look-alikes of each other,
        so each view is a pose of its own.
        """
        n = len(self.views)
        if n < FULL_MODEL_VIEWS or n < 1.25 * self._board_checked_at:
            return
        self._board_checked_at = n
        residuals = reprojection_residuals(self.camera, self.views, rvecs, tvecs)
        board = residual_patterns(self.camera, self.views, rvecs, tvecs, residuals, range(n))
        self._board_hint = (
            f"The board is off its spec: the same corners come out {board.board_rms_mm * 1000:.0f} um off in every pose. "
            "Check that it lies flat and that its squares measure what was given (--square-mm); more frames will not "
            "fix it." if board.board.flagged else "")

    def _refresh_lens(self) -> None:
        """New intrinsics: candidate poses, ranges, reachable regions, and the map re-read from the kept frames.

        The candidates (~0.15 s to build at the default board, ~0.4 s at 20 x 20 squares) are rebuilt
        only when the lens model moved by more than `_LENS_MOVED_SHARE` of the diagonal anywhere in the
        image: later solves refine the intrinsics by fractions of a pixel, which change neither which
        poses register nor where the board would be.
        """
        ranges = ranges_for(self.camera, self.geometry)
        moved_limit = max(_LENS_MOVED_MIN_PX, _LENS_MOVED_SHARE * float(np.hypot(*self.image_size)))
        if self._candidates_camera is None or lens_moved_px(self._candidates_camera, self.camera) > moved_limit:
            self._candidates = candidate_poses(self.camera, self.geometry, ranges)
            self._candidates_camera = self.camera
        old = self.selector.coverage
        reachable = reachable_cells(self._candidates, self.image_size, region_grid_shape(self.image_size),
                                    corners_to_reach(old.requirements.corners_per_region_cell, self.board.corner_count))
        self.selector.coverage = CoverageMap(self.image_size, old.requirements, ranges=ranges, reachable=reachable)
        for view in self.views:
            det = view_detection(view)
            pose = self._pose(det)
            self.selector.coverage.add(self.selector.coverage.contribution(det, pose), pose.footprint if pose else None)

    def _rank(self) -> None:
        information = self._information
        weight = self._error_weight
        if information is None or weight is None or not self.views:
            # Nothing seen yet: ask for the easiest view, the board facing the camera at the centre, mid range.
            first = [c for c in self._candidates if c.key[0] == 2 and c.key[1] == 1 and c.key[2] == 0 and c.key[3] == "mid"]
            self.guide.update([RankedPose(c, 1.0, 0.0, 1.0) for c in first], self.camera, accepted=len(self.views))
            return
        ranking = rank_poses(self.camera, information, weight, self._candidates, self.selector.coverage,
                             board_centre_m=self.geometry.centre_m, excluded=self.guide.failed,
                             use_error=len(self.views) >= MIN_VIEWS_FOR_INCREMENTAL_SOLVE)
        self.guide.update(ranking, self.camera, accepted=len(self.views))

    def _check_stop(self) -> None:
        """Coverage complete and E at its target, or nothing left worth asking for, or the budget full."""
        if not self.settings.stop_when_done or self.uncertainty is None:
            return
        n = len(self.views)
        if n >= self.settings.selector.max_frames:
            self._stop(f"the frame budget ({self.settings.selector.max_frames}) is full")
            return
        if n < MIN_VIEWS_TO_STOP or self.noise_px is None:
            return
        E, target = self.uncertainty.expected_error_px, self.target_px
        complete = self.selector.coverage.is_complete()
        best = self.guide.best
        if complete and target is not None and E <= target:
            self._stop(f"coverage complete and E {E:.3f} px within its {target:.3f} px target")
        elif best is None or (best.coverage_gain <= 0.0 and best.error_cut < DIMINISHING_CUT):
            cut = 0.0 if best is None else best.error_cut
            self._stop(f"diminishing returns: the best next pose would cut E ({E:.3f} px) by only {cut * 100:.1f}%")

    def _stop(self, reason: str) -> None:
        self._done, self.stop_reason = True, reason

    def stop_accepting(self, first_bad_index: int, detail: str) -> None:
        """The focus moved: accept nothing more, and leave frames from `first_bad_index` on out of the solve."""
        self.focus_drift = detail
        self.drifted_ranges.append((int(first_bad_index), None))

    def accept_again(self, *, from_index: int) -> None:
        """Focus is back at the locked value (a resumed capture): accept frames from `from_index` on."""
        if self.drifted_ranges and self.drifted_ranges[-1][1] is None:
            self.drifted_ranges[-1] = (self.drifted_ranges[-1][0], int(from_index))

    @property
    def accepting(self) -> bool:
        """False from a focus drift on, until a resumed capture at the recorded lock accepts again."""
        return not (self.drifted_ranges and self.drifted_ranges[-1][1] is None)

    def progress(self) -> Progress:
        best = self.guide.best
        return Progress(
            frames_seen=self.frames_seen,
            frames_accepted=len(self.views),
            coverage=self.selector.coverage.completeness(),
            expected_error_px=None if self.uncertainty is None or self.noise_px is None else self.uncertainty.expected_error_px,
            target_px=self.target_px,
            uncertainty_p95_px=None if self.uncertainty is None or self.noise_px is None else self.uncertainty.p95_covered_px,
            best_next_cut=None if best is None or not self.views else best.error_cut,
            rejections={k: v for k, v in self.selector.counts.items() if k != "accepted" and v},
            done=self._done,
            stop_reason=self.stop_reason,
        )

    def _outcome(self, frame: Frame, detection: Detection, pose: BoardPose | None, decision: Decision,
                 blur: float | None, motion: float | None) -> FrameOutcome:
        centre = None
        if pose is not None:
            px = self.camera.project((pose_matrix(pose.rvec) @ self.geometry.centre_m + pose.tvec).reshape(1, 3))[0]
            centre = px if np.all(np.isfinite(px)) else None
        return FrameOutcome(frame.index, frame.name, detection, pose, decision, blur, motion,
                            self.guide.guidance(done=self._done, hint=self._holding_hint(decision)), self.progress(),
                            self.camera, self.selector.coverage, centre)

    def _holding_hint(self, decision: Decision) -> str:
        """Say how to hold the board when most recent frames with a board were smeared or soft (or that
        the board itself is off its spec, `_check_board`).

        Over the last 30 frames that showed a usable board: more than 60% "moving" means the hand
        is not still during the exposure; more than 60% "blurred", the focus or the light.
        """
        if decision.reason not in ("no board", "too few corners", "collinear"):
            self._recent.append(decision.reason)
            del self._recent[:-30]
        if self._board_hint or len(self._recent) < 15:  # a board off its spec comes first: holding it better will not help
            return self._board_hint
        share = {r: self._recent.count(r) / len(self._recent) for r in ("moving", "blurred")}
        if share["moving"] > 0.6:
            return ("Most frames are smeared: hold the board still for a second at each pose (rest your elbows); "
                    "more light lets the camera use a shorter exposure.")
        if share["blurred"] > 0.6:
            return "Most frames are soft: check the focus (lock it where the board is held) and add light."
        return ""
