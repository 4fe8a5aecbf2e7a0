"""Video files as a replay source: Motion-JPEG AVIs from their container, anything else through FFmpeg."""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path

import cv2
import numpy as np

from calibcoach.drivers.avi_mjpg import MjpgIndex, decode_packet, decode_packet_grey, mjpg_index, read_packet
from calibcoach.drivers.base import DEFAULT_FPS, Frame, FrameSource, SkippedFrame, SourceInfo, frames_ahead
from calibcoach.drivers.errors import SourceError
from calibcoach.drivers.image_files import decoded_ahead


class VideoFileSource(FrameSource):
    """Frames of a video file: (H, W, 3) uint8 BGR, or of a Motion-JPEG AVI their grey (see below).

    A Motion-JPEG AVI (what webcams record) is read straight from its container and its JPEGs
    decoded by libjpeg on two threads (drivers/avi_mjpg.py), the luminance alone: each frame's
    `image` is its grey, what detection reads, and `Frame.colour()` decodes the colour from the
    JPEG it keeps (`Frame.encoded`) for the few frames a person sees (previews, the check picture):
    decoding all of every frame and converting it to grey took 2.7x the CPU at 1080p. Any other
    video is read by OpenCV's VideoCapture (FFmpeg), in colour. A frame that fails to decode costs
    its index and is reported in `skipped`; after `max_consecutive_failures` failures in a row the
    rest of the file is taken to be damaged and reading stops, with one `skipped` entry saying so
    (a broken tail would otherwise be read for ever).
    """

    def __init__(self, path: str | Path, *, max_consecutive_failures: int = 25) -> None:
        super().__init__()
        self.path = Path(path)
        self._max_failures = max(1, int(max_consecutive_failures))
        self._capture: cv2.VideoCapture | None = None
        self._rotation_deg = 0  # the container's display rotation, not applied (see `_open`)
        if not self.path.is_file():
            raise SourceError(f"{self.path} is not a file; pass a video file")
        if self.path.stat().st_size == 0:
            raise SourceError(f"{self.path} is empty (0 bytes); the copy or recording probably failed, so copy it again")
        self._mjpg = self._mjpg_index()
        if self._mjpg is not None:
            self._fps, self._image_size = self._mjpg.fps, self._mjpg.image_size
            self._frame_count: int | None = len(self._mjpg.packets) + self._mjpg.cut_off
            return
        probe = self._open()
        try:
            first = None
            for _ in range(self._max_failures):  # a few bad leading frames are tolerated, as in frames()
                ok, image = probe.read()
                if ok and image is not None:
                    first = image
                    break
            fps = probe.get(cv2.CAP_PROP_FPS)
            count = probe.get(cv2.CAP_PROP_FRAME_COUNT)
        finally:
            probe.release()  # frames() reopens the file: the simplest rewind every backend supports
        if first is None:
            raise SourceError(
                f"{self.path} opens as a video but none of its first {self._max_failures} frames decodes; convert it "
                f"with ffmpeg (e.g. `ffmpeg -i {self.path.name} -c:v ffv1 out.mkv`) or pass a folder of images"
            )
        self._fps = float(fps) if math.isfinite(fps) and fps > 0 else None
        self._frame_count = int(count) if math.isfinite(count) and count > 0 else None
        self._image_size = (int(first.shape[1]), int(first.shape[0]))  # (width, height) pixels

    def _mjpg_index(self) -> MjpgIndex | None:
        """The file's MJPG frames when libjpeg decodes them at the announced size (else VideoCapture reads it)."""
        index = mjpg_index(self.path) if hasattr(os, "pread") else None
        if index is None:
            return None
        with open(self.path, "rb") as file:
            for packet in index.packets[: self._max_failures]:  # the first frame that decodes, as VideoCapture's probe
                image = decode_packet(read_packet(file.fileno(), packet))
                if image is not None:
                    return index if (image.shape[1], image.shape[0]) == index.image_size else None
        return None  # none decodes here: VideoCapture judges the file (and says so if it fails too)

    def _open(self) -> cv2.VideoCapture:
        capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            raise SourceError(
                f"OpenCV cannot open {self.path} as a video (unknown or damaged format); convert it with ffmpeg "
                f"(e.g. `ffmpeg -i {self.path.name} -c:v ffv1 out.mkv`) or pass a folder of images instead"
            )
        # The frames as stored, the sensor's own pixel grid, as for photos (EXIF orientation ignored):
        # FFmpeg would otherwise turn a phone's portrait video by its rotation tag, and the camera matrix
        # would be for the turned picture (fx and fy, cx and cy swapped against the same phone's photos).
        capture.set(cv2.CAP_PROP_ORIENTATION_AUTO, 0)
        rotation = capture.get(cv2.CAP_PROP_ORIENTATION_META)
        self._rotation_deg = int(round(rotation)) % 360 if math.isfinite(rotation) else 0
        return capture

    @property
    def info(self) -> SourceInfo:
        width, height = self._image_size
        fps = f"{self._fps:g} fps" if self._fps else "unknown fps"
        count = f"{self._frame_count} frames" if self._frame_count else "unknown length"
        turned = (f"; stored as the sensor gives it, though its players show it turned {self._rotation_deg} deg: "
                  "the calibration is for the stored frames" if self._rotation_deg else "")
        return SourceInfo(
            description=f"video file {self.path.name} ({width}x{height}, {fps}, {count}{turned})",
            kind="video", image_size=self._image_size, fps=self._fps, frame_count=self._frame_count,
        )

    def frames(self) -> Iterator[Frame]:
        self.skipped = []
        failed: list[int] = []  # indices of the current run of undecodable frames
        with closing(self._unpacked() if self._mjpg is not None else self._captured()) as decoded:
            for index, image, timestamp_ns, encoded in decoded:
                if image is None:
                    failed.append(index)
                    if len(failed) >= self._max_failures:
                        # With no frame count a normal end looks the same, so only a known count is reported.
                        if self._frame_count is not None:
                            self.skipped.append(SkippedFrame(failed[0], "", (
                                f"frames {failed[0]}-{failed[-1]} failed to decode in a row, so reading stopped; "
                                f"the header announces {self._frame_count} frames, the rest of the file is damaged")))
                        return
                    continue
                self.skipped += [SkippedFrame(i, "", "frame could not be decoded (damaged video data)") for i in failed]
                failed.clear()
                yield Frame(index=index, timestamp_ns=timestamp_ns, image=image, encoded=encoded)
        if self._mjpg is not None and self._mjpg.cut_off:
            cut = len(self._mjpg.packets)
            self.skipped.append(SkippedFrame(cut, "", (
                f"the file ends inside frame {cut}, so it was cut off (copied or recorded incompletely); "
                "the frames before it are read")))

    def _unpacked(self) -> Iterator[tuple[int, np.ndarray | None, int, bytes | None]]:
        """(index, grey image or None, timestamp, the frame's JPEG) of every MJPG frame, decoded ahead on
        worker threads: the luminance alone (`decode_packet_grey`), the colour on demand (`Frame.colour`)."""
        index = self._mjpg
        assert index is not None
        period_ns = 1e9 / (index.fps or DEFAULT_FPS)
        ahead = frames_ahead(index.image_size[0] * index.image_size[1])
        fd = os.open(self.path, os.O_RDONLY)

        def decode(packet: tuple[int, int]) -> tuple[np.ndarray | None, bytes]:
            data = read_packet(fd, packet)
            return decode_packet_grey(data), data.tobytes()

        images = decoded_ahead(index.packets, decode, ahead=ahead)
        try:
            for i, (image, encoded) in enumerate(images):
                yield i, image, round(i * period_ns), encoded
        finally:
            images.close()  # its decodes finish before the file they read is closed
            os.close(fd)

    def _captured(self) -> Iterator[tuple[int, np.ndarray | None, int, None]]:
        """(index, BGR image or None, timestamp, None) of every frame VideoCapture reads, up to the end it announces."""
        capture = self._capture = self._open()
        period_ns = 1e9 / (self._fps or DEFAULT_FPS)
        index, previous_ns = 0, -1
        try:
            while True:
                ok, image = capture.read()  # image: (H, W, 3) uint8 BGR
                if not ok or image is None:
                    if self._frame_count is not None and index >= self._frame_count:
                        return  # the end the header announced
                    yield index, None, 0, None
                else:
                    timestamp_ns = self._timestamp_ns(capture, index, previous_ns, period_ns)
                    yield index, image, timestamp_ns, None
                    previous_ns = timestamp_ns
                index += 1
        finally:
            capture.release()
            self._capture = None

    @staticmethod
    def _timestamp_ns(capture: cv2.VideoCapture, index: int, previous_ns: int, period_ns: float) -> int:
        """The container's time of the frame just read if it is sane (finite, increasing), else index / fps.

        Some backends report 0 ms for every frame, and FFmpeg reports 0 after a failed decode.
        """
        position_ms = capture.get(cv2.CAP_PROP_POS_MSEC)
        if math.isfinite(position_ms) and position_ms >= 0:
            position_ns = round(position_ms * 1e6)
            if index == 0 or position_ns > previous_ns:
                return position_ns
        return round(index * period_ns)

    def close(self) -> None:
        if self._capture is not None:
            self._capture.release()
            self._capture = None
