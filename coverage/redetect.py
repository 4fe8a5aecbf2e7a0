"""When to re-detect a frame on a local view (coverage/local_view.py), and with which hint.

Re-detection costs about one more detection (~30 ms at 720p), so it runs only where it can help:

- the lens is wide (`WIDE_LENS_DEG`), where bent and squeezed markers lose frames;
- the frame gave too few corners to use (`FEW_CORNERS`), or far fewer than the board's visible
  extent promises (`PARTIAL_SHARE`, from a pose on the corners found);
- something says where the board is: markers or corners of this frame, or else the previous
  frame's detection (a board held still barely moves between frames).

It is deterministic: the decisions depend only on the frames, in order, and on the lens estimate
the caller passes, so a replay re-detects exactly the frames the live session did.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import CharucoBoardDetector, Detection
from calibcoach.coverage.local_view import redetect_in_local_view
from calibcoach.coverage.pose import estimate_pose
from calibcoach.coverage.virtual_view import BORDER_MARGIN_PX, seen_in_image
from calibcoach.drivers.geometry import pose_matrix
from calibcoach.drivers.lens import CameraModel

# Re-detect only through lenses at least this wide (horizontal, through the edge midpoints), so
# that sessions with ordinary lenses decide exactly as before (their benchmarks and recordings
# stand). Not because the view cannot help there: on the rendered 70 deg webcam it recovered 17
# of 28 lost frames too (far boards, by its magnification; bench/results/redetect.md), which is
# left for a decision of its own. 90 deg: the rational model's range, where bending starts to matter.
WIDE_LENS_DEG = 90.0
# The selector's minimum (SelectorSettings.min_corners): a frame below it is of no use as it is.
FEW_CORNERS = 6
# A frame with at least FEW_CORNERS is re-detected when it shows fewer than this share of the
# corners its pose puts inside the image: half the board missing is a whole row of markers the
# fisheye bent, not the occasional corner lost at the edge (plain detection on the rendered
# fisheye found 80-100% of the corners in view on the frames it did not lose).
PARTIAL_SHARE = 0.5
# Markers or corners needed to point a view: one marker's four corners fix a (rough) pose.
MIN_HINT_POINTS = 4


@dataclass(slots=True)
class RedetectionCounts:
    tried: int = 0  # frames re-detected
    improved: int = 0  # frames where the view found more corners than the plain detection
    recovered: int = 0  # of those, frames that went from < FEW_CORNERS to >= FEW_CORNERS
    corners_added: int = 0
    from_previous_frame: int = 0  # improved frames whose hint was the previous frame's detection


class Redetector:
    """Re-detects the frames where a local view can help; see the module docstring.

    `improve(index, grey, detection, camera)` is called once per frame, in frame order.
    """

    def __init__(self, spec: BoardSpec) -> None:
        self._detector = CharucoBoardDetector(spec)
        self._corners_m = spec.corner_points_m()
        self._previous: tuple[int, Detection] | None = None
        self._wide: tuple[CameraModel, bool] | None = None  # the last lens asked about, and the answer
        self.counts = RedetectionCounts()

    @property
    def spec(self) -> BoardSpec:
        return self._detector.spec

    def improve(self, index: int, grey: np.ndarray, detection: Detection, camera: CameraModel) -> Detection:
        """The better of `detection` and its re-detection on a local view (the same object when not re-detected)."""
        previous, self._previous = self._previous, None
        hint = self._hint(index, detection, previous)
        result = detection
        if hint is not None and self._is_wide(camera) and self._worth_trying(detection, camera):
            self.counts.tried += 1
            found = redetect_in_local_view(grey, camera, self._detector, detection, hint=None if hint is detection else hint)
            if found is not None:
                result = found.detection
                self.counts.improved += 1
                self.counts.recovered += int(detection.corner_count < FEW_CORNERS <= result.corner_count)
                self.counts.corners_added += result.corner_count - detection.corner_count
                self.counts.from_previous_frame += int(hint is not detection)
        if result.corner_count >= FEW_CORNERS:
            self._previous = (index, result)
        return result

    def _hint(self, index: int, detection: Detection, previous: tuple[int, Detection] | None) -> Detection | None:
        if detection.corner_count + 4 * detection.marker_corners_px.shape[0] >= MIN_HINT_POINTS:
            return detection
        if previous is not None and previous[0] == index - 1:
            return previous[1]
        return None

    def _is_wide(self, camera: CameraModel) -> bool:
        if self._wide is None or self._wide[0] is not camera:  # the session makes a new CameraModel per solve
            self._wide = (camera, camera.field_of_view_deg()[0] >= WIDE_LENS_DEG)
        return self._wide[1]

    def _worth_trying(self, detection: Detection, camera: CameraModel) -> bool:
        if detection.corner_count < FEW_CORNERS:
            return True
        pose = estimate_pose(detection, camera)
        if pose is None:
            return False
        points = self._corners_m @ pose_matrix(pose.rvec).T + pose.tvec
        _px, seen = seen_in_image(camera, points, BORDER_MARGIN_PX)
        return detection.corner_count < PARTIAL_SHARE * int(seen.sum())
