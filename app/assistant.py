"""The embedding API: drive a guided capture from a robot, a ROS node or a script.

    import calibcoach
    assistant = calibcoach.Assistant(board=calibcoach.BoardSpec(), image_size=(1280, 720), model="auto")
    for image, timestamp_ns in camera:
        step = assistant.feed(image, timestamp_ns)
        show(step.guidance.sentence, step.guidance.target)   # where the board should go next
        if step.progress.done:
            break
    result = assistant.finish()                               # camera_matrix, dist_coeffs, verdict ...

`feed` detects the board and decides one frame. It looks one frame ahead (the board must be still
on both sides of a frame, which catches the first frame of a move), so each step decides the
frame fed before; the very first call decides nothing (`frame_index` -1) and `finish` decides the
last. `calibcoach calibrate` and `calibcoach live` run on the same `Assistant` steps
(`feed_detected` when detection ran elsewhere, e.g. on worker threads).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from calibcoach.app.board_watch import BoardWatch
from calibcoach.app.focus_watch import RELOCK_EVENT, FocusEvent, FocusWatch
from calibcoach.app.session import CalibrationSession, FrameOutcome, SessionResult, SessionSettings
from calibcoach.app.solve.result import Verdict
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.coverage.guidance import Guidance, Target
from calibcoach.coverage.redetect import Redetector
from calibcoach.drivers.base import Frame

__all__ = ["Assistant", "Guidance", "Progress", "Result", "Step", "Target"]


@dataclass(frozen=True, slots=True)
class Progress:
    frames_accepted: int
    coverage: float  # 0..1 of what this lens can show
    expected_error_px: float | None  # E: expected projection error over the covered region; None before the first solve
    target_px: float | None  # the stop rule's target for E; None until the corner noise is measured
    done: bool  # the stop rule is met: call finish()
    stop_reason: str = ""


@dataclass(frozen=True, slots=True)
class Step:
    frame_index: int  # the frame this step decides (the one fed before; -1 on the first call)
    accepted: bool
    reason: str  # "accepted" or why not ("moving", "adds nothing", ...)
    detail: str  # the numbers behind the reason
    guidance: Guidance  # .sentence, .target (None only when done)
    progress: Progress
    outcome: FrameOutcome | None  # everything the session knows about the frame (corners, pose ...); None on the first call
    frame: Frame | None = None  # the frame decided (image, timestamp); None on the first call


@dataclass(frozen=True, slots=True)
class Result:
    camera_matrix: np.ndarray  # (3, 3) float64
    dist_coeffs: np.ndarray  # (5,) pinhole, (8,) rational, (4,) fisheye
    model: str  # "pinhole" | "rational" | "fisheye"
    image_size: tuple[int, int]  # (width, height)
    rms_px: float
    expected_error_px: float  # E of the final solve
    verdict: Verdict  # .grade, .trusted, .reasons
    session: SessionResult  # the full result (per-frame errors, coverage, uncertainty map ...) for the outputs


def step_record(outcome: FrameOutcome, timestamp_ns: int) -> dict:
    """One step as plain JSON types: what `calibcoach live --guidance-jsonl` writes per line."""
    g, p, d = outcome.guidance, outcome.progress, outcome.decision
    target = None
    if g.target is not None:
        t = g.target
        target = {"centre_px": [float(v) for v in t.centre_px], "rvec": t.rvec.tolist(), "tvec_m": t.tvec_m.tolist(),
                  "tilt_x_deg": t.tilt_x_deg, "tilt_y_deg": t.tilt_y_deg, "distance_m": t.distance_m,
                  "outline_px": t.outline_px.tolist()}
    return {
        "frame_index": outcome.frame_index, "timestamp_ns": int(timestamp_ns), "accepted": d.accepted, "reason": d.reason,
        "detail": d.detail, "guidance": {"sentence": g.sentence, "target": target, "why": g.why, "hint": g.hint},
        "progress": {"frames_accepted": p.frames_accepted, "coverage": p.coverage, "expected_error_px": p.expected_error_px,
                     "target_px": p.target_px, "done": p.done, "stop_reason": p.stop_reason},
    }


class Assistant:
    """A guided capture: feed frames, follow `step.guidance`, stop at `step.progress.done`, then `finish()`.

    Args:
        board: the printed board (default: 8 x 11, DICT_5X5_100, 30.01 / 22.01 mm).
        image_size: (width, height) of the frames that will be fed.
        model: "auto", "pinhole", "rational" or "fisheye" (default: the settings', "auto").
        settings: the full session settings, for what the arguments above do not cover.
        locked_controls: the focus controls read back after locking focus (a driver's per-frame
            reports are compared with them; see app/focus_watch.py). Empty: only softness is watched.
        focus_events: drift events a recording stored (replay applies them as the live session did).
        detector: the detector settling the print's variant when detection runs elsewhere (replay,
            live): frames are re-detected on a local view (coverage/redetect.py) with its board
            once settled. `feed` makes its own.
    """

    def __init__(self, board: BoardSpec | None = None, image_size: tuple[int, int] = (1280, 720), model: str | None = None,
                 *, settings: SessionSettings | None = None, locked_controls: Mapping[str, float] | None = None,
                 focus_events: Sequence[FocusEvent] = (), detector: CharucoBoardDetector | None = None) -> None:
        self.board = board or BoardSpec()
        base = settings or SessionSettings()
        if model is not None and model != base.model:
            base = replace(base, model=model)
        self.session = CalibrationSession(self.board, (int(image_size[0]), int(image_size[1])), base)
        self._detector = detector
        self.redetector: Redetector | None = None  # built once the print's variant is settled
        self._held: tuple[Frame, Detection, bool] | None = None
        self._count = 0
        self.last_outcome: FrameOutcome | None = None
        self.watch = FocusWatch(locked_controls)
        # says when the frames show some other board (mirrored, other size ...)
        self.board_watch = BoardWatch(self.session.settings.selector.min_corners)
        self._locked = dict(locked_controls or {})
        self._recorded_events = list(focus_events)  # in the order they happened

    @property
    def focus_drift(self) -> FocusEvent | None:
        """The drift that stopped acceptance (noticed here or stored in the recording), if any."""
        return self.watch.event

    def resume_accepting(self, *, from_index: int) -> FocusEvent | None:
        """A resumed capture at the recorded lock: accept frames from `from_index` on again.

        Frames ruled out by an earlier drift stay out of the final solve. Returns the relock event
        to store in the recording (None when nothing had drifted)."""
        if self.session.accepting:
            return None
        event = FocusEvent(from_index, from_index, "capture resumed at the recorded focus lock", RELOCK_EVENT)
        self._relock(event)
        return event

    def _relock(self, event: FocusEvent) -> None:
        self.watch = FocusWatch(self._locked, from_index=event.frame_index)
        self.session.accept_again(from_index=event.frame_index)

    # --- per frame --------------------------------------------------------------------------------
    def feed(self, image: np.ndarray, timestamp_ns: int) -> Step:
        """Detect the board in `image` ((H, W) uint8 grey or (H, W, 3) BGR) and decide the previous frame."""
        frame = Frame(index=self._count, timestamp_ns=int(timestamp_ns), image=image)
        if self._detector is None:
            self._detector = CharucoBoardDetector(self.board)
        return self.feed_detected(frame, self._detector.detect(frame.grey()))

    def feed_detected(self, frame: Frame, detection: Detection, *, in_transit: bool = False) -> Step:
        """`feed` for a frame whose detection is already known (frame.index as the source numbers it).

        `in_transit`: a replay's scan saw the board in transit (see `CalibrationSession.process`).
        Once the session is done, frames are still taken but decided as "frame limit"."""
        if self._detector is not None and self._detector.settled:
            self.session.board = self._detector.spec
        detection = self._redetected(frame, detection)
        self._count = frame.index + 1
        held, self._held = self._held, (frame, detection, in_transit)
        if held is None:
            return Step(-1, False, "waiting", "a step decides the frame before it (one frame of lookahead)",
                        self.session.guide.guidance(done=self.session.done), self._progress(), None)
        return self._decide(held, following=(detection, frame.timestamp_ns))

    def _redetected(self, frame: Frame, detection: Detection) -> Detection:
        """The frame's detection, re-detected on a local view where that can help (wide lenses).

        Here, on the thread that feeds the session in frame order, because the view needs the
        session's current lens estimate: a replay then re-detects exactly as the live run did.
        The estimate is the one from before the frame held for lookahead is decided (one frame
        behind), the same lag live and in replay; re-detecting here rather than when the frame is
        decided lets the lookahead's motion test compare re-detected corners on both sides.
        """
        if self._detector is None or not self._detector.settled or self.session.done:
            # the settled print (legacy/inverted) is what finds the same corners; once done, frames only count
            return detection
        if self.redetector is None or self.redetector.spec != self._detector.spec:
            self.redetector = Redetector(self._detector.spec)
        return self.redetector.improve(frame.index, frame.grey(), detection, self.session.detection_lens)

    def _decide(self, item: tuple[Frame, Detection, bool], *, following: tuple[Detection, int] | None) -> Step:
        frame, detection, in_transit = item
        while self._recorded_events and self._recorded_events[0].due(frame.index):  # as the live session did
            event = self._recorded_events.pop(0)
            if event.kind == RELOCK_EVENT:
                self._relock(event)
            elif self.watch.event is None:
                self._stop_accepting(event)
        outcome = self.session.process(frame, detection, following=following, in_transit=in_transit)
        event = self.watch.check(frame, outcome.blur_px, self.session.selector.accepted_blurs)
        if event is not None:
            self._stop_accepting(event)
        board_hint = self.board_watch.see(frame, detection, self.session.board)
        self.session.board_mismatch = self.board_watch.finding  # the end of a capture without the board says it, not diagnosing again
        if board_hint:  # no frame has shown the board: nothing the session could say about holding it applies
            outcome = replace(outcome, guidance=replace(outcome.guidance, hint=board_hint))
        self.last_outcome = outcome
        d = outcome.decision
        return Step(outcome.frame_index, d.accepted, d.reason, d.detail, outcome.guidance, self._progress(), outcome, frame)

    def _stop_accepting(self, event: FocusEvent) -> None:
        self.watch.event = event
        self.session.stop_accepting(event.first_bad_index, event.detail)

    def flush(self) -> Step | None:
        """Decide the frame still held for lookahead (the source ended); None when there is none."""
        held, self._held = self._held, None
        step = None if held is None or self.session.done else self._decide(held, following=None)
        self.board_watch.settle()  # a diagnosis still running: its answer is the capture's end's finding
        self.session.board_mismatch = self.board_watch.finding
        return step

    def _progress(self) -> Progress:
        p = self.session.progress()
        return Progress(p.frames_accepted, p.coverage, p.expected_error_px, p.target_px, p.done, p.stop_reason)

    @property
    def done(self) -> bool:
        return self.session.done

    # --- the end ----------------------------------------------------------------------------------
    def finish(self) -> Result:
        """Decide the last frame, then the final robust solve, model choice and verdict.

        Raises:
            calibcoach.drivers.errors.CalibrationError: too few usable frames to calibrate at all (the message says why).
        """
        self.flush()
        result = self.session.finish()
        cal = result.calibration
        return Result(
            camera_matrix=cal.camera.camera_matrix.copy(), dist_coeffs=cal.camera.dist_coeffs.copy(),
            model=cal.camera.model, image_size=cal.camera.image_size, rms_px=cal.rms_px,
            expected_error_px=result.uncertainty.expected_error_px, verdict=result.verdict, session=result,
        )
