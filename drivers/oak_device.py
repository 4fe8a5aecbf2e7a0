"""The live OAK device half of the DepthAI driver (see oak.py for the why; this needs hardware).

Kept thin on purpose: frames go through `oak.frames_from_queue` / `oak.imgframe_to_frame`, which the
host-only `DepthAIReplay` tests exercise; what is left here is pipeline wiring, focus control and
turning depthai's link errors into `SourceError`s. `build_focus_control` and `DepthAIFocus` run
without a device (the control is a host object; the focus takes any queue-like objects).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from types import MappingProxyType
from typing import Any

import depthai as dai

from calibcoach.drivers.base import Frame, FrameSource, SourceInfo
from calibcoach.drivers.errors import CalibcoachError, SourceError
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.oak import (
    FOCUS_SETTLE_S,
    QUEUE_SIZE,
    FocusControlError,
    apply_intrinsics,
    check_lens_position,
    frames_from_queue,
    list_depthai_devices,
)

FIRST_FRAME_TIMEOUT = timedelta(seconds=5)  # sensor start-up plus 3A warm-up on a USB2 link


def build_focus_control(position: int | None = None, *, auto: bool = False) -> dai.CameraControl:
    """The CameraControl a focus lock sends: autofocus OFF plus the manual position (if any).

    `auto=True` builds the unlock instead (continuous-video autofocus, the camera's default).
    Built on the host, so the tests can check what would go to the device.
    """
    control = dai.CameraControl()
    if auto:
        control.setAutoFocusMode(dai.CameraControl.AutoFocusMode.CONTINUOUS_VIDEO)
        return control
    control.setAutoFocusMode(dai.CameraControl.AutoFocusMode.OFF)
    if position is not None:
        control.setManualFocus(check_lens_position(position))
    return control


class DepthAIFocus:
    """Focus of one running OAK camera: lock/unlock via its control queue, confirmed from frames.

    DepthAI has no "read focus" request: the only evidence of where the lens is, is the lens
    position each ImgFrame reports. `lock` therefore sends the control and then reads frames until
    one reports the asked position. Frames read while settling are not yielded by `frames()`: they
    were taken while the lens moved and are useless for calibration anyway.
    """

    def __init__(self, control_queue: Any, frame_queue: Any, camera_id: str, *,
                 settle_s: float = FOCUS_SETTLE_S):
        self._control, self._frames, self.camera_id, self.settle_s = control_queue, frame_queue, camera_id, settle_s
        self.mode = "manual"  # the pipeline starts with autofocus OFF (initialControl)
        self.position: int | None = None  # last lens position a frame reported

    def observe(self, img: Any) -> None:
        """Record the lens position of a frame (called for every frame `frames()` yields)."""
        self.position = int(img.getLensPosition())

    def lock(self, position: int) -> int:
        """Manual focus at `position`; returns it once a frame confirms it, else FocusControlError."""
        position = check_lens_position(position)
        self._control.send(build_focus_control(position))
        self.mode = "manual"
        deadline = time.monotonic() + self.settle_s
        seen: list[int] = []
        while time.monotonic() < deadline:
            img = self._frames.tryGet()
            if img is None:
                time.sleep(0.005)  # frames arrive every 15-70 ms; no need to spin
                continue
            self.observe(img)
            seen.append(self.position)
            if self.position == position:
                return position
        reported = f"frames reported {sorted(set(seen))}" if seen else "no frame arrived"
        raise FocusControlError(
            f"OAK camera {self.camera_id}: asked for lens position {position} but the lens did not settle "
            f"there within {self.settle_s:g} s ({reported}); check that this module has a motorised lens "
            f"(fixed-focus modules ignore focus commands) and that nothing else sends camera controls")

    def unlock(self) -> None:
        """Back to continuous autofocus. Not confirmable from frames (the lens may not move at all)."""
        self._control.send(build_focus_control(auto=True))
        self.mode = "auto"

    def status(self) -> dict[str, object]:
        """{"focus_mode": "manual" | "auto", "lens_position": last position a frame reported, or None}."""
        return {"focus_mode": self.mode, "lens_position": self.position}


class DepthAICamera(FrameSource):
    """Live frames from CAM_A of an OAK camera, un-undistorted, with the focus locked.

    Opening connects, starts the pipeline, waits for the first frame and locks the focus (at
    `lens_position`, or where the first frame says the lens is), so an unusable camera fails here
    with a clear message rather than after the user has started moving the board.
    """

    def __init__(self, device_id: str | None = None, *, size: tuple[int, int] = (1920, 1080),
                 fps: float = 30.0, lens_position: int | None = None):
        super().__init__()
        width, height = (int(v) for v in size)
        if width <= 0 or height <= 0 or fps <= 0:
            raise SourceError(f"OAK output {size} at {fps} fps is invalid; use a positive size and rate")
        if lens_position is not None:
            check_lens_position(lens_position)
        devices = list_depthai_devices()
        chosen = next((d for d in devices if device_id in (None, d["device_id"], d["name"])), None)
        if chosen is None:
            visible = ", ".join(f"{d['device_id']} ({d['state']})" for d in devices) or "none"
            raise SourceError(
                f"OAK camera {device_id or '(any)'} not found; visible DepthAI devices: {visible}. Check the "
                f"USB cable (a USB3 cable and port), the udev rule for 03e7 devices, and that no other "
                f"program holds the camera")
        self.camera_id = chosen["device_id"]
        self._closed = False
        self._pipeline: Any = None
        try:
            self._device = dai.Device(self.camera_id)
            self._pipeline = dai.Pipeline(self._device)
            cam = self._pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
            cam.initialControl.setAutoFocusMode(dai.CameraControl.AutoFocusMode.OFF)
            if lens_position is not None:
                cam.initialControl.setManualFocus(lens_position)
            # enableUndistortion=False: the device must not undistort with its factory calibration.
            out = cam.requestOutput((width, height), dai.ImgFrame.Type.NV12, fps=fps, enableUndistortion=False)
            self._queue = out.createOutputQueue(maxSize=QUEUE_SIZE, blocking=False)
            control_queue = cam.inputControl.createInputQueue()
            self._pipeline.start()
            first = self._queue.get(FIRST_FRAME_TIMEOUT)
        except RuntimeError as exc:
            self.close()
            raise SourceError(f"cannot start OAK camera {self.camera_id}: {exc}; unplug and replug it, "
                              f"and check that CAM_A supports {width}x{height} at {fps:g} fps") from exc
        if first is None:
            self.close()
            raise SourceError(f"OAK camera {self.camera_id} started but sent no frame within "
                              f"{FIRST_FRAME_TIMEOUT.total_seconds():g} s; check the USB link")
        self._focus = DepthAIFocus(control_queue, self._queue, self.camera_id)
        self._focus.observe(first)
        try:  # lock explicitly even at the current position: proves focus control works before capture
            self._focus.lock(lens_position if lens_position is not None else int(first.getLensPosition()))
        except FocusControlError:
            self.close()
            raise
        self._info = SourceInfo(
            description=f"OAK camera {self.camera_id} CAM_A ({width}x{height}, {fps:g} fps, "
                        f"lens locked at {self._focus.position})",
            kind="depthai", camera_id=self.camera_id, image_size=(width, height), fps=float(fps),
            controls=MappingProxyType({"lens_position": float(self._focus.position)}))

    @property
    def info(self) -> SourceInfo:
        return self._info

    @property
    def focus(self) -> DepthAIFocus:
        return self._focus

    def frames(self) -> Iterator[Frame]:
        count = 0
        try:
            # A 2 s gap at >= 1 fps means the link is gone even if depthai has not noticed yet.
            for frame in frames_from_queue(self._queue, with_controls=True, timeout=timedelta(seconds=2),
                                           on_frame=self._focus.observe):
                count += 1
                yield frame
        except (RuntimeError, TimeoutError) as exc:
            if self._closed:
                return
            raise SourceError(
                f"OAK camera {self.camera_id} disconnected after {count} frames ({exc}); check the USB "
                f"cable and power (OAK-D needs a powered port or the barrel supply), then restart") from exc
        if not self._closed:  # a live camera never ends by itself: the queue closed under us
            raise SourceError(f"OAK camera {self.camera_id} disconnected after {count} frames (the frame "
                              f"queue closed); check the USB cable and power, then restart")

    def close(self) -> None:
        self._closed = True
        for stop in (getattr(self._pipeline, "stop", None), getattr(getattr(self, "_device", None), "close", None)):
            if stop is not None:
                try:
                    stop()
                except RuntimeError:
                    pass  # already gone with the device; nothing left to release


def flash_intrinsics(device_id: str | None, camera: CameraModel, *, backup_path: Path, socket: str = "CAM_A",
                     lens_position: int | None = None) -> Path:
    """Write `camera` into the device's EEPROM calibration (only on the user's explicit request).

    The device's current calibration is saved to `backup_path` first, then only `socket`'s
    intrinsics are replaced on it, so stereo extrinsics and the other cameras stay untouched.
    Returns the backup path.
    """
    try:
        device = dai.Device(device_id) if device_id else dai.Device()
    except RuntimeError as exc:
        raise SourceError(f"cannot open the OAK camera to flash its calibration ({exc}); is it plugged in?") from None
    with device:
        current = device.readCalibration()
        if not current.eepromToJsonFile(Path(backup_path)):
            raise CalibcoachError(f"could not back up the device calibration to {backup_path}; nothing was flashed")
        try:
            device.flashCalibration(apply_intrinsics(current, camera, socket=socket, lens_position=lens_position))
        except RuntimeError as exc:
            raise CalibcoachError(f"flashing the calibration failed ({exc}); the previous one is saved in {backup_path}") from None
    return Path(backup_path)
