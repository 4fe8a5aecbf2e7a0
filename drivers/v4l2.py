"""Live V4L2 (UVC webcam) cameras through linuxpy: listing, opening, decoding, focus lock.

`list_v4l2_devices` answers "which camera, which formats, can its focus be locked?" before a
capture starts. `V4L2Camera` is the `FrameSource` for a live camera: it negotiates a format (MJPG
for large frames, because USB 2 cannot carry uncompressed 1080p at 30 fps; YUYV otherwise, which
has no compression artefacts near the board corners), decodes every buffer, stamps it with the
driver's capture time, and attaches a snapshot of the focus controls every few frames so that a
focus drift during capture is visible in the recording. An MJPG buffer is decoded to its luminance
alone, what detection reads, and keeps its JPEG (`Frame.encoded`) for the previews and for the
recording, as an MJPG video's frames are (drivers/avi_mjpg.py): on the bench's MJPG frames 2.2-5.1
ms at 720p against 5.7-9.4 ms for the colour and its conversion to grey, 6.1 against 12.7 ms at 1080p.

Focus, exposure and white-balance locking live in `v4l2_controls` (`V4L2FocusControl`).
No V4L2 device exists on the CI machines; the streaming path is kept thin and the control logic is
tested against a fake ioctl layer.
"""

from __future__ import annotations

import errno
import os
import time
from collections.abc import Iterator
from pathlib import Path
from types import MappingProxyType
from typing import Any

import cv2
import numpy as np

from calibcoach.drivers.avi_mjpg import decode_packet_grey
from calibcoach.drivers.base import Frame, FrameSource, SkippedFrame, SourceInfo
from calibcoach.drivers.errors import SourceError
from calibcoach.drivers.v4l2_controls import (
    CALIBRATION_CONTROLS,
    FocusControlError,
    V4L2FocusControl,
    describe_control,
)

__all__ = ["FocusControlError", "V4L2Camera", "V4L2FocusControl", "frame_pixels", "list_v4l2_devices",
           "parse_v4l2_target"]

_JPEG_FORMATS = ("MJPEG", "JPEG", "MJPG")  # linuxpy's names and the FourCC
_MJPG_FROM_PIXELS = 1280 * 720  # at or above this size prefer MJPG: YUYV 720p30 already fills USB 2
SNAPSHOT_EVERY = 10  # frames between focus snapshots: drift is slow, a read costs an ioctl per control
# errnos that mean the device went away (unplugged, reset, USB bus error) rather than a bad request
_GONE_ERRNOS = {errno.ENODEV, errno.ENXIO, errno.EIO, errno.ESHUTDOWN, errno.EPIPE, errno.EBADF}


def parse_v4l2_target(spec: str | int) -> str:
    """The device path of "v4l2:/dev/video0", "v4l2:0", "/dev/video0" or 0 (any absolute path is kept).

    Example:
        >>> parse_v4l2_target("v4l2:2")
        '/dev/video2'
    """
    if isinstance(spec, int) and not isinstance(spec, bool):
        return f"/dev/video{spec}" if spec >= 0 else _bad_target(spec)
    if not isinstance(spec, str):
        return _bad_target(spec)
    rest = spec[len("v4l2:"):] if spec.startswith("v4l2:") else spec
    if rest.isdigit():
        return f"/dev/video{int(rest)}"
    if rest.startswith("/"):  # /dev/videoN, a udev link under /dev/v4l/by-id/, or a test node
        return rest
    return _bad_target(spec)


def _bad_target(spec: object) -> str:
    raise SourceError(
        f"camera {spec!r} is not a V4L2 camera; write it as v4l2:/dev/videoN or v4l2:N "
        f"(list cameras with `calibcoach devices` or `v4l2-ctl --list-devices`)")


def _import_linuxpy() -> Any:
    try:
        from linuxpy.video import device as lvd
    except ImportError as exc:  # linuxpy only installs on Linux
        raise SourceError(f"V4L2 cameras need linuxpy (pip install linuxpy) on Linux: {exc}") from exc
    return lvd


def _describe_formats(lvd: Any, device: Any) -> list[dict[str, Any]]:
    """Pixel formats with their discrete sizes and frame rates (stepwise sizes reported as ranges)."""
    formats = []
    for fmt in device.info.formats:
        entry: dict[str, Any] = {"pixel_format": fmt.pixel_format.name, "description": fmt.description,
                                 "sizes": []}
        for size in device.info.format_frame_sizes(fmt.pixel_format):
            if size.type == lvd.FrameSizeType.DISCRETE:
                w, h = size.info.width, size.info.height
                rates = sorted({float(t.max_fps) for t in device.info.fps_intervals(fmt.pixel_format, w, h)
                                if t.max_fps}, reverse=True)
                entry["sizes"].append({"width": w, "height": h, "fps": rates})
            else:
                s = size.info
                entry["sizes"].append({"width": [s.min_width, s.max_width, s.step_width],
                                       "height": [s.min_height, s.max_height, s.step_height], "fps": []})
        formats.append(entry)
    return formats


def list_v4l2_devices(dev_dir: str | Path = "/dev") -> list[dict[str, Any]]:
    """Every /dev/video* capture device with its formats and calibration controls.

    linuxpy's `iter_video_capture_devices` silently drops nodes the user may not open and raises on
    the first node that fails QUERYCAP, so the nodes are globbed here and each is opened on its own:
    a node that cannot be opened is reported with the reason ("error") instead of hiding it, since
    "permission denied" (user not in group video) is the most common reason a camera is "missing".
    Metadata-only nodes (UVC creates one per camera) are left out.

    Returns:
        One dict per device: path, card, driver, bus, formats (pixel_format, sizes with fps) and
        controls (id, name, driver_name, min, max, step, default, value), or path and error.
        [] when there is no /dev/video* (returns at once, without importing linuxpy).
    """
    paths = sorted(Path(dev_dir).glob("video*"), key=lambda p: (len(p.name), p.name))
    if not paths:
        return []
    lvd = _import_linuxpy()
    found = []
    for path in paths:
        try:
            with lvd.Device(path) as device:
                caps = device.info.device_capabilities
                if lvd.Capability.VIDEO_CAPTURE not in caps:
                    continue  # metadata or output node, not a camera
                found.append({
                    "path": str(path), "card": device.info.card, "driver": device.info.driver,
                    "bus": device.info.bus_info,
                    "formats": _describe_formats(lvd, device),
                    "controls": [describe_control(c) for c in device.controls.values()
                                 if int(getattr(c, "id", -1)) in CALIBRATION_CONTROLS],
                })
        except (OSError, ValueError, lvd.V4L2Error) as exc:
            reason = os.strerror(exc.errno) if isinstance(exc, OSError) and exc.errno else str(exc)
            found.append({"path": str(path), "error": f"cannot open: {reason}"})
    return found


def open_v4l2_device(path: str):
    """An opened linuxpy Device (controls only, no streaming), or a SourceError saying what to check."""
    lvd = _import_linuxpy()
    device = lvd.Device(path)
    try:
        device.open()
    except OSError as exc:
        raise SourceError(
            f"cannot open camera {path}: {exc.strerror or exc}; check that it exists "
            f"(ls /dev/video*), that your user is in group video, and that no other program "
            f"uses it (fuser {path})") from exc
    return device


class V4L2Camera(FrameSource):
    """A live V4L2 camera as a frame source; frames are BGR (YUYV) or grey (GREY; MJPG, with its JPEG).

    Opening negotiates the format and reads back what the driver chose: drivers substitute the
    nearest size they support without an error, so a mismatch with the requested size raises.
    """

    def __init__(self, device: str | int, *, size: tuple[int, int] | None = None, fps: float | None = None,
                 pixel_format: str | None = None) -> None:
        super().__init__()
        self.path = parse_v4l2_target(device)
        lvd = self._lvd = _import_linuxpy()
        self._device = open_v4l2_device(self.path)
        try:
            self._configure(size, fps, pixel_format)
        except (OSError, lvd.V4L2Error) as exc:
            self._device.close()
            raise SourceError(f"camera {self.path} refused the capture format: {exc}") from exc
        except SourceError:
            self._device.close()
            raise
        self._focus = V4L2FocusControl(self._device)

    def _configure(self, size: tuple[int, int] | None, fps: float | None, pixel_format: str | None) -> None:
        lvd = self._lvd
        capture = lvd.BufferType.VIDEO_CAPTURE
        current = self._device.get_format(capture)
        width, height = size or (current.width, current.height)
        offered = [f.pixel_format.name for f in self._device.info.formats]
        chosen = _pixel_format_name(lvd, pixel_format) if pixel_format else _choose_pixel_format(
            offered, width * height)
        if chosen not in offered:
            raise SourceError(f"camera {self.path} does not offer pixel format {pixel_format or chosen}; "
                              f"it offers {', '.join(offered) or 'none'}")
        self._device.set_format(capture, width, height, lvd.PixelFormat[chosen])
        self._format = self._device.get_format(capture)
        if (self._format.width, self._format.height) != (width, height):
            raise SourceError(
                f"camera {self.path} cannot deliver {width}x{height} in {chosen}: the driver chose "
                f"{self._format.width}x{self._format.height}; pick a size from `calibcoach devices`")
        if fps:
            self._device.set_fps(capture, fps)
        self._fps = float(self._device.get_fps(capture) or 0) or None

    @property
    def focus(self) -> V4L2FocusControl:
        return self._focus

    @property
    def info(self) -> SourceInfo:
        w, h = self._format.width, self._format.height
        return SourceInfo(
            description=f"V4L2 camera {self.path} {self._device.info.card} ({w}x{h} "
                        f"{self._format.pixel_format.name}, {self._fps or '?'} fps)",
            kind="v4l2", camera_id=self._device.info.bus_info or self.path, image_size=(w, h), fps=self._fps,
            controls=MappingProxyType(self._focus.snapshot()))

    def frames(self) -> Iterator[Frame]:
        count = 0
        controls: dict[str, float] = {}
        try:
            with self._lvd.VideoCapture(self._device) as stream:
                for raw in stream:
                    image, jpeg = frame_pixels(raw.data, raw.pixel_format.name, raw.width, raw.height)
                    if image is None:
                        self.skipped.append(SkippedFrame(count, "", f"undecodable {raw.pixel_format.name} "
                                                                    f"buffer of {len(raw.data)} bytes"))
                        count += 1
                        continue
                    if count % SNAPSHOT_EVERY == 0:
                        controls = self._focus.snapshot()
                    secs, usecs = raw.buff.timestamp.secs, raw.buff.timestamp.usecs
                    # the driver stamps at capture (CLOCK_MONOTONIC on UVC): better than our dequeue time
                    stamp = secs * 1_000_000_000 + usecs * 1000 if secs or usecs else time.monotonic_ns()
                    yield Frame(count, stamp, image, controls=MappingProxyType(dict(controls)), encoded=jpeg)
                    count += 1
        except (OSError, FocusControlError) as exc:
            cause = exc if isinstance(exc, OSError) else exc.__cause__
            if isinstance(cause, OSError) and cause.errno in _GONE_ERRNOS:
                raise SourceError(
                    f"camera {self.path} disconnected after {count} frames "
                    f"({errno.errorcode.get(cause.errno, cause.errno)}: {cause.strerror}); check the USB "
                    f"cable and hub power, then start again; frames already processed are kept") from exc
            if isinstance(exc, OSError):
                raise SourceError(f"camera {self.path} failed after {count} frames: {exc}") from exc
            raise

    def close(self) -> None:
        self._device.close()


def _pixel_format_name(lvd: Any, spec: str) -> str:
    """linuxpy's name for a pixel format given as a FourCC ("MJPG") or a name ("MJPEG")."""
    if spec.upper() in lvd.PixelFormat.__members__:
        return spec.upper()
    if len(spec) == 4:
        try:
            return lvd.PixelFormat(lvd.raw.v4l2_fourcc(*spec)).name
        except ValueError:
            pass
    raise SourceError(f"pixel format {spec!r} is unknown; use a FourCC such as MJPG, YUYV or GREY")


def _choose_pixel_format(offered: list[str], pixels: int) -> str:
    """MJPG for large frames (USB 2 bandwidth), else YUYV (no compression artefacts), else GREY/MJPG."""
    order = ["MJPEG", "YUYV", "GREY"] if pixels >= _MJPG_FROM_PIXELS else ["YUYV", "GREY", "MJPEG"]
    for name in order:
        if name in offered:
            return name
    return offered[0] if offered else "YUYV"


def frame_pixels(data: bytes, pixel_format: str, width: int, height: int) -> tuple[np.ndarray | None, bytes | None]:
    """One buffer as a frame's `image` and `encoded`; the image None when the buffer cannot be decoded.

    MJPG: the (H, W) uint8 luminance and the JPEG itself (`Frame.colour()` decodes the colour where
    a person sees the frame); a JPEG that decodes to another size than the format's is not decodable
    here (a frame of another size would stop the session). YUYV: (H, W, 3) uint8 BGR; GREY: (H, W)
    uint8; neither keeps an encoded form.

    Example:
        >>> image, jpeg = frame_pixels(bytes(8), "GREY", 4, 2)
        >>> image.shape, jpeg
        ((2, 4), None)
    """
    buf = np.frombuffer(data, dtype=np.uint8)
    if pixel_format in _JPEG_FORMATS:
        jpeg = bytes(data)  # a copy: the buffer goes back to the driver once the frame is yielded
        grey = decode_packet_grey(np.frombuffer(jpeg, np.uint8))  # None for a truncated or damaged JPEG
        return (grey, jpeg) if grey is not None and grey.shape == (height, width) else (None, None)
    if pixel_format == "YUYV":
        if buf.size < width * height * 2:
            return None, None
        return cv2.cvtColor(buf[: width * height * 2].reshape(height, width, 2), cv2.COLOR_YUV2BGR_YUYV), None
    if pixel_format == "GREY":
        if buf.size < width * height:
            return None, None
        return buf[: width * height].reshape(height, width).copy(), None
    return None, None
