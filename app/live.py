"""Live capture: a camera (or a file paced like one) in front of the very same session as replay.

Capture never waits for detection or solving: a capture thread keeps only the newest frame
(older ones are dropped and counted), and the loop processes whatever is newest when it is free.
Each processed frame is recorded first (crash-safe), so `calibcoach calibrate RECORDING`
replays exactly the frames the live session saw and reproduces its decisions and its result.
Like replay, the loop looks one frame ahead (the two-sided stillness test), which costs one frame
of latency and keeps live and replay identical.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import cv2

from calibcoach.app.assistant import Assistant, Step
from calibcoach.app.focus_watch import FocusEvent, focus_events, lock_mismatch
from calibcoach.app.session import CalibrationSession, FrameOutcome, SessionSettings
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.drivers.base import Frame, FrameSource, SourceInfo
from calibcoach.drivers.errors import CalibcoachError, SourceError
from calibcoach.drivers.recording import RecordingWriter
from calibcoach.drivers.replay import RecordingSource

_DETECT_THREADS = 2  # the live loop's detection: the cores a laptop has to spare


def detect_on_all_cores(detector: CharucoBoardDetector, frame: Frame) -> Detection:
    """Detect with OpenCV's own threads, then go back to one for the session's solves.

    Live detection runs on the processing thread, one frame at a time, so OpenCV's threads are
    what puts the second core to work: 1080p detection takes ~23 ms instead of ~37 ms, which keeps
    the processing near the camera's 30 fps. Detection is bit-identical on any thread count
    (tests/app/test_live.py checks it), unlike calibrateCamera, whose threaded sums differ in the
    9th digit and must stay single-threaded for a replay to reproduce a live session.
    """
    cv2.setNumThreads(_DETECT_THREADS)
    try:
        return detector.detect(frame.grey())
    finally:
        cv2.setNumThreads(1)


class CameraLostError(CalibcoachError):
    """The camera vanished mid-session; everything recorded so far is on disk and resumable."""

    exit_code = 4


class PacedSource(FrameSource):
    """A file source delivered at its own frame rate, like a camera (`speed` > 1 plays faster)."""

    def __init__(self, source: FrameSource, *, speed: float = 1.0) -> None:
        super().__init__()
        self.inner = source
        self.speed = speed

    @property
    def info(self) -> SourceInfo:
        return self.inner.info

    def frames(self) -> Iterator[Frame]:
        start = time.monotonic()
        first_ns: int | None = None
        for frame in self.inner.frames():
            first_ns = frame.timestamp_ns if first_ns is None else first_ns
            due = start + (frame.timestamp_ns - first_ns) / 1e9 / self.speed
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            yield frame
        self.skipped = self.inner.skipped

    def close(self) -> None:
        self.inner.close()


class _NoFrames(FrameSource):
    def __init__(self, info: SourceInfo) -> None:
        super().__init__()
        self._info = info

    @property
    def info(self) -> SourceInfo:
        return self._info

    def frames(self) -> Iterator[Frame]:
        return iter(())


class FrameGrabber:
    """A capture thread that keeps only the newest frame; the consumer never makes it wait."""

    def __init__(self, source: FrameSource, on_capture: Callable[[Frame], None] | None = None) -> None:
        self.source = source
        self.on_capture = on_capture  # called on the capture thread for every frame (the live preview)
        self.preview_error: BaseException | None = None  # a failing preview stops previews, never capture
        self.dropped = 0  # frames overwritten before the consumer took them
        self.captured = 0
        self.error: BaseException | None = None
        self._latest: Frame | None = None
        self._ended = False
        self._stop = threading.Event()
        self._ready = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="capture", daemon=True)

    def start(self) -> FrameGrabber:
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            for frame in self.source.frames():
                with self._ready:
                    if self._latest is not None:
                        self.dropped += 1
                    self._latest = frame
                    self.captured += 1
                    self._ready.notify()
                if self.on_capture is not None and self.preview_error is None:
                    try:
                        self.on_capture(frame)
                    except Exception as exc:  # noqa: BLE001 - the preview is a view, the capture is the data
                        self.preview_error = exc
                if self._stop.is_set():
                    break
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, which reports it once
            self.error = exc
        finally:
            with self._ready:
                self._ended = True
                self._ready.notify()

    def next(self) -> Frame | None:
        """The newest frame not yet taken; None once the source has ended (check `error`)."""
        with self._ready:
            while self._latest is None and not self._ended:
                self._ready.wait(0.5)
            frame, self._latest = self._latest, None
            return frame

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)


@dataclass(frozen=True, slots=True)
class LiveStats:
    frames_processed: int
    frames_dropped: int
    seconds: float
    stopped_early: bool  # the stop rule was met
    interrupted: bool  # Ctrl-C
    resumed_frames: int  # frames replayed from the recording that was resumed
    focus_drift: str | None  # why acceptance stopped, if the focus moved
    board: BoardSpec

    @property
    def processed_fps(self) -> float:
        return self.frames_processed / self.seconds if self.seconds > 0 else 0.0


def run_live(
    source: FrameSource,
    board: BoardSpec,
    settings: SessionSettings,
    *,
    record: Path | None = None,
    resume: Path | None = None,
    locked_controls: dict[str, float] | None = None,
    on_outcome: Callable[[FrameOutcome, Frame, LiveStats], None] | None = None,
    on_capture: Callable[[Frame], None] | None = None,
) -> tuple[CalibrationSession | None, LiveStats]:
    """Guide a live capture until the stop rule, the end of the source, Ctrl-C or a lost camera.

    Raises:
        CameraLostError: the source failed mid-stream; the recording holds every processed frame.
    """
    info = source.info
    detector = CharucoBoardDetector(board)
    assistant: Assistant | None = None
    writer: RecordingWriter | None = None
    locked = dict(locked_controls or {})
    recorded = RecordingSource(resume) if resume is not None else None
    if recorded is not None:  # a resumed capture must go on at the focus its frames were taken at
        moved = lock_mismatch(recorded.info.locked_controls, locked)
        if moved:
            raise CalibcoachError(f"focus is locked elsewhere than when {resume} was recorded ({moved}); set the lens "
                                  "back (--lens-position) or record a new session instead of resuming this one")
    noted: list[FocusEvent] = []  # events already in the recording
    start = time.perf_counter()
    processed = resumed = 0
    stopped = interrupted = False
    grabber: FrameGrabber | None = None

    def stats() -> LiveStats:
        dropped = 0 if grabber is None else grabber.dropped
        drift = None if assistant is None or assistant.focus_drift is None else assistant.focus_drift.detail
        return LiveStats(processed, dropped, time.perf_counter() - start, stopped, interrupted, resumed,
                         drift, detector.spec)

    def handle(step: Step | None) -> bool:
        """One decided frame: the focus watch, the caller's callback; True when the stop rule is met."""
        nonlocal processed
        if step is None or step.outcome is None or step.frame is None:
            return False
        assert assistant is not None
        processed += 1
        event = assistant.focus_drift
        if event is not None and event not in noted:  # into the recording at once: replay applies it
            noted.append(event)
            if writer is not None:
                writer.note_event(event.to_dict())
        if on_outcome is not None:
            on_outcome(step.outcome, step.frame, stats())
        return step.progress.done

    def feed(frame: Frame, detection: Detection) -> bool:
        nonlocal assistant
        if assistant is None:
            assistant = Assistant(detector.spec, frame.image_size, settings=settings, locked_controls=locked,
                                  focus_events=() if recorded is None else focus_events(recorded.info.events),
                                  detector=detector)
        return handle(assistant.feed_detected(frame, detection))  # decides the frame before this one

    if recorded is not None:  # replay what was recorded, exactly as `calibrate` would, then go on live
        noted.extend(focus_events(recorded.info.events))  # already in the recording
        for frame in recorded.frames():
            detection = detect_on_all_cores(detector, frame)
            resumed += 1
            if feed(frame, detection):
                stopped = True
                break
    if stopped:  # the resumed recording already met the stop rule: nothing left to capture
        source = _NoFrames(info)
    grabber = FrameGrabber(source, on_capture).start()
    target = resume if resume is not None else record
    first_live = False
    try:
        while True:
            frame = grabber.next()
            if frame is None:
                break
            if target is not None:
                if writer is None:
                    writer = RecordingWriter(
                        target, camera_id=info.camera_id or info.description, kind=info.kind, image_size=frame.image_size,
                        fps=info.fps, controls=dict(info.controls), board=detector.spec.to_dict(), append=resume is not None,
                        locked_controls=locked,
                    )
                    first_live = True
                frame = replace(frame, index=writer.write(frame))  # recorded before processed: crash-safe
                if first_live and assistant is not None:  # resumed at a matching lock: accept again from here
                    relocked = assistant.resume_accepting(from_index=frame.index)
                    if relocked is not None:
                        writer.note_event(relocked.to_dict())
                first_live = False
            if feed(frame, detect_on_all_cores(detector, frame)):
                stopped = True
                break
        if assistant is not None and not stopped:
            stopped = handle(assistant.flush())  # the last frame, decided without lookahead
    except KeyboardInterrupt:
        interrupted = True
    finally:
        grabber.stop()
        if writer is not None:
            writer.close()
    if grabber.error is not None and not isinstance(grabber.error, KeyboardInterrupt):
        where = f"; every processed frame is in {target}: continue with --resume {target}" if target else \
            " (nothing was recorded: pass --record DIR to keep a session across such losses)"
        reason = str(grabber.error) if isinstance(grabber.error, SourceError) else repr(grabber.error)
        raise CameraLostError(f"the camera stopped delivering frames after {processed} processed frames ({reason}){where}")
    return (None if assistant is None else assistant.session), stats()
