"""Sparse scan: look closely at a dense image sequence only where it can change the calibration.

A 30 fps sequence shows every pose many times over: a board held still for a second is thirty
near-identical frames, a slow move is a chain of frames each a few pixels from the last. Decoding
and detecting all of them is nearly all of a replay's cost, while the selector would reject almost
all of them as duplicates. So a replay of a source with random access (a folder of images) looks at
every `stride`-th frame first and, between two looked-at frames, bisects only where they differ:
the board moved more than 1% of the image diagonal at some corner, most corners
came or went, the board came or went, or (with no board at either end) the scene changed. A move
is thus sampled more densely the faster it goes, and a folder of independent stills, whose
neighbours always differ, is read completely.

Two cases are sampled rather than skipped: a held board whose detection flickers (each frame finds
another part of its corners) is looked at every 8th frame, and once the folder has shown itself
to be footage, stretches with no marker in sight every 4th, so a board shown for 4 frames is still
found. A capture with few usable frames even counting the held repeats passed over gets a second
pass near its usable boards (`fill_in`, driven by app/replay.py).

What is passed over lies between two frames showing the same view within 1% of the image:
far closer to one of them than the selector's own duplicate distance (6%), so it could only have
been rejected as a duplicate or have added a sliver of information. Every decision depends on the
detections alone, never on timing or threads, so a replay is reproducible whatever the machine.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from calibcoach.coverage.detector import Detection
from calibcoach.drivers.base import Frame, FrameSource, SkippedFrame

DEFAULT_STRIDE = 8
# Largest corner movement between two "same view" frames, share of the image diagonal (15 px at
# 720p): a held board's tremor stays under it; a slow sweep through new tilts, where the
# information is, goes over it within a few frames.
SAME_VIEW_FRAC = 0.01
_MIN_CORNERS = 6  # below this a frame shows no usable board; such frames are compared by thumbnail
_SHARED_CORNERS = 0.5  # detection drops and regains a third of the corners of a still, tilted board from frame to frame
# ...so the two ends together must hold nearly every corner the board shows inside the image: a
# frame in between cannot then add corners, only repeat them.
_UNION_OF_VISIBLE = 0.9
_STABLE_DETECTION = 0.9  # ...unless the detection is steady: both ends found (nearly) the same corners
# A held board whose detection flickers is looked at every 8th frame (samples of its corners), and
# footage with no board in sight every 4th: a board shown for 4 frames (~0.13 s at 30 fps) is found.
_HELD_GAP = 8
_AWAY_GAP = 4
_FILL_NEAR = 4  # the second pass of a hurried capture reads what was passed over this close to a usable board
_THUMB_SIZE = (32, 18)  # (width, height): the scene's layout, blind to sensor noise
_THUMB_SAME_GREY = 6.0  # largest thumbnail cell change (grey levels) of an unchanged scene: a board passing
# through one corner of the image changes a few cells a lot and the mean hardly at all
# A folder counts as video once this many pairs of looked-at frames showed the board in the same
# view, or neighbouring frames looked alike: independent stills never do, footage does within its
# first seconds.
_VIDEO_AFTER_SAME_VIEWS = 3
_ADJACENT_SAME_GREY = 1.5  # mean thumbnail change between neighbouring frames of footage (stills change far more)


@dataclass(frozen=True, slots=True)
class Look:
    """One frame looked at: decoded, detected and thumbnailed (or unreadable)."""

    index: int
    frame: Frame | None  # None when the file could not be read
    skipped: SkippedFrame | None
    detection: Detection | None
    thumb: np.ndarray | None  # (18, 32) float32 grey thumbnail
    visible_corners: int | None = None  # board corners inside the image by the detected corners' homography


def visible_corner_count(detection: Detection, board_corners_m: np.ndarray, image_size: tuple[int, int]) -> int | None:
    """How many of the board's corners lie inside the image, by the homography of the detected ones.

    None when the detection cannot say (too few corners, or a degenerate homography).
    """
    if detection.corner_count < _MIN_CORNERS:
        return None
    homography, _ = cv2.findHomography(detection.object_points_m[:, :2].astype(np.float64),
                                       detection.corners_px.astype(np.float64))
    if homography is None:
        return None
    projected = cv2.perspectiveTransform(board_corners_m[None, :, :2].astype(np.float64), homography)[0]
    w, h = image_size
    inside = (projected[:, 0] >= 0) & (projected[:, 0] < w) & (projected[:, 1] >= 0) & (projected[:, 1] < h)
    return int(inside.sum())


def compare_views(a: Look, b: Look, image_size: tuple[int, int], *, frac: float = SAME_VIEW_FRAC,
                  video: bool = False) -> str:
    """"same" when nothing between `a` and `b` can show a view neither of them shows; "held" when the
    board is held in the same place but the detection flickers (each frame finds another part of its
    corners, so frames between may find more); "away" when, in footage (`video`), neither end shows
    a marker: the board is out of sight or swung too fast to read, and only a brief glimpse could
    lie between; "different" otherwise.
    """
    if a.detection is None or b.detection is None or a.thumb is None or b.thumb is None:
        return "different"
    na, nb = a.detection.corner_count, b.detection.corner_count
    if na < _MIN_CORNERS and nb < _MIN_CORNERS:
        if float(np.max(np.abs(a.thumb - b.thumb))) <= _THUMB_SAME_GREY:
            return "same"
        if video and a.detection.marker_ids.size == 0 and b.detection.marker_ids.size == 0:
            return "away"
        return "different"
    if na < _MIN_CORNERS or nb < _MIN_CORNERS:
        return "different"  # the board came or went in between
    shared, ia, ib = np.intersect1d(a.detection.ids, b.detection.ids, assume_unique=True, return_indices=True)
    if shared.size < _SHARED_CORNERS * max(na, nb):
        return "different"  # most corners came or went: the board slid over an edge or something covered it
    moved = np.linalg.norm(a.detection.corners_px[ia] - b.detection.corners_px[ib], axis=1)
    if float(moved.max()) > frac * float(np.hypot(*image_size)):
        return "different"
    union = np.union1d(a.detection.ids, b.detection.ids).size
    stable = shared.size >= _STABLE_DETECTION * union  # both ends found the same corners: so would the frames between
    complete = a.visible_corners is not None and b.visible_corners is not None and \
        union >= _UNION_OF_VISIBLE * max(a.visible_corners, b.visible_corners)
    return "same" if stable or complete else "held"


def same_view(a: Look, b: Look, image_size: tuple[int, int], *, frac: float = SAME_VIEW_FRAC,
              video: bool = False) -> bool:
    """True when nothing between `a` and `b` can show a view neither of them shows."""
    return compare_views(a, b, image_size, frac=frac, video=video) == "same"


class SparseScan:
    """(frame, detection) pairs of a random-access source in index order, passing over repeats.

    `detect` must be thread-safe (e.g. one detector per thread). Frames before `start` are left to
    the caller. `passed_over` counts frames never decoded; unreadable frames go to `source.skipped`.
    """

    def __init__(self, source: FrameSource, detect: Callable[[Frame], Detection], *, start: int = 0,
                 stride: int = DEFAULT_STRIDE, workers: int = 2, lookahead: int = 6,
                 board_corners_m: np.ndarray | None = None) -> None:
        count = source.frame_count_for_random_access
        if count is None:
            raise ValueError(f"{type(source).__name__} has no random access; iterate it instead")
        self._source, self._detect, self._count = source, detect, count
        self._start, self._stride = start, max(1, int(stride))
        self._workers, self._lookahead = max(1, int(workers)), max(2, int(lookahead))
        self._size = source.info.image_size
        self._board_corners_m = board_corners_m  # (N, 3) every ChArUco corner, by id; None: no completeness check
        self.passed_over = 0
        self.held_repeats = 0  # frames passed over between two looks at a usable, held board
        self._passed: list[tuple[int, int]] = []  # (a, b): the frames strictly between were passed over
        self._usable: list[int] = []  # frames read that showed a usable board
        self._continuity = 0  # evidence of footage: pairs showing the board held, neighbours alike
        self._futures: dict[int, Future[Look]] = {}

    def _look(self, index: int) -> Look:
        item = self._source.load(index)
        if isinstance(item, SkippedFrame):
            return Look(index, None, item, None, None)
        grey = item.grey()
        thumb = cv2.resize(grey, _THUMB_SIZE, interpolation=cv2.INTER_AREA).astype(np.float32)
        detection = self._detect(item)
        visible = None if self._board_corners_m is None else visible_corner_count(detection, self._board_corners_m, item.image_size)
        return Look(index, item, None, detection, thumb, visible)

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
                    self._prefetch(keys, position)
                    b = self._get(keys[position])
                    yield from self._between(a, b)
                    yield from self._emit(b)
                    a = b
            finally:
                for future in self._futures.values():
                    future.cancel()
                self._futures.clear()

    def _prefetch(self, keys: list[int], position: int) -> None:
        """Ask for the middles of later key pairs that already look different, so that both workers
        stay busy while this pair is bisected. Only what is read early changes, never what is yielded:
        each pair is judged again, in order, when its turn comes."""
        for j in range(position, min(position + self._lookahead - 1, len(keys) - 1)):
            low, high = self._futures.get(keys[j]), self._futures.get(keys[j + 1])
            if low is None or high is None or not (low.done() and high.done()) or keys[j + 1] - keys[j] <= 1:
                continue
            if not self._same(low.result(), high.result(), count=False, gap=keys[j + 1] - keys[j]):
                self._ask((keys[j] + keys[j + 1]) // 2)

    def _between(self, a: Look, b: Look) -> Iterator[tuple[Frame, Detection]]:
        if b.index - a.index <= 1:
            self._same(a, b)  # nothing between them; still evidence whether this is footage
            return
        if self._same(a, b, gap=b.index - a.index):
            self.passed_over += b.index - a.index - 1
            self._passed.append((a.index, b.index))
            if min(a.detection.corner_count, b.detection.corner_count) >= _MIN_CORNERS:  # type: ignore[union-attr]
                self.held_repeats += b.index - a.index - 1
            return
        middle = self._get((a.index + b.index) // 2)
        for low, high in ((a, middle), (middle, b)):  # ask both halves' middles now, so both workers share them
            if high.index - low.index > 1 and not self._same(low, high, count=False, gap=high.index - low.index):
                self._ask((low.index + high.index) // 2)
        yield from self._between(a, middle)
        yield from self._emit(middle)
        yield from self._between(middle, b)

    def _same(self, a: Look, b: Look, *, count: bool = True, gap: int = 0) -> bool:
        """Whether the frames between a and b can be passed over (gap: how many apart they are;
        a held board with a flickering detection is looked at every `_HELD_GAP` frames, footage
        without a board every `_AWAY_GAP`)."""
        video = self._continuity >= _VIDEO_AFTER_SAME_VIEWS
        verdict = compare_views(a, b, self._size, video=video)
        same = verdict == "same" or (verdict == "held" and gap <= _HELD_GAP) or (verdict == "away" and gap <= _AWAY_GAP)
        if count and a.detection is not None and b.detection is not None and a.thumb is not None and b.thumb is not None:
            board_held = same and min(a.detection.corner_count, b.detection.corner_count) >= _MIN_CORNERS
            neighbours_alike = b.index - a.index == 1 and float(np.mean(np.abs(a.thumb - b.thumb))) < _ADJACENT_SAME_GREY
            self._continuity += int(board_held or neighbours_alike)
        return same

    def _emit(self, look: Look) -> Iterator[tuple[Frame, Detection]]:
        if look.frame is None:
            assert look.skipped is not None
            self._source.skipped.append(look.skipped)
            return
        assert look.detection is not None
        if look.detection.corner_count >= _MIN_CORNERS:
            self._usable.append(look.index)
        yield look.frame, look.detection

    def fill_in(self, *, near: int = _FILL_NEAR) -> Iterator[tuple[Frame, Detection]]:
        """The frames passed over within `near` frames of a usable board: the nearest first
        (distance 1 everywhere, then 2, ...), each distance in index order.

        For a hurried capture, where the selector is short of frames to choose from: a board seen
        briefly or moving is where the frames that were passed over still differ a little.
        """
        usable = np.array(sorted(self._usable))
        by_distance: list[tuple[int, int]] = []
        if usable.size:
            for low, high in self._passed:
                for index in range(low + 1, high):
                    at = int(np.searchsorted(usable, index))
                    nearest = min(abs(int(usable[k]) - index) for k in (at - 1, at) if 0 <= k < usable.size)
                    if nearest <= near:
                        by_distance.append((nearest, index))
        wanted = [index for _, index in sorted(by_distance)]
        with ThreadPoolExecutor(max_workers=self._workers, thread_name_prefix="scan") as pool:
            pending: deque[Future[Look]] = deque()
            try:
                for index in wanted:
                    pending.append(pool.submit(self._look, index))
                    if len(pending) >= 2 * self._workers + 2:
                        self.passed_over -= 1
                        yield from self._emit(pending.popleft().result())
                while pending:
                    self.passed_over -= 1
                    yield from self._emit(pending.popleft().result())
            finally:
                for future in pending:
                    future.cancel()

    def _ask(self, index: int) -> None:
        if index not in self._futures:
            self._futures[index] = self._pool.submit(self._look, index)

    def _get(self, index: int) -> Look:
        self._ask(index)
        return self._futures.pop(index).result()
