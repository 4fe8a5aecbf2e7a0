"""Replay: run a recorded source through the session as fast as the machine allows.

Detection dominates the per-frame cost and OpenCV's `detectBoard` releases the GIL, so frames are
detected ahead on worker threads (one detector per thread) while the session consumes outcomes
strictly in frame order; the decisions are therefore identical to a single-threaded run.
Replay stops reading as soon as the session's stop rule is met.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

from calibcoach.app.assistant import Assistant
from calibcoach.app.focus_watch import FocusEvent, focus_events
from calibcoach.app.scan import SparseScan
from calibcoach.app.session import CalibrationSession, FrameOutcome, SessionSettings
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.coverage.redetect import RedetectionCounts
from calibcoach.drivers.base import Frame, FrameSource, SkippedFrame
from calibcoach.drivers.errors import SourceError

_SETTLE_FRAMES = 30  # frames detected one by one while the print's variant is still unknown


@dataclass(frozen=True, slots=True)
class ReplayStats:
    frames_read: int
    seconds: float
    stopped_early: bool  # the stop rule was met before the source ended
    interrupted: bool  # Ctrl-C: the session holds every frame accepted until then
    board: BoardSpec  # with legacy/inverted settled
    variant_found: str | None
    passed_over: int = 0  # frames of a sparse scan never decoded: they repeated their neighbours' view
    redetection: RedetectionCounts | None = None  # frames re-detected on a local view (wide lenses), None if none were


class _ThreadDetectors:
    """One CharucoBoardDetector per worker thread, all built from the settled board."""

    def __init__(self, spec: BoardSpec) -> None:
        self.spec = spec
        self._local = threading.local()

    def detect(self, frame: Frame) -> Detection:
        detector = getattr(self._local, "detector", None)
        if detector is None:
            detector = self._local.detector = CharucoBoardDetector(self.spec)
        return detector.detect(frame.grey())


def detected_frames(source: FrameSource, board: BoardSpec, *, workers: int = 2,
                    settle: CharucoBoardDetector | None = None, scans_out: list[SparseScan] | None = None,
                    every_frame: bool = False) -> Iterator[tuple[Frame, Detection]]:
    """Yield (frame, detection) in source order, detecting ahead on `workers` threads.

    Sources with random access (image folders) are read by a `SparseScan` that passes over frames
    repeating their neighbours' view, unless `every_frame`; the scan is appended to `scans_out` so
    the caller can report how much was passed over.
    """
    first = settle or CharucoBoardDetector(board)
    count = None if every_frame else source.frame_count_for_random_access
    if count is not None:
        loaded = _LoadedInOrder(source, count)
        yield from _settling(loaded, first)
        detectors = _ThreadDetectors(_settled_spec(first))
        sparse = SparseScan(source, detectors.detect, start=loaded.next_index, workers=workers,
                            board_corners_m=detectors.spec.corner_points_m())
        if scans_out is not None:
            scans_out.append(sparse)
        yield from sparse
        return
    frames = iter(source)
    yield from _settling(frames, first)
    detectors = _ThreadDetectors(_settled_spec(first))
    pending: deque[tuple[Frame, Future[Detection]]] = deque()
    with ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="detect") as pool:
        try:
            for frame in frames:
                pending.append((frame, pool.submit(detectors.detect, frame)))
                if len(pending) >= 2 * workers + 2:
                    f, fut = pending.popleft()
                    yield f, fut.result()
            while pending:
                f, fut = pending.popleft()
                yield f, fut.result()
        finally:
            for _f, fut in pending:
                fut.cancel()


def _settling(frames: Iterable[Frame], detector: CharucoBoardDetector) -> Iterator[tuple[Frame, Detection]]:
    """Detect one by one until the print's legacy/inverted variant is known (or enough frames tried)."""
    for frame in frames:
        yield frame, detector.detect(frame.grey())
        if detector.settled or frame.index >= _SETTLE_FRAMES:
            return


class _LoadedInOrder:
    """A random-access source's frames in order through `load`; `next_index` is where to go on."""

    def __init__(self, source: FrameSource, count: int) -> None:
        self.source, self.count, self.next_index = source, count, 0
        source.skipped = []

    def __iter__(self) -> Iterator[Frame]:
        while self.next_index < self.count:
            item = self.source.load(self.next_index)
            self.next_index += 1
            if isinstance(item, SkippedFrame):
                self.source.skipped.append(item)
                continue
            yield item


def _settled_spec(detector: CharucoBoardDetector) -> BoardSpec:
    """The board as settled, or with the variants not yet seen taken as plain."""
    if detector.settled:
        return detector.spec
    return detector.spec.with_detected(legacy=bool(detector.spec.legacy), inverted=bool(detector.spec.inverted))


def _with_end(stream: Iterator[tuple[Frame, Detection]]) -> Iterator[tuple[Frame, Detection] | None]:
    yield from stream
    yield None


def run_replay(
    source: FrameSource,
    board: BoardSpec,
    settings: SessionSettings | None = None,
    *,
    workers: int = 2,
    on_outcome: Callable[[FrameOutcome, Frame], None] | None = None,
    every_frame: bool = False,
) -> tuple[CalibrationSession, ReplayStats]:
    """Feed the frames of `source` to a new session until the source ends or the stop rule is met.

    Image folders are read sparsely (see app/scan.py) unless `every_frame`. When the capture was
    hurried (few usable frames, even counting the repeats of held boards that were passed over),
    the frames passed over next to a usable board are read too, in a second pass.
    """
    info = source.info
    settings = settings or SessionSettings(use_motion_gate=info.kind != "folder")
    settle = CharucoBoardDetector(board)
    feed = _Feeder(settle, settings, on_outcome, locked_controls=info.locked_controls,
                   focus_events=focus_events(info.events))
    start = time.perf_counter()
    scans: list[SparseScan] = []
    stream = detected_frames(source, board, workers=workers, settle=settle, scans_out=scans, every_frame=every_frame)
    feed.run(stream)
    session = feed.session
    if session is not None and scans and not (feed.stopped or feed.interrupted) and \
            session.short_of_choice(unread_repeats=scans[0].held_repeats):
        feed.run(scans[0].fill_in())
    if session is None:
        skipped = f" ({len(source.skipped)} unreadable: {source.skipped[0].reason})" if source.skipped else ""
        raise SourceError(f"{info.description} delivered no frames{skipped}; check the path and the file format")
    session.board = settle.spec
    passed_over = sum(scan.passed_over for scan in scans)
    redetector = None if feed.assistant is None else feed.assistant.redetector
    return session, ReplayStats(feed.read, time.perf_counter() - start, feed.stopped, feed.interrupted, settle.spec,
                                settle.variant_found, passed_over, None if redetector is None else redetector.counts)


class _Feeder:
    """Feeds (frame, detection) streams to one `Assistant` (which looks one frame ahead, like live)."""

    def __init__(self, settle: CharucoBoardDetector, settings: SessionSettings,
                 on_outcome: Callable[[FrameOutcome, Frame], None] | None, *,
                 locked_controls: Mapping[str, float], focus_events: Sequence[FocusEvent]) -> None:
        self.settle, self.settings, self.on_outcome = settle, settings, on_outcome
        self.locked_controls, self.focus_events = locked_controls, focus_events
        self.assistant: Assistant | None = None
        self.read = 0
        self.stopped = self.interrupted = False

    @property
    def session(self) -> CalibrationSession | None:
        return None if self.assistant is None else self.assistant.session

    def run(self, stream: Iterator[tuple[Frame, Detection]]) -> None:
        """Feed `stream` until it ends or the stop rule is met."""
        try:
            for item in _with_end(stream):
                if item is None:
                    step = None if self.assistant is None else self.assistant.flush()
                else:
                    self.read += 1
                    frame, detection = item
                    if self.assistant is None:
                        self.assistant = Assistant(self.settle.spec, frame.image_size, settings=self.settings,
                                                   locked_controls=self.locked_controls, focus_events=self.focus_events,
                                                   detector=self.settle)
                    step = self.assistant.feed_detected(frame, detection)
                if step is not None and step.outcome is not None and step.frame is not None:
                    if self.on_outcome is not None:
                        self.on_outcome(step.outcome, step.frame)
                    if step.progress.done:
                        self.stopped = True
                        break
        except KeyboardInterrupt:
            self.interrupted = True  # stop reading; what was accepted is solved as usual
        finally:
            close = getattr(stream, "close", None)
            if close is not None:
                close()
