"""The camera preview the viewer shows: the frame shrunk by a whole factor and JPEG-encoded.

Kept free of rerun so that a replay's own thread can encode previews (OpenCV releases the GIL)
while the Rerun logger, on a thread of its own, imports rerun only once the reading is done
(app/viewer_thread.py).
"""

from __future__ import annotations

import copy
from dataclasses import replace
from typing import TYPE_CHECKING

import cv2
import numpy as np

from calibcoach.drivers.base import Frame

if TYPE_CHECKING:
    from calibcoach.app.session_types import FrameOutcome

PREVIEW_MAX_WIDTH = 960  # px: enough to judge focus and corners, small enough for ~30 fps over the wire
JPEG_QUALITY = 75


def preview_factor(width: int) -> int:
    """Integer shrink factor to at most PREVIEW_MAX_WIDTH (1280 -> 640, 1920 -> 960, 3840 -> 960).

    INTER_AREA over whole pixel blocks costs ~0.3 ms at 720p where a fractional 1280 -> 960 cost
    ~2.7 ms, which made logging the largest per-frame cost after detection.
    """
    return max(1, -(-width // PREVIEW_MAX_WIDTH))


def preview_jpeg(image: np.ndarray) -> bytes | None:
    """The preview of an (H, W) grey or (H, W, 3) BGR frame as JPEG bytes (None if encoding fails)."""
    h, w = image.shape[:2]
    factor = preview_factor(w)
    preview = image if factor == 1 else cv2.resize(image, (w // factor, h // factor), interpolation=cv2.INTER_AREA)
    return _encoded(preview)


# libjpeg decodes a JPEG shrunk by 2, 4 or 8 in its DCT: the preview of an MJPG frame without decoding
# all of it (1080p: 4.0 ms instead of 9.4 ms and a resize)
_REDUCED_COLOUR = {2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4, 8: cv2.IMREAD_REDUCED_COLOR_8}


def frame_preview_jpeg(frame: Frame) -> bytes | None:
    """The preview of a frame as JPEG bytes, in colour where the frame has it (`Frame.colour`)."""
    w, h = frame.image_size
    factor = preview_factor(w)
    if frame.encoded is not None and factor in _REDUCED_COLOUR:
        small = cv2.imdecode(np.frombuffer(frame.encoded, np.uint8), _REDUCED_COLOUR[factor] | cv2.IMREAD_IGNORE_ORIENTATION)
        if small is not None and small.shape[:2] == (h // factor, w // factor):  # libjpeg rounds a partial block up
            return _encoded(small)
    return preview_jpeg(frame.colour())


def _encoded(preview: np.ndarray) -> bytes | None:
    ok, jpeg = cv2.imencode(".jpg", preview, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])  # BGR or grey in, as OpenCV has it
    return jpeg.tobytes() if ok else None


def frame_for_log(frame: Frame) -> tuple[Frame, bytes | None]:
    """The frame as a deferred logger holds it: its size, name and controls without its pixels
    (1-6 MB), and its preview JPEG (~50 KB). Controls become a plain dict, which pickles."""
    w, h = frame.image_size
    pixelless = replace(frame, image=np.empty((h, w, 0), np.uint8), controls=dict(frame.controls), encoded=None)
    return pixelless, frame_preview_jpeg(frame)


def outcome_for_log(outcome: FrameOutcome) -> FrameOutcome:
    """The outcome as a deferred logger holds it: an accepted frame's coverage map is the session's
    live one, which the next accept changes, so it is copied as it is now; other frames' is left out
    (the log shows coverage on a kept frame only, and the live map must not be pickled on another
    thread while the session changes it: app/viewer_process.py)."""
    return replace(outcome, coverage=copy.deepcopy(outcome.coverage) if outcome.decision.accepted else None)
