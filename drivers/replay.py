"""Replay sources: video files, folders of images and calibcoach recordings, behind `FrameSource`.

Replays are how most calibrations start (a phone video, a folder of stills) and how the live
pipeline is tested, so they must never stop half-way on one bad frame: undecodable frames go to
`source.skipped` with a reason and the stream carries on. Problems that make a source useless
(missing path, a folder without images, a file OpenCV cannot decode) are found when the source is
opened and raised as `SourceError` with one sentence saying what was found and what to do.
"""

from __future__ import annotations

import math
import os
import re
from collections import Counter, deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import closing
from functools import partial
from pathlib import Path
from types import MappingProxyType
from typing import TypeVar

import cv2
import numpy as np

from calibcoach.drivers.avi_mjpg import MjpgIndex, decode_packet, decode_packet_grey, mjpg_index, read_packet
from calibcoach.drivers.base import Frame, FrameSource, SkippedFrame, SourceInfo, frames_ahead
from calibcoach.drivers.errors import SourceError
from calibcoach.drivers.image_header import header_size
from calibcoach.drivers.png_fast import decode_png
from calibcoach.drivers.recording import SESSION_FILE, read_session

T = TypeVar("T")
D = TypeVar("D")  # what `_decoded_ahead` decodes an item to
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
_VIDEO_EXTENSIONS = (".avi", ".mp4", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg")  # for hints only
_DEFAULT_FPS = 30.0  # clock for sources without one: timestamps advance as if captured at 30 fps
_LIVE_SPEC = re.compile(r"^(v4l2|depthai)(:.*)?$|^/dev/video\d+$")
# Grey images stay (H, W), colour becomes (H, W, 3) BGR, 16-bit is scaled to 8-bit by OpenCV (>> 8).
# EXIF orientation is ignored: calibration needs the sensor's own pixel grid, and a phone rotating
# some stills would also make them a different size from the rest.
_IMREAD_FLAGS = cv2.IMREAD_ANYCOLOR | cv2.IMREAD_IGNORE_ORIENTATION


def open_source(spec: str | Path) -> FrameSource:
    """Open a replay source from a path: recording folder, image folder or video file.

    Args:
        spec: a folder holding session.json (recording), any other folder (images), or a video file.

    Returns:
        A `RecordingSource`, `ImageFolderSource` or `VideoFileSource`, already checked to hold frames.

    Raises:
        SourceError: the path is missing, holds nothing replayable, or names a live camera.
    """
    path = Path(spec).expanduser()
    if _LIVE_SPEC.match(str(spec)) and not (path.is_file() or path.is_dir()):
        raise SourceError(
            f"{str(spec)!r} is a live camera, not a file or folder; live cameras are opened by "
            f"`calibcoach live --source {spec}`"
        )
    if not path.exists():
        raise SourceError(f"{path} does not exist; pass a video file, a folder of images or a recording folder")
    if path.is_dir():
        return RecordingSource(path) if (path / SESSION_FILE).is_file() else ImageFolderSource(path)
    if not path.is_file():
        raise SourceError(f"{path} is neither a file nor a folder; pass a video file, a folder of images or a recording")
    if path.suffix.lower() in IMAGE_EXTENSIONS:
        raise SourceError(f"{path} is a single image; pass the folder that holds the images instead ({path.parent})")
    return VideoFileSource(path)


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
        period_ns = 1e9 / (index.fps or _DEFAULT_FPS)
        ahead = frames_ahead(index.image_size[0] * index.image_size[1])
        fd = os.open(self.path, os.O_RDONLY)

        def decode(packet: tuple[int, int]) -> tuple[np.ndarray | None, bytes]:
            data = read_packet(fd, packet)
            return decode_packet_grey(data), data.tobytes()

        images = _decoded_ahead(index.packets, decode, ahead=ahead)
        try:
            for i, (image, encoded) in enumerate(images):
                yield i, image, round(i * period_ns), encoded
        finally:
            images.close()  # its decodes finish before the file they read is closed
            os.close(fd)

    def _captured(self) -> Iterator[tuple[int, np.ndarray | None, int, None]]:
        """(index, BGR image or None, timestamp, None) of every frame VideoCapture reads, up to the end it announces."""
        capture = self._capture = self._open()
        period_ns = 1e9 / (self._fps or _DEFAULT_FPS)
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


class ImageFolderSource(FrameSource):
    """The images of one folder in natural order (cal2 before cal10), each a frame named by its file.

    Hidden files (".DS_Store", macOS "._cal1.png") are ignored. The camera's resolution is the one
    most images have (read from PNG and JPEG headers; the first decodable image's when no header
    tells), so a stray screenshot sorted first does not disqualify the rest. Images that do not
    decode, or of another size, go to `skipped` with the reason. Without `fps`, timestamps advance
    at 30 fps (info.fps stays None so nobody mistakes it for a measured rate). Of a JPEG only the
    luminance is decoded, its colour on demand (`Frame.colour`), as of an MJPG video's frames.
    """

    def __init__(self, path: str | Path, *, fps: float | None = None) -> None:
        super().__init__()
        self.path = Path(path)
        self._fps = fps
        if not self.path.is_dir():
            raise SourceError(f"{self.path} is not a folder; pass a folder of images")
        self._files = sorted(
            (p for p in self.path.iterdir()
             if p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".") and p.is_file()),
            key=_natural_key,
        )
        if not self._files:
            raise SourceError(_no_images_message(self.path))
        sizes = [header_size(path) for path in self._files]
        counts = Counter(size for size in sizes if size is not None)
        majority = max(counts, key=lambda size: (counts[size], -sizes.index(size))) if counts else None
        first, first_path = next(
            ((image, path) for path, size in zip(self._files, sizes, strict=True)
             if (majority is None or size == majority) and (image := _read_image(path)) is not None), (None, None))
        if first is None and majority is not None:  # the headers lied or those files are damaged: any image will do
            first, first_path = next(
                ((image, path) for path in self._files if (image := _read_image(path)) is not None), (None, None))
        self._size_source = "" if first_path is None else (
            f"{counts[majority]} of the {len(self._files)} images are"
            if majority is not None and majority == (int(first.shape[1]), int(first.shape[0])) and counts[majority] > 1
            else f"the first image ({first_path.name}) is")
        # One encoder wrote the folder: when its first image is a PNG the fast decoder handles, so are
        # the rest (and when not, none is tried: a failed try costs its inflate, ~1 ms).
        self._fast_png = first_path is not None and _fast_png_decodes(first_path, first)
        if first is None:
            raise SourceError(
                f"none of the {len(self._files)} images in {self.path} decodes (e.g. {self._files[0].name}); "
                "check that they are complete image files, not damaged or still being copied"
            )
        self._image_size = (int(first.shape[1]), int(first.shape[0]))  # (width, height) pixels
        self._frame_bytes = int(first.nbytes)

    @property
    def info(self) -> SourceInfo:
        width, height = self._image_size
        return SourceInfo(
            description=f"folder {self.path.name} ({len(self._files)} images, {width}x{height})",
            kind="folder", image_size=self._image_size, fps=self._fps, frame_count=len(self._files),
        )

    def frames(self) -> Iterator[Frame]:
        self.skipped = []
        for index, (image, encoded) in enumerate(_decoded_ahead(
                self._files, partial(_read_frame_image, fast_png=self._fast_png), ahead=frames_ahead(self._frame_bytes))):
            item = self._frame_or_skip(index, image, encoded)
            if isinstance(item, SkippedFrame):
                self.skipped.append(item)
                continue
            yield item

    def _frame_or_skip(self, index: int, image: np.ndarray | None, encoded: bytes | None = None) -> Frame | SkippedFrame:
        """The frame, or why it is skipped; image: (H, W) uint8 grey or (H, W, 3) uint8 BGR, or None;
        encoded: a JPEG's bytes where only its grey was decoded (`_read_frame_image`)."""
        path = self._files[index]
        if image is None:
            return SkippedFrame(index, path.name, _unreadable_reason(path))
        size = (int(image.shape[1]), int(image.shape[0]))
        if size != self._image_size:
            return SkippedFrame(index, path.name, (
                f"image is {size[0]}x{size[1]} but {self._size_source} "
                f"{self._image_size[0]}x{self._image_size[1]}; all images must share one camera resolution"))
        period_ns = 1e9 / (self._fps or _DEFAULT_FPS)
        return Frame(index=index, timestamp_ns=round(index * period_ns), image=image, name=path.name, encoded=encoded)


class RecordingSource(FrameSource):
    """A calibcoach recording (docs/recording-format.md), replayed with its controls and board.

    A recording cut off by a crash replays from frames.jsonl; frames whose PNG is missing, damaged
    or of the wrong size go to `skipped`, as do unusable lines of the frame list.
    """

    def __init__(self, path: str | Path) -> None:
        super().__init__()
        self.path = Path(path)
        contents = read_session(self.path)
        if not contents.entries:
            raise SourceError(
                f"recording {self.path} lists no usable frames (it was probably stopped before the first frame "
                "was saved); record the session again"
            )
        self._contents = contents
        header = contents.header
        camera = header["camera"]
        self._image_size = (int(camera["image_size"][0]), int(camera["image_size"][1]))  # (width, height) pixels
        fps = camera.get("fps")
        self._fps = float(fps) if isinstance(fps, int | float) and fps > 0 else None
        self._camera_id = str(camera.get("id", ""))
        self._controls = MappingProxyType(dict(header.get("controls") or {}))
        locked = header.get("locked_controls")
        self._locked = MappingProxyType(dict(locked) if isinstance(locked, dict) else {})
        events = header.get("events")
        self._events = tuple(MappingProxyType(dict(e)) for e in events if isinstance(e, dict)) if isinstance(events, list) else ()
        board = header.get("board")
        self._board = MappingProxyType(dict(board)) if isinstance(board, dict) else None

    @property
    def info(self) -> SourceInfo:
        width, height = self._image_size
        count = len(self._contents.entries)
        state = "" if self._contents.complete else ", cut off before it was closed"
        return SourceInfo(
            description=f"recording {self.path.name} ({self._camera_id}, {width}x{height}, {count} frames{state})",
            kind="recording", camera_id=self._camera_id, image_size=self._image_size, fps=self._fps,
            frame_count=count, controls=self._controls, board=self._board, locked_controls=self._locked,
            events=self._events,
        )

    def frames(self) -> Iterator[Frame]:
        self.skipped = list(self._contents.problems)
        paths = [self.path / entry["file"] for entry in self._contents.entries]
        # IMREAD_UNCHANGED: replay exactly what was written, grey as (H, W), BGR as (H, W, 3). The
        # fast PNG decoder when it gives the first frame's pixels exactly (as for a folder).
        first = next((path for path in paths if path.is_file()), None)
        decoded = None if first is None else _read_image(first, cv2.IMREAD_UNCHANGED)
        fast_png = decoded is not None and _fast_png_decodes(first, decoded)
        ahead = frames_ahead(3 * self._image_size[0] * self._image_size[1])
        for entry, path, image in zip(self._contents.entries, paths,
                                      _decoded_ahead(
                                          paths, partial(_read_image, flags=cv2.IMREAD_UNCHANGED, fast_png=fast_png), ahead=ahead), strict=True):
            if image is None:
                self.skipped.append(SkippedFrame(entry["index"], path.name, _unreadable_reason(path)))
                continue
            size = (int(image.shape[1]), int(image.shape[0]))
            if size != self._image_size or image.dtype != np.uint8:
                self.skipped.append(SkippedFrame(entry["index"], path.name, (
                    f"frame is {size[0]}x{size[1]} {image.dtype} but the recording is "
                    f"{self._image_size[0]}x{self._image_size[1]} uint8")))
                continue
            yield Frame(index=entry["index"], timestamp_ns=entry["timestamp_ns"], image=image, name=path.name,
                        controls=MappingProxyType(dict(entry["controls"])))


# --- helpers ----------------------------------------------------------------------------------


def _natural_key(path: Path) -> tuple[tuple[tuple[int, int | str], ...], str]:
    """Sort key comparing digit runs as numbers, case-insensitively: cal2 < cal10 < Cal11."""
    parts = re.split(r"(\d+)", path.name.lower())
    return tuple((0, int(p)) if p.isdigit() else (1, p) for p in parts if p), path.name


_DECODE_WORKERS = 2  # decoding releases the GIL; a 720p PNG takes ~5 ms in OpenCV, ~2.9 ms in png_fast


def _decoded_ahead(items: Sequence[T], decode: Callable[[T], D], *, ahead: int = 8) -> Iterator[D]:
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


def _read_frame_image(path: Path, *, fast_png: bool = False) -> tuple[np.ndarray | None, bytes | None]:
    """A folder's frame as `_read_image` decodes it, but of a JPEG only the luminance, with its bytes:
    what detection reads, at ~40% of the cost; `Frame.colour()` decodes the rest where a person sees
    the frame (as of an MJPG video's frames: drivers/avi_mjpg.py)."""
    try:
        data = np.fromfile(path, np.uint8)
    except OSError:
        return None, None
    grey = decode_packet_grey(data)  # None for anything but a JPEG that decodes
    if grey is not None:
        return grey, data.tobytes()
    return decode_image(data, fast_png=fast_png), None


def _read_image(path: Path, flags: int = _IMREAD_FLAGS, *, fast_png: bool = False) -> np.ndarray | None:
    """Decode an image file, or None if it is missing, empty or not decodable (never raises)."""
    try:
        data = np.fromfile(path, np.uint8)  # imdecode, not imread: no path-encoding trouble, no stderr noise
    except OSError:
        return None
    return decode_image(data, flags, fast_png=fast_png)


def decode_image(data: np.ndarray, flags: int = _IMREAD_FLAGS, *, fast_png: bool = False) -> np.ndarray | None:
    """An image file's bytes decoded, or None if empty or not decodable (never raises).

    `fast_png`: try drivers/png_fast.py first (~3x faster on the PNGs OpenCV writes by default, ~2x on
    adaptively filtered ones, 720p grey), OpenCV if it declines.
    """
    if data.size == 0:
        return None
    if fast_png and flags in (_IMREAD_FLAGS, cv2.IMREAD_UNCHANGED):  # both give grey as (H, W), colour as BGR
        image = decode_png(data.data)
        if image is not None:
            return image
    image = cv2.imdecode(data, flags)
    if image is None or image.ndim not in (2, 3):
        return None
    return image


def _fast_png_decodes(path: Path, decoded: np.ndarray) -> bool:
    """Whether drivers/png_fast.py decodes this file to the pixels OpenCV `decoded` it to."""
    if path.suffix.lower() != ".png":
        return False
    fast = decode_png(np.fromfile(path, np.uint8).data)
    return fast is not None and np.array_equal(fast, decoded)


def _unreadable_reason(path: Path) -> str:
    if not path.exists():
        return "file is missing"
    if path.stat().st_size == 0:
        return "file is empty (0 bytes)"
    return f"file does not decode as an image (damaged, truncated, or not really a {path.suffix} file)"


def _no_images_message(folder: Path) -> str:
    """One sentence: which extensions were looked for, what the folder holds instead, what to pass."""
    entries = [p for p in folder.iterdir() if not p.name.startswith(".")]
    files = [p for p in entries if p.is_file()]
    folders = [p for p in entries if p.is_dir()]
    counts = Counter(p.suffix.lower() or "extension-less" for p in files)
    parts = [f"{n} {suffix} file{'s' if n != 1 else ''}" for suffix, n in counts.most_common(4)]
    if len(counts) > 4:
        parts.append(f"{sum(counts.values()) - sum(n for _, n in counts.most_common(4))} other files")
    if folders:
        parts.append(f"{len(folders)} folder{'s' if len(folders) != 1 else ''}")
    found = "it is empty" if not parts else "it contains " + (
        parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1])
    videos = sorted(p for p in files if p.suffix.lower() in _VIDEO_EXTENSIONS)
    image_folders = sorted(d for d in folders if any(
        p.suffix.lower() in IMAGE_EXTENSIONS for p in d.iterdir() if p.is_file()))
    if videos:
        advice = f"pass the video file itself, e.g. {videos[0]}"
    elif image_folders:
        advice = f"pass the folder that holds the images, e.g. {image_folders[0]}"
    else:
        advice = "pass the folder that holds the calibration images"
    looked_for = ", ".join(IMAGE_EXTENSIONS)
    return f"{folder} holds no images (looked for {looked_for}); {found}; {advice}"
