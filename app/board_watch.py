"""Noticing, while the capture runs, that the camera shows some other board than the one configured.

A webcam in mirror mode, a 5x7 board printed where the default 8x11 was configured, the wrong
dictionary: every frame then says "no board", and the capture's end explains why
(`diagnose_board_mismatch`, run when not one frame showed the board). Live, the person would
stand there until they gave up. So `BoardWatch` keeps a few of the frames that showed no usable
board and, once enough of them came in a row, asks the same diagnosis; its answer becomes the
guidance's hint until a frame shows the configured board.

Every decision counts frames, never seconds, so a recording replays the hint at the frame the live
session showed it.
"""

from __future__ import annotations

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
# at 30 fps): a camera left on a scene without a board spends ~4% of its time here, and a board
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

    def see(self, frame: Frame, detection: Detection, spec: BoardSpec) -> str:
        """Take one decided frame and its detection with `spec` (the board as configured, its print's
        variant settled where known); returns the current hint ("" when there is nothing to say)."""
        if self._found:
            return ""
        if detection.corner_count >= self.min_corners:
            self._found, self.hint, self.finding, self._samples = True, "", None, []
            return ""
        if self.hint:
            return self.hint  # said: it holds until the board is seen
        self._streak += 1
        self._corners_seen = self._corners_seen or detection.corner_count > 0
        if self._streak % SAMPLE_EVERY == 1:
            self._keep(frame.index, frame.grey(), int(detection.marker_ids.size))
        if self._streak == self._next_check:
            self.checks += 1
            self._next_check += CHECK_EVERY * min(2 ** self.checks, MAX_BACKOFF)
            most_markers = max(markers for markers, _i, _g in self._samples)
            # The right board far away or mostly out of view shows a corner or a few; a 5x7 print under
            # the default 8x11, a mirrored or another dictionary's board show none. So frames with a
            # corner of the configured board are not diagnosed: no "another board" for the right one,
            # and no 1-2 s diagnosis in the frame loop every 180 frames while it is held too far.
            error = None if self._corners_seen else diagnose_board_mismatch(
                spec, [g for _m, _i, g in self._samples], specific_only=most_markers < MARKERS_FOR_A_BOARD)
            self._samples, self._corners_seen = [], False  # the next diagnosis looks at frames it has not seen
            if error is not None:
                self.finding = error
                self.hint = f"No corners of the configured board yet: {error}."
        return self.hint

    def _keep(self, frame_index: int, grey: np.ndarray, markers: int) -> None:
        self._samples.append((markers, frame_index, halved_to_width(grey, MAX_SAMPLE_WIDTH).copy()))
        if len(self._samples) > SAMPLES:
            # the fewest markers go first, and of those the oldest
            self._samples.remove(min(self._samples, key=lambda s: (s[0], s[1])))
