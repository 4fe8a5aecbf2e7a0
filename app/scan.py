"""Held-frame scan: every frame of a replay is decoded and seen, but a held board is tracked, not detected.

Footage of a handheld board is mostly holds: the board sits at one pose for a second or more and
each frame shows it again, a pixel or two away (tremor). Those frames are what the final solve
wants most -- sharp, still, each with its own sensor noise, so together they average a pose's
corner noise down -- yet a full `detectBoard` on each of them (marker search over the whole
image) is nearly all of a replay's cost. So each frame is decoded and the board of the frame
before it is *tracked* into it (`CharucoBoardDetector.track`: the previous markers handed to
`detectBoard`, which then only interpolates and refines its corners, ~0.5 ms instead of ~15 at
720p, to the same accuracy). A frame is detected in full when:

- it lies on the re-detection grid (every `REDETECT_EVERY`-th frame), so every hold is seen with
  the corners a fresh detection finds (a corner the first frame missed, the session's own
  judgement of the hold);
- its thumbnail changed too much since the frame before for the board to be tracked (the board
  moved more than about `TRACK_MAX_SHIFT_PX`; these are detected ahead on worker threads);
- tracking failed (the board moved more, or a corner jumped).

A frame of footage into and out of which the scene changed fast (`_TRANSIT_CHANGE`) shows a board
in transit: it is marked so and the session rejects it as moving whatever its edges say (it
smears, and on other renderers and real cameras its corners are biased along the motion); only
its first and last frames (which give the frames beside it their speed) and every 8th are
detected, every 32nd once a board has been seen. The tracked
frames of a hold join the session's reserve when a fully detected frame of the same hold was
judged usable and either the board moved at most the selector's smear limit into and out of them
or their own image passes its smear and blur tests (app/replay.py).

Frames without a board whose thumbnail did not change either show no board either: their empty
detection is repeated. Every decision depends on the images alone, never on timing or threads,
so a replay is reproducible whatever the machine; `--every-frame` detects every frame in full
(the reference this scan is measured against in bench/heldout.py), and a calibcoach recording is
always replayed that way, frame by frame as it was decided live.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace

import cv2
import numpy as np

from calibcoach.coverage.detector import (
    MIN_FRAME_CORNERS,
    TRACK_MAX_SHIFT_PX,
    CharucoBoardDetector,
    Detection,
    shared_corners,
)
from calibcoach.coverage.select import SelectorSettings
from calibcoach.coverage.sharpness import percentile_spread
from calibcoach.drivers.base import DEFAULT_FPS, Frame, frames_ahead

try:  # built by `pip install` where a C compiler is present (pyproject ext-modules, optional)
    from calibcoach.coverage._block_mean import block_means as _block_means
except ImportError:  # pragma: no cover - no compiler at install: cv2.resize, the same numbers
    _block_means = None

# Every 5th frame (1/6 s at 30 fps) is detected in full, the rest of a hold tracked. A tracked
# corner starts from the frame before and OpenCV's refinement stops within 0.1 px of its start, so
# it inherits part of that frame's error down the chain (consecutive frames' corner errors
# correlate 0.13 tracked against 0.02 detected on a careful 720p render, 0.31 against 0.05 on a
# fisheye). Restarting the chain every 5th frame instead of every 15th lowered the held-out error
# (30 renders, 6 cells: geometric mean 0.92x, 18 better; fisheye 0.77x, careful and wide 0.86x,
# dim 1.09x) for ~15% fewer tracked frames (replay ratio 0.59 -> 0.60).
REDETECT_EVERY = 5
_THUMB_SIZE = (80, 45)  # (width, height): 16 px cells at 720p
# Largest thumbnail cell change, as a share of the thumbnail's contrast, that a trackable move
# (<= 3 px) makes: on 720p renders a 2-4 px move changed the most-changed 16 px cell by 20-40
# grey levels of the board's ~200 of contrast (p5-p95). Above it tracking would likely fail, so
# the frame is detected ahead. Only the speed depends on it: a frame below it whose tracking fails
# is detected there and then.
_TRACKABLE_CHANGE = 0.1
# A change this large (p5 of 8+ px moves on 720p renders) into and out of a frame of footage is a
# board in transit: at 30 fps it smears >= 2 px even in an 8 ms exposure, past the selector's
# 1.5 px limit, so only some such frames are detected: the session still sees the board pass, and
# counts it moving. Until the scan has seen a board at all, every 8th (`_TRANSIT_SAMPLE`; a second
# of transit gives 3-4): footage whose board is only ever in motion must not read as footage without
# a board (the session would look for a wrong board spec instead of saying "hold it still"). Once a
# board has been seen, every 32nd: a transit's smear hides the board from the detector -- of the 196
# frames sampled at every 8th on five renders (careful, shaky, dim, two messy), 4 showed one -- and
# each costs a full detection (~5 ms at 720p; 0.2 s of a careful replay's CPU at every 8th).
# Independent stills change this much between all neighbours: they are detected until the source
# has shown itself to be footage (`_FOOTAGE_AFTER` pieces of evidence: neighbours alike, or a board
# found in two neighbouring frames at nearly the same place, see `_FOOTAGE_SHIFT`).
_TRANSIT_CHANGE = 0.4
# ... and that premise holds only where the frames come fast enough: a transit's move of half a
# thumbnail cell a frame (8 px at 720p) smears it past the selector's limit within the shortest
# usual indoor exposure (8 ms, a quarter of a 30 fps frame) only from ~23 fps at 720p (16 fps at
# 1080p) up. Slower footage (a 6 fps webcam video of real captures: boards 2-19 px apart from frame
# to frame, sharp) is detected frame by frame, its speed judged by the session.
_TRANSIT_MOVE_CELLS = 0.5
_SHORTEST_EXPOSURE_S = 0.008
_TRANSIT_SAMPLE = 8
_TRANSIT_SAMPLE_ONCE_SEEN = 32
_FOOTAGE_AFTER = 5
# A board fully detected in two neighbouring frames whose corners moved at most this share of the
# image diagonal (15 px at 720p) is footage too. Fast-swinging footage has short holds whose tremor
# moves the thumbnails past `_TRACKABLE_CHANGE`, so alike neighbours alone came late: on a messy 720p
# render (boards held 2-6 frames) only at frame 219 of 784, every transit before it detected and
# judged. Its boards moved 0.7-7.6 px between neighbouring detections (p5-p95, 126 pairs; careful:
# 0.3-3.4), while between neighbouring photos of real photo sets they moved 66 px or more (3 cameras
# of pycamset, 1280x1024: 57 pairs, 5% of the diagonal): the bound is 5x under the closest photos.
_FOOTAGE_SHIFT = 0.01
_SAME_SCENE_CHANGE = 0.015  # no board and a change this small (~3 of 200 grey levels): the same empty scene


@dataclass(frozen=True, slots=True)
class Seen:
    """One frame as the scan saw it."""

    frame: Frame
    detection: Detection
    tracked_from: int | None  # the frame whose board was tracked into this one; None: detected in full
    shift_px: float | None  # tracked frames: how far the board moved since `tracked_from`, px
    in_transit: bool = False  # the scene changed fast into and out of it (see `_TRANSIT_CHANGE`): never in a solve
    skipped: bool = False  # in transit and not sampled: not detected (its detection is empty)

    @property
    def detected_in_full(self) -> bool:
        """Neither tracked nor skipped in transit: the frames the session judges."""
        return not self.skipped and self.tracked_from is None


def transit_smears(image_width_px: int, fps: float | None) -> bool:
    """Whether a transit (see `_TRANSIT_CHANGE`) smears past the selector's limit at this size and frame
    rate within `_SHORTEST_EXPOSURE_S`; `fps` None: a folder's nominal 30 fps (its timestamps')."""
    move_px = _TRANSIT_MOVE_CELLS * image_width_px / _THUMB_SIZE[0]
    return move_px * (fps or DEFAULT_FPS) * _SHORTEST_EXPOSURE_S >= SelectorSettings().max_smear_px


def thumbnail(grey: np.ndarray) -> np.ndarray:
    """(45, 80) float32 cell means of a grey frame: cv2.resize(INTER_AREA)'s numbers, bit for bit.

    Where the frame's sides are whole multiples of the cells' of at least 3 px (720p: 16, 1080p:
    24, 4K: 48) and the C extension was built, its block means are 5x cheaper (0.05 ms instead of
    0.23 at 720p, for every frame a replay decodes) and round as OpenCV does; OpenCV's 2x2 case
    rounds differently, so it and every other size go to cv2.resize.
    """
    height, width = grey.shape
    cell_w, cell_h = width // _THUMB_SIZE[0], height // _THUMB_SIZE[1]
    if _block_means is not None and cell_w >= 3 and cell_h >= 3 and cell_w * _THUMB_SIZE[0] == width \
            and cell_h * _THUMB_SIZE[1] == height and grey.dtype == np.uint8 and grey.flags.c_contiguous:
        means = np.empty(_THUMB_SIZE[::-1], np.float32)
        _block_means(grey, height, width, cell_h, cell_w, means)
        return means
    return cv2.resize(grey, _THUMB_SIZE, interpolation=cv2.INTER_AREA).astype(np.float32)


def scene_change(before: np.ndarray, after: np.ndarray) -> float:
    """Largest thumbnail cell change between two frames, as a share of the scene's contrast (p1 to p99)."""
    return float(np.max(np.abs(after - before))) / max(percentile_spread(after, 1.0, 99.0), 10.0)


class HeldFrameScan:
    """(frame, detection) for every frame of `frames`, tracking held boards; see the module docstring.

    `make_detector` builds one settled detector per thread (detectors are not thread-safe).
    `tracked` counts the frames tracked rather than detected, `repeated` the empty frames whose
    detection was repeated.
    """

    def __init__(self, frames: Iterable[Frame], make_detector: Callable[[], CharucoBoardDetector], *,
                 workers: int = 2, lookahead: int | None = None, track: bool = True, judge_transit: bool = True) -> None:
        self._frames = iter(frames)
        self._track = track  # False: every frame detected in full (--every-frame, recordings)
        self._judge_transit = judge_transit  # False: no frame is marked in transit (a recording replays live decisions)
        self._make_detector = make_detector
        self._local = threading.local()
        # frames planned (their detections started) ahead of the one being seen; None: `frames_ahead` of the first
        self._workers, self._lookahead = max(1, int(workers)), None if lookahead is None else max(2, int(lookahead))
        self.tracked = 0
        self.repeated = 0
        self.detected = 0
        self.skipped = 0
        self._richest: Seen | None = None  # the fully detected frame of the current hold with the most corners
        self._board_seen = False  # a frame seen so far showed a board (>= MIN_FRAME_CORNERS): transits are sampled sparser
        self._continuity = 0  # neighbouring frames alike so far: evidence of footage rather than independent stills

    def _detector(self) -> CharucoBoardDetector:
        detector = getattr(self._local, "detector", None)
        if detector is None:
            detector = self._local.detector = self._make_detector()
        return detector

    def __iter__(self) -> Iterator[Seen]:
        with ThreadPoolExecutor(max_workers=self._workers, thread_name_prefix="scan") as pool, \
                ThreadPoolExecutor(max_workers=1, thread_name_prefix="thumbnail") as thumbnails:
            window: deque[_Plan] = deque()
            previous: Seen | None = None
            # the newest frame waits for its successor, whose change in is its change out
            newest: Frame | None = None
            newest_thumb, newest_change = np.zeros(0, np.float32), float("inf")
            try:
                for frame, thumb in _thumbnailed(self._frames, thumbnails):
                    if self._lookahead is None:
                        self._lookahead = frames_ahead(frame.image.nbytes)
                    change_in = float("inf") if newest is None else scene_change(newest_thumb, thumb)
                    if newest is not None:
                        self._append(window, self._plan(newest, newest_change, change_out=change_in, pool=pool), pool)
                    newest, newest_thumb, newest_change = frame, thumb, change_in
                    while len(window) > self._lookahead:
                        previous = self._see(window.popleft(), previous)
                        yield previous
                if newest is not None:
                    self._append(window, self._plan(newest, newest_change, change_out=float("inf"), pool=pool), pool)
                while window:
                    previous = self._see(window.popleft(), previous)
                    yield previous
            finally:
                for plan in window:
                    if plan.detection is not None:
                        plan.detection.cancel()

    def _plan(self, frame: Frame, change_in: float, *, change_out: float,
              pool: ThreadPoolExecutor) -> _Plan:
        """What to do with `frame`, decided from the images alone so that detections can start ahead."""
        if change_in <= _TRACKABLE_CHANGE:
            self._continuity += 1
        transit = self._judge_transit and self._continuity >= _FOOTAGE_AFTER and min(change_in, change_out) > _TRANSIT_CHANGE
        if transit and self._track and frame.index % _TRANSIT_SAMPLE_ONCE_SEEN:
            # every 8th is detected when it is seen, and only if no board has been seen by then: the
            # frames before it are seen in order, so the choice is the images', whatever the lookahead
            return _Plan(frame, change_in, None, transit=True, skip=frame.index % _TRANSIT_SAMPLE != 0,
                         sample_unless_seen=frame.index % _TRANSIT_SAMPLE == 0)
        if not self._track or frame.index % REDETECT_EVERY == 0 or change_in > _TRACKABLE_CHANGE:
            return _Plan(frame, change_in, pool.submit(self._detect, frame), transit=transit)
        return _Plan(frame, change_in, None, transit=transit)

    def _append(self, window: deque[_Plan], plan: _Plan, pool: ThreadPoolExecutor) -> None:
        """Add `plan` after the frame before it, detecting a transit's first and last frames.

        The frames either side of a judged frame give its speed (the motion hint and the transit
        veto; app/replay.py). Beside an undetected transit frame only the other side gives it,
        and at the edge of a swing that side reads the board slower than it is (a messy 720p
        video: frames at 55-76 px/s one-sided, 100-136 px/s across both neighbours, over the
        80 px/s veto, entered the final solve: 0.026 px against the truth where `--every-frame`
        gave 0.008). So a transit's frames next to frames that are not in transit are detected
        (and still rejected as in transit), and the frames beside them are judged as
        `--every-frame` judges them.
        """
        before = window[-1] if window else None
        if before is not None and not before.transit and _unseen(plan):
            plan = self._detected_ahead(plan, pool)
        elif before is not None and not plan.transit and _unseen(before):
            window[-1] = self._detected_ahead(before, pool)
        window.append(plan)

    def _detected_ahead(self, plan: _Plan, pool: ThreadPoolExecutor) -> _Plan:
        """`plan` with its frame's detection started (no longer skipped or merely sampled)."""
        return replace(plan, detection=pool.submit(self._detect, plan.frame), skip=False, sample_unless_seen=False)

    def _detect(self, frame: Frame) -> Detection:
        return self._detector().detect(frame.grey())

    def _see(self, plan: _Plan, previous: Seen | None) -> Seen:
        seen = self._see_frame(plan, previous)
        self._board_seen = self._board_seen or seen.detection.corner_count >= MIN_FRAME_CORNERS
        if plan.change_in > _TRACKABLE_CHANGE and previous is not None and _board_stayed(previous, seen):
            self._continuity += 1  # alike neighbours were counted when planned; this pair was not
        return seen

    def _see_frame(self, plan: _Plan, previous: Seen | None) -> Seen:
        frame = plan.frame
        if plan.sample_unless_seen and not self._board_seen:
            self.detected += 1
            return self._fresh(Seen(frame, self._detect(frame), None, None, in_transit=True), previous)
        if plan.skip or plan.sample_unless_seen:
            self.skipped += 1
            return Seen(frame, Detection.empty(), None, None, in_transit=True, skipped=True)
        if plan.detection is not None:
            self.detected += 1
            return self._fresh(Seen(frame, plan.detection.result(), None, None, in_transit=plan.transit), previous)
        assert previous is not None  # the first frame is always detected
        if previous.detection.corner_count >= MIN_FRAME_CORNERS:
            # From the hold's richest detection when it found more corners than the frame before
            # (a partial view's detection flickers: each fresh one finds another few), else from
            # the frame before; the shift is always measured from the frame before.
            sources = [self._richest] if self._richest is not None and \
                self._richest.detection.corner_count > previous.detection.corner_count else []
            for source in [*sources, previous]:
                tracked = self._detector().track(frame.grey(), source.detection)
                if tracked is not None:
                    self.tracked += 1
                    return Seen(frame, tracked, previous.frame.index, board_shift_px(previous.detection, tracked),
                                in_transit=plan.transit)
        elif not previous.skipped and plan.change_in <= _SAME_SCENE_CHANGE:  # previous is the frame just before
            self.repeated += 1
            return Seen(frame, previous.detection, None, None, in_transit=plan.transit)
        self.detected += 1
        return self._fresh(Seen(frame, self._detect(frame), None, None, in_transit=plan.transit), previous)

    def _fresh(self, seen: Seen, previous: Seen | None) -> Seen:
        """Note a full detection as the hold's richest when it continues the hold (trackable from the frame before)."""
        continues = previous is not None and self._richest is not None and \
            board_shift_px(previous.detection, seen.detection) <= TRACK_MAX_SHIFT_PX
        if seen.detection.corner_count >= MIN_FRAME_CORNERS and \
                (not continues or seen.detection.corner_count >= self._richest.detection.corner_count):  # type: ignore[union-attr]
            self._richest = seen
        elif not continues:
            self._richest = None
        return seen


def _thumbnailed(frames: Iterable[Frame], pool: ThreadPoolExecutor, ahead: int = 4) -> Iterator[tuple[Frame, np.ndarray]]:
    """(frame, its thumbnail), the thumbnails made a few frames ahead on `pool` (OpenCV releases the GIL),
    off the thread that plans, tracks and judges."""
    pending: deque[tuple[Frame, Future[np.ndarray]]] = deque()
    for frame in frames:
        pending.append((frame, pool.submit(lambda f: thumbnail(f.grey()), frame)))
        if len(pending) > ahead:
            done, thumb = pending.popleft()
            yield done, thumb.result()
    while pending:
        done, thumb = pending.popleft()
        yield done, thumb.result()


@dataclass(frozen=True, slots=True)
class _Plan:
    frame: Frame
    change_in: float  # `scene_change` from the frame before (inf for the first)
    detection: Future[Detection] | None  # started ahead; None: track the board (or repeat the empty scene)
    transit: bool = False
    skip: bool = False  # in transit and not sampled: not detected at all
    sample_unless_seen: bool = False  # in transit: detected when seen if no board has been seen yet, else skipped


def _unseen(plan: _Plan) -> bool:
    """A transit frame planned not to be detected (skipped, or sampled only while no board has been seen)."""
    return plan.transit and plan.detection is None and (plan.skip or plan.sample_unless_seen)


def _board_stayed(before: Seen, after: Seen) -> bool:
    """Both frames were detected in full, show a board, and it moved at most `_FOOTAGE_SHIFT` of the diagonal."""
    if not (before.detected_in_full and after.detected_in_full):
        return False
    if min(before.detection.corner_count, after.detection.corner_count) < MIN_FRAME_CORNERS:
        return False
    width, height = after.frame.image_size
    return board_shift_px(before.detection, after.detection) <= _FOOTAGE_SHIFT * float(np.hypot(width, height))


def board_shift_px(before: Detection, after: Detection) -> float:
    """Largest move of a corner both detections found, px (inf when they share fewer than 4)."""
    shared = shared_corners(before, after)
    if shared is None:
        return float("inf")
    ia, ib = shared
    return float(np.linalg.norm(after.corners_px[ib] - before.corners_px[ia], axis=1).max())
