"""Frame selection: keep a frame only when it is usable and adds something; count every rejection.

Gates, cheapest first (each rejection is counted with its reason):
1. at least 6 ChArUco corners (the method's minimum);
2. not collinear: the corners span at least two board rows and two columns and a real area;
3. still: the board did not smear during the exposure by more than `max_smear_px`, as measured in
   the frame itself (`sharpness.py`: the blur of the edges across the motion against the blur of
   the edges along it). A hand's jitter between frames (a pixel or two) is no harm; a board in
   transit is. Inter-frame corner speed is only a hint, used while the camera's own sharpness is
   not yet known (the first three kept frames), when a smear along a board diagonal cannot be seen;
4. sharp: the estimated edge blur is below `max_blur_px` and twice the camera's own;
5. diverse: not a near-duplicate of an accepted frame, and it fills unmet coverage or shrinks the
   calibration's uncertainty. Twenty look-alike frames are worse than ten diverse ones.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from calibcoach.coverage.detector import MIN_FRAME_CORNERS, Detection, shared_corners
from calibcoach.coverage.grid import Contribution, CoverageMap
from calibcoach.coverage.pose import BoardPose
from calibcoach.coverage.sharpness import EdgeBlur

_SEEN_FOR_SHARPNESS = 8  # frames with a board judged before their sharpness stands in for the camera's own

REJECT_REASONS = ("no board", "too few corners", "collinear", "moving", "blurred", "duplicate", "adds nothing", "frame limit",
                  "focus drift")


@dataclass(frozen=True, slots=True)
class SelectorSettings:
    min_corners: int = MIN_FRAME_CORNERS
    min_spread: float = 0.25  # minor/major principal spread of the corners on the board; 0 = a line
    # Smear within the exposure, px, as a frame's own edges show it (live). Measured first on renders
    # that drew a smear under ~4 px as a sharp frame ("up to 3 px corners keep their accuracy"); on
    # renders that smear every motion they keep it to 8 px at normal light and lose 5-13% in low light
    # (`max_solve_smear_px`). 1.5 px leaves that margin for what renders lack (acceleration during
    # the exposure, rolling shutter), and lies above the measure's own scatter (~0.5 px) on still frames.
    max_smear_px: float = 1.5
    # ... counted only where it widens the edges by more than this over their reference: the edge
    # width measure scatters by ~5% between frames of one camera (3 sigma), and a smear that widens
    # a soft image's edges by less changes its corners by less than that.
    min_smear_widening: float = 1.15
    # The smear no frame of the final solve may have, read at its end from each frame's fastest
    # corner's speed times the exposure read off the whole capture (coverage/exposure.py). Measured
    # on renders that smear every motion over ~1 px (bench/results/smear_corners.md, 15 renders): a
    # frame's corners after a pose fit under the true lens keep the residuals of still frames up to
    # 4 px of smear (0.67-1.16x; the smear averages noise away at normal light); past 4 px low light
    # loses 6-27% and one shaky render 18-51%. Leaving out everything over 1.5 px cost accuracy on
    # long-exposure shaky renders (bench/results/smear_filter_1.5px.md: the frames carry poses the
    # solve needs); at 4 px, 0-7 frames a render, 0.99x the error over 36 renders.
    max_solve_smear_px: float = 4.0
    # The speed hint until the camera's own sharpness is known, at 1280 px width (scaled): 0.5 px
    # of smear in a 20 ms exposure. Only for the first three kept frames.
    max_speed_px_s: float = 25.0
    # Above this corner speed a frame is in transit whatever its edges say, at 1280 px width
    # (scaled): 7x the median of a real handheld video (11 px/s at 720p, shared/notes/guidance.md),
    # near the p95 of the simulator's shaky hand (4x real). On the closed-loop simulator, frames
    # at 100-140 px/s that the smear measure let through, taken into the final solve, tripled the
    # true error of one webcam capture (0.024 -> 0.081 px); a rolling shutter would skew them too.
    transit_speed_px_s: float = 80.0
    max_blur_px: float = 3.0  # estimated gaussian edge blur, px, whatever the other frames look like
    max_blur_ratio: float = 2.0  # and at most this multiple of the median blur of the frames kept so far
    min_coverage_gain: float = 0.0015  # share of the whole coverage map a frame must add
    min_uncertainty_gain: float = 0.02  # relative drop of the intrinsics' variance a frame must bring
    duplicate_centre: float = 0.06  # fraction of the image diagonal
    duplicate_footprint: float = 0.15  # relative footprint difference
    duplicate_tilt_deg: float = 8.0
    max_frames: int = 60
    keep_all_usable: bool = False  # a set of deliberate photos that fits the budget: keep every usable one


@dataclass(frozen=True, slots=True)
class Decision:
    accepted: bool
    reason: str  # "accepted" or one of REJECT_REASONS
    detail: str = ""  # numbers behind the reason, e.g. "4 corners" or "41 px/s"
    coverage_gain: float = 0.0
    uncertainty_gain: float = 0.0
    quality: float = 1.0  # weight of the frame's corners should it be used after all (0 = useless)


@dataclass(frozen=True, slots=True)
class AcceptedView:
    frame_index: int
    centre_px: np.ndarray  # (2,) float64
    footprint: float
    tilt_x_deg: float
    tilt_y_deg: float


def corner_spread(detection: Detection) -> float:
    """Minor over major standard deviation of the corners on the board: 0 for a line, ~1 for a square patch.

    Measured in board coordinates, not pixels, so perspective cannot make a line of corners look
    like an area. Five corners down one column plus one beside it score ~0.15: such a view has
    an ill-defined pose, and one of them was seen to send OpenCV's calibrateCamera from RMS 0.07 to
    RMS 60 on an otherwise clean 32-view solve.
    """
    pts = detection.object_points_m[:, :2].astype(np.float64)
    if pts.shape[0] < 3:
        return 0.0
    s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    return float(s[1] / max(s[0], 1e-9))


def spans_rows_and_columns(detection: Detection, squares_x: int) -> bool:
    """True when the corner ids cover at least two board rows and two board columns."""
    per_row = squares_x - 1
    rows = np.unique(detection.ids // per_row)
    cols = np.unique(detection.ids % per_row)
    return rows.size >= 2 and cols.size >= 2


def board_motion_px(previous: Detection | None, current: Detection) -> float | None:
    """Median displacement of the corners both frames share, px; None when they share fewer than 4."""
    shared = None if previous is None else shared_corners(previous, current)
    if shared is None:
        return None
    ia, ib = shared
    return float(np.median(np.linalg.norm(previous.corners_px[ia] - current.corners_px[ib], axis=1)))


def board_speed_px_s(other: Detection | None, other_ns: int, current: Detection, current_ns: int) -> float | None:
    """`board_motion_px` between two frames over the time between them, px/s; None when unknown."""
    moved = None if other is None else board_motion_px(other, current)
    dt_s = abs(current_ns - other_ns) / 1e9
    return None if moved is None or dt_s <= 0 else moved / dt_s


class FrameSelector:
    """Decides frame by frame; owns the coverage map and the list of accepted views."""

    def __init__(
        self,
        image_size: tuple[int, int],
        *,
        squares_x: int,
        settings: SelectorSettings | None = None,
        coverage: CoverageMap,
    ) -> None:
        self.image_size = image_size
        self.settings = settings or SelectorSettings()
        self.squares_x = squares_x
        self.coverage = coverage
        self.accepted: list[AcceptedView] = []
        self.counts: dict[str, int] = dict.fromkeys(("accepted", *REJECT_REASONS), 0)
        self._diag = float(np.hypot(*image_size))
        self._blurs: list[float] = []  # edge blur of the frames kept, px
        self._seen_sharpness: list[float] = []  # sharper edge family of frames judged, until three are kept
        self._speed_limit = self.settings.max_speed_px_s * image_size[0] / 1280.0
        self._transit_limit = self.settings.transit_speed_px_s * image_size[0] / 1280.0

    def gate(self, detection: Detection) -> Decision | None:
        """The hard per-frame gates (1-2): frames failing them are of no use at all. None = passed."""
        s = self.settings
        if detection.corner_count == 0:
            return Decision(False, "no board", f"{detection.marker_ids.size} markers", quality=0.0)
        if detection.corner_count < s.min_corners:
            return Decision(False, "too few corners", f"{detection.corner_count} corners, need {s.min_corners}", quality=0.0)
        spread = corner_spread(detection)
        if spread < s.min_spread or not spans_rows_and_columns(detection, self.squares_x):
            return Decision(False, "collinear", f"spread {spread:.2f}", quality=0.0)
        return None

    @property
    def accepted_blurs(self) -> list[float]:
        """Edge blur (px) of every frame kept so far: this camera's own sharpness baseline."""
        return list(self._blurs)

    def own_sharpness_px(self) -> float | None:
        """This camera's sharpness: the median edge blur of the frames kept so far (None before three)."""
        if len(self._blurs) >= 3:
            return float(np.median(self._blurs))
        # Before three frames are kept, the sharpest of the frames seen with a board (5th percentile): every
        # capture holds the board still now and then, and waiting for kept frames instead let the
        # speed hint (below) reject a shaky hand's every frame -- no frame kept, so no reference,
        # so nothing kept (a 1080p capture at 20 fps with 2x tremor kept nothing for 80 frames).
        if len(self._seen_sharpness) >= _SEEN_FOR_SHARPNESS:
            return float(np.percentile(self._seen_sharpness, 5))
        return None

    def note_sharpness(self, edges: EdgeBlur | None) -> None:
        """A frame with a board had its edges measured: its sharper family counts towards this camera's
        sharpness until three frames are kept (`own_sharpness_px`). Judged frames (`decide`) and the
        frames a replay tracked and measured (`CalibrationSession.sharp_edges`) alike: a replay that
        judged only its fully detected frames learnt the camera's sharpness later than `--every-frame`
        and kept rejecting moving-looking frames on the speed hint alone meanwhile."""
        if edges is not None and np.isfinite(edges.sharp_px) and edges.sharp_px <= self.settings.max_blur_px \
                and len(self._blurs) < 3:
            self._seen_sharpness.append(float(edges.sharp_px))

    def blur_limit_px(self) -> float:
        """The blur a frame may show: absolute, or relative to this camera's own sharpness once known."""
        s = self.settings
        if len(self._blurs) >= 3:
            return min(s.max_blur_px, s.max_blur_ratio * float(np.median(self._blurs)))
        return s.max_blur_px

    def unsharp(self, *, motion_px_s: float | None, blur_px: float | None, edges: EdgeBlur | None) -> Decision | None:
        """Why the frame is not sharp enough for the final solve (smeared, moving, blurred), or None.

        The stillness and blur part of `decide`, also asked of the frames a replay tracked through
        a hold that moved more than the smear limit between frames (app/replay.py): their images,
        not their motion, then decide, as they would with every frame detected.
        """
        s = self.settings
        own = self.own_sharpness_px()
        if motion_px_s is not None and motion_px_s > self._transit_limit:
            return Decision(False, "moving", f"{motion_px_s:.0f} px/s: in transit (limit {self._transit_limit:.0f})",
                            quality=0.0)
        moving_hint = motion_px_s is not None and motion_px_s > self._speed_limit
        if edges is not None:
            along = edges.along_smear_px()
            if along > s.max_smear_px and edges.along_widening() > s.min_smear_widening:
                return Decision(False, "moving", f"smeared {along:.1f} px during the exposure, limit {s.max_smear_px:.1f}",
                                quality=0.0)
            if own is not None and moving_hint:  # a diagonal smear looks like defocus unless the board moved
                diagonal = edges.diagonal_smear_px(own)
                if diagonal > s.max_smear_px and edges.diagonal_widening(own) > s.min_smear_widening:
                    return Decision(False, "moving", f"smeared {diagonal:.1f} px along a board diagonal, limit "
                                    f"{s.max_smear_px:.1f} ({motion_px_s:.0f} px/s)", quality=0.0)
        if moving_hint and (own is None or edges is None or not np.isfinite(edges.sharp_px)):
            return Decision(False, "moving", f"{motion_px_s:.0f} px/s, limit {self._speed_limit:.0f} until this camera's "
                            "own sharpness is known", quality=0.0)
        blur_limit = self.blur_limit_px()
        if blur_px is not None and blur_px > blur_limit:
            return Decision(False, "blurred", f"edge blur {blur_px:.1f} px, limit {blur_limit:.1f}",
                            quality=(blur_limit / blur_px) ** 2)
        return None

    def decide(
        self,
        frame_index: int,
        detection: Detection,
        pose: BoardPose | None,
        *,
        motion_px_s: float | None,
        blur_px: float | None,
        edges: EdgeBlur | None = None,
        uncertainty_gain: Callable[[], float] | None = None,
        uncertainty_needed: float | None = None,
        just_appeared: bool = False,
    ) -> tuple[Decision, Contribution | None]:
        """Full decision for one frame; the caller commits accepted frames with `commit`.

        `uncertainty_gain` returns the relative cut of the expected error E the frame would bring;
        a frame without new coverage is kept when it reaches `uncertainty_needed` (the session
        asks for half of what its best target pose would bring, so a frame that does what the
        guidance asked is kept). Without it: 1.5 / (frames kept + 1), clearly more than an
        average kept frame's share.

        `edges` are the frame's edge widths (`sharpness.edge_blur`), from which the smear is read;
        None falls back on the speed alone.
        Smeared frames get quality 0: they never enter the final solve. Softly blurred frames keep
        a `quality` < 1 for the record; the final solve takes only frames of quality 1.
        """
        s = self.settings
        gated = self.gate(detection)
        if gated is not None:
            return gated, None
        if blur_px is not None and blur_px > s.max_blur_px:
            return Decision(False, "blurred", f"edge blur {blur_px:.1f} px, limit {s.max_blur_px:.1f}", quality=0.0), None
        if just_appeared:
            # The frame before showed no board: it is still being brought in, and a move's last frame
            # is smeared by the deceleration (0.4 px coherent corner shifts seen in simulation) while
            # the speed to the next frame already looks still.
            return Decision(False, "moving", "board just came into view", quality=0.25), None
        self.note_sharpness(edges)
        unsharp = self.unsharp(motion_px_s=motion_px_s, blur_px=blur_px, edges=edges)
        if unsharp is not None:
            return unsharp, None
        if len(self.accepted) >= s.max_frames:
            return Decision(False, "frame limit", f"{s.max_frames} frames kept already"), None
        contribution = self.coverage.contribution(detection, pose)
        cov_gain = self.coverage.gain(contribution)
        if s.keep_all_usable:
            return Decision(True, "accepted", f"usable photo, adds {cov_gain * 100:.1f}% coverage", cov_gain), contribution
        twin = self._duplicate_of(detection, pose)
        if twin is not None:
            # A look-alike of a kept frame re-counts the same corners in the same cells, and a repeat
            # of a view cuts the predicted error about as much as a new one would (averaging noise),
            # while it weights one pose over the others: twenty look-alikes are worse than ten
            # diverse frames. It is never kept live; the final solve may take it from the reserve.
            return Decision(False, "duplicate", f"looks like frame {twin}", cov_gain, quality=1.0), None
        if cov_gain >= s.min_coverage_gain:
            return Decision(True, "accepted", f"adds {cov_gain * 100:.1f}% coverage", coverage_gain=cov_gain), contribution
        # No new coverage (or a look-alike of a kept frame): keep it only if it cuts the expected
        # error by enough; look-alikes stop counting as soon as the data has them.
        unc_gain = uncertainty_gain() if uncertainty_gain is not None else 0.0
        needed = uncertainty_needed if uncertainty_needed is not None else max(s.min_uncertainty_gain, 1.5 / (len(self.accepted) + 1))
        if unc_gain >= needed:
            return Decision(True, "accepted", f"cuts the expected error by {unc_gain * 100:.0f}%", cov_gain, unc_gain), contribution
        return Decision(False, "adds nothing", f"coverage +{cov_gain * 100:.2f}%, expected error -{unc_gain * 100:.1f}% (needs {needed * 100:.1f}%)", cov_gain, unc_gain), None

    def record(self, decision: Decision) -> None:
        self.counts[decision.reason] = self.counts.get(decision.reason, 0) + 1

    def commit(self, frame_index: int, detection: Detection, pose: BoardPose | None, contribution: Contribution,
               *, blur_px: float | None = None) -> None:
        if blur_px is not None and np.isfinite(blur_px):
            self._blurs.append(blur_px)
        self.coverage.add(contribution, pose.footprint if pose is not None else None)
        if pose is not None:
            self.accepted.append(accepted_view(frame_index, detection, pose))
        else:
            centre = detection.corners_px.astype(np.float64).mean(axis=0)
            self.accepted.append(AcceptedView(frame_index, centre, 0.0, 0.0, 0.0))

    def _duplicate_of(self, detection: Detection, pose: BoardPose | None) -> int | None:
        if pose is None:
            return None
        here = accepted_view(-1, detection, pose)
        for view in self.accepted:
            if look_alike(view, here, self.settings, self._diag):
                return view.frame_index
        return None


def accepted_view(frame_index: int, detection: Detection, pose: BoardPose) -> AcceptedView:
    """What the look-alike test compares of a frame: corner centroid, footprint, tilts."""
    return AcceptedView(frame_index, detection.corners_px.astype(np.float64).mean(axis=0), pose.footprint,
                        pose.tilt_x_deg, pose.tilt_y_deg)


def look_alike(a: AcceptedView, b: AcceptedView, settings: SelectorSettings, diagonal_px: float) -> bool:
    """Two frames show the board at nearly the same place, size and tilt (one hold, say)."""
    return bool(_alike(a.centre_px, a.footprint, a.tilt_x_deg, a.tilt_y_deg,
                       b.centre_px, b.footprint, b.tilt_x_deg, b.tilt_y_deg, settings, diagonal_px))


def _alike(centre_a, footprint_a, tilt_x_a, tilt_y_a, centre_b, footprint_b, tilt_x_b, tilt_y_b,
           s: SelectorSettings, diagonal_px: float):
    """The look-alike test of earlier frame(s) a against frame(s) b; the arguments broadcast like
    numpy arrays (centres (..., 2)), so one frame pair and all pairs of a final solve share it."""
    return ((np.linalg.norm(np.asarray(centre_a) - np.asarray(centre_b), axis=-1) < s.duplicate_centre * diagonal_px)
            & (np.abs(np.subtract(footprint_a, footprint_b)) < s.duplicate_footprint * np.maximum(footprint_a, 1e-6))
            & (np.abs(np.subtract(tilt_x_a, tilt_x_b)) < s.duplicate_tilt_deg)
            & (np.abs(np.subtract(tilt_y_a, tilt_y_b)) < s.duplicate_tilt_deg))


def _stacked(looks: Sequence[AcceptedView | None]) -> tuple[np.ndarray, ...]:
    """(valid (n,), centre (n, 2), footprint, tilt_x, tilt_y (n,)) of frames; None (no pose) is not valid."""
    n = len(looks)
    valid = np.array([v is not None for v in looks], bool)
    known = [v if v is not None else AcceptedView(-1, np.zeros(2), 0.0, 0.0, 0.0) for v in looks]
    centre = np.array([v.centre_px for v in known], np.float64).reshape(n, 2)
    footprint, tilt_x, tilt_y = (np.array([getattr(v, name) for v in known], np.float64)
                                 for name in ("footprint", "tilt_x_deg", "tilt_y_deg"))
    return valid, centre, footprint, tilt_x, tilt_y


class LookAlikeTable:
    """`look_alike` between any two of a fixed list of frames, one frame against all others at a time.

    The final solve's budget fill asks it thousands of times among hundreds of frames; each frame
    asked about as the later one ("b") is compared with every frame at once and remembered, which
    keeps the memory to frames x frames asked about rather than frames squared. A frame without a
    pose (None) looks like nothing.
    """

    def __init__(self, looks: Sequence[AcceptedView | None], settings: SelectorSettings, diagonal_px: float) -> None:
        self._arrays = _stacked(looks)
        self._settings, self._diagonal = settings, diagonal_px
        self._against: dict[int, np.ndarray] = {}

    def __call__(self, a: int, b: int) -> bool:
        """look_alike(looks[a], looks[b])."""
        column = self._against.get(b)
        if column is None:
            valid, centre, footprint, tilt_x, tilt_y = self._arrays
            column = _alike(centre, footprint, tilt_x, tilt_y, centre[b], footprint[b], tilt_x[b], tilt_y[b],
                            self._settings, self._diagonal) & valid & valid[b]
            self._against[b] = column
        return bool(column[a])


def look_alike_groups(looks: list[AcceptedView | None], settings: SelectorSettings, diagonal_px: float) -> list[int]:
    """A group number per frame: frames that look alike (transitively, in order) share one.

    Each frame joins the group of the first earlier frame it looks alike (`look_alike`, tested
    for all pairs at once: a final solve has hundreds of frames). Frames without a pose (None)
    are a group of their own.
    """
    n = len(looks)
    valid, centre, footprint, tilt_x, tilt_y = _stacked(looks)
    # alike[j, i]: earlier frame j (the "a" of look_alike) and frame i
    alike = _alike(centre[:, None, :], footprint[:, None], tilt_x[:, None], tilt_y[:, None],
                   centre[None, :, :], footprint[None, :], tilt_x[None, :], tilt_y[None, :], settings, diagonal_px) \
        & valid[:, None] & valid[None, :]
    groups: list[int] = []
    for i in range(n):
        earlier = np.flatnonzero(alike[:i, i])
        groups.append(groups[int(earlier[0])] if earlier.size else i)
    return groups
