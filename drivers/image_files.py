"""Decoding a replay's image files and video frames, ahead of the reader on worker threads.

Shared by the folder and recording sources (drivers/replay.py) and the video source
(drivers/video_file.py): a file's bytes to an image (the fast PNG path where it gives OpenCV's
pixels, a JPEG's luminance alone where only detection needs it), never raising on a bad file, and
the pipeline that keeps two decodes running ahead of the consumer.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from calibcoach.drivers.avi_mjpg import decode_packet_grey
from calibcoach.drivers.png_fast import decode_png

T = TypeVar("T")
D = TypeVar("D")  # what `decoded_ahead` decodes an item to
# Grey images stay (H, W), colour becomes (H, W, 3) BGR, 16-bit is scaled to 8-bit by OpenCV (>> 8).
# EXIF orientation is ignored: calibration needs the sensor's own pixel grid, and a phone rotating
# some stills would also make them a different size from the rest.
IMREAD_FLAGS = cv2.IMREAD_ANYCOLOR | cv2.IMREAD_IGNORE_ORIENTATION

_DECODE_WORKERS = 2  # decoding releases the GIL; a 720p PNG takes ~5 ms in OpenCV, ~2.9 ms in png_fast


def decoded_ahead(items: Sequence[T], decode: Callable[[T], D], *, ahead: int = 8) -> Iterator[D]:
    """`decode(item)` of every item (a file, a video frame's place in its file), in order, run on
    worker threads `ahead` items ahead.

    Replay is otherwise bound by decoding on the consumer's thread (half of a 784-frame replay's
    time was imdecode); the consumer never waits once the pipeline is full. Closing the iterator
    waits for the decodes already running (the pool's exit), so what they read can be closed after.
    """
    with ThreadPoolExecutor(max_workers=_DECODE_WORKERS, thread_name_prefix="decode") as pool:
        pending: deque[Future[np.ndarray | None]] = deque()
        try:
            for item in items:
                pending.append(pool.submit(decode, item))
                if len(pending) >= ahead:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:
            for future in pending:
                future.cancel()


def read_frame_image(path: Path, flags: int = IMREAD_FLAGS, *, fast_png: bool = False) -> tuple[np.ndarray | None, bytes | None]:
    """A folder's or recording's frame as `read_image` decodes it, but of a JPEG only the luminance,
    with its bytes: what detection reads, at ~40% of the cost; `Frame.colour()` decodes the rest where
    a person sees the frame (as of an MJPG video's frames: drivers/avi_mjpg.py)."""
    try:
        data = np.fromfile(path, np.uint8)
    except OSError:
        return None, None
    grey = decode_packet_grey(data)  # None for anything but a JPEG that decodes
    if grey is not None:
        return grey, data.tobytes()
    return decode_image(data, flags, fast_png=fast_png), None


def read_image(path: Path, flags: int = IMREAD_FLAGS, *, fast_png: bool = False) -> np.ndarray | None:
    """Decode an image file, or None if it is missing, empty or not decodable (never raises)."""
    try:
        data = np.fromfile(path, np.uint8)  # imdecode, not imread: no path-encoding trouble, no stderr noise
    except OSError:
        return None
    return decode_image(data, flags, fast_png=fast_png)


def decode_image(data: np.ndarray, flags: int = IMREAD_FLAGS, *, fast_png: bool = False) -> np.ndarray | None:
    """An image file's bytes decoded, or None if empty or not decodable (never raises).

    `fast_png`: try drivers/png_fast.py first (~3x faster on the PNGs OpenCV writes by default, ~2x on
    adaptively filtered ones, 720p grey), OpenCV if it declines.
    """
    if data.size == 0:
        return None
    if fast_png and flags in (IMREAD_FLAGS, cv2.IMREAD_UNCHANGED):  # both give grey as (H, W), colour as BGR
        image = decode_png(data.data)
        if image is not None:
            return image
    image = cv2.imdecode(data, flags)
    if image is None or image.ndim not in (2, 3):
        return None
    return image


def fast_png_decodes(path: Path, decoded: np.ndarray) -> bool:
    """Whether drivers/png_fast.py decodes this file to the pixels OpenCV `decoded` it to."""
    if path.suffix.lower() != ".png":
        return False
    fast = decode_png(np.fromfile(path, np.uint8).data)
    return fast is not None and np.array_equal(fast, decoded)


def unreadable_reason(path: Path) -> str:
    """Why a file gave no image, in words for `SkippedFrame.reason`."""
    if not path.exists():
        return "file is missing"
    if path.stat().st_size == 0:
        return "file is empty (0 bytes)"
    return f"file does not decode as an image (damaged, truncated, or not really a {path.suffix} file)"
