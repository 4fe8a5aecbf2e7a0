"""The frames of a Motion-JPEG .avi found in its container, so libjpeg decodes them on threads.

Webcams record MJPG (it is what they send over USB at 720p and up), and OpenCV's VideoWriter
and `ffmpeg -c:v copy` keep it in an AVI. Each frame of such a file is a complete JPEG in one
chunk of the container: nothing depends on the frame before, so the frames can be decoded in
any order and on any thread. OpenCV's VideoCapture decodes them through FFmpeg one after the
other on the reading thread, colour-converting each with swscale. Reading the chunks' places
from the RIFF structure and handing the JPEGs to `cv2.imdecode` (libjpeg-turbo, which also
decodes the live V4L2 MJPG stream, drivers/v4l2.py) on two threads decodes a 784-frame 720p
capture in 1.3 s instead of 2.1-2.3 and made whole replays 0.97x (dim) and 0.86x (messy) as
long (bench/results/replay_speed.md). The pixels differ from FFmpeg's by ~0.7 of a grey level
(another IDCT and colour rounding).

Only plain cases are indexed here; anything else returns None and is read by VideoCapture as
before: another codec, a video stream that is not the first, a zero-length chunk (a dropped
frame, whose timing FFmpeg accounts for its own way), a structure that does not parse, or fewer
frames found in a whole file than its headers count (the stream's length, OpenDML's total). Both
the AVI 1.0 body and OpenDML's extension ("AVIX" RIFF chunks beyond 1 GB) are walked; a chunk
that runs past the end of the file (a copy cut off) ends the index and is counted in `cut_off`.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

_MJPG_CODES = {b"MJPG"}  # FourCCs whose every chunk is a baseline JPEG (upper-cased before the test)
# a frame is the sensor's pixel grid, whatever orientation tag a JPEG might carry
_IMDECODE_FLAGS = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION
_IMDECODE_GREY_FLAGS = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION


@dataclass(frozen=True, slots=True)
class MjpgIndex:
    """Where each video frame's JPEG lies in the file, and the stream's header values."""

    packets: tuple[tuple[int, int], ...]  # (byte offset, length) of frame i's JPEG
    fps: float | None  # the stream header's rate / scale; None when absent
    image_size: tuple[int, int]  # (width, height) the stream header announces
    cut_off: int = 0  # 1 when the file ends inside a frame's chunk (that frame is not in `packets`)


def mjpg_index(path: str | Path) -> MjpgIndex | None:
    """The MJPG frames of an AVI file, or None when it is not a plain MJPG AVI (see the module docstring)."""
    try:
        with open(path, "rb") as file:
            return _Walk(file, os.fstat(file.fileno()).st_size).index()
    except (OSError, struct.error, ValueError):
        return None


def read_packet(fd: int, packet: tuple[int, int]) -> np.ndarray:
    """Frame bytes at (offset, length) of an open file descriptor (`os.pread`: safe from any thread)."""
    offset, length = packet
    return np.frombuffer(os.pread(fd, length, offset), np.uint8)


def decode_packet(data: np.ndarray) -> np.ndarray | None:
    """(H, W, 3) uint8 BGR as VideoCapture gives a frame, or None when the JPEG does not decode."""
    if data.size < 4 or data[0] != 0xFF or data[1] != 0xD8:  # no JPEG start: damaged (libjpeg would only complain)
        return None
    image = cv2.imdecode(data, _IMDECODE_FLAGS)
    return image if image is not None and image.ndim == 3 else None


def decode_packet_grey(data: np.ndarray) -> np.ndarray | None:
    """(H, W) uint8: the JPEG's luminance alone, or None when it does not decode.

    What detection reads, at ~40% of a colour decode's cost (1080p: 4.0 ms against 9.4 ms, and no
    conversion to grey after): libjpeg skips the chroma's upsampling and the colour transform. The
    grey is the colour decode's conversion to grey but for rounding: the same on every pixel of
    the bench's MJPG renders, within 2 grey levels on 0.1% of a colourful photo's pixels.
    """
    if data.size < 4 or data[0] != 0xFF or data[1] != 0xD8:
        return None
    image = cv2.imdecode(data, _IMDECODE_GREY_FLAGS)
    return image if image is not None and image.ndim == 2 else None


class _Walk:
    """One pass over the RIFF chunks: the header list first, then every 'movi' list's chunks."""

    def __init__(self, file: BinaryIO, size: int) -> None:
        self._file, self._size = file, size
        self._video_ids: tuple[bytes, ...] = ()  # the video stream's chunk names, once its header is read
        self._fps: float | None = None
        self._image_size: tuple[int, int] | None = None
        self._packets: list[tuple[int, int]] = []
        self._cut_off = 0
        self._announced = 0  # frames the headers count (the stream's length, OpenDML's total)

    def _header(self, offset: int) -> tuple[bytes, int]:
        self._file.seek(offset)
        raw = self._file.read(8)
        if len(raw) < 8:
            raise ValueError("truncated chunk header")
        return raw[:4], struct.unpack("<I", raw[4:])[0]

    def index(self) -> MjpgIndex | None:
        offset = 0
        while offset + 12 <= self._size:  # 'RIFF' 'AVI ' and, past 1 GB, 'RIFF' 'AVIX' chunks
            kind, length = self._header(offset)
            form = self._file.read(4)
            if kind != b"RIFF" or form != (b"AVI " if offset == 0 else b"AVIX"):
                if offset == 0:
                    return None
                break  # trailing bytes after the last RIFF chunk: ignored, as players do
            if not self._list(offset + 12, min(offset + 8 + length, self._size)):
                return None
            if self._cut_off:
                break
            offset += 8 + length + (length & 1)
        if not self._video_ids or self._image_size is None or not self._packets:
            return None
        if not self._cut_off and len(self._packets) < self._announced:
            # Fewer frames than the header counts in a whole file: the walk lost its way (a writer that
            # did not pad odd chunks, say); VideoCapture reads such files by their index instead.
            return None
        return MjpgIndex(tuple(self._packets), self._fps, self._image_size, self._cut_off)

    def _list(self, start: int, end: int) -> bool:
        """Walk the chunks in [start, end); False where the file is not one this module indexes."""
        offset = start
        while offset + 8 <= end:
            kind, length = self._header(offset)
            body = offset + 8
            if kind == b"LIST":
                form = self._file.read(4)
                list_end = min(body + length, self._size)  # a list cut off is walked up to the end of the file
                if form == b"hdrl":
                    self._file.seek(body)
                    if not self._stream_headers(self._file.read(list_end - body)):
                        return False
                elif form in (b"movi", b"rec "):
                    if not self._video_ids or not self._list(body + 4, list_end):
                        return False
            elif kind in self._video_ids:
                if body + length > self._size:
                    self._cut_off = 1
                    return True
                if length == 0:
                    return False  # a dropped frame: left to FFmpeg's own accounting
                self._packets.append((body, length))
            if body + length > self._size:
                return True  # the file ends inside this chunk: nothing further to find
            offset = body + length + (length & 1)
        return True

    def _stream_headers(self, hdrl: bytes) -> bool:
        """The first stream's header ('strh') and format ('strf'): MJPG video, its size, rate and
        length; and OpenDML's total frame count ('dmlh'), where the file has one."""
        video = None
        for kind, body, length in _chunks(hdrl, 4):  # past the list's form type
            form = hdrl[body:body + 4] if kind == b"LIST" else b""
            if form == b"strl" and video is None:
                video = self._first_stream(hdrl[body + 4:body + length])
            elif form == b"odml" and hdrl[body + 4:body + 8] == b"dmlh" and body + 16 <= len(hdrl):
                self._announced = max(self._announced, struct.unpack_from("<I", hdrl, body + 12)[0])
        return bool(video)

    def _first_stream(self, strl: bytes) -> bool:
        chunks: dict[bytes, bytes] = {}
        for kind, body, length in _chunks(strl, 0):
            chunks.setdefault(kind, strl[body:body + length])
        strh, strf = chunks.get(b"strh", b""), chunks.get(b"strf", b"")
        if len(strh) < 36 or len(strf) < 20 or strh[:4] != b"vids":
            return False
        handler, compression = strh[4:8].upper(), strf[16:20].upper()
        if compression not in _MJPG_CODES and not (compression == b"\0\0\0\0" and handler in _MJPG_CODES):
            return False
        scale, rate = struct.unpack_from("<II", strh, 20)
        width, height = struct.unpack_from("<ii", strf, 4)
        if width <= 0 or height == 0:
            return False
        self._video_ids = (b"00dc", b"00db")  # the first stream's compressed and uncompressed chunk names
        self._fps = rate / scale if scale and rate else None
        self._announced = max(self._announced, struct.unpack_from("<I", strh, 32)[0])  # dwLength: the stream's frames
        self._image_size = (int(width), abs(int(height)))
        return True


def _chunks(data: bytes, start: int) -> Iterator[tuple[bytes, int, int]]:
    """(name, body offset, body length) of each RIFF chunk in `data` from `start`, odd lengths padded."""
    offset = start
    while offset + 8 <= len(data):
        kind, length = data[offset:offset + 4], struct.unpack_from("<I", data, offset + 4)[0]
        yield kind, offset + 8, length
        offset += 8 + length + (length & 1)
