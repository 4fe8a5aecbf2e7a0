"""BoardSpec validation and the detector's automatic print variants and mismatch diagnosis."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
from _boards import board_photo

from calibcoach.coverage.board import BoardSpec, dictionary_id
from calibcoach.coverage.board_diagnosis import BOARD_LIKE_MARKERS, diagnose_board_mismatch
from calibcoach.coverage.detector import CharucoBoardDetector
from calibcoach.drivers.errors import BoardError


def test_default_board_is_the_methods_board() -> None:
    spec = BoardSpec()
    assert (spec.squares_x, spec.squares_y, spec.square_mm, spec.marker_mm, spec.dictionary) == (8, 11, 30.01, 22.01, "DICT_5X5_100")
    assert spec.corner_count == 70
    assert spec.corner_points_m()[1] == pytest.approx([0.06002, 0.03001, 0.0])


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"marker_mm": 31.0}, "smaller than the square"),
    ({"dictionary": "DICT_9X9_1"}, "unknown ArUco dictionary"),
    ({"squares_x": 20, "squares_y": 20, "dictionary": "DICT_4X4_50"}, "has only 50"),
])
def test_bad_board_specs_say_what_to_pass(kwargs: dict, message: str) -> None:
    with pytest.raises(BoardError, match=message):
        BoardSpec(**kwargs)


def test_dictionary_names_are_forgiving() -> None:
    assert dictionary_id("5x5_100") == dictionary_id("DICT_5X5_100") == cv2.aruco.DICT_5X5_100
    assert BoardSpec(dictionary="4x4_1000").dictionary == "DICT_4X4_1000"


def test_board_toml_ours_and_caliscopes(tmp_path) -> None:
    ours = tmp_path / "board.toml"
    ours.write_text('squares_x = 5\nsquares_y = 7\nsquare_mm = 40.0\nmarker_mm = 30.0\ndictionary = "DICT_4X4_50"\n')
    assert BoardSpec.from_toml(ours) == BoardSpec(5, 7, 40.0, 30.0, "DICT_4X4_50")
    theirs = tmp_path / "charuco.toml"
    theirs.write_text('columns = 4\nrows = 5\ndictionary = "DICT_4X4_1000"\naruco_scale = 0.75\nsquare_size_override_cm = 5.4\ninverted = true\n')
    spec = BoardSpec.from_toml(theirs)
    assert (spec.squares_x, spec.squares_y, spec.square_mm, spec.marker_mm, spec.inverted) == (4, 5, 54.0, 40.5, True)
    bad = tmp_path / "bad.toml"
    bad.write_text("squares_x = 5\nsquare_size = 3\n")
    with pytest.raises(BoardError, match="unknown keys"):
        BoardSpec.from_toml(bad)


def test_detector_finds_all_corners_with_subpixel_accuracy() -> None:
    spec = BoardSpec()
    det = CharucoBoardDetector(spec).detect(board_photo(spec))
    assert det.corner_count == 70
    assert det.corners_px.shape == (70, 2) and det.object_points_m.shape == (70, 3)
    # a flat print under perspective: the corners must fit one homography to sub-pixel accuracy
    H, _ = cv2.findHomography(det.object_points_m[:, :2].astype(np.float64), det.corners_px.astype(np.float64))
    mapped = cv2.perspectiveTransform(det.object_points_m[:, :2].reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
    error = np.linalg.norm(mapped - det.corners_px, axis=1)
    # (the warp's bilinear resampling itself costs ~0.1 px; the simulator tests hold the tight bound)
    assert np.median(error) < 0.2 and np.max(error) < 0.45


def test_inverted_print_is_detected_and_reported() -> None:
    spec = BoardSpec()
    detector = CharucoBoardDetector(spec)
    det = detector.detect(255 - board_photo(spec))
    assert det.corner_count == 70
    assert detector.variant_found == "inverted print" and detector.spec.inverted is True


def test_legacy_pattern_is_detected_on_an_even_row_board() -> None:
    spec = BoardSpec(squares_x=7, squares_y=10, square_mm=30.0, marker_mm=22.0)
    photo = board_photo(spec, legacy=True)
    assert CharucoBoardDetector(BoardSpec(7, 10, 30.0, 22.0, legacy=False, inverted=False)).detect(photo).corner_count < 6
    detector = CharucoBoardDetector(spec)
    assert detector.detect(photo).corner_count == 54
    assert detector.variant_found == "legacy pattern"


@pytest.mark.parametrize(("wrong", "advice"), [
    (BoardSpec(dictionary="DICT_4X4_100"), "pass --dictionary DICT_5X5_100"),
    (BoardSpec(squares_x=11, squares_y=8), "--squares 8x11"),
    (BoardSpec(squares_x=6, squares_y=7), "ids up to 43"),
    (BoardSpec(squares_x=6, squares_y=7), "they form the corners of a 8x11 board: pass --squares 8x11"),
])
def test_wrong_board_gets_a_one_line_fix(wrong: BoardSpec, advice: str) -> None:
    photo = board_photo(BoardSpec())
    assert CharucoBoardDetector(wrong).detect(photo).corner_count < 6
    error = diagnose_board_mismatch(wrong, [photo])
    assert error is not None and advice in str(error)
    assert "\n" not in str(error)


@pytest.mark.parametrize(("printed", "legacy"), [((5, 7), False), ((7, 5), False), ((4, 5), False), ((6, 8), True)])
def test_a_smaller_print_than_configured_is_measured_from_its_markers(printed: tuple[int, int], legacy: bool) -> None:
    """The commonest mistake: a 5x7 (or 4x5 ...) board printed, the default 8x11 configured. Its markers
    read as ids 0-16 of the same dictionary, inside the configured board's range; every layout up to 16
    squares a side is tried on them, and the one forming the corners is named, legacy pattern and all."""
    photo = board_photo(BoardSpec(squares_x=printed[0], squares_y=printed[1]), legacy=legacy)
    assert CharucoBoardDetector(BoardSpec(legacy=legacy)).detect(photo).corner_count < 6
    error = diagnose_board_mismatch(BoardSpec(), [photo])
    words = f"--squares {printed[0]}x{printed[1]}" + (" --legacy" if legacy else " (")
    assert error is not None and words in str(error) and "\n" not in str(error)


@pytest.mark.parametrize("spec", [BoardSpec(), BoardSpec(squares_x=4, squares_y=5, dictionary="DICT_4X4_1000")])
def test_a_mirrored_image_is_named_as_such(spec: BoardSpec) -> None:
    """A mirrored marker reads as another code or none, which would send the person after the wrong fix
    (a 4x5 board's dictionary is large enough that its mirrored markers read as ids far beyond the board's)."""
    mirrored = cv2.flip(board_photo(spec), 1)
    assert CharucoBoardDetector(spec).detect(mirrored).corner_count < 6
    error = diagnose_board_mismatch(spec, [mirrored])
    assert error is not None and str(error).startswith("the images are mirrored left to right")
    assert "ffmpeg -vf hflip" in str(error) and "\n" not in str(error)
    assert "mirrored" not in str(diagnose_board_mismatch(BoardSpec(dictionary="DICT_4X4_100"), [board_photo(BoardSpec())]))


def plain_chessboard_photo(squares: tuple[int, int]) -> np.ndarray:
    """A plain chessboard (no markers) of `squares` (across, down), tilted, in a 720p frame, softened as a webcam's."""
    cols, rows = squares
    board = np.kron((np.indices((rows, cols)).sum(axis=0) % 2 * 255).astype(np.uint8), np.ones((60, 60), np.uint8))
    board = cv2.copyMakeBorder(board, 40, 40, 40, 40, cv2.BORDER_CONSTANT, value=255)
    h, w = board.shape
    corners = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
    placed = np.float32([[300, 120], [980, 170], [940, 640], [330, 600]])
    photo = cv2.warpPerspective(board, cv2.getPerspectiveTransform(corners, placed), (1280, 720), borderValue=110)
    return cv2.GaussianBlur(photo, (0, 0), 0.8)


def test_a_plain_chessboard_is_named_with_its_size() -> None:
    """The commonest calibration target of all: said to be a plain chessboard, not "no board", so the person
    prints a ChArUco board instead of checking focus and light."""
    error = diagnose_board_mismatch(BoardSpec(), [plain_chessboard_photo((9, 6))], specific_only=True)
    assert error is not None and "a plain chessboard (at least 9x6 squares" in str(error)
    assert "calibcoach board --out board.pdf" in str(error) and "\n" not in str(error)


@pytest.mark.parametrize("blur_px", [0.0, 2.0, 3.0, 5.0])
def test_the_right_board_too_soft_for_its_markers_is_not_called_a_plain_chessboard(blur_px: float) -> None:
    """OpenCV's chessboard search finds a ChArUco board's checker even where its markers no longer read
    (blurred by 3 px): the markers inside its white squares tell it from a plain print."""
    photo = board_photo(BoardSpec())
    soft = cv2.GaussianBlur(photo, (0, 0), blur_px) if blur_px else photo
    found, _corners, _meta = cv2.findChessboardCornersSBWithMeta(soft, (3, 3), cv2.CALIB_CB_LARGER)
    assert found or blur_px > 3  # the checker is found: the test is the flatness of its squares
    assert "chessboard" not in str(diagnose_board_mismatch(BoardSpec(dictionary="DICT_4X4_50"), [soft]))


def test_the_right_board_with_scattered_markers_is_not_called_another_size() -> None:
    """A far, soft board of a messy render read as 11 scattered markers and 3 corners; a 9 x 10 layout's
    interpolation pulled 6+ "corners" onto the dense checker and it was told --squares 9x10. The same
    markers, kept readable on a rendered board: they sit where the configured board has them."""
    spec = BoardSpec()
    photo = board_photo(spec)
    found = CharucoBoardDetector(spec).detect(photo)
    for corners, marker_id in zip(found.marker_corners_px, found.marker_ids, strict=True):
        if int(marker_id) not in {1, 3, 5, 10, 12, 15, 17, 21, 29, 34, 42}:  # what the messy frame read
            cv2.fillConvexPoly(photo, np.round(corners).astype(np.int32), 255)
    assert CharucoBoardDetector(spec).detect(photo).corner_count < 6
    assert diagnose_board_mismatch(spec, [photo], specific_only=True) is None
    said = str(diagnose_board_mismatch(spec, [photo]))
    assert "where a 8x11 squares" in said and "bring the board closer" in said and "--squares" not in said


def test_no_markers_at_all_gives_no_diagnosis() -> None:
    assert diagnose_board_mismatch(BoardSpec(), [np.full((720, 1280), 128, np.uint8)]) is None


def test_the_right_boards_own_soft_frames_are_never_called_another_board(request: pytest.FixtureRequest) -> None:
    """The bundled recording's frames with fewer than 6 corners (moving, soft, partly out of view), three at a
    time as the live watch samples them: one such triple was told "it matches with --legacy" (an 8 x 11 board
    prints the same in both patterns; its inverted-marker variant found 6 corners where the session found 5)."""
    frames = sorted((request.config.rootpath / "recordings" / "demo_webcam720_careful" / "frames").glob("*.png"))
    detector = CharucoBoardDetector(BoardSpec())
    greys = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in frames[::5]]
    assert detector.detect(greys[0]).corner_count >= 6  # settled on the print, as the session's detector is
    soft = [g for g in greys if detector.detect(g).corner_count < 6]
    assert len(soft) >= 9
    for i in range(0, len(soft) - 2, 3):
        assert diagnose_board_mismatch(BoardSpec(), soft[i:i + 3], specific_only=True) is None


@pytest.mark.parametrize("markers", [1, BOARD_LIKE_MARKERS - 1, BOARD_LIKE_MARKERS])
def test_a_stray_marker_of_another_dictionary_is_not_taken_for_a_board(markers: int) -> None:
    """A textured scene reads as a marker or two of some dictionary (ARUCO_ORIGINAL, 4X4_1000 on renders'
    backgrounds): the person must not be told to pass that dictionary; a few at once are a board."""
    scene = np.full((720, 1280), 128, np.uint8)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_ARUCO_ORIGINAL)
    for k in range(markers):
        x, y = 100 + 250 * k, 200
        scene[y - 20:y + 140, x - 20:x + 140] = 255
        scene[y:y + 120, x:x + 120] = cv2.aruco.generateImageMarker(dictionary, 7 + k, 120)
    error = diagnose_board_mismatch(BoardSpec(), [scene])
    if markers < BOARD_LIKE_MARKERS:
        assert error is None
    else:
        assert error is not None and "pass --dictionary DICT_ARUCO_ORIGINAL" in str(error)


def test_plain_print_of_an_even_row_board_is_not_called_inverted_or_legacy() -> None:
    # inverted-marker mode also finds normal markers; the plain variant must win the tie
    spec = BoardSpec(squares_x=7, squares_y=10, square_mm=30.0, marker_mm=22.0)
    detector = CharucoBoardDetector(spec)
    assert detector.detect(board_photo(spec)).corner_count == 54
    assert detector.variant_found == "standard pattern"


@pytest.mark.parametrize(("fields", "says"), [
    ({"squares_x": 8.5}, "whole number of squares"),
    ({"squares_y": 1}, "at least 2x2"),
    ({"square_mm": 1e300, "marker_mm": 7e299}, "between 1 mm and 2000 mm"),
    ({"square_mm": float("nan")}, "between 1 mm and 2000 mm"),
    ({"square_mm": 0.5, "marker_mm": 0.3}, "--square-mm"),
    ({"marker_mm": 31.0}, "smaller than the square size"),
    ({"squares_x": 10, "dictionary": "DICT_4X4_50"}, "pass a larger dictionary"),
    ({"dictionary": "DICT_9X9_1"}, "unknown ArUco dictionary"),
])
def test_board_spec_refuses_what_no_print_can_be_with_the_fix(fields: dict, says: str) -> None:
    with pytest.raises(BoardError, match=re.escape(says)):
        BoardSpec(**fields)
