"""V4L2 focus locking and device listing against a fake camera at the ioctl layer.

There is no /dev/video* on CI. As in linuxpy's own tests, the only thing replaced is
`linuxpy.ioctl.fcntl.ioctl`: linuxpy opens a real (regular) file and builds real ctypes structures,
and `FakeCamera.ioctl` answers them from a dict of controls the way the kernel does:
VIDIOC_QUERYCAP, VIDIOC_QUERY_EXT_CTRL (enumeration with V4L2_CTRL_FLAG_NEXT_CTRL),
VIDIOC_QUERYMENU, VIDIOC_G_EXT_CTRLS / VIDIOC_S_EXT_CTRLS (current and default values),
VIDIOC_ENUM_FMT, VIDIOC_ENUM_FRAMESIZES and VIDIOC_ENUM_FRAMEINTERVALS. Everything above that
(linuxpy's control classes, our range checks, writes and read-backs) runs for real.
"""

from __future__ import annotations

import errno
import itertools
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from unittest import mock

import cv2
import numpy as np
import pytest
from linuxpy.video import raw
from linuxpy.video.device import Device, FrameIntervalType, FrameSizeType

from calibcoach.drivers.base import Frame
from calibcoach.drivers.errors import CalibcoachError, SourceError
from calibcoach.drivers.v4l2 import V4L2Camera, frame_pixels, list_v4l2_devices, parse_v4l2_target
from calibcoach.drivers.v4l2_controls import (
    V4L2_CID_AUTO_WHITE_BALANCE,
    V4L2_CID_EXPOSURE_ABSOLUTE,
    V4L2_CID_EXPOSURE_AUTO,
    V4L2_CID_FOCUS_ABSOLUTE,
    V4L2_CID_FOCUS_AUTO,
    V4L2_CID_WHITE_BALANCE_TEMPERATURE,
    FocusControlError,
    V4L2FocusControl,
)

_NEXT = raw.ControlFlag.NEXT_CTRL | raw.ControlFlag.NEXT_COMPOUND
_DESCRIPTIONS = {raw.PixelFormat.YUYV: b"YUYV 4:2:2", raw.PixelFormat.GREY: b"8-bit Greyscale",
                 raw.PixelFormat.MJPEG: b"Motion-JPEG"}


@dataclass
class Ctrl:
    name: str  # the driver's name; the old UVC names on purpose, since lookup must go by ID
    type: int
    minimum: int
    maximum: int
    step: int
    default: int
    value: int
    menu: dict[int, str] = field(default_factory=dict)


def webcam_controls() -> dict[int, Ctrl]:
    """A Logitech-C920-like UVC camera, in continuous autofocus and aperture-priority exposure."""
    t = raw.CtrlType
    return {
        V4L2_CID_AUTO_WHITE_BALANCE: Ctrl("White Balance Temperature, Auto", t.BOOLEAN, 0, 1, 1, 1, 1),
        V4L2_CID_WHITE_BALANCE_TEMPERATURE: Ctrl("White Balance Temperature", t.INTEGER, 2000, 6500, 1,
                                                 4000, 4650),
        V4L2_CID_EXPOSURE_AUTO: Ctrl("Exposure, Auto", t.MENU, 0, 3, 1, 3, 3,
                                     {1: "Manual Mode", 3: "Aperture Priority Mode"}),
        V4L2_CID_EXPOSURE_ABSOLUTE: Ctrl("Exposure (Absolute)", t.INTEGER, 3, 2047, 1, 250, 312),
        V4L2_CID_FOCUS_ABSOLUTE: Ctrl("Focus (absolute)", t.INTEGER, 0, 250, 5, 0, 85),
        V4L2_CID_FOCUS_AUTO: Ctrl("Focus, Auto", t.BOOLEAN, 0, 1, 1, 1, 1),
    }


class FakeCamera:
    """Answers linuxpy's ioctls from `controls`; `clamp` and `ignore` model misbehaving firmware."""

    BUFFER_BYTES = 4096  # one page per buffer, so that mmap offsets are page-aligned

    def __init__(self, controls: dict[int, Ctrl], node: Path | None = None) -> None:
        self.controls = controls
        self.writes: list[tuple[int, int]] = []  # (control id, value) of every S_EXT_CTRLS, in order
        self.clamp: dict[int, int] = {}  # id -> the largest value the firmware really stores
        self.ignore: set[int] = set()  # ids whose writes are acknowledged but not applied
        # streaming: buffers live in the regular file `node`, which linuxpy mmaps for real
        self.node = node
        self.pixel_formats = [raw.PixelFormat.YUYV]
        self.max_size = (640, 480)  # S_FMT clamps larger requests to this, as drivers do, silently
        self.format = [640, 480, raw.PixelFormat.YUYV]
        self.fps = 30
        self.frames: list[bytes] = []  # what DQBUF delivers, in order (repeats the last one)
        self.gone_after: int | None = None  # unplug after this many frames: every ioctl says ENODEV
        self.gone = False
        self.streaming = False
        self._queued: list[int] = []
        self._sent = 0

    def ioctl(self, fd: int, request: int, arg: object, *rest: object) -> int:
        ioc = raw.IOC
        if self.gone:
            raise OSError(errno.ENODEV, "No such device")
        if request in (ioc.G_FMT, ioc.S_FMT, ioc.G_PARM, ioc.S_PARM, ioc.REQBUFS, ioc.QUERYBUF, ioc.QBUF,
                       ioc.DQBUF, ioc.STREAMON, ioc.STREAMOFF):
            self._stream_ioctl(request, arg)
        elif request == ioc.QUERYCAP:
            arg.driver, arg.card, arg.bus_info = b"uvcvideo", b"HD Pro Webcam C920", b"usb-0000:00:14.0-1"
            caps = raw.Capability.VIDEO_CAPTURE | raw.Capability.STREAMING | raw.Capability.DEVICE_CAPS
            arg.capabilities, arg.device_caps = caps, raw.Capability.VIDEO_CAPTURE | raw.Capability.STREAMING
        elif request == ioc.QUERY_EXT_CTRL:
            self._query(arg)
        elif request == ioc.QUERYMENU:
            name = self.controls[arg.id].menu.get(arg.index)
            if name is None:
                raise OSError(errno.EINVAL, "no such menu item")
            arg.name = name.encode()
        elif request == ioc.G_EXT_CTRLS:
            for i in range(arg.count):
                ctrl = self._lookup(arg, i)
                default = arg.which == raw.ControlWhichValue.DEF_VAL
                arg.controls[i].value = ctrl.default if default else ctrl.value
        elif request == ioc.S_EXT_CTRLS:
            for i in range(arg.count):
                ctrl, cid, value = self._lookup(arg, i), arg.controls[i].id, arg.controls[i].value
                self.writes.append((cid, value))
                if cid not in self.ignore:
                    ctrl.value = min(value, self.clamp.get(cid, value))
        elif request == ioc.ENUM_FMT:
            if arg.index >= len(self.pixel_formats):
                raise OSError(errno.EINVAL, "end of list")
            arg.pixelformat = self.pixel_formats[arg.index]
            arg.description = _DESCRIPTIONS[self.pixel_formats[arg.index]]
        elif request == ioc.ENUM_FRAMESIZES:
            if arg.index > 0:
                raise OSError(errno.EINVAL, "end of list")
            arg.type = FrameSizeType.DISCRETE
            arg.m1.discrete.width, arg.m1.discrete.height = 640, 480
        elif request == ioc.ENUM_FRAMEINTERVALS:
            if arg.index > 0:
                raise OSError(errno.EINVAL, "end of list")
            arg.type = FrameIntervalType.DISCRETE
            arg.m1.discrete.numerator, arg.m1.discrete.denominator = 1, 30
        else:
            raise OSError(errno.ENOTTY, f"fake camera does not answer ioctl {request!r}")
        return 0

    def _stream_ioctl(self, request: int, arg: object) -> None:
        ioc = raw.IOC
        if request == ioc.G_FMT:
            arg.fmt.pix.width, arg.fmt.pix.height, arg.fmt.pix.pixelformat = self.format
        elif request == ioc.S_FMT:
            pix = arg.fmt.pix
            fourcc = pix.pixelformat if pix.pixelformat in self.pixel_formats else self.pixel_formats[0]
            self.format = [min(pix.width, self.max_size[0]), min(pix.height, self.max_size[1]), fourcc]
            pix.width, pix.height, pix.pixelformat = self.format
        elif request == ioc.G_PARM:
            arg.parm.capture.timeperframe.numerator, arg.parm.capture.timeperframe.denominator = 1, self.fps
        elif request == ioc.S_PARM:
            frac = arg.parm.capture.timeperframe
            self.fps = frac.denominator // frac.numerator
        elif request == ioc.QUERYBUF:
            arg.length, arg.m.offset = self.BUFFER_BYTES, arg.index * self.BUFFER_BYTES
        elif request == ioc.QBUF:
            self._queued.append(arg.index)
        elif request == ioc.DQBUF:
            if self.gone_after is not None and self._sent >= self.gone_after:
                self.gone = True
                raise OSError(errno.ENODEV, "No such device")
            index = self._queued.pop(0)
            data = self.frames[min(self._sent, len(self.frames) - 1)]
            with open(self.node, "r+b") as node:  # the mmap is shared: the reader sees this write
                node.seek(index * self.BUFFER_BYTES)
                node.write(data)
            arg.index, arg.bytesused, arg.sequence = index, len(data), self._sent
            arg.timestamp.secs, arg.timestamp.usecs = 1000 + self._sent, 250_000
            self._sent += 1
        elif request in (ioc.STREAMON, ioc.STREAMOFF):
            self.streaming = request == ioc.STREAMON
        # REQBUFS: the count asked for is granted as is

    def _query(self, arg: raw.v4l2_query_ext_ctrl) -> None:
        """The kernel's enumeration: with NEXT_CTRL set, answer the first control with a larger id."""
        if arg.id & raw.ControlFlag.NEXT_CTRL:
            base = arg.id & ~_NEXT
            ids = [cid for cid in sorted(self.controls) if cid > base]
        else:
            ids = [arg.id] if arg.id in self.controls else []
        if not ids:
            raise OSError(errno.EINVAL, "no more controls")
        ctrl = self.controls[ids[0]]
        arg.id, arg.type, arg.name = ids[0], ctrl.type, ctrl.name.encode()
        arg.minimum, arg.maximum, arg.step, arg.default_value = ctrl.minimum, ctrl.maximum, ctrl.step, ctrl.default
        arg.flags, arg.elems, arg.elem_size, arg.nr_of_dims = 0, 1, 4, 0

    def _lookup(self, arg: raw.v4l2_ext_controls, i: int) -> Ctrl:
        cid = arg.controls[i].id
        if cid not in self.controls:
            arg.error_idx = i
            raise OSError(errno.EINVAL, f"no control 0x{cid:08X}")
        return self.controls[cid]


@pytest.fixture
def camera(tmp_path: Path) -> Iterator[FakeCamera]:
    fake = FakeCamera(webcam_controls())
    with mock.patch("linuxpy.ioctl.fcntl.ioctl", fake.ioctl):
        yield fake


@pytest.fixture
def device(tmp_path: Path, camera: FakeCamera) -> Iterator[Device]:
    node = tmp_path / "video0"
    node.write_bytes(b"")  # a regular file: linuxpy opens it for real, only the ioctls are fake
    with Device(node) as dev:
        yield dev


def test_lock_turns_off_autofocus_and_sets_focus(camera: FakeCamera, device: Device) -> None:
    confirmed = V4L2FocusControl(device).lock(250)
    assert confirmed == {"focus_automatic_continuous": 0, "focus_absolute": 250}
    # autofocus off first, then the position; nothing else touched
    assert camera.writes == [(V4L2_CID_FOCUS_AUTO, 0), (V4L2_CID_FOCUS_ABSOLUTE, 250)]
    assert camera.controls[V4L2_CID_FOCUS_AUTO].value == 0
    assert camera.controls[V4L2_CID_FOCUS_ABSOLUTE].value == 250


def test_lock_without_position_keeps_where_autofocus_left_it(camera: FakeCamera, device: Device) -> None:
    confirmed = V4L2FocusControl(device).lock()
    assert confirmed == {"focus_automatic_continuous": 0, "focus_absolute": 85}
    assert camera.writes == [(V4L2_CID_FOCUS_AUTO, 0), (V4L2_CID_FOCUS_ABSOLUTE, 85)]


def test_camera_without_focus_controls_gets_advice(tmp_path: Path) -> None:
    controls = webcam_controls()
    del controls[V4L2_CID_FOCUS_ABSOLUTE], controls[V4L2_CID_FOCUS_AUTO]
    fake = FakeCamera(controls)
    node = tmp_path / "video0"
    node.write_bytes(b"")
    with mock.patch("linuxpy.ioctl.fcntl.ioctl", fake.ioctl), Device(node) as dev:
        with pytest.raises(FocusControlError) as err:
            V4L2FocusControl(dev).lock(100)
    message = str(err.value)
    assert "has no focus_absolute control" in message
    assert "fixed-focus or needs the vendor's tool" in message
    assert "--allow-autofocus" in message
    assert isinstance(err.value, CalibcoachError)
    assert fake.writes == []


def test_clamping_driver_is_caught_naming_both_values(camera: FakeCamera, device: Device) -> None:
    camera.controls[V4L2_CID_FOCUS_ABSOLUTE].maximum = 1020  # declares 0..1020, really stores 0..255
    camera.clamp[V4L2_CID_FOCUS_ABSOLUTE] = 255
    with pytest.raises(FocusControlError) as err:
        V4L2FocusControl(device).lock(300)
    message = str(err.value)
    assert "focus_absolute" in message
    assert "asked for 300, camera reports 255" in message
    assert "declared range 0..1020" in message
    assert camera.controls[V4L2_CID_FOCUS_ABSOLUTE].value == 255


def test_ignored_autofocus_off_is_caught(camera: FakeCamera, device: Device) -> None:
    camera.ignore.add(V4L2_CID_FOCUS_AUTO)  # acknowledged, but continuous AF stays on
    with pytest.raises(FocusControlError) as err:
        V4L2FocusControl(device).lock(100)
    message = str(err.value)
    assert "focus_automatic_continuous (control 0x009A090C)" in message
    assert "asked for 0, camera reports 1" in message
    assert camera.writes == [(V4L2_CID_FOCUS_AUTO, 0), (V4L2_CID_FOCUS_ABSOLUTE, 100)]


@pytest.mark.parametrize(("position", "expected"), [
    (300, "focus_absolute 300 is out of range for camera"),
    (-5, "focus_absolute -5 is out of range for camera"),
    (102, "focus_absolute 102 is off the step grid of camera"),
])
def test_bad_position_rejected_before_any_write(camera: FakeCamera, device: Device, position: int,
                                                expected: str) -> None:
    with pytest.raises(FocusControlError) as err:
        V4L2FocusControl(device).lock(position)
    assert expected in str(err.value)
    assert "valid values are 0..250 in steps of 5" in str(err.value)
    assert camera.writes == []  # refused before VIDIOC_S_EXT_CTRLS
    assert camera.controls[V4L2_CID_FOCUS_AUTO].value == 1


def test_off_grid_error_names_the_neighbours(camera: FakeCamera, device: Device) -> None:
    with pytest.raises(FocusControlError, match=r"nearest: 100 or 105"):
        V4L2FocusControl(device).lock(102)


def test_lock_exposure_and_white_balance_keep_current_values(camera: FakeCamera, device: Device) -> None:
    confirmed = V4L2FocusControl(device).lock(120, lock_exposure=True, lock_white_balance=True)
    assert confirmed == {
        "focus_automatic_continuous": 0, "focus_absolute": 120,
        "auto_exposure": 1, "exposure_time_absolute": 312,
        "white_balance_automatic": 0, "white_balance_temperature": 4650,
    }
    assert camera.writes == [
        (V4L2_CID_FOCUS_AUTO, 0), (V4L2_CID_FOCUS_ABSOLUTE, 120),
        (V4L2_CID_EXPOSURE_AUTO, 1), (V4L2_CID_EXPOSURE_ABSOLUTE, 312),
        (V4L2_CID_AUTO_WHITE_BALANCE, 0), (V4L2_CID_WHITE_BALANCE_TEMPERATURE, 4650),
    ]


def test_exposure_stuck_in_auto_is_caught(camera: FakeCamera, device: Device) -> None:
    camera.ignore.add(V4L2_CID_EXPOSURE_AUTO)
    with pytest.raises(FocusControlError, match=r"auto_exposure .*asked for 1, camera reports 3"):
        V4L2FocusControl(device).lock(120, lock_exposure=True)


def test_unlock_restores_the_saved_auto_modes(camera: FakeCamera, device: Device) -> None:
    focus = V4L2FocusControl(device)
    focus.lock(50, lock_exposure=True)
    camera.writes.clear()
    assert focus.unlock() == {"focus_automatic_continuous": 1, "auto_exposure": 3}
    assert camera.writes == [(V4L2_CID_FOCUS_AUTO, 1), (V4L2_CID_EXPOSURE_AUTO, 3)]


def test_status_and_snapshot_report_by_our_names(camera: FakeCamera, device: Device) -> None:
    focus = V4L2FocusControl(device)
    expected = {"white_balance_automatic": 1, "white_balance_temperature": 4650, "auto_exposure": 3,
                "exposure_time_absolute": 312, "focus_absolute": 85, "focus_automatic_continuous": 1}
    assert focus.status() == expected
    snapshot = focus.snapshot()
    assert snapshot == {name: float(value) for name, value in expected.items()}
    assert all(isinstance(v, float) for v in snapshot.values())
    assert camera.writes == []  # reading never writes


def test_list_v4l2_devices_on_this_machine_is_empty() -> None:
    if list(Path("/dev").glob("video*")):
        pytest.skip("this machine has /dev/video* nodes")
    assert list_v4l2_devices() == []


def test_list_v4l2_devices_describes_cameras_and_reports_unopenable(tmp_path: Path,
                                                                      camera: FakeCamera) -> None:
    (tmp_path / "video0").write_bytes(b"")
    (tmp_path / "video1").mkdir()  # opening a directory read-write fails: EISDIR
    found = list_v4l2_devices(tmp_path)
    assert len(found) == 2
    cam, broken = found
    assert (cam["path"], cam["card"], cam["driver"]) == (str(tmp_path / "video0"), "HD Pro Webcam C920",
                                                         "uvcvideo")
    assert cam["formats"] == [{"pixel_format": "YUYV", "description": "YUYV 4:2:2",
                               "sizes": [{"width": 640, "height": 480, "fps": [30.0]}]}]
    focus = next(c for c in cam["controls"] if c["id"] == V4L2_CID_FOCUS_ABSOLUTE)
    assert focus == {"id": V4L2_CID_FOCUS_ABSOLUTE, "name": "focus_absolute", "driver_name": "Focus (absolute)",
                     "min": 0, "max": 250, "step": 5, "default": 0, "value": 85}
    assert sorted(c["name"] for c in cam["controls"]) == [
        "auto_exposure", "exposure_time_absolute", "focus_absolute", "focus_automatic_continuous",
        "white_balance_automatic", "white_balance_temperature"]
    assert broken == {"path": str(tmp_path / "video1"), "error": "cannot open: Is a directory"}


@pytest.mark.parametrize(("spec", "path"), [
    ("v4l2:/dev/video0", "/dev/video0"), ("v4l2:0", "/dev/video0"), ("v4l2:12", "/dev/video12"),
    (3, "/dev/video3"), ("/dev/video2", "/dev/video2"),
])
def test_parse_v4l2_target(spec: str | int, path: str) -> None:
    assert parse_v4l2_target(spec) == path


@pytest.mark.parametrize("spec", ["visca:/dev/ttyUSB0", "v4l2:", "v4l2:cam", -1])
def test_parse_v4l2_target_rejects(spec: str | int) -> None:
    with pytest.raises(SourceError, match=r"write it as v4l2:/dev/videoN or v4l2:N"):
        parse_v4l2_target(spec)


def test_decode_yuyv_grey_and_broken_buffers() -> None:
    # Y=128 with neutral chroma (U=V=128) is grey; OpenCV's BT.601 video range maps it to
    # (128 - 16) * 255 / 219 = 130.4 -> 130 in every channel
    bgr, kept = frame_pixels(bytes([128] * (4 * 2 * 2)), "YUYV", 4, 2)
    assert bgr.shape == (2, 4, 3) and kept is None
    assert int(bgr.min()) == int(bgr.max()) == 130
    grey, kept = frame_pixels(bytes(range(8)), "GREY", 4, 2)
    assert grey.tolist() == [[0, 1, 2, 3], [4, 5, 6, 7]] and kept is None
    assert frame_pixels(b"\xff\xd8 truncated", "MJPEG", 4, 2) == (None, None)
    assert frame_pixels(bytes(5), "YUYV", 4, 2) == (None, None)  # short buffer


def _red_jpeg(width: int = 24, height: int = 16) -> bytes:
    ok, jpeg = cv2.imencode(".jpg", np.full((height, width, 3), (0, 0, 255), np.uint8))  # pure red, BGR
    assert ok
    return jpeg.tobytes()


def test_mjpg_buffer_is_its_luminance_and_keeps_its_jpeg() -> None:
    """Detection reads the luminance (libjpeg skips the chroma); the colour comes back from the kept JPEG."""
    jpeg = _red_jpeg()
    grey, kept = frame_pixels(memoryview(jpeg), "MJPEG", 24, 16)
    assert kept == jpeg and isinstance(kept, bytes)  # a copy, not a view of the driver's buffer
    assert grey.shape == (16, 24) and grey.dtype == np.uint8
    assert np.array_equal(grey, cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE))
    colour = Frame(0, 0, grey, encoded=kept).colour()
    assert colour.shape == (16, 24, 3)
    assert colour[8, 12, 2] > 240 and colour[8, 12, 0] < 15  # red stays red, not blue
    # a JPEG of another size than the negotiated format is no frame of this stream
    assert frame_pixels(jpeg, "MJPEG", 32, 16) == (None, None)


@pytest.fixture
def streaming(tmp_path: Path) -> Iterator[FakeCamera]:
    """A 64x32 GREY camera whose two mmap buffers are pages of the regular file standing in for /dev/video0."""
    node = tmp_path / "video0"
    node.write_bytes(bytes(2 * FakeCamera.BUFFER_BYTES))
    fake = FakeCamera(webcam_controls(), node)
    fake.pixel_formats = [raw.PixelFormat.GREY]
    fake.format = [64, 32, raw.PixelFormat.GREY]
    fake.frames = [bytes([i]) * (64 * 32) for i in range(20)]  # frame i is filled with the value i
    with mock.patch("linuxpy.ioctl.fcntl.ioctl", fake.ioctl):
        yield fake


def test_camera_streams_frames_with_driver_timestamps_and_focus_snapshots(streaming: FakeCamera) -> None:
    with V4L2Camera(f"v4l2:{streaming.node}", size=(64, 32), fps=15) as cam:
        assert cam.info.image_size == (64, 32)
        assert cam.info.fps == 15.0
        assert cam.info.kind == "v4l2"
        assert cam.info.controls["focus_absolute"] == 85.0
        stream = cam.frames()
        frames = list(itertools.islice(stream, 6))
        streaming.controls[V4L2_CID_FOCUS_ABSOLUTE].value = 90  # the lens drifts during capture
        frames += list(itertools.islice(stream, 6))
        stream.close()
    assert streaming.streaming is False  # STREAMOFF was sent when the stream was closed
    assert [f.index for f in frames] == list(range(12))
    assert [int(f.image[0, 0]) for f in frames] == list(range(12))
    assert frames[3].image.shape == (32, 64)
    assert frames[3].timestamp_ns == 1003 * 1_000_000_000 + 250_000_000  # the driver's capture time
    # snapshots every 10 frames: frames 0..9 carry the one from frame 0, frame 10 sees the drift
    assert frames[9].controls["focus_absolute"] == 85.0
    assert frames[10].controls["focus_absolute"] == 90.0
    assert frames[11].controls["focus_automatic_continuous"] == 1.0


def test_mjpg_camera_streams_grey_frames_that_keep_their_jpeg(streaming: FakeCamera) -> None:
    jpegs = [cv2.imencode(".jpg", np.full((32, 64, 3), (40 * i, 90, 200 - 40 * i), np.uint8))[1].tobytes()
             for i in range(4)]
    assert max(len(j) for j in jpegs) <= FakeCamera.BUFFER_BYTES
    streaming.pixel_formats = [raw.PixelFormat.MJPEG]
    streaming.format = [64, 32, raw.PixelFormat.MJPEG]
    streaming.frames = jpegs
    with V4L2Camera(str(streaming.node), size=(64, 32)) as cam:
        stream = cam.frames()
        frames = list(itertools.islice(stream, 4))
        stream.close()
    assert [f.encoded for f in frames] == jpegs  # each buffer's own bytes (bytesused), copied before requeueing
    for frame, jpeg in zip(frames, jpegs, strict=True):
        assert np.array_equal(frame.image, cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE))
        assert np.array_equal(frame.colour(), cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR))


def test_camera_unplugged_mid_stream_raises_source_error(streaming: FakeCamera) -> None:
    streaming.gone_after = 3
    received = []
    with V4L2Camera(str(streaming.node), size=(64, 32)) as cam, pytest.raises(SourceError) as err:
        for frame in cam.frames():
            received.append(frame.index)
    assert received == [0, 1, 2]
    assert str(err.value).startswith(f"camera {streaming.node} disconnected after 3 frames (ENODEV: ")
    assert "check the USB cable" in str(err.value)


def test_camera_refuses_a_size_the_driver_replaced(streaming: FakeCamera) -> None:
    streaming.max_size = (64, 32)
    with pytest.raises(SourceError, match=r"cannot deliver 128x64 in GREY: the driver chose 64x32"):
        V4L2Camera(str(streaming.node), size=(128, 64))


def test_camera_refuses_a_pixel_format_it_does_not_offer(streaming: FakeCamera) -> None:
    with pytest.raises(SourceError, match=r"does not offer pixel format MJPG; it offers GREY"):
        V4L2Camera(str(streaming.node), size=(64, 32), pixel_format="MJPG")
