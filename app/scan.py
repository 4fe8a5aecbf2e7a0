"""Sparse scan: look closely at a dense image sequence only where it can change the calibration.

A 30 fps sequence shows every pose many times over: a board held still for a second is thirty
near-identical frames, a slow move is a chain of frames each a few pixels from the last. Decoding
and detecting all of them is nearly all of a replay's cost, while the selector would reject almost
all of them as duplicates. So a replay of a source with random access (a folder of images) looks at
every `stride`-th frame first and fills in between two looked-at frames only where they differ:
the board moved more than `same_view_frac` of the image diagonal at any corner, corners appeared
or vanished, the board came or went, or (with no board in either) the scene changed. Filling in
bisects, so a move is sampled more densely the faster it goes, and a folder of independent stills,
whose neighbours always differ, is read completely.

What is passed over lies between two frames showing the same view within a few per cent of the
image: closer to one of them than the selector's own duplicate distance, so it could only have
been rejected as a duplicate or have added a sliver of information. Every decision depends on the
detections alone, never on timing, so a replay is reproducible whatever the machine.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from calibcoach.coverage.detector import Detection
from calibcoach.drivers.base import Frame, FrameSource, SkippedFrame

DEFAULT_STRIDE = 8
SAME_VIEW_FRAC = 0.03  # largest corner movement between two "same view" frames, share of the image diagonal
_MIN_CORNERS = 6  # below this a frame shows no usable board; such frames are compared by thumbnail
_SHARED_CORNERS = 0.5  # detection drops and regains a third of the corners of a still, tilted board from frame to frame
_THUMB_SIZE = (32, 18)  # (width, height): the scene's layout, blind to sensor noise
_THUMB_SAME_GREY = 2.0  # mean absolute thumbnail difference (grey levels) of an unchanged scene
# A folder counts as video once this many stride-apart pairs showed the board in the same view:
# independent stills never do, footage does within its first seconds.
_VIDEO_AFTER_SAME_VIEWS = 3


@dataclass(frozen=True, slots=True)
class Look:
    """One frame looked at: decoded, detected and thumbnailed (or unreadable)."""

    index: int
    frame: Frame | None  # None when the file could not be read
    skipped: SkippedFrame | None
    detection: Detection | None
    thumb: np.ndarray | None  # (18, 32) float32 grey thumbnail


def same_view(a: Look, b: Look, image_size: tuple[int, int], *, frac: float = SAME_VIEW_FRAC,
              video: bool = False) -> bool:
    """True when nothing between `a` and `b` can show a view neither of them shows.

    `video`: the sequence has shown itself to be continuous footage, where a board seen sharply at
    neither end of a fraction of a second was moving (blurred) or away the whole time.
    """
    if a.detection is None or b.detection is None or a.thumb is None or b.thumb is None:
        return False
    na, nb = a.detection.corner_count, b.detection.corner_count
    if na < _MIN_CORNERS and nb < _MIN_CORNERS:
        if video and a.detection.marker_ids.size == 0 and b.detection.marker_ids.size == 0:
            return True
        return float(np.mean(np.abs(a.thumb - b.thumb))) <= _THUMB_SAME_GREY
    if na < _MIN_CORNERS or nb < _MIN_CORNERS:
        return False  # the board came or went in between
    shared, ia, ib = np.intersect1d(a.detection.ids, b.detection.ids, assume_unique=True, return_indices=True)
    if shared.size < _SHARED_CORNERS * max(na, nb):
        return False  # most corners came or went: the board slid over an edge or something covered it
    moved = np.linalg.norm(a.detection.corners_px[ia] - b.detection.corners_px[ib], axis=1)
    return float(moved.max()) <= frac * float(np.hypot(*image_size))


class SparseScan:
    """(frame, detection) pairs of a random-access source in index order, passing over repeats.

    `detect` must be thread-safe (e.g. one detector per thread). Frames before `start` are left to
    the caller. `passed_over` counts frames never decoded; unreadable frames go to `source.skipped`.
    """

    def __init__(self, source: FrameSource, detect: Callable[[Frame], Detection], *, start: int = 0,
                 stride: int = DEFAULT_STRIDE, workers: int = 2, lookahead: int = 6) -> None:
        count = source.frame_count_for_random_access
        if count is None:
            raise ValueError(f"{type(source).__name__} has no random access; iterate it instead")
        self._source, self._detect, self._count = source, detect, count
        self._start, self._stride = start, max(1, int(stride))
        self._workers, self._lookahead = max(1, int(workers)), max(2, int(lookahead))
        self._size = source.info.image_size
        self.passed_over = 0
        self._board_still_pairs = 0  # stride-apart pairs that showed the board in the same view
        self._futures: dict[int, Future[Look]] = {}

    def _look(self, index: int) -> Look:
        item = self._source.load(index)
        if isinstance(item, SkippedFrame):
            return Look(index, None, item, None, None)
        grey = item.grey()
        thumb = cv2.resize(grey, _THUMB_SIZE, interpolation=cv2.INTER_AREA).astype(np.float32)
        return Look(index, item, None, self._detect(item), thumb)

    def __iter__(self) -> Iterator[tuple[Frame, Detection]]:
        if self._start >= self._count:
            return
        keys = list(range(self._start, self._count, self._stride))
        if keys[-1] != self._count - 1:
            keys.append(self._count - 1)
        with ThreadPoolExecutor(max_workers=self._workers, thread_name_prefix="scan") as pool:
            self._pool = pool
            try:
                for key in keys[: self._lookahead]:
                    self._ask(key)
                a = self._get(keys[0])
                yield from self._emit(a)
                for position in range(1, len(keys)):
                    if position + self._lookahead - 1 < len(keys):
                        self._ask(keys[position + self._lookahead - 1])
                    b = self._get(keys[position])
                    yield from self._between(a, b)
                    yield from self._emit(b)
                    a = b
            finally:
                for future in self._futures.values():
                    future.cancel()
                self._futures.clear()

    def _between(self, a: Look, b: Look) -> Iterator[tuple[Frame, Detection]]:
        if b.index - a.index <= 1:
            return
        if self._same(a, b):
            self.passed_over += b.index - a.index - 1
            return
        middle = self._get((a.index + b.index) // 2)
        for low, high in ((a, middle), (middle, b)):  # ask both halves' middles now, so both workers share them
            if high.index - low.index > 1 and not self._same(low, high, count=False):
                self._ask((low.index + high.index) // 2)
        yield from self._between(a, middle)
        yield from self._emit(middle)
        yield from self._between(middle, b)

    def _same(self, a: Look, b: Look, *, count: bool = True) -> bool:
        video = self._board_still_pairs >= _VIDEO_AFTER_SAME_VIEWS
        same = same_view(a, b, self._size, video=video)
        if count and same and b.index - a.index >= self._stride and min(
                a.detection.corner_count, b.detection.corner_count) >= _MIN_CORNERS:  # type: ignore[union-attr]
            self._board_still_pairs += 1
        return same

    def _emit(self, look: Look) -> Iterator[tuple[Frame, Detection]]:
        if look.frame is None:
            assert look.skipped is not None
            self._source.skipped.append(look.skipped)
            return
        assert look.detection is not None
        yield look.frame, look.detection

    def _ask(self, index: int) -> None:
        if index not in self._futures:
            self._futures[index] = self._pool.submit(self._look, index)

    def _get(self, index: int) -> Look:
        self._ask(index)
        return self._futures.pop(index).result()
