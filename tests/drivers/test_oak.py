"""DepthAI (OAK) driver tests that run without a device.

What runs here for real, through depthai itself: device discovery (which finds nothing), the
host-only ReplayVideo pipeline feeding the same ImgFrame -> Frame conversion the live camera uses,
the CameraControl a focus lock sends, and calibration JSON written and read back by depthai's own
CalibrationHandler. The live pipeline's focus settling and link-loss handling run against small
queue stand-ins carrying real host-built ImgFrames.

depthai prints "USB protocol not available" on import through its own logger (stderr), not as a
Python warning, so nothing needs filtering under filterwarnings=error.
"""

from __future__ import annotations

import time
from datetime import timedelta

import cv2
import depthai as dai
import numpy as np
import pytest

from calibcoach.drivers import oak
from calibcoach.drivers.errors import CalibcoachError, SourceError
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.oak import (
    DepthAIReplay,
    FocusControlError,
    imgframe_to_frame,
    list_depthai_devices,
    parse_depthai_target,
    write_depthai_calibration,
)
from calibcoach.drivers.oak_device import DepthAICamera, DepthAIFocus, build_focus_control

# --- discovery and targets ----------------------------------------------------------------------


def test_list_devices_returns_empty_fast_without_a_device():
    start = time.monotonic()
    assert list_depthai_devices() == []
    assert time.monotonic() - start < 5.0


def test_list_devices_never_raises_and_honours_its_timeout(monkeypatch):
    def broken():
        raise RuntimeError("XLink exploded")

    monkeypatch.setattr(dai.Device, "getAllAvailableDevices", staticmethod(broken))
    assert list_depthai_devices() == []

    monkeypatch.setattr(dai.Device, "getAllAvailableDevices", staticmethod(lambda: time.sleep(3) or []))
    start = time.monotonic()
    assert list_depthai_devices(timeout_s=0.2) == []
    assert time.monotonic() - start < 1.0


def test_opening_a_camera_without_a_device_fails_fast_with_advice():
    start = time.monotonic()
    with pytest.raises(SourceError, match=r"OAK camera 1844301011B546F500 not found; visible DepthAI devices: none"):
        DepthAICamera("1844301011B546F500")
    assert time.monotonic() - start < 5.0


@pytest.mark.parametrize(("spec", "expected"), [
    ("depthai", None), ("depthai:1844301011B546F500", "1844301011B546F500"), ("depthai:192.168.1.44", "192.168.1.44"),
])
def test_parse_target(spec, expected):
    assert parse_depthai_target(spec) == expected


@pytest.mark.parametrize("spec", ["depthai:", "oak:123", "visca:/dev/ttyUSB0", "depthai2"])
def test_parse_target_rejects_other_specs(spec):
    with pytest.raises(SourceError, match="write it as depthai"):
        parse_depthai_target(spec)


# --- ImgFrame -> Frame, through a real host-only ReplayVideo pipeline -----------------------------


def _write_video(path, count=10, size=(320, 240)):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, size)
    assert writer.isOpened()
    for i in range(count):
        image = np.full((size[1], size[0], 3), 20 + 20 * i, np.uint8)
        cv2.putText(image, str(i), (20, 120), cv2.FONT_HERSHEY_SIMPLEX, 2, (255, 255, 255), 3)
        writer.write(image)
    writer.release()


def test_replay_yields_every_frame_in_order_through_the_shared_conversion(tmp_path):
    video = tmp_path / "ramp.avi"
    _write_video(video)
    source = DepthAIReplay(video, fps=60)
    assert source.info.image_size == (320, 240)
    assert source.info.frame_count == 10
    with source:
        frames = list(source)
    assert [f.index for f in frames] == list(range(10))
    assert all(f.image.shape == (240, 320, 3) and f.image.dtype == np.uint8 for f in frames)
    means = [float(f.image.mean()) for f in frames]
    assert all(b - a > 10 for a, b in zip(means, means[1:], strict=False)), means  # source order kept
    stamps = [f.timestamp_ns for f in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))
    # A file has no lens: replayed frames must not pretend to carry camera settings.
    assert all(dict(f.controls) == {} for f in frames)


def test_replay_of_a_missing_file_names_the_path(tmp_path):
    with pytest.raises(SourceError, match="nope.avi does not exist"):
        DepthAIReplay(tmp_path / "nope.avi")


def _host_imgframe(image, seq, t_us, frame_type=dai.ImgFrame.Type.BGR888i):
    img = dai.ImgFrame()
    img.setCvFrame(image, frame_type)
    img.setSequenceNum(seq)
    img.setTimestamp(timedelta(microseconds=t_us))
    return img


def test_conversion_of_bgr_and_grey_frames_keeps_pixels_and_exact_timestamps():
    rng = np.random.default_rng(3)
    bgr = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    frame = imgframe_to_frame(_host_imgframe(bgr, 7, 1_234_567), 7)
    np.testing.assert_array_equal(frame.image, bgr)
    assert frame.timestamp_ns == 1_234_567_000 and frame.index == 7
    # Sensor frames carry their lens state; host-built ones report zeros (there is no setter).
    assert dict(frame.controls) == {"lens_position": 0.0, "exposure_us": 0.0, "iso": 0.0}
    grey = bgr[:, :, 0].copy()
    frame = imgframe_to_frame(_host_imgframe(grey, 0, 5, dai.ImgFrame.Type.GRAY8), 0, with_controls=False)
    np.testing.assert_array_equal(frame.image, grey)


# --- focus control ------------------------------------------------------------------------------


def test_focus_lock_control_is_autofocus_off_at_the_position():
    control = build_focus_control(130)
    assert control.autoFocusMode == dai.CameraControl.AutoFocusMode.OFF
    assert control.getLensPosition() == 130
    assert control.getCommand(dai.CameraControl.Command.AF_MODE)
    assert control.getCommand(dai.CameraControl.Command.MOVE_LENS)
    unlock = build_focus_control(auto=True)
    assert unlock.autoFocusMode == dai.CameraControl.AutoFocusMode.CONTINUOUS_VIDEO
    assert not unlock.getCommand(dai.CameraControl.Command.MOVE_LENS)


@pytest.mark.parametrize("position", [-1, 256, 12.5, True])
def test_focus_lock_rejects_positions_outside_0_255(position):
    with pytest.raises(FocusControlError, match="out of range"):
        build_focus_control(position)


class _Lens:
    """An ImgFrame stand-in that reports only a lens position (all DepthAIFocus reads)."""

    def __init__(self, position):
        self.position = position

    def getLensPosition(self):  # noqa: N802 - depthai's name
        return self.position


class _ControlQueue:
    def __init__(self):
        self.sent = []

    def send(self, control):
        self.sent.append(control)


class _FrameQueue:
    def __init__(self, positions):
        self.items = [_Lens(p) for p in positions]

    def tryGet(self):  # noqa: N802 - depthai's name
        return self.items.pop(0) if self.items else None


def test_focus_lock_waits_until_a_frame_reports_the_position():
    controls = _ControlQueue()
    focus = DepthAIFocus(controls, _FrameQueue([100, 112, 125, 130, 130]), "TESTCAM")
    assert focus.lock(130) == 130
    assert controls.sent[0].getLensPosition() == 130
    assert focus.status() == {"focus_mode": "manual", "lens_position": 130}
    focus.unlock()
    assert focus.status()["focus_mode"] == "auto"
    assert controls.sent[-1].autoFocusMode == dai.CameraControl.AutoFocusMode.CONTINUOUS_VIDEO


def test_focus_lock_that_does_not_settle_says_where_the_lens_stayed():
    focus = DepthAIFocus(_ControlQueue(), _FrameQueue([90, 90, 90]), "TESTCAM", settle_s=0.1)
    with pytest.raises(FocusControlError, match=r"TESTCAM: asked for lens position 130 .*\(frames reported \[90\]\)"):
        focus.lock(130)


# --- link loss ----------------------------------------------------------------------------------


class _DyingQueue:
    """Delivers real ImgFrames, then fails the way depthai does when the device vanishes."""

    def __init__(self, count):
        self.items = [_host_imgframe(np.full((8, 8, 3), i, np.uint8), 50 + i, 1000 * i) for i in range(count)]

    def get(self, timeout=None):
        if not self.items:
            raise RuntimeError("Communication exception - possible device error/misconfiguration")
        return self.items.pop(0)


def test_link_loss_becomes_a_source_error_with_the_frame_count():
    camera = object.__new__(DepthAICamera)  # the device half of __init__ cannot run here
    camera.camera_id, camera._closed, camera._queue = "TESTCAM", False, _DyingQueue(3)
    camera._focus = DepthAIFocus(_ControlQueue(), camera._queue, "TESTCAM")
    seen = []
    with pytest.raises(SourceError, match="OAK camera TESTCAM disconnected after 3 frames"):
        for frame in camera.frames():
            seen.append(frame.index)
    assert seen == [0, 1, 2]  # indices count from the first sequence number


# --- calibration in the device's own format -------------------------------------------------------

_K = [[1402.5, 0.0, 955.25], [0.0, 1401.75, 541.5], [0.0, 0.0, 1.0]]
_CASES = {
    "pinhole": ([-0.12, 0.031, 0.0008, -0.0004, -0.006], dai.CameraModel.Perspective),
    "rational": ([2.1, 0.35, 0.0006, -0.0002, 0.004, 2.45, 0.9, 0.05], dai.CameraModel.Perspective),
    "fisheye": ([0.021, -0.013, 0.004, -0.0011], dai.CameraModel.Fisheye),
}


@pytest.mark.parametrize("model", list(_CASES))
def test_calibration_round_trips_through_depthai(tmp_path, model):
    coeffs, camera_type = _CASES[model]
    camera = CameraModel(model, np.array(_K), np.array(coeffs), (1920, 1080))
    path = write_depthai_calibration(tmp_path / f"{model}.json", camera, lens_position=130)
    assert path.is_file()
    back = dai.CalibrationHandler(str(path))
    socket = dai.CameraBoardSocket.CAM_A
    np.testing.assert_allclose(back.getCameraIntrinsics(socket), _K, rtol=1e-6)
    read = back.getDistortionCoefficients(socket)
    # depthai stores float32 and 14 coefficients for Perspective (only 4 are reported for Fisheye).
    assert len(read) == (4 if model == "fisheye" else oak.DEPTHAI_COEFF_COUNT)
    np.testing.assert_allclose(read[: len(coeffs)], coeffs, rtol=1e-6)
    assert not np.any(read[len(coeffs):])
    assert back.getDistortionModel(socket) == camera_type
    assert back.getLensPosition(socket) == 130
    assert (back.getSourceWidth(socket), back.getSourceHeight(socket)) == (1920, 1080)
    assert "UNTRUSTED" not in back.getEepromData().productName


def test_an_untrusted_calibration_says_so_inside_the_depthai_file(tmp_path):
    camera = CameraModel("pinhole", np.array(_K), np.zeros(5), (1920, 1080))
    path = write_depthai_calibration(tmp_path / "depthai_calibration_untrusted.json", camera, untrusted=True)
    back = dai.CalibrationHandler(str(path))
    assert back.getEepromData().productName.startswith("UNTRUSTED")
    np.testing.assert_allclose(back.getCameraIntrinsics(dai.CameraBoardSocket.CAM_A), _K, rtol=1e-6)  # still loads


def test_calibration_rejects_an_unknown_socket(tmp_path):
    camera = CameraModel.from_fov((640, 480), 70.0)
    with pytest.raises(CalibcoachError, match="'CAM_Z' is not a DepthAI board socket; use one of CAM_A"):
        write_depthai_calibration(tmp_path / "c.json", camera, socket="CAM_Z")


def test_flashing_replaces_only_the_calibrated_socket() -> None:
    # before flashing, the device's own calibration gets CAM_A's new intrinsics and nothing else
    from calibcoach.drivers.oak import apply_intrinsics

    device_calibration = dai.CalibrationHandler()
    other = [[800.0, 0.0, 640.0], [0.0, 800.0, 400.0], [0.0, 0.0, 1.0]]
    device_calibration.setCameraIntrinsics(dai.CameraBoardSocket.CAM_B, other, 1280, 800)
    camera = CameraModel("pinhole", [[1500.0, 0, 960.0], [0, 1500.0, 540.0], [0, 0, 1]], [-0.1, 0.05, 0, 0, 0], (1920, 1080))
    updated = apply_intrinsics(device_calibration, camera, lens_position=120)
    a = np.array(updated.getCameraIntrinsics(dai.CameraBoardSocket.CAM_A, 1920, 1080))
    b = np.array(updated.getCameraIntrinsics(dai.CameraBoardSocket.CAM_B, 1280, 800))
    np.testing.assert_allclose(a, camera.camera_matrix, rtol=1e-6)
    np.testing.assert_allclose(b, other, rtol=1e-6)
