"""Replay: run a recorded source through the session as fast as the machine allows.

Frames are decoded and detected (or tracked: app/scan.py) ahead on worker threads, one detector
per thread, while the session consumes them strictly in frame order, so the decisions are those
of a single-threaded run. Footage (videos, image folders) is scanned in a child process of its
own (app/scan_process.py, started by app/scan_stream.py), so the scan's Python and the
session's never wait for one GIL.
Replay stops reading as soon as the session's stop rule is met.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

from calibcoach.app.assistant import Assistant, Step
from calibcoach.app.focus_watch import FocusEvent, focus_events
from calibcoach.app.scan import Seen, board_shift_px
from calibcoach.app.scan_stream import ScanStream
from calibcoach.app.session import CalibrationSession, FrameOutcome, SessionSettings
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.coverage.exposure import velocities_across, worst_corner_speed_px_s
from calibcoach.coverage.redetect import RedetectionCounts
from calibcoach.coverage.select import board_speed_px_s
from calibcoach.drivers.base import Frame, FrameSource
from calibcoach.drivers.errors import SourceError


@dataclass(frozen=True, slots=True)
class ReplayStats:
    frames_read: int
    seconds: float
    stopped_early: bool  # the stop rule was met before the source ended
    interrupted: bool  # Ctrl-C: the session holds every frame accepted until then
    board: BoardSpec  # with legacy/inverted settled
    variant_found: str | None
    tracked: int = 0  # frames whose held board was tracked from the frame before instead of detected anew
    redetection: RedetectionCounts | None = None  # frames re-detected on a local view (wide lenses), None if none were


def run_replay(
    source: FrameSource,
    board: BoardSpec,
    settings: SessionSettings | None = None,
    *,
    workers: int = 2,
    on_outcome: Callable[[FrameOutcome, Frame], None] | None = None,
    every_frame: bool = False,
    in_child: bool = True,
    scan: ScanStream | None = None,
) -> tuple[CalibrationSession, ReplayStats]:
    """Feed the frames of `source` to a new session until the source ends or the stop rule is met.

    Held boards are tracked rather than detected anew (app/scan.py) unless `every_frame`; the
    tracked frames of a hold the session judged usable join its reserve for the final solve.
    Footage (folders, videos) is scanned in a child process beside the session
    (app/scan_process.py) unless `in_child` is False; the decisions are the same either way.
    `scan` is that scan when the caller started it already (app/commands.py starts it before the
    session's modules load); `workers`, `every_frame` and `in_child` are then the scan's own.
    The scan is closed when the reading ends.
    """
    info = source.info
    settings = settings or SessionSettings(use_motion_gate=info.kind != "folder")
    if scan is None:
        scan = ScanStream(source, board, workers=workers, every_frame=every_frame, in_child=in_child)
    settle = scan.settle
    feed = _Feeder(settle, settings, on_outcome, locked_controls=info.locked_controls,
                   focus_events=focus_events(info.events))
    feed.run(scan)
    tracked = scan.tracked
    session = feed.session
    if session is None:
        skipped = f" ({len(source.skipped)} unreadable: {source.skipped[0].reason})" if source.skipped else ""
        raise SourceError(f"{info.description} delivered no frames{skipped}; check the path and the file format")
    session.board = settle.spec
    redetector = None if feed.assistant is None else feed.assistant.redetector
    return session, ReplayStats(feed.read, time.perf_counter() - scan.started_at, feed.stopped, feed.interrupted, settle.spec,
                                settle.variant_found, tracked, None if redetector is None else redetector.counts)


@dataclass
class _Hold:
    """Frames tracked between two fully detected frames, waiting for the session's judgement of those."""

    before: int  # the fully detected frame before them
    after: int | None  # ... and after them (None until it comes)
    repeats: list[tuple[Frame, Detection, float]]  # (frame, tracked detection, shift since the frame before, px)
    speeds: list[float | None]  # each repeat's median corner speed since the frame before, px/s (None: unknown)
    shift_after: float = float("inf")  # shift from the last repeat to the frame after it, px
    speed_after: float | None = None  # ... and its median corner speed, px/s


class _Feeder:
    """Feeds scanned frames to one `Assistant` (which looks one frame ahead, like live).

    Fully detected frames go through the session's judgement; tracked frames wait until a fully
    detected frame of their hold (before or after them) has been judged, then join the reserve if
    the hold was usable and the board stood still on both sides of each (`_still_repeats`) or, where
    it moved more, the frame's own image shows it sharp (`CalibrationSession.sharp_edges`).
    Frames skipped in transit are only counted as seen.
    """

    def __init__(self, settle: CharucoBoardDetector, settings: SessionSettings,
                 on_outcome: Callable[[FrameOutcome, Frame], None] | None, *,
                 locked_controls: Mapping[str, float], focus_events: Sequence[FocusEvent]) -> None:
        self.settle, self.settings, self.on_outcome = settle, settings, on_outcome
        self.locked_controls, self.focus_events = locked_controls, focus_events
        self.assistant: Assistant | None = None
        self.read = 0
        self.stopped = self.interrupted = False
        self._holds: deque[_Hold] = deque()
        self._usable: dict[int, str] = {}  # fully detected frame -> "usable", "moving", "no board" or "unusable"
        self._last_full: Seen | None = None
        self._last_seen: Seen | None = None  # the frame before the one being fed
        self._two_before: Seen | None = None  # ... and the one before that
        self._corner_speeds: dict[int, float | None] = {}  # tracked frame -> its fastest corner's speed across it, px/s

    @property
    def session(self) -> CalibrationSession | None:
        return None if self.assistant is None else self.assistant.session

    def run(self, stream: Iterable[Seen]) -> None:
        """Feed `stream` until it ends or the stop rule is met, then close it (the scan ends)."""
        try:
            for seen in stream:
                self.read += 1
                before, self._last_seen = self._last_seen, seen
                self._two_before, two_before = before, self._two_before
                self._note_velocities(two_before, before, seen)
                if seen.skipped and self.session is not None:
                    self.session.add_held_repeats([(seen.frame, seen.detection)], usable=False)  # counted as seen
                    continue
                if seen.tracked_from is not None and self._last_full is not None and not seen.in_transit:
                    self._track(seen, before)
                    continue
                self._close_hold(seen, before)
                if self.assistant is None:
                    self.assistant = Assistant(self.settle.spec, seen.frame.image_size, settings=self.settings,
                                               locked_controls=self.locked_controls, focus_events=self.focus_events,
                                               detector=self.settle)
                if self._judged(self.assistant.feed_detected(seen.frame, seen.detection, in_transit=seen.in_transit)):
                    break
            else:
                # the last frame has no frame after it: its speed is measured from the one before, as live
                self._note_velocities(self._two_before, self._last_seen, None)
                if self.assistant is not None:
                    self._judged(self.assistant.flush())
        except KeyboardInterrupt:
            self.interrupted = True  # stop reading; what was accepted is solved as usual
        finally:
            close = getattr(stream, "close", None)
            if close is not None:
                close()
            self._settle_holds(final=True)

    def _note_velocities(self, before: Seen | None, middle: Seen | None, after: Seen | None) -> None:
        """`middle`'s neighbours in the footage: the session, which judges only some frames, measures a
        judged frame's speed and smear across them; a tracked frame's fastest corner is kept for its hold."""
        if before is None or middle is None or middle.skipped or self.session is None:
            return  # a frame skipped in transit is never judged, nor held
        sides = footage_neighbours(before, after)
        if middle.tracked_from is None or middle.in_transit:  # judged: a tracked frame in transit too, never held
            self.session.note_neighbours(middle.frame.index, *sides)
        else:  # a tracked frame of a hold: its fastest corner, for the final solve's smear test
            velocities = velocities_across((middle.detection, middle.frame.timestamp_ns), *sides)
            self._corner_speeds[middle.frame.index] = worst_corner_speed_px_s(velocities)

    def _track(self, seen: Seen, before: Seen | None) -> None:
        assert self._last_full is not None
        if not self._holds or self._holds[-1].after is not None:
            self._holds.append(_Hold(self._last_full.frame.index, None, [], []))
        self._holds[-1].repeats.append((seen.frame, seen.detection, float(seen.shift_px or 0.0)))
        self._holds[-1].speeds.append(_speed_px_s(before, seen))

    def _close_hold(self, seen: Seen, before: Seen | None) -> None:
        """A fully detected frame ends the hold being tracked (if any)."""
        if self._holds and self._holds[-1].after is None:
            hold = self._holds[-1]
            hold.after = seen.frame.index
            hold.shift_after = board_shift_px(hold.repeats[-1][1], seen.detection)
            hold.speed_after = _speed_px_s(before, seen)
        self._last_full = seen

    def _judged(self, step: Step | None) -> bool:
        """Hand a decided frame on; True when the stop rule is met."""
        if step is None or step.outcome is None or step.frame is None:
            return False
        decision = step.outcome.decision
        self._usable[step.frame.index] = "usable" if decision.accepted or decision.quality >= 1.0 else \
            decision.reason if decision.reason in ("moving", "no board") else "unusable"
        self._settle_holds()
        if self.on_outcome is not None:
            self.on_outcome(step.outcome, step.frame)
        if step.progress.done:
            self.stopped = True
            return True
        return False

    def _settle_holds(self, *, final: bool = False) -> None:
        """Give the session every hold whose fully detected frames have been judged (at the end: all)."""
        session = self.session
        while self._holds and session is not None:
            hold = self._holds[0]
            judged = [self._usable.get(hold.before), None if hold.after is None else self._usable.get(hold.after)]
            if not final and "usable" not in judged and None in judged:
                return  # wait for the frame after the hold to be judged
            self._holds.popleft()
            # The hold's frames are as sharp as a usable frame of it; where its fully detected
            # frames were rejected only for moving (a move's first or last frame, a board just
            # come into view) or showed no board (it left), the tracked frames' own stillness
            # decides. (A two-frame glimpse of a messy capture -- just come into view, then gone
            # -- kept its second frame with --every-frame, for 9.4% of the coverage; a replay lost it.)
            usable = "usable" in judged or all(j in ("moving", "no board", None) for j in judged)
            # A repeat between which and its neighbours the board moved at most the smear limit cannot
            # have smeared more; one that moved more is judged by its own image, as every frame is
            # with --every-frame (on a 104 deg 1080p lens at 20 fps, a steady hand's tremor moves the
            # board's outer corners 2-4 px a frame: the bound alone kept half the still frames).
            still = _still_repeats(hold, self.settings.selector.max_smear_px)
            speeds = _repeat_speeds(hold)
            blurs: list[float | None] = [None] * len(still)
            if usable:
                own = [None if ok else session.sharp_edges(f, d, motion_px_s=v)
                       for (f, d, _s), ok, v in zip(hold.repeats, still, speeds, strict=True)]
                still = [ok or edges is not None for ok, edges in zip(still, own, strict=True)]
                # the blur the masked corners keep clear of: a repeat's own where measured, else the
                # hold's judged frame's (a usable one first)
                judged = sorted((hold.before, hold.after), key=lambda i: self._usable.get(i) != "usable")
                hold_blur = session.hold_blur_px(judged)
                blurs = [hold_blur if edges is None else edges.blur_px for edges in own]
            speeds_px_s = [self._corner_speeds.pop(f.index, None) for f, _d, _s in hold.repeats]
            session.add_held_repeats([(f, d) for (f, d, _s), ok in zip(hold.repeats, still, strict=True) if ok], usable=usable,
                                     blur_px=[b for b, ok in zip(blurs, still, strict=True) if ok],
                                     corner_speeds_px_s=[v for v, ok in zip(speeds_px_s, still, strict=True) if ok])
            session.add_held_repeats([(f, d) for (f, d, _s), ok in zip(hold.repeats, still, strict=True) if not ok], usable=False)


def footage_neighbours(before: Seen, after: Seen | None) -> tuple[tuple[Detection, int] | None, tuple[Detection, int] | None]:
    """(detection, timestamp_ns) of the frames either side of one, None for a frame skipped in transit
    (never detected: the other side alone tells the speed) and after the footage's last frame."""
    before_side, after_side = ((None if s is None or s.skipped else (s.detection, s.frame.timestamp_ns)) for s in (before, after))
    return before_side, after_side


def _still_repeats(hold: _Hold, max_move_px: float) -> list[bool]:
    """Whether the board moved at most `max_move_px` into and out of each tracked frame.

    A board that moved no more than that between frames cannot have smeared more within the
    exposure (never longer than the frame interval): the selector's own smear limit.
    """
    into = [shift for _f, _d, shift in hold.repeats]
    out_of = into[1:] + [hold.shift_after]
    return [a <= max_move_px and b <= max_move_px for a, b in zip(into, out_of, strict=True)]


def _speed_px_s(before: Seen | None, seen: Seen) -> float | None:
    """Median corner speed from the frame before to this one, px/s (as the session measures it), or None."""
    if before is None:
        return None
    return board_speed_px_s(before.detection, before.frame.timestamp_ns, seen.detection, seen.frame.timestamp_ns)


def _repeat_speeds(hold: _Hold) -> list[float | None]:
    """The larger of each tracked frame's speeds into and out of it (None where neither is known)."""
    out_of = hold.speeds[1:] + [hold.speed_after]
    return [None if a is None and b is None else max(x for x in (a, b) if x is not None)
            for a, b in zip(hold.speeds, out_of, strict=True)]
