"""ChArUco detection: image -> Detection, with the print's quirks found automatically.

Uses OpenCV 5's `CharucoDetector.detectBoard` with `CORNER_REFINE_SUBPIX` (CONTOUR does no
refinement of the chessboard corners that matter here) and `board.matchImagePoints`.
Legacy-pattern prints (OpenCV < 4.6 boards with an even number of rows) and inverted
(white-on-black) prints are found on the first frames that show markers and then kept, so the
per-frame cost stays one `detectBoard` call.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from calibcoach.coverage.board import DICTIONARY_NAMES, BoardSpec, dictionary_id
from calibcoach.drivers.errors import BoardError

# The method: a frame counts only with at least 6 ChArUco corners. A board's pose has 6 degrees of
# freedom and a homography 8, so 4 corners fit any plane exactly and hide a misplaced corner; with 6
# the fit has slack to show one. Every "does this frame show the board" test reads this one number
# (the selector's `SelectorSettings.min_corners` starts from it).
MIN_FRAME_CORNERS = 6


@dataclass(frozen=True, slots=True)
class Detection:
    """The board as seen in one frame."""

    corners_px: np.ndarray  # (N, 2) float32 ChArUco corner positions, pixels
    ids: np.ndarray  # (N,) int32 ChArUco corner ids, 0 .. corner_count-1
    object_points_m: np.ndarray  # (N, 3) float32 the same corners in the board frame, metres
    marker_ids: np.ndarray  # (M,) int32 ArUco marker ids found (M may be > 0 with N == 0)
    # (M, 4, 2) float32 those markers' corners, pixels; empty when the detection was rebuilt from
    # stored corners. They say where the board is when too few ChArUco corners were found
    # (coverage/local_view.py re-detects around them).
    marker_corners_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 2), np.float32))

    @property
    def corner_count(self) -> int:
        return int(self.ids.shape[0])

    @staticmethod
    def empty(marker_ids: np.ndarray | None = None) -> Detection:
        return Detection(
            corners_px=np.zeros((0, 2), np.float32),
            ids=np.zeros((0,), np.int32),
            object_points_m=np.zeros((0, 3), np.float32),
            marker_ids=np.zeros((0,), np.int32) if marker_ids is None else marker_ids,
        )


# OpenCV refines the marker corners and then the ChArUco corners with cornerSubPix, stopping once
# a step is under this (its default). Refining further moved corners away from the truth, most on
# noisy footage: rms on held frames +1% careful, +2% shaky, +4.5% fisheye, +5.4% dim 720p
# (bench/results/corner_refinement.md; over the 30 held-out renders 1.43x the error). Refining only
# tracked frames further (they start from the previous frame's markers, and at 0.1 px inherit part
# of its error) made them as good as full detections on clean footage but 3.5% worse on dim; so
# detection and tracking both keep OpenCV's step.
CORNER_ACCURACY_PX = 0.1


# OpenCV 4.14+/5 reads a marker's cells as dark shares and counts a cell within this much of one
# half as wrong either way (`validBitIdThreshold`); at its default 0.49 soft and dim markers are
# lost that OpenCV 4.12 read (pycamset cam 1, a defocused photo: 31 markers where 4.12 found 37).
# At 0.6, dim 720p renders gave +49% ChArUco corners (median corner error +5%, no wrong id) and
# messy ones +86%, yet the replays' true error went 0.041 / 0.095 / 0.208 -> 0.081 / 0.079 / 0.103
# px on dim s101-103 and 0.153 -> 0.216 on messy s101; over all 11 cached renders (careful x4,
# dim x3, messy, shaky, wide, fisheye) the geometric mean of the error ratio was 1.03, 7 worse:
# no better on balance (the corners gained are the softest), so OpenCV's value stays, set here so
# that a new default of OpenCV's would not change calibcoach unseen.
VALID_BIT_THRESHOLD = 0.49


def _aruco_parameters(*, inverted: bool, accuracy_px: float = CORNER_ACCURACY_PX) -> cv2.aruco.DetectorParameters:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementMinAccuracy = accuracy_px
    params.detectInvertedMarker = inverted
    if hasattr(params, "validBitIdThreshold"):
        params.validBitIdThreshold = VALID_BIT_THRESHOLD
    return params


class CharucoBoardDetector:
    """Detects one board spec; settles legacy/inverted on the first frames that show markers.

    `variant_found` is None until the print's pattern and polarity are known; then it says which
    (e.g. "inverted print") and `spec` carries the settled values.
    """

    def __init__(self, spec: BoardSpec, *, corner_accuracy_px: float = CORNER_ACCURACY_PX) -> None:
        self.spec = spec
        self._accuracy_px = corner_accuracy_px  # the refinement's stopping step (bench/corner_refinement.py varies it)
        self._settled = spec.legacy is not None and spec.inverted is not None
        self._detector = self._make(legacy=bool(spec.legacy), inverted=bool(spec.inverted))
        self._board = spec.cv_board(legacy=bool(spec.legacy))
        self.variant_found: str | None = None

    def _make(self, *, legacy: bool, inverted: bool) -> cv2.aruco.CharucoDetector:
        board = self.spec.cv_board(legacy=legacy)
        return cv2.aruco.CharucoDetector(board, cv2.aruco.CharucoParameters(),
                                         _aruco_parameters(inverted=inverted, accuracy_px=self._accuracy_px))

    @property
    def settled(self) -> bool:
        return self._settled

    def detect(self, grey: np.ndarray) -> Detection:
        """Detect the board in a (H, W) uint8 image."""
        if grey.ndim != 2 or grey.dtype != np.uint8:
            raise ValueError(f"detect wants a (H, W) uint8 grey image, got {grey.shape} {grey.dtype}")
        if not self._settled:
            return self._detect_and_settle(grey)
        return self._run(self._detector, self._board, grey)

    def _run(self, detector: cv2.aruco.CharucoDetector, board: cv2.aruco.CharucoBoard, grey: np.ndarray) -> Detection:
        corners, ids, marker_corners, marker_ids = detector.detectBoard(grey)
        mids = np.zeros((0,), np.int32) if marker_ids is None else np.asarray(marker_ids, np.int32).reshape(-1)
        mcorners = np.asarray(marker_corners, np.float32).reshape(-1, 4, 2) if mids.size else np.zeros((0, 4, 2), np.float32)
        if ids is None or len(ids) == 0:
            return replace(Detection.empty(mids), marker_corners_px=mcorners)
        corners = np.asarray(corners, np.float32).reshape(-1, 2)
        ids = np.asarray(ids, np.int32).reshape(-1)
        obj, _img = board.matchImagePoints(corners.reshape(-1, 1, 2), ids.reshape(-1, 1))
        return Detection(corners, ids, np.asarray(obj, np.float32).reshape(-1, 3), mids, mcorners)

    def track(self, grey: np.ndarray, previous: Detection) -> Detection | None:
        """The board of `previous` (a frame or two ago, barely moved) found again in `grey`, ~20x cheaper.

        The marker search is skipped: `detectBoard` is handed the previous frame's marker corners,
        from which it interpolates the ChArUco corners and refines them in this image with its own
        windows. Its refinement stops once a step is under `cornerRefinementMinAccuracy` (0.1 px),
        so where it starts matters to that degree: the markers are moved by the first pass's
        median corner shift and the board refined again. On 362 held frames of a 720p render the
        corners so found lie 0.051 px (median; p95 0.102) from the truth, as the full detection's
        (0.050; 0.102), in 0.8 ms instead of 15. None when the board cannot be tracked (it moved
        more than `TRACK_MAX_SHIFT_PX`, or its shift is not one rigid move: corners jumped).
        """
        if not self._settled or previous.marker_corners_px.shape[0] == 0 or previous.corner_count < 4:
            return None
        markers = tuple(m.reshape(1, 4, 2) for m in previous.marker_corners_px)
        ids = previous.marker_ids.reshape(-1, 1)
        first = self._refined_from(grey, markers, ids)
        if first is None:
            return None
        shift = _shift_from(previous, first)
        if shift is None:
            return None
        moved = tuple((m + shift.astype(np.float32)) for m in markers)
        second = self._refined_from(grey, moved, ids)
        if second is None or second.corner_count < min(previous.corner_count, 6):
            return None
        if _shift_from(previous, second) is None:
            return None
        return Detection(second.corners_px, second.ids, second.object_points_m, previous.marker_ids,
                         np.concatenate([m.reshape(1, 4, 2) for m in moved]))

    def _refined_from(self, grey: np.ndarray, markers: tuple[np.ndarray, ...], ids: np.ndarray) -> Detection | None:
        corners, cids, _m, _ids = self._detector.detectBoard(grey, markerCorners=markers, markerIds=ids)
        if cids is None or len(cids) == 0:
            return None
        corners = np.asarray(corners, np.float32).reshape(-1, 2)
        cids = np.asarray(cids, np.int32).reshape(-1)
        obj, _img = self._board.matchImagePoints(corners.reshape(-1, 1, 2), cids.reshape(-1, 1))
        return Detection(corners, cids, np.asarray(obj, np.float32).reshape(-1, 3), ids.reshape(-1).astype(np.int32),
                         np.concatenate(markers).reshape(-1, 4, 2).astype(np.float32))

    def _detect_and_settle(self, grey: np.ndarray) -> Detection:
        """Try the print variants the spec leaves open; settle on the first that clearly works.

        The plain variant goes first and wins ties: inverted-marker mode also finds normal markers
        (sometimes one more), so a variant is taken only when it finds clearly more corners than
        the plain one, or the plain one finds too few to use.
        """
        legacies = [self.spec.legacy] if self.spec.legacy is not None else [False, True]
        if self.spec.squares_y % 2 == 1:
            legacies = legacies[:1]  # an odd row count prints identically in both patterns
        inverts = [self.spec.inverted] if self.spec.inverted is not None else [False, True]
        variants = [(bool(legacy), bool(inverted)) for inverted in inverts for legacy in legacies]
        best: tuple[bool, bool, Detection] | None = None
        for legacy, inverted in variants:
            det = self._run(self._make(legacy=legacy, inverted=inverted), self.spec.cv_board(legacy=legacy), grey)
            if best is None:
                best = (legacy, inverted, det)
                continue
            plain = best[2].corner_count
            if det.corner_count >= MIN_FRAME_CORNERS and (plain < MIN_FRAME_CORNERS or det.corner_count > 1.5 * plain):
                best = (legacy, inverted, det)
            elif det.corner_count == best[2].corner_count == 0 and det.marker_ids.size > best[2].marker_ids.size:
                best = (legacy, inverted, det)  # no corners anywhere: keep the richer marker list for diagnosis
        assert best is not None
        legacy, inverted, det = best
        if det.corner_count >= MIN_FRAME_CORNERS:
            self.settle(legacy=legacy, inverted=inverted)
        return det

    def settle(self, *, legacy: bool, inverted: bool) -> None:
        """Take the print's variant as known (found here, or by a detector in another process)."""
        self.spec = self.spec.with_detected(legacy=legacy, inverted=inverted)
        self._detector = self._make(legacy=legacy, inverted=inverted)
        self._board = self.spec.cv_board(legacy=legacy)
        self._settled = True
        found = [name for name, on in (("legacy pattern", legacy), ("inverted print", inverted)) if on]
        self.variant_found = ", ".join(found) if found else "standard pattern"


# A held board moves by its tremor, a pixel or two per frame; past 3 px the refinement may start
# nearer another saddle than its own (the subpixel window is ~9 px at 720p) and the frame is
# detected afresh.
TRACK_MAX_SHIFT_PX = 3.0
# The corners of a held board move together: a small rigid motion of the board is, in the image,
# an affine map to within hundredths of a pixel over one frame. A corner 0.5 px off the best
# affine map was pulled to the wrong place (a marker edge, a reflection): detect afresh.
TRACK_MAX_SPREAD_PX = 0.5


def _shift_from(previous: Detection, current: Detection) -> np.ndarray | None:
    """The median shift (2,) of the corners both found, None when it is not one small rigid move."""
    _shared, ia, ib = np.intersect1d(previous.ids, current.ids, assume_unique=True, return_indices=True)
    if ia.size < 4:
        return None
    before = previous.corners_px[ia].astype(np.float64)
    after = current.corners_px[ib].astype(np.float64)
    moves = after - before
    if np.linalg.norm(moves, axis=1).max() > TRACK_MAX_SHIFT_PX:
        return None
    design = np.column_stack([before, np.ones(len(before))])
    affine, *_ = np.linalg.lstsq(design, after, rcond=None)
    if np.linalg.norm(design @ affine - after, axis=1).max() > TRACK_MAX_SPREAD_PX:
        return None
    return np.median(moves, axis=0)


# A board in view shows several markers at once; a textured scene without one was read as 1-2 markers
# of some dictionary in a frame (ARUCO_ORIGINAL, 4X4_1000 on renders' backgrounds): below this many in
# one frame, markers are not taken for a board of any dictionary.
BOARD_LIKE_MARKERS = 4
# OpenCV names some dictionaries twice (DICT_APRILTAG_16H5 and _16h5): each is searched once, under its first name.
_DISTINCT_DICTIONARIES = list({getattr(cv2.aruco, name): name for name in reversed(DICTIONARY_NAMES)}.values())[::-1]


def diagnose_board_mismatch(spec: BoardSpec, greys: list[np.ndarray], *, specific_only: bool = False) -> BoardError | None:
    """Explain why `spec` finds no corners in frames that may show some other board.

    Tries, on a few sample frames: a mirrored image, other dictionaries, swapped width/height, legacy
    pattern, inverted polarity, and marker ids beyond the board's range. Returns an error whose message
    says what was seen and what to pass instead, or None when nothing board-like is visible at all.
    `specific_only`: None also where only the board's own markers were seen and none of those tests
    names a cause (the right board too far or too soft for corners looks the same).
    """
    if not greys:
        return None
    # First, as its markers mislead every other test: a mirrored marker reads as some other code, or
    # none (caliscope's cam_1, a webcam in mirror mode: a 4x5 board's ids 0-9 read as ids up to 871).
    flipped = CharucoBoardDetector(spec)
    if any(flipped.detect(cv2.flip(grey, 1)).corner_count >= MIN_FRAME_CORNERS for grey in greys):
        return BoardError(
            f"the images are mirrored left to right: the board ({spec.describe()}) reads only in the flipped image "
            "(a webcam's mirror or selfie mode, or a flipped recording); turn the camera's mirroring (horizontal "
            "flip) off, or flip the frames back (ffmpeg -vf hflip), and capture or run again"
        )
    own = dictionary_id(spec.dictionary)
    counts: dict[str, int] = {}  # markers found in all the frames, per dictionary
    most: dict[str, int] = {}  # ... and in the richest frame: what tells a board from stray look-alikes
    own_ids: set[int] = set()
    own_markers: list[tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray]] = []  # (grey, corners, ids) of the board's dictionary
    for name in _DISTINCT_DICTIONARIES:
        detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)), _aruco_parameters(inverted=True))
        found = []
        for grey in greys:
            corners, ids, _rej = detector.detectMarkers(grey)
            found.append(0 if ids is None else len(ids))
            if getattr(cv2.aruco, name) == own and ids is not None:
                own_ids.update(int(i) for i in np.asarray(ids).reshape(-1))
                own_markers.append((grey, corners, ids))
        counts[name], most[name] = sum(found), max(found)
    boards = [name for name in counts if most[name] >= BOARD_LIKE_MARKERS]
    if not boards:
        chessboard = _plain_chessboard(greys)
        if chessboard is not None:
            return BoardError(
                f"the images show a plain chessboard (at least {chessboard[0]}x{chessboard[1]} squares, no markers in its "
                "white squares), not a ChArUco board; calibcoach calibrates from ChArUco boards, whose markers name every "
                "corner so that partial and steep views count: print one with `calibcoach board --out board.pdf` "
                f"(the default {BoardSpec().describe()}), measure a square and a marker, and capture again"
            )
        return None  # nothing board-like: no markers, or a stray one or two a textured scene reads as markers
    seen = max(boards, key=lambda n: counts[n])
    own_count = sum(n for name, n in counts.items() if getattr(cv2.aruco, name) == own)  # under whichever alias
    if own_count < 0.5 * counts[seen] and getattr(cv2.aruco, seen) != own:
        # Dictionaries share their first codes (4X4_50 is a prefix of 4X4_1000), so name the family seen.
        return BoardError(
            f"the images show ArUco markers of {seen} ({counts[seen]} found), not {spec.dictionary}; "
            f"pass --dictionary {seen} (or the board file that matches the print)"
        )
    markers_on_board = (spec.squares_x * spec.squares_y) // 2
    beyond = sorted(i for i in own_ids if i >= markers_on_board)
    if len(beyond) >= BOARD_LIKE_MARKERS:  # a misread id or two on the right board's soft frames is not a larger print
        size = _squares_that_match(spec, own_markers)
        return BoardError(
            f"the images show marker ids up to {beyond[-1]}, but a {spec.squares_x}x{spec.squares_y} board uses ids "
            f"0-{markers_on_board - 1}; the print has more squares"
            + (f": they form the corners of a {_size_words(*size)}" if size else ": pass the right --squares WxH")
        )
    candidates = [(f"--squares {spec.squares_y}x{spec.squares_x} (width and height swapped)",
                   BoardSpec(spec.squares_y, spec.squares_x, spec.square_mm, spec.marker_mm, spec.dictionary, spec.legacy, spec.inverted))]
    if spec.squares_y % 2 == 0:  # an odd row count prints the same in both patterns
        candidates.append(("--legacy (a board printed by OpenCV < 4.6)", BoardSpec(
            spec.squares_x, spec.squares_y, spec.square_mm, spec.marker_mm, spec.dictionary, not bool(spec.legacy), spec.inverted)))
    # The configured board, detected the same way (its print's variants tried): the right board's soft
    # or moving frames, under 6 corners as the session detected them, can reach 6 here, and did under
    # the identical "legacy" print (bench/board_mismatch.py). A candidate must do clearly better.
    configured = max(CharucoBoardDetector(spec).detect(g).corner_count for g in greys)
    for advice, candidate in candidates:
        detector = CharucoBoardDetector(candidate)
        found = max(detector.detect(g).corner_count for g in greys)
        if found >= MIN_FRAME_CORNERS and found >= 2 * configured:
            return BoardError(
                f"markers of {spec.dictionary} are visible but no corners match a {spec.describe()} board; "
                f"it matches with {advice}"
            )
    size = _squares_that_match(spec, own_markers)
    if size is not None:
        return BoardError(
            f"markers of {spec.dictionary} are visible but no corners match a {spec.describe()} board; they form the "
            f"corners of a {_size_words(*size)}"
        )
    if specific_only:
        return None
    return BoardError(
        f"markers of {spec.dictionary} are visible (ids {sorted(own_ids)[:12]}) but they never form the corners of a "
        f"{spec.squares_x}x{spec.squares_y} board; check --squares, --square-mm/--marker-mm and the dictionary"
    )


# A chessboard's squares are flat inside; a ChArUco board's white squares hold markers. Inside the
# middle half of each square found, a plain print's grey levels spread by ~1% of the black-white
# contrast (BoofCV's real photos: 0.00-0.01; JPEG noise and uneven light included), a ChArUco board's
# marker squares by 40-400% (rendered, sharp to blurred by 3 px, where the markers no longer read but
# OpenCV's chessboard search still finds their checker): a square counts as flat under 10%, and the
# print as plain when three quarters of its squares are flat.
_FLAT_SQUARE = 0.10
_FLAT_SHARE = 0.75
# Frames wider than this are searched halved (and halved again): a chessboard's squares stay 15+ px wide
# at 640 px, and the search costs ~0.03 s a frame instead of ~0.15 at 720p (the live board watch asks
# it of every diagnosis, every 6 s of a scene without the board).
_CHESSBOARD_SEARCH_WIDTH = 640


def _plain_chessboard(greys: list[np.ndarray]) -> tuple[int, int] | None:
    """(squares across, squares down) of a plain chessboard (no markers) in any of `greys`, or None."""
    for grey in greys:
        while grey.shape[1] > _CHESSBOARD_SEARCH_WIDTH:
            grey = cv2.resize(grey, (grey.shape[1] // 2, grey.shape[0] // 2), interpolation=cv2.INTER_AREA)
        found, corners, meta = cv2.findChessboardCornersSBWithMeta(grey, (3, 3), cv2.CALIB_CB_LARGER)
        if not found or meta is None:
            continue
        rows, cols = meta.shape[:2]  # inner corners found (the pattern may extend beyond them)
        if _squares_flat(grey, np.asarray(corners, np.float64).reshape(rows, cols, 2)):
            return cols + 1, rows + 1
    return None


def _squares_flat(grey: np.ndarray, grid: np.ndarray) -> bool:
    """Whether the squares between `grid`'s (rows, cols, 2) inner corners are flat, as a plain chessboard's are."""
    spreads, means = [], []
    for r in range(grid.shape[0] - 1):
        for c in range(grid.shape[1] - 1):
            quad = np.array([grid[r, c], grid[r, c + 1], grid[r + 1, c + 1], grid[r + 1, c]])
            middle = quad.mean(axis=0) + 0.5 * (quad - quad.mean(axis=0))  # clear of the edges' blur
            x0, y0 = np.floor(middle.min(axis=0)).astype(int)
            x1, y1 = np.ceil(middle.max(axis=0)).astype(int) + 1
            if x0 < 0 or y0 < 0 or x1 > grey.shape[1] or y1 > grey.shape[0]:
                continue
            mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
            cv2.fillConvexPoly(mask, np.round(middle - [x0, y0]).astype(np.int32), 1)
            pixels = grey[y0:y1, x0:x1][mask > 0].astype(np.float64)
            if pixels.size >= 9:
                spreads.append(pixels.std())
                means.append(pixels.mean())
    if len(means) < 4:
        return False
    contrast = float(np.percentile(means, 90) - np.percentile(means, 10))
    if contrast < 20.0:  # no black and white squares to compare with
        return False
    return float(np.mean(np.array(spreads) < _FLAT_SQUARE * contrast)) >= _FLAT_SHARE


# Boards up to this many squares a side are tried when the frames' markers form no corners of the
# configured one (a 5 x 7 print with the default 8 x 11 configured is the commonest mistake).
_MAX_SQUARES_TRIED = 16


def _squares_that_match(spec: BoardSpec,
                        markers: list[tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray]]) -> tuple[int, int, bool] | None:
    """(squares_x, squares_y, legacy) of the board of `spec`'s dictionary whose corners the frames'
    `markers` form (grey, corners, ids per frame: what the dictionary search found), or None.

    Each layout only interpolates its corners from the markers (`detectBoard` handed them, ~1 ms),
    so every board of 3 to `_MAX_SQUARES_TRIED` squares a side with a marker for the highest id
    seen is tried (~0.5 s on three 720p frames). A layout is
    named when it forms at least 6 corners in a frame and twice what the configured one forms from
    the same markers: the right board's frames must not be called another board
    (bench/board_mismatch.py: soft and moving frames of renders were, before the configured layout
    was asked the same way).
    """
    found = [(grey, corners, ids) for grey, corners, ids in markers if len(ids) >= BOARD_LIKE_MARKERS]
    if not found:
        return None
    codes = cv2.aruco.getPredefinedDictionary(dictionary_id(spec.dictionary)).bytesList.shape[0]  # a larger board cannot be printed
    highest = max(int(np.max(ids)) for _g, _c, ids in found)

    def formed(squares_x: int, squares_y: int, legacy: bool) -> int:
        """Most corners one frame's markers form on this layout."""
        board = BoardSpec(squares_x, squares_y, spec.square_mm, spec.marker_mm, spec.dictionary).cv_board(legacy=legacy)
        detector = cv2.aruco.CharucoDetector(board)
        counts = [detector.detectBoard(grey, markerCorners=corners, markerIds=ids)[1] for grey, corners, ids in found]
        return max(0 if c is None else len(c) for c in counts)

    def legacies(squares_y: int) -> tuple[bool, ...]:
        return (False, True) if squares_y % 2 == 0 else (False,)  # odd rows print alike in both

    # The configured layout, asked the same way: the right board's soft or moving frames (fewer than 6
    # corners as the session detects them) still form its corners here, and so would every layout
    # sharing its rows (8 x 9, 8 x 12 ... under 8 x 11): that is the right board, not another.
    configured = max(formed(spec.squares_x, spec.squares_y, legacy) for legacy in legacies(spec.squares_y))
    best: tuple[int, int, int, int, bool] | None = None  # (corners, markers, squares_x, squares_y, legacy)
    for squares_x in range(3, _MAX_SQUARES_TRIED + 1):
        for squares_y in range(3, _MAX_SQUARES_TRIED + 1):
            markers = squares_x * squares_y // 2
            if not highest < markers <= codes or (squares_x, squares_y) == (spec.squares_x, spec.squares_y):
                continue
            for legacy in legacies(squares_y):
                corners = formed(squares_x, squares_y, legacy)
                if corners >= MIN_FRAME_CORNERS and corners >= 2 * configured and (best is None or (corners, -markers) > (best[0], -best[1])):
                    best = (corners, markers, squares_x, squares_y, legacy)
    return None if best is None else (best[2], best[3], best[4])


def _size_words(squares_x: int, squares_y: int, legacy: bool) -> str:
    pattern = ", legacy pattern" if legacy else ""
    return (f"{squares_x}x{squares_y} board{pattern}: pass --squares {squares_x}x{squares_y}{' --legacy' if legacy else ''} "
            "(and its measured --square-mm and --marker-mm)")
