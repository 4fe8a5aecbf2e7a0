"""Noticing, while the capture runs, that the camera shows some other board than the one configured.

A webcam in mirror mode, a 5x7 board printed where the default 8x11 was configured, the wrong
dictionary: every frame then says "no board", and the capture's end explains why
(`diagnose_board_mismatch`, run when not one frame showed the board). Live, the person would
stand there until they gave up. So `BoardWatch` keeps a few of the frames that showed no usable
board and, once enough of them came in a row, asks the same diagnosis; its answer becomes the
guidance's hint until a frame shows the configured board.

Every decision counts frames, never seconds, so a recording replays the hint at the frame the live
session showed it. A diagnosis runs on a thread of its own while the frames keep coming, and its
answer is taken a fixed number of frames later (`ANSWER_AFTER`), waiting for it there if it is not
done: in the frame loop it stalled the live preview for 0.25-1 s at every check (the first one 1.5 s
into every capture whose board was not yet in view), and a fixed lag keeps the hint's frame the same
live and in a replay, however fast the machine.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.board_diagnosis import diagnose_board_mismatch, halved_to_width
from calibcoach.coverage.detector import Detection
from calibcoach.drivers.base import Frame
from calibcoach.drivers.errors import BoardError

# Frames in a row without a usable board before the first diagnosis: 1.5 s at 30 fps. A person
# bringing the right board into view is past it within a few frames of it entering, so it is not
# diagnosed on the way; someone who sees "no board" for longer has started to wonder. A diagnosis
# costs ~0.25 s on three 720p frames with nothing board-like in them (22 dictionaries searched;
# ~1 s with a board's markers in all three, and then it names the cause and stops). One that found
# nothing is asked again after twice as many frames, then every `CHECK_EVERY * MAX_BACKOFF` (6 s
# at 30 fps): a camera left on a scene without a board spends ~4% of a core on it, and a board
# shown late is named within 6 s.
CHECK_EVERY = 45
MAX_BACKOFF = 4
# Samples wider than this are halved (and halved again) first: a 4K frame's markers stay many pixels
# wide, and the diagnosis costs what a 1080p one does (~4x less than at 4K).
MAX_SAMPLE_WIDTH = 1920
# Kept frames: among every 8th frame since the last diagnosis, the three with the most of the
# board's own markers (a mirrored or other-dictionary board shows none: then the latest three).
SAMPLES = 3
SAMPLE_EVERY = 8
# The right board, far away or soft, can show a few of its markers and no corners; with this many
# of them in one frame it would have given corners (each pair of neighbours gives one), so only
# then is "visible but never forming the board's corners" said.
MARKERS_FOR_A_BOARD = 8
# Frames between a diagnosis's start and the frame that takes its answer: 1 s at 30 fps, longer than a
# diagnosis takes on a core of its own (~0.25 s with nothing board-like in view, ~1 s with another
# board's markers), shorter than the next check's wait (2 * CHECK_EVERY), so one runs at a time.
ANSWER_AFTER = 30


class _Diagnosis:
    """`diagnose()` run on a daemon thread (nothing waits for it at exit); `answer()` waits for it."""

    def __init__(self, diagnose: Callable[[], BoardError | None], due: int) -> None:
        self.due = due  # the streak at which the answer is taken
        self._answer: BoardError | None = None
        self._failure: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(diagnose,), name="board-diagnosis", daemon=True)
        self._thread.start()

    def _run(self, diagnose: Callable[[], BoardError | None]) -> None:
        try:
            self._answer = diagnose()
        except BaseException as exc:  # noqa: BLE001 - raised where the answer is taken
            self._failure = exc

    def answer(self) -> BoardError | None:
        self._thread.join()
        if self._failure is not None:
            raise self._failure
        return self._answer


class BoardWatch:
    """Feed it every decided frame (`see`); `hint` is what to tell the person about the board, or "".

    `min_corners`: the corners a frame needs to count (the session's `SelectorSettings.min_corners`);
    one that has them shows the configured board.
    """

    def __init__(self, min_corners: int) -> None:
        self.min_corners = min_corners
        self.hint = ""
        self.finding: BoardError | None = None  # the cause `hint` names, for the capture's end to say again
        self.checks = 0  # diagnoses due so far (each a few hundred ms of detection, unless skipped for corners seen)
        self._found = False  # a frame showed the configured board: it is the right one, nothing to watch
        self._streak = 0  # frames in a row without a usable board
        self._next_check = CHECK_EVERY  # ... at which the next diagnosis runs
        self._samples: list[tuple[int, int, np.ndarray]] = []  # (own markers, frame index, grey) since the last diagnosis
        self._corners_seen = False  # ... and whether a frame since then showed any corner of the configured board
        self._running: _Diagnosis | None = None  # the diagnosis whose answer is still to be taken

    def see(self, frame: Frame, detection: Detection, spec: BoardSpec) -> str:
        """Take one decided frame and its detection with `spec` (the board as configured, its print's
        variant settled where known); returns the current hint ("" when there is nothing to say)."""
        if self._found:
            return ""
        if detection.corner_count >= self.min_corners:
            # the right board: a diagnosis still running is not asked for its answer
            self._found, self.hint, self.finding, self._samples, self._running = True, "", None, [], None
            return ""
        if self.hint:
            return self.hint  # said: it holds until the board is seen
        self._streak += 1
        self._corners_seen = self._corners_seen or detection.corner_count > 0
        if self._running is not None and self._streak == self._running.due:
            self.settle()
        if self._streak % SAMPLE_EVERY == 1:
            self._keep(frame.index, frame.grey(), int(detection.marker_ids.size))
        if self._streak == self._next_check:
            self.checks += 1
            self._next_check += CHECK_EVERY * min(2 ** self.checks, MAX_BACKOFF)
            # The right board far away or mostly out of view shows a corner or a few; a 5x7 print under
            # the default 8x11, a mirrored or another dictionary's board show none. So frames with a
            # corner of the configured board are not diagnosed: no "another board" for the right one,
            # and no 1-2 s diagnosis every 180 frames while it is held too far.
            if not self._corners_seen:
                greys = [g for _m, _i, g in self._samples]
                specific = max(markers for markers, _i, _g in self._samples) < MARKERS_FOR_A_BOARD
                self._running = _Diagnosis(lambda: diagnose_board_mismatch(spec, greys, specific_only=specific),
                                           due=self._streak + ANSWER_AFTER)
            self._samples, self._corners_seen = [], False  # the next diagnosis looks at frames it has not seen
        return self.hint

    def settle(self) -> None:
        """Take the running diagnosis's answer now, waiting for it (the capture ended before its frame came)."""
        running, self._running = self._running, None
        error = None if running is None else running.answer()
        if error is not None:
            self.finding = error
            self.hint = f"No corners of the configured board yet: {error}."

    def _keep(self, frame_index: int, grey: np.ndarray, markers: int) -> None:
        self._samples.append((markers, frame_index, halved_to_width(grey, MAX_SAMPLE_WIDTH).copy()))
        if len(self._samples) > SAMPLES:
            # the fewest markers go first, and of those the oldest
            self._samples.remove(min(self._samples, key=lambda s: (s[0], s[1])))
