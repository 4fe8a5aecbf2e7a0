"""A replay's frames as the scan saw them, started as soon as the source is open.

The scan (decode, thumbnail, detect or track: app/scan.py) needs only the source, the board and
OpenCV; the session, the final solve and the outputs need ~0.15 s more of imports, and the first
frame the session judges costs it more again. Footage is scanned in a process of its own
(app/scan_process.py), so `ScanStream` forks it the moment it is made, and the command loads the
rest of the replay beside it (app/commands.py): before, the child was forked only once all of
that had loaded, and the start of every replay ran on one core. Nothing here imports the session.

A calibcoach recording, or footage where fork is not available, is scanned in process instead,
lazily, when the frames are first asked for; the decisions are the same either way.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator

from calibcoach.app.scan import HeldFrameScan, Seen, transit_smears
from calibcoach.app.scan_process import ChildScan, fork_available
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.drivers.base import Frame, FrameSource

TRACKED_KINDS = ("folder", "video")  # footage from elsewhere; recordings replay a live session frame by frame
_SETTLE_FRAMES = 30  # frames detected one by one while the print's variant is still unknown


def detected_frames(source: FrameSource, board: BoardSpec, *, workers: int = 2,
                    settle: CharucoBoardDetector | None = None, scans_out: list[HeldFrameScan] | None = None,
                    every_frame: bool = False) -> Iterator[Seen]:
    """Every frame of `source` in order with its detection (the source decodes ahead, `workers` threads detect).

    A held board is tracked from the frame before rather than detected anew (`HeldFrameScan`,
    app/scan.py) in footage from elsewhere (video files, image folders) unless `every_frame`; a
    calibcoach recording is a live session's frames, and its replay decides each of them as the
    live session did, so every frame is detected. The scan is appended to `scans_out` so the
    caller can report how many frames were tracked.
    """
    info = source.info
    footage = info.kind in TRACKED_KINDS
    first = settle or CharucoBoardDetector(board)
    frames: Iterator[Frame] = iter(source)  # sources decode ahead themselves (drivers/image_files.py `decoded_ahead`)
    width = info.image_size[0] if info.image_size else 0
    for frame, detection in _settling(frames, first):
        width = width or frame.image_size[0]
        yield Seen(frame, detection, None, None)
    spec = _settled_spec(first)
    scan = HeldFrameScan(frames, lambda: CharucoBoardDetector(spec), workers=workers, track=footage and not every_frame,
                         judge_transit=footage and transit_smears(width, info.fps))
    if scans_out is not None:
        scans_out.append(scan)
    yield from scan


def _settling(frames: Iterable[Frame], detector: CharucoBoardDetector) -> Iterator[tuple[Frame, Detection]]:
    """Detect one by one until the print's legacy/inverted variant is known (or enough frames tried)."""
    for frame in frames:
        yield frame, detector.detect(frame.grey())
        if detector.settled or frame.index >= _SETTLE_FRAMES:
            return


def _settled_spec(detector: CharucoBoardDetector) -> BoardSpec:
    """The board as settled, or with the variants not yet seen taken as plain."""
    if detector.settled:
        return detector.spec
    return detector.spec.with_detected(legacy=bool(detector.spec.legacy), inverted=bool(detector.spec.inverted))


class ScanStream:
    """Every frame of `source` with its detection, in order: iterate once, then `close()` (or use `with`).

    Footage (folders, videos) is scanned in a child process forked when this is made, unless
    `in_child` is False or fork is not available; anything else is scanned in process as it is
    read. `settle` is the detector whose print variant (legacy, inverted) the scan settles, seen
    here as each frame arrives; `tracked` counts the frames whose held board was tracked.
    """

    def __init__(self, source: FrameSource, board: BoardSpec, *, workers: int = 2, every_frame: bool = False,
                 in_child: bool = True) -> None:
        info = source.info
        self.started_at = time.perf_counter()  # the replay's reading time counts from here
        self.settle = CharucoBoardDetector(board)
        self._scans: list[HeldFrameScan] = []  # the scan when it runs in process (a child keeps its own)
        self._tracked_in_child = 0  # the child's count of tracked frames, as it last said
        frame_bytes = 3 * info.image_size[0] * info.image_size[1] if info.image_size is not None else 0
        self.in_child = info.kind in TRACKED_KINDS and bool(frame_bytes) and in_child and fork_available()
        self._stream: ChildScan | Iterator[Seen]
        if self.in_child:
            self._stream = self._start_child(source, board, frame_bytes, workers=workers, every_frame=every_frame)
        else:
            self._stream = detected_frames(source, board, workers=workers, settle=self.settle, scans_out=self._scans,
                                           every_frame=every_frame)

    def _start_child(self, source: FrameSource, board: BoardSpec, frame_bytes: int, *, workers: int,
                     every_frame: bool) -> ChildScan:
        """`detected_frames` in a child process; the print's variant, the scan's counts and the source's
        unreadable frames are mirrored into `settle`, `tracked` and `source.skipped` as they come."""
        settle = self.settle
        scans: list[HeldFrameScan] = []  # the child's scan, in the child

        def make_seen() -> Iterator[Seen]:  # runs in the child, on its copies of source and settle
            return detected_frames(source, board, workers=workers, settle=settle, scans_out=scans, every_frame=every_frame)

        def state() -> tuple:  # in the child
            variant = (bool(settle.spec.legacy), bool(settle.spec.inverted)) if settle.settled else None
            return variant, sum(scan.tracked for scan in scans), list(source.skipped)

        def apply_state(child_state: tuple) -> None:  # in the parent
            variant, self._tracked_in_child, source.skipped = child_state
            if variant is not None and not settle.settled:
                settle.settle(legacy=variant[0], inverted=variant[1])

        return ChildScan(make_seen, frame_bytes, state=state, apply_state=apply_state)

    @property
    def tracked(self) -> int:
        """Frames whose held board was tracked from the frame before, so far."""
        return self._tracked_in_child if self.in_child else sum(scan.tracked for scan in self._scans)

    def __iter__(self) -> Iterator[Seen]:
        return iter(self._stream)

    def close(self) -> None:
        """End the scan: its child process, or the in-process scan's threads (idempotent)."""
        self._stream.close()

    def __enter__(self) -> ScanStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
