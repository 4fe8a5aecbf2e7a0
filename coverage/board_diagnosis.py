"""Why frames show no corners of the configured board: what the camera shows instead, in words to act on.

A webcam in mirror mode, another dictionary, a print of another size or pattern, a plain chessboard:
each makes every frame "no board", and the person would otherwise be told only that. The diagnosis
looks at a few frames and names what it finds, with the flag that fixes it; the right board too far
or too soft for corners must not be called another board (bench/board_mismatch.py measures both).
Asked live by app/board_watch.py and at the end of a capture that never showed the board.
"""

from __future__ import annotations

import cv2
import numpy as np

from calibcoach.coverage.board import DICTIONARY_NAMES, BoardSpec, dictionary_id
from calibcoach.coverage.detector import MIN_FRAME_CORNERS, CharucoBoardDetector, _aruco_parameters
from calibcoach.drivers.errors import BoardError

# A board in view shows several markers at once; a textured scene without one was read as 1-2 markers
# of some dictionary in a frame (ARUCO_ORIGINAL, 4X4_1000 on renders' backgrounds): below this many in
# one frame, markers are not taken for a board of any dictionary.
BOARD_LIKE_MARKERS = 4
# OpenCV names some dictionaries twice (DICT_APRILTAG_16H5 and _16h5): each is searched once, under its first name.
_DISTINCT_DICTIONARIES = list({getattr(cv2.aruco, name): name for name in reversed(DICTIONARY_NAMES)}.values())[::-1]


def diagnose_board_mismatch(spec: BoardSpec, greys: list[np.ndarray], *, specific_only: bool = False) -> BoardError | None:
    """Explain why `spec` finds no corners in frames that may show some other board.

    Tries, on a few sample frames: a mirrored image, other dictionaries (and, with no markers at all, a
    plain chessboard), marker ids beyond the board's range, swapped width/height, legacy pattern,
    inverted polarity and other sizes -- unless the markers sit where the configured board has them.
    Returns an error whose message says what was seen and what to pass instead, or None when nothing
    board-like is visible at all.
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
    # The right board far away or soft reads as markers that form few corners, and another layout's
    # interpolation can then pull more "corners" onto its dense checker (a far board of a messy render
    # was told --squares 9x10). Where the markers sit where the configured board puts them, it is
    # that board: no other layout or variant is named.
    configured_board = spec.cv_board(legacy=bool(spec.legacy))
    if any(_markers_fit_layout(configured_board, corners, ids) for _g, corners, ids in own_markers):
        return None if specific_only else BoardError(
            f"markers of {spec.dictionary} are visible where a {spec.describe()} board has them, but too few of them "
            "next to each other to give corners: bring the board closer, into focus and light, and hold it still"
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


def halved_to_width(grey: np.ndarray, max_width: int) -> np.ndarray:
    """`grey` halved (INTER_AREA), and halved again, until it is at most `max_width` wide; itself if it already is."""
    while grey.shape[1] > max_width:
        grey = cv2.resize(grey, (grey.shape[1] // 2, grey.shape[0] // 2), interpolation=cv2.INTER_AREA)
    return grey


def _plain_chessboard(greys: list[np.ndarray]) -> tuple[int, int] | None:
    """(squares across, squares down) of a plain chessboard (no markers) in any of `greys`, or None."""
    for grey in (halved_to_width(g, _CHESSBOARD_SEARCH_WIDTH) for g in greys):
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


# Markers fit a layout when one homography takes their corners on that board onto the image to within
# this share of their side: a misplaced marker is off by a square (1.4 sides at the default print),
# detection noise and a lens's curvature over a board small enough to give no corners are hundredths.
_LAYOUT_FIT_SHARE = 0.15


def _markers_fit_layout(board: cv2.aruco.CharucoBoard, corners: tuple[np.ndarray, ...], ids: np.ndarray) -> bool:
    """Whether 4+ detected markers, spanning two rows and two columns of `board`, sit where `board` has them."""
    where = {int(i): k for k, i in enumerate(np.asarray(board.getIds()).reshape(-1))}
    layout = board.getObjPoints()
    on_board = [(np.asarray(layout[where[int(i)]], np.float64)[:, :2], np.asarray(c, np.float64).reshape(4, 2))
                for c, i in zip(corners, np.asarray(ids).reshape(-1), strict=True) if int(i) in where]
    if len(on_board) < BOARD_LIKE_MARKERS:
        return False
    board_xy = np.concatenate([b for b, _i in on_board])
    image_xy = np.concatenate([i for _b, i in on_board])
    centres = np.array([b.mean(axis=0) for b, _i in on_board])
    if np.unique(np.round(centres[:, 0], 6)).size < 2 or np.unique(np.round(centres[:, 1], 6)).size < 2:
        return False  # one row or one column: any layout with them in a line would fit
    homography, _mask = cv2.findHomography(board_xy, image_xy, 0)
    if homography is None:
        return False
    mapped = cv2.perspectiveTransform(board_xy.reshape(-1, 1, 2), homography).reshape(-1, 2)
    side = float(np.median(np.linalg.norm(image_xy.reshape(-1, 4, 2) - np.roll(image_xy.reshape(-1, 4, 2), 1, axis=1), axis=2)))
    return float(np.sqrt(np.mean(np.sum((mapped - image_xy) ** 2, axis=1)))) < _LAYOUT_FIT_SHARE * side


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
