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

from calibcoach.coverage.board import BoardSpec

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


# Fewer corners than this in common and no move is read between two detections: three are too few
# to tell a move from a misread corner (an affine map of the board fits any three).
MIN_SHARED_CORNERS = 4


def shared_corners(before: Detection, after: Detection) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the corners both detections found sit in each: (indices into `before`, into `after`),
    in id order; None when they share fewer than `MIN_SHARED_CORNERS`."""
    if min(before.corner_count, after.corner_count) < MIN_SHARED_CORNERS:
        return None  # asked of every frame a replay reads, most of them without a board: no set intersection
    _shared, ia, ib = np.intersect1d(before.ids, after.ids, assume_unique=True, return_indices=True)
    return None if ia.size < MIN_SHARED_CORNERS else (ia, ib)


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
        more than `TRACK_MAX_SHIFT_PX`, or its shift is not one rigid move: a corner jumped further
        than the corners' own noise explains, `_shift_from`).
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
# ... unless the corners' own noise scatters them that far: off the affine map, each corner's
# distance is the noise of two frames' corners, Rayleigh-distributed, whose scale its median
# gives (median = 1.1774 scale). Noise alone puts one corner of 88 past 5 scales once in ~3000
# frames; a corner pulled further than that still stands out. On dim 720p renders (~0.15 px
# corner noise) the fixed 0.5 px sent 57-130 held frames of each (of ~260) to full detections
# on the thread that sees the frames; with the noise allowed for they are tracked, and after the
# masked refinement the final solve takes their corners lie as near the truth as their fresh
# detections' (0.086-0.105 px against 0.088-0.107, median per render, 12 renders). Replays of
# those 12: 10-20% faster, error against the truth 0.87x [0.69, 1.11] (geometric mean, 7 better,
# 5 worse); careful, shaky, messy and wide renders track the same frames (0.03 px noise), the
# fisheye 1-4 more (3 renders, 0.96x the error; bench/results/track_rigidity.md).
TRACK_SPREAD_NOISE_SCALES = 5.0
_RAYLEIGH_MEDIAN = 1.1774  # median / scale of a Rayleigh distribution: sqrt(2 ln 2)
# The noise is read off the corners only where there are enough of them: the affine map has 3
# parameters a coordinate, and with a handful of corners it absorbs much of a pulled corner's
# error, spreading it over the rest, whose median then excuses it.
TRACK_NOISE_MIN_CORNERS = 12


def _shift_from(previous: Detection, current: Detection) -> np.ndarray | None:
    """The median shift (2,) of the corners both found, None when it is not one small rigid move
    (a corner off the others' affine map by more than `TRACK_MAX_SPREAD_PX` and their noise allows)."""
    shared = shared_corners(previous, current)
    if shared is None:
        return None
    ia, ib = shared
    before = previous.corners_px[ia].astype(np.float64)
    after = current.corners_px[ib].astype(np.float64)
    moves = after - before
    if np.linalg.norm(moves, axis=1).max() > TRACK_MAX_SHIFT_PX:
        return None
    design = np.column_stack([before, np.ones(len(before))])
    affine, *_ = np.linalg.lstsq(design, after, rcond=None)
    off_map = np.linalg.norm(design @ affine - after, axis=1)
    noise_scale = float(np.median(off_map)) / _RAYLEIGH_MEDIAN if ia.size >= TRACK_NOISE_MIN_CORNERS else 0.0
    if off_map.max() > max(TRACK_MAX_SPREAD_PX, TRACK_SPREAD_NOISE_SCALES * noise_scale):
        return None
    return np.median(moves, axis=0)
