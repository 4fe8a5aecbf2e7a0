"""Replay sources: folders of images and calibcoach recordings, and `open_source` for any path (a video
file opens as drivers/video_file.py's `VideoFileSource`), behind `FrameSource`.

Replays are how most calibrations start (a phone video, a folder of stills) and how the live
pipeline is tested, so they must never stop half-way on one bad frame: undecodable frames go to
`source.skipped` with a reason and the stream carries on. Problems that make a source useless
(missing path, a folder without images, a file OpenCV cannot decode) are found when the source is
opened and raised as `SourceError` with one sentence saying what was found and what to do.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from types import MappingProxyType

import cv2
import numpy as np

from calibcoach.drivers.base import DEFAULT_FPS, Frame, FrameSource, SkippedFrame, SourceInfo, frames_ahead
from calibcoach.drivers.errors import SourceError
from calibcoach.drivers.image_files import (
    decoded_ahead,
    fast_png_decodes,
    read_frame_image,
    read_image,
    unreadable_reason,
)
from calibcoach.drivers.image_header import header_size
from calibcoach.drivers.recording import SESSION_FILE, read_session
from calibcoach.drivers.video_file import VideoFileSource

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
_VIDEO_EXTENSIONS = (".avi", ".mp4", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg")  # for hints only
_LIVE_SPEC = re.compile(r"^(v4l2|depthai)(:.*)?$|^/dev/video\d+$")


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
             if (majority is None or size == majority) and (image := read_image(path)) is not None), (None, None))
        if first is None and majority is not None:  # the headers lied or those files are damaged: any image will do
            first, first_path = next(
                ((image, path) for path in self._files if (image := read_image(path)) is not None), (None, None))
        self._size_source = "" if first_path is None else (
            f"{counts[majority]} of the {len(self._files)} images are"
            if majority is not None and majority == (int(first.shape[1]), int(first.shape[0])) and counts[majority] > 1
            else f"the first image ({first_path.name}) is")
        # One encoder wrote the folder: when its first image is a PNG the fast decoder handles, so are
        # the rest (and when not, none is tried: a failed try costs its inflate, ~1 ms).
        self._fast_png = first_path is not None and fast_png_decodes(first_path, first)
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
        for index, (image, encoded) in enumerate(decoded_ahead(
                self._files, partial(read_frame_image, fast_png=self._fast_png), ahead=frames_ahead(self._frame_bytes))):
            item = self._frame_or_skip(index, image, encoded)
            if isinstance(item, SkippedFrame):
                self.skipped.append(item)
                continue
            yield item

    def _frame_or_skip(self, index: int, image: np.ndarray | None, encoded: bytes | None = None) -> Frame | SkippedFrame:
        """The frame, or why it is skipped; image: (H, W) uint8 grey or (H, W, 3) uint8 BGR, or None;
        encoded: a JPEG's bytes where only its grey was decoded (`read_frame_image`)."""
        path = self._files[index]
        if image is None:
            return SkippedFrame(index, path.name, unreadable_reason(path))
        size = (int(image.shape[1]), int(image.shape[0]))
        if size != self._image_size:
            return SkippedFrame(index, path.name, (
                f"image is {size[0]}x{size[1]} but {self._size_source} "
                f"{self._image_size[0]}x{self._image_size[1]}; all images must share one camera resolution"))
        period_ns = 1e9 / (self._fps or DEFAULT_FPS)
        return Frame(index=index, timestamp_ns=round(index * period_ns), image=image, name=path.name, encoded=encoded)


class RecordingSource(FrameSource):
    """A calibcoach recording (docs/recording-format.md), replayed with its controls and board.

    A recording cut off by a crash replays from frames.jsonl; frames whose file (PNG, or a camera's
    JPEG) is missing, damaged or of the wrong size go to `skipped`, as do unusable lines of the frame list.
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
        # IMREAD_UNCHANGED: replay exactly what was written, grey as (H, W), BGR as (H, W, 3); of a
        # camera's JPEG (RecordingWriter.write) its luminance, as the live session decoded it, and the
        # JPEG for its colour. The fast PNG decoder when it gives the first PNG's pixels exactly (as
        # for a folder).
        first = next((path for path in paths if path.suffix.lower() == ".png" and path.is_file()), None)
        decoded = None if first is None else read_image(first, cv2.IMREAD_UNCHANGED)
        fast_png = decoded is not None and fast_png_decodes(first, decoded)
        ahead = frames_ahead(3 * self._image_size[0] * self._image_size[1])
        read = partial(read_frame_image, flags=cv2.IMREAD_UNCHANGED, fast_png=fast_png)
        for entry, path, (image, encoded) in zip(self._contents.entries, paths, decoded_ahead(paths, read, ahead=ahead),
                                                 strict=True):
            if image is None:
                self.skipped.append(SkippedFrame(entry["index"], path.name, unreadable_reason(path)))
                continue
            size = (int(image.shape[1]), int(image.shape[0]))
            if size != self._image_size or image.dtype != np.uint8:
                self.skipped.append(SkippedFrame(entry["index"], path.name, (
                    f"frame is {size[0]}x{size[1]} {image.dtype} but the recording is "
                    f"{self._image_size[0]}x{self._image_size[1]} uint8")))
                continue
            yield Frame(index=entry["index"], timestamp_ns=entry["timestamp_ns"], image=image, name=path.name,
                        controls=MappingProxyType(dict(entry["controls"])), encoded=encoded)


# --- helpers ----------------------------------------------------------------------------------


def _natural_key(path: Path) -> tuple[tuple[tuple[int, int | str], ...], str]:
    """Sort key comparing digit runs as numbers, case-insensitively: cal2 < cal10 < Cal11."""
    parts = re.split(r"(\d+)", path.name.lower())
    return tuple((0, int(p)) if p.isdigit() else (1, p) for p in parts if p), path.name


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
