"""Luxonis OAK cameras through DepthAI v3: live frames with the focus locked, and calibration files.

Calibration needs raw, un-undistorted pixels at a fixed focus: every lens move changes the
intrinsics, and an image the device has already undistorted with its factory calibration hides
exactly the distortion we are trying to measure. So the live source
- builds a `dai.node.Camera` on CAM_A and requests its output with `enableUndistortion=False`,
- starts with autofocus OFF (`initialControl`), at the asked lens position or, without one, at the
  position the first frame reports, which is then locked explicitly and confirmed,
- reads a non-blocking queue (maxSize 4) so a slow consumer drops old frames instead of stalling
  the device; dropped frames show up as gaps in `Frame.index` (taken from the sequence number).

Every `dai.ImgFrame` becomes a `Frame` through one function, `imgframe_to_frame`, which is shared
with `DepthAIReplay`, a host-only source (`dai.Pipeline(createImplicitDevice=False)` plus
`dai.node.ReplayVideo`) that needs no device. The tests run the conversion through that replay, so
the device path stays a thin shell around code that is exercised on every machine.

`write_depthai_calibration` writes a result in the device's own format (`CalibrationHandler` JSON);
flashing it to the EEPROM is deliberately not done here.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from types import MappingProxyType
from typing import Any

import depthai as dai
import numpy as np

from calibcoach.drivers.base import Frame, FrameSource, SourceInfo
from calibcoach.drivers.errors import CalibcoachError, SourceError
from calibcoach.drivers.lens import CameraModel

TARGET_PREFIX = "depthai"
LENS_RANGE = (0, 255)  # CameraControl.setManualFocus and ImgFrame.getLensPosition use 0..255
DEPTHAI_COEFF_COUNT = 14  # CalibrationHandler stores 14 distortion coefficients per camera
FOCUS_SETTLE_S = 1.0  # a voice-coil lens settles in a few frames; a second means it was refused
QUEUE_SIZE = 4  # frames buffered per output queue: enough to ride out a GC pause, little latency


class FocusControlError(CalibcoachError):
    """The OAK camera's lens could not be moved to, or confirmed at, the asked position."""


# --- discovery and targets ----------------------------------------------------------------------


def _enum_name(value: Any, prefix: str = "X_LINK_") -> str:
    name = getattr(value, "name", str(value))
    return name[len(prefix):] if name.startswith(prefix) else name


def list_depthai_devices(timeout_s: float = 2.0) -> list[dict[str, str]]:
    """OAK devices visible on USB and the network: [{"device_id", "name", "state", "platform"}].

    Discovery runs in a daemon thread joined with `timeout_s`, so a slow XLink search (network
    devices, a wedged USB hub) can never hold up the caller, and no environment variable (such as
    DEPTHAI_SEARCH_TIMEOUT) has to be changed for the whole process. Never raises: "no devices"
    and "discovery failed" both mean there is nothing to open, which the caller reports.
    """
    found: list[Any] = []

    def probe() -> None:
        try:
            found.extend(dai.Device.getAllAvailableDevices())
        except Exception:  # noqa: BLE001 - discovery failure is reported as "no devices"
            pass

    thread = threading.Thread(target=probe, name="depthai-discovery", daemon=True)
    thread.start()
    thread.join(max(0.0, timeout_s))
    if thread.is_alive():
        return []
    return [
        {
            "device_id": info.getDeviceId(),  # the MXID on RVC2 devices
            "name": info.name,  # USB path ("1.3") or IP address
            "state": _enum_name(info.state),  # BOOTED / UNBOOTED / BOOTLOADER ...
            "platform": _enum_name(info.platform),  # MYRIAD_X (RVC2) / RVC4 ...
        }
        for info in list(found)
    ]


def parse_depthai_target(spec: str) -> str | None:
    """"depthai" -> None (the first device found); "depthai:1844301011B546F500" -> that device id."""
    name, sep, device_id = spec.partition(":")
    if name != TARGET_PREFIX or (sep and not device_id.strip()):
        raise SourceError(
            f"source {spec!r} is not a DepthAI target; write it as depthai (first OAK camera found) or "
            f"depthai:DEVICE_ID, e.g. depthai:1844301011B546F500 (calibcoach devices lists the ids)")
    return device_id.strip() or None


# --- ImgFrame -> Frame (shared by the device and the host-only replay) ----------------------------


def _ns(delta: timedelta) -> int:
    """timedelta -> integer nanoseconds without going through float seconds (keeps microseconds exact)."""
    return ((delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds) * 1_000


def imgframe_to_frame(img: dai.ImgFrame, index: int, *, with_controls: bool = True) -> Frame:
    """One `dai.ImgFrame` as a `Frame`: BGR (or grey) uint8 pixels, host-clock timestamp, lens state.

    `getCvFrame()` does the NV12 -> BGR conversion (and honours plane strides, which a hand-written
    cv2.COLOR_YUV2BGR_NV12 on `getData()` would have to redo). The timestamp is `getTimestamp()`,
    the device clock already mapped to the host's steady clock, so frames from an OAK line up with
    host events. `with_controls=False` is for frames that did not come from a sensor (a replayed
    file reports lens position, exposure and ISO as 0, which would read as real settings).
    """
    image = np.ascontiguousarray(img.getCvFrame())
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise SourceError(
            f"DepthAI frame {index} has type {_enum_name(img.getType(), '')} ({image.dtype}, shape "
            f"{image.shape}), which calibcoach cannot use; request NV12, BGR888i or GRAY8 output")
    controls: dict[str, float] = {}
    if with_controls:
        controls = {
            "lens_position": float(img.getLensPosition()),
            "exposure_us": img.getExposureTime() / timedelta(microseconds=1),
            "iso": float(img.getSensitivity()),
        }
    return Frame(index=index, timestamp_ns=_ns(img.getTimestamp()), image=image,
                 controls=MappingProxyType(controls))


def frames_from_queue(queue: dai.MessageQueue, *, with_controls: bool, timeout: timedelta | None,
                      on_frame=None) -> Iterator[Frame]:
    """Frames from an output queue until it closes; `Frame.index` counts from the first sequence number.

    Indices come from `getSequenceNum()` so frames dropped by a non-blocking queue leave gaps
    instead of silently renumbering the stream. A closed queue (`QueueException`) ends the stream:
    that is how ReplayVideo says "end of file". `RuntimeError` and a timeout propagate to the
    caller, which knows whether that means "device lost".
    """
    first_seq: int | None = None
    while True:
        try:
            img = queue.get() if timeout is None else queue.get(timeout)
        except dai.MessageQueue.QueueException:
            return
        if img is None:
            raise TimeoutError(f"no frame within {timeout}")
        seq = int(img.getSequenceNum())
        first_seq = seq if first_seq is None else first_seq
        if on_frame is not None:
            on_frame(img)
        yield imgframe_to_frame(img, seq - first_seq, with_controls=with_controls)


class DepthAIReplay(FrameSource):
    """A video file played through DepthAI's `ReplayVideo` node on the host (no device needed).

    It exists so that the exact conversion the live OAK source uses is exercised without hardware,
    and to feed recorded OAK footage through the same path. The queue is blocking: a file has no
    real-time constraint, and dropping frames would make the replay differ from run to run.
    """

    def __init__(self, video_path: str | Path, *, fps: float | None = None,
                 frame_type: dai.ImgFrame.Type = dai.ImgFrame.Type.NV12):
        super().__init__()
        self.path = Path(video_path)
        if not self.path.is_file():
            raise SourceError(f"video file {self.path} does not exist; check the path")
        import cv2  # only to read the container's size and rate up front for `info`

        cap = cv2.VideoCapture(str(self.path))
        try:
            if not cap.isOpened():
                raise SourceError(f"cannot open video file {self.path}; is it a video OpenCV/FFmpeg can decode?")
            size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
            file_fps = float(cap.get(cv2.CAP_PROP_FPS)) or None
            count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or None
        finally:
            cap.release()
        # Replay at the file's own rate by default so timestamp spacing matches the recording.
        self.fps = float(fps) if fps else (file_fps or 30.0)
        self.frame_type = frame_type
        self._info = SourceInfo(
            description=f"video file {self.path.name} replayed through DepthAI ({size[0]}x{size[1]}, "
                        f"{self.fps:g} fps, {count if count else '?'} frames)",
            kind="video", image_size=size, fps=self.fps, frame_count=count)

    @property
    def info(self) -> SourceInfo:
        return self._info

    def frames(self) -> Iterator[Frame]:
        with dai.Pipeline(createImplicitDevice=False) as pipeline:
            replay = pipeline.create(dai.node.ReplayVideo)
            replay.setReplayVideoFile(self.path)
            replay.setOutFrameType(self.frame_type)
            replay.setFps(self.fps)
            replay.setLoop(False)  # one pass; the queue closes at the end of the file
            queue = replay.out.createOutputQueue(maxSize=QUEUE_SIZE, blocking=True)
            pipeline.start()
            count = 0
            for frame in frames_from_queue(queue, with_controls=False, timeout=None):
                count += 1
                yield frame
        if count == 0:  # ReplayVideo reports decode failures only in its log: say so here
            raise SourceError(f"DepthAI ReplayVideo delivered no frames from {self.path}, which OpenCV can "
                              f"open; re-encode it (e.g. ffmpeg -i IN -c:v mjpeg OUT.avi) and try again")


# --- calibration file in the device's format -----------------------------------------------------


def write_depthai_calibration(path: str | Path, camera: CameraModel, *, socket: str = "CAM_A",
                              lens_position: int | None = None, untrusted: bool = False) -> Path:
    """Write `camera` as a DepthAI calibration JSON (what `CalibrationHandler(path)` reads back).

    DepthAI keeps 14 coefficients per camera: OpenCV's order k1 k2 p1 p2 k3 k4 k5 k6 s1..s4 tx ty
    for `Perspective`, Kannala-Brandt k1..k4 for `Fisheye`; unused ones are zero. The lens position
    is stored when known because the intrinsics are only valid at that focus. The file is only
    written here; flashing it to a device's EEPROM is a separate, explicitly requested step.
    `untrusted` writes "UNTRUSTED" into the file's product name, the one free-text field the format has.
    """
    handler = apply_intrinsics(dai.CalibrationHandler(), camera, socket=socket, lens_position=lens_position)
    if untrusted:
        handler.setProductName("UNTRUSTED calibcoach calibration (refused; see calibration.json)")
    out = Path(path)
    if not handler.eepromToJsonFile(out):
        raise CalibcoachError(f"DepthAI could not write the calibration file {out}; check that the folder "
                              f"exists and is writable")
    return out


def apply_intrinsics(handler: dai.CalibrationHandler, camera: CameraModel, *, socket: str = "CAM_A",
                     lens_position: int | None = None) -> dai.CalibrationHandler:
    """Set one socket's intrinsics, distortion, camera type (and lens position) on `handler`.

    Used on a fresh handler for the JSON file, and on the device's own calibration before flashing,
    so that the other sockets' intrinsics and the stereo extrinsics stay as the factory left them.
    """
    board_socket = getattr(dai.CameraBoardSocket, socket, None)
    if not isinstance(board_socket, dai.CameraBoardSocket):
        names = ", ".join(sorted(n for n in dai.CameraBoardSocket.__members__ if n.startswith("CAM_")))
        raise CalibcoachError(f"camera socket {socket!r} is not a DepthAI board socket; use one of {names}")
    coeffs = [float(c) for c in camera.dist_coeffs]
    coeffs += [0.0] * (DEPTHAI_COEFF_COUNT - len(coeffs))
    width, height = camera.image_size
    handler.setCameraIntrinsics(board_socket, camera.camera_matrix.tolist(), width, height)
    handler.setDistortionCoefficients(board_socket, coeffs)
    handler.setCameraType(board_socket, dai.CameraModel.Fisheye if camera.model == "fisheye"
                          else dai.CameraModel.Perspective)
    if lens_position is not None:
        handler.setLensPosition(board_socket, check_lens_position(lens_position))
    return handler


def check_lens_position(position: object) -> int:
    """`position` as an int if it is a valid OAK lens position, else FocusControlError."""
    if isinstance(position, bool) or not isinstance(position, int | np.integer) \
            or not LENS_RANGE[0] <= int(position) <= LENS_RANGE[1]:
        raise FocusControlError(
            f"lens position {position!r} is out of range: OAK lens positions are whole numbers "
            f"{LENS_RANGE[0]}..{LENS_RANGE[1]}; fixed-focus modules (e.g. OAK-D W) have no lens to move")
    return int(position)



def __getattr__(name: str) -> Any:
    """`oak.DepthAICamera` etc. live in oak_device.py (file length); load them on first use.

    Lazy (PEP 562) rather than a top-level import because oak_device imports this module's helpers.
    """
    if name in ("DepthAICamera", "DepthAIFocus", "build_focus_control"):
        from calibcoach.drivers import oak_device

        return getattr(oak_device, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
