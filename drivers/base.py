"""The frame-source boundary: what every source (replay, simulator, V4L2, DepthAI) delivers.

A `FrameSource` is iterated once and yields `Frame`s in capture order. Everything above this
boundary (detection, coverage, solving, outputs) is identical for live cameras and recordings,
which is what lets the tests exercise the live pipeline by replaying recorded sessions.
"""

from __future__ import annotations

import abc
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

# What a pipeline stage (decoding ahead, the replay's scan) may hold of frames not yet consumed.
FRAMES_AHEAD_BYTES = 64 * 2**20
# The clock of sources without one (folders, videos that give no rate): timestamps advance as if captured at 30 fps.
DEFAULT_FPS = 30.0


def frames_ahead(frame_bytes: int) -> int:
    """How many frames of `frame_bytes` a stage may run ahead of its consumer: 64 MB of them, 8 to 48.

    A board coming to rest after a move costs a burst of full detections that outlasts a short
    queue, and the decoders then idle: 48 frames ahead instead of 8 cut a 784-frame 720p replay
    by ~8%; a 4K BGR frame (25 MB) still gets the 8 that keep two decoders busy.
    """
    return int(np.clip(FRAMES_AHEAD_BYTES // max(int(frame_bytes), 1), 8, 48))


@dataclass(frozen=True, slots=True)
class Frame:
    """One captured image and what was known about the camera when it was taken."""

    index: int  # position in the source's stream, 0-based, counting frames that could not be decoded too
    timestamp_ns: int  # capture time; sources without clocks use index / fps
    image: np.ndarray  # (H, W) uint8 grey or (H, W, 3) uint8 BGR
    name: str = ""  # file name for folder sources, "" otherwise
    controls: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))  # focus etc.
    # The JPEG a source delivered `image` from when it decoded only the luminance (an MJPG video,
    # drivers/avi_mjpg.py; a folder's JPEGs): `image` is then that grey, and `colour()` decodes the
    # rest on demand.
    encoded: bytes | None = field(default=None, repr=False, compare=False)
    # the grey image of a BGR frame once converted: a replayed frame is asked for it 2-4 times
    # (thumbnail, detection or tracking, sharpness), 0.4 ms each at 720p
    _grey: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return int(self.image.shape[1]), int(self.image.shape[0])

    def colour(self) -> np.ndarray:
        """The frame as the camera delivered it: (H, W, 3) BGR decoded from `encoded` where the source
        kept only its grey in `image` (else `image` itself, grey or BGR)."""
        if self.encoded is None:
            return self.image
        from calibcoach.drivers.avi_mjpg import decode_packet

        colour = decode_packet(np.frombuffer(self.encoded, np.uint8))
        return self.image if colour is None else colour

    def grey(self) -> np.ndarray:
        """The image as (H, W) uint8 grey, converting BGR once (the conversion is kept with the frame)."""
        if self.image.ndim == 2:
            return self.image
        if self._grey is None:
            import cv2

            object.__setattr__(self, "_grey", cv2.cvtColor(self.image, cv2.COLOR_BGR2GRAY))  # frozen: a cache, not state
        return self._grey  # type: ignore[return-value]

    @property
    def grey_made(self) -> np.ndarray | None:
        """The grey of a BGR frame once `grey()` has made it (None before, and for a grey frame)."""
        return self._grey

    def keep_grey(self, grey: np.ndarray) -> None:
        """Take `grey` as this BGR frame's conversion, made elsewhere from the same pixels (the
        replay's scan process converts every frame it detects: app/scan_process.py)."""
        object.__setattr__(self, "_grey", grey)  # frozen: a cache, not state


@dataclass(frozen=True, slots=True)
class SourceInfo:
    """What a source says about itself before the first frame."""

    description: str  # human-readable, e.g. "video file demo.avi (1280x720, 30 fps, 600 frames)"
    kind: str  # "video" | "folder" | "recording" | "sim" | "v4l2" | "depthai"
    camera_id: str = ""
    image_size: tuple[int, int] | None = None  # (width, height) when known up front
    fps: float | None = None  # nominal frame rate when known
    frame_count: int | None = None  # total frames when known (files), None for live cameras
    controls: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))
    board: Mapping[str, Any] | None = None  # board description stored with a recording, if any
    locked_controls: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))  # a recording's focus lock
    events: tuple[Mapping[str, Any], ...] = ()  # events a recording stored (focus drift), in order


@dataclass(frozen=True, slots=True)
class SkippedFrame:
    """A frame a source could not deliver (truncated file, decode error), reported, not fatal."""

    index: int
    name: str
    reason: str


class FrameSource(abc.ABC):
    """A stream of frames. Iterate once; use as a context manager so devices are released."""

    def __init__(self) -> None:
        self.skipped: list[SkippedFrame] = []  # frames the source could not decode, with reasons

    @property
    @abc.abstractmethod
    def info(self) -> SourceInfo:
        """Description, size and frame rate, known before iteration starts."""

    @abc.abstractmethod
    def frames(self) -> Iterator[Frame]:
        """Yield frames in capture order. Unreadable frames go to `self.skipped`, not exceptions."""

    def __iter__(self) -> Iterator[Frame]:
        return self.frames()

    def close(self) -> None:  # noqa: B027 - optional hook, most replay sources hold nothing open
        """Release the device or file handle."""

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
