"""Focus, exposure and white-balance locking of V4L2 (UVC) cameras, proved by reading back.

Every focus change alters the intrinsics (the focal length moves by up to a few percent across the
focus range of a webcam), so a calibration is only valid for the focus it was captured at. UVC
webcams start in continuous autofocus; `V4L2FocusControl.lock` switches it off, sets
focus_absolute, optionally freezes exposure and white balance (which otherwise hunt as the board
moves and change the image statistics between frames), and then reads every control back. Cameras
and drivers are known to accept a write and keep another value: firmware clamps to a narrower range
than it declares, or ignores manual focus while a vendor "smart focus" is on. A lock that is not
read back is not a lock.

Controls are found by their V4L2 control ID, not by name: the kernel renamed them in 5.x
("Focus, Auto" -> "Focus, Automatic Continuous", "Exposure, Auto" -> "Auto Exposure") and some
drivers use their own names. linuxpy enumerates them with VIDIOC_QUERY_EXT_CTRL (menus with
VIDIOC_QUERYMENU) and reads and writes them with VIDIOC_G_EXT_CTRLS / VIDIOC_S_EXT_CTRLS.

linuxpy clips out-of-range writes silently by default; here a value outside [min, max] or off the
step grid is refused before anything is written, because a silently clipped focus position is a
calibration for a focus nobody asked for.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from calibcoach.drivers.errors import CalibcoachError

# V4L2 control IDs (linux/v4l2-controls.h). User class 0x0098xxxx, camera class 0x009Axxxx.
V4L2_CID_FOCUS_AUTO = 0x009A090C  # bool: continuous autofocus
V4L2_CID_FOCUS_ABSOLUTE = 0x009A090A  # int: lens position, driver units
V4L2_CID_EXPOSURE_AUTO = 0x009A0901  # menu: 0 auto, 1 manual, 2 shutter prio, 3 aperture prio
V4L2_CID_EXPOSURE_ABSOLUTE = 0x009A0902  # int: exposure time in 100 us units
V4L2_CID_AUTO_WHITE_BALANCE = 0x0098090C  # bool
V4L2_CID_WHITE_BALANCE_TEMPERATURE = 0x0098091A  # int: kelvin
V4L2_CID_ZOOM_ABSOLUTE = 0x009A090D  # int: driver units

V4L2_EXPOSURE_MANUAL = 1  # value of the auto-exposure menu that fixes the exposure time

# Our names (the current kernel names) for the controls that matter for calibration, by ID.
CALIBRATION_CONTROLS: dict[int, str] = {
    V4L2_CID_FOCUS_AUTO: "focus_automatic_continuous",
    V4L2_CID_FOCUS_ABSOLUTE: "focus_absolute",
    V4L2_CID_EXPOSURE_AUTO: "auto_exposure",
    V4L2_CID_EXPOSURE_ABSOLUTE: "exposure_time_absolute",
    V4L2_CID_AUTO_WHITE_BALANCE: "white_balance_automatic",
    V4L2_CID_WHITE_BALANCE_TEMPERATURE: "white_balance_temperature",
    V4L2_CID_ZOOM_ABSOLUTE: "zoom_absolute",
}


class FocusControlError(CalibcoachError):
    """The camera's focus, exposure or white balance could not be set or confirmed over V4L2."""


def describe_control(control: Any) -> dict[str, Any]:
    """id, name (ours and the driver's), min, max, step, default and current value of a linuxpy control.

    Reading a value can fail (write-only or inactive controls on some drivers); the reason is reported
    in "error" instead of raising, because a listing must show everything it can.
    """
    info: dict[str, Any] = {
        "id": int(control.id),
        "name": CALIBRATION_CONTROLS.get(int(control.id), control.config_name),
        "driver_name": control.name,
        "min": int(control.minimum),
        "max": int(control.maximum),
        "step": int(control.step),
    }
    try:
        info["default"] = int(control.default)
        info["value"] = int(control.value)
    except (OSError, AttributeError, ValueError) as exc:
        info["error"] = f"cannot read: {exc}"
    return info


class V4L2FocusControl:
    """Focus, exposure and white-balance controls of one opened linuxpy `Device`.

    The device must stay open while this object is used; it is not closed here (the owner of the
    device, usually `V4L2Camera`, closes it).
    """

    def __init__(self, device: Any) -> None:
        self.device = device
        self.path = str(getattr(device, "filename", "the V4L2 device"))
        # controls by ID. values() (not `in`) makes linuxpy enumerate the controls on first use.
        self._controls = {int(c.id): c for c in device.controls.values()
                          if int(getattr(c, "id", -1)) in CALIBRATION_CONTROLS}
        self._saved_modes: dict[int, int] = {}  # auto modes before lock(), restored by unlock()

    # --- reading -------------------------------------------------------------------------------

    def has(self, cid: int) -> bool:
        return cid in self._controls

    def _read(self, cid: int) -> int:
        try:
            return int(self._controls[cid].value)
        except OSError as exc:
            raise FocusControlError(
                f"camera {self.path}: cannot read {CALIBRATION_CONTROLS[cid]} (control 0x{cid:08X}): "
                f"{exc}; check that the camera is still connected and not used by another program "
                f"(fuser {self.path})") from exc

    def status(self) -> dict[str, int]:
        """Current value of every calibration control the camera has, by our names."""
        return {CALIBRATION_CONTROLS[cid]: self._read(cid) for cid in self._controls}

    def snapshot(self) -> dict[str, float]:
        """Focus, zoom, exposure and white balance now, for `Frame.controls`; cheap enough per frame.

        One VIDIOC_G_EXT_CTRLS per control (a few microseconds each on UVC, which caches the values
        it set); call it every few frames to notice a focus that drifted despite the lock.
        """
        return {name: float(value) for name, value in self.status().items()}

    # --- writing -------------------------------------------------------------------------------

    def _check_value(self, cid: int, value: int) -> None:
        """Refuse a value outside [min, max] or off the step grid, before anything is written."""
        control = self._controls[cid]
        name = CALIBRATION_CONTROLS[cid]
        lo, hi, step = int(control.minimum), int(control.maximum), max(int(control.step), 1)
        if isinstance(value, bool) or not isinstance(value, int):
            raise FocusControlError(f"{name} value {value!r} is not a whole number; "
                                    f"camera {self.path} accepts {lo}..{hi} in steps of {step}")
        if not lo <= value <= hi:
            raise FocusControlError(
                f"{name} {value} is out of range for camera {self.path}: valid values are {lo}..{hi} "
                f"in steps of {step}; nothing was written (the driver would clip it silently)")
        if (value - lo) % step:
            below = lo + (value - lo) // step * step
            raise FocusControlError(
                f"{name} {value} is off the step grid of camera {self.path}: valid values are "
                f"{lo}..{hi} in steps of {step} (nearest: {below} or {below + step}); nothing was written")

    def _write(self, cid: int, value: int) -> None:
        control = self._controls[cid]
        # belt and braces: our own check already ran, but never let linuxpy clip behind our back
        if hasattr(control, "clipping"):
            control.clipping = False
        try:
            control.value = value
        except (OSError, AttributeError, ValueError) as exc:
            # AttributeError: linuxpy refuses read-only/disabled/grabbed controls; OSError: driver said no
            raise FocusControlError(
                f"camera {self.path} refused {CALIBRATION_CONTROLS[cid]} = {value} "
                f"(control 0x{cid:08X}): {exc}; close other programs using the camera "
                f"(fuser {self.path}) and check that the control is not locked by another mode") from exc

    def _verify(self, written: Mapping[int, int]) -> dict[str, int]:
        """Read back every written control; raise naming the first one the camera did not keep."""
        confirmed: dict[str, int] = {}
        for cid, asked in written.items():
            actual = self._read(cid)
            if actual != asked:
                name = CALIBRATION_CONTROLS[cid]
                control = self._controls[cid]
                raise FocusControlError(
                    f"camera {self.path} did not keep {name} (control 0x{cid:08X}): asked for {asked}, "
                    f"camera reports {actual} (declared range {control.minimum}..{control.maximum}); "
                    f"the driver or firmware clamped or ignored it. Try a value nearer {actual}, switch "
                    f"off any vendor auto mode (v4l2-ctl -d {self.path} --list-ctrls), or calibrate at "
                    f"the value the camera reports")
            confirmed[CALIBRATION_CONTROLS[cid]] = actual
        return confirmed

    def lock(self, position: int | None = None, *, lock_exposure: bool = False,
             lock_white_balance: bool = False) -> dict[str, int]:
        """Manual focus at `position` (None: where autofocus left it), optionally fixed exposure and WB.

        Order matters: auto modes are switched off first, because UVC drivers mark the absolute
        controls inactive (and may ignore writes) while the auto mode owns them. Values that are
        kept ("where it is now") are read after the auto mode is off and written back explicitly, so
        the read-back proves the camera holds them.

        Returns:
            The read-back value of every control written, by our names.

        Raises:
            FocusControlError: no focus_absolute control, a value out of range or off the step grid
                (before any write), a refused write, or a control that reads back different.
        """
        if not self.has(V4L2_CID_FOCUS_ABSOLUTE):
            raise FocusControlError(
                f"camera {self.path}: this camera has no focus_absolute control: it is fixed-focus or "
                f"needs the vendor's tool; pass --allow-autofocus only if you are sure focus cannot change")
        if position is not None:
            self._check_value(V4L2_CID_FOCUS_ABSOLUTE, position)
        if lock_exposure and not self.has(V4L2_CID_EXPOSURE_AUTO):
            raise FocusControlError(
                f"camera {self.path} has no auto_exposure control, so its exposure cannot be locked "
                f"over V4L2; drop --lock-exposure if its exposure is fixed, or set it with the vendor's tool")
        if lock_white_balance and not self.has(V4L2_CID_AUTO_WHITE_BALANCE):
            raise FocusControlError(
                f"camera {self.path} has no white_balance_automatic control, so its white balance "
                f"cannot be locked over V4L2; drop --lock-white-balance")

        written: dict[int, int] = {}
        self._switch_off(V4L2_CID_FOCUS_AUTO, 0, written)
        self._set_absolute(V4L2_CID_FOCUS_ABSOLUTE, position, written)
        if lock_exposure:
            # read the exposure time while auto exposure still owns it: that is the one to keep
            keep = self._read(V4L2_CID_EXPOSURE_ABSOLUTE) if self.has(V4L2_CID_EXPOSURE_ABSOLUTE) else None
            self._switch_off(V4L2_CID_EXPOSURE_AUTO, V4L2_EXPOSURE_MANUAL, written)
            self._set_absolute(V4L2_CID_EXPOSURE_ABSOLUTE, keep, written)
        if lock_white_balance:
            keep = (self._read(V4L2_CID_WHITE_BALANCE_TEMPERATURE)
                    if self.has(V4L2_CID_WHITE_BALANCE_TEMPERATURE) else None)
            self._switch_off(V4L2_CID_AUTO_WHITE_BALANCE, 0, written)
            self._set_absolute(V4L2_CID_WHITE_BALANCE_TEMPERATURE, keep, written)
        return self._verify(written)

    def _switch_off(self, cid: int, manual_value: int, written: dict[int, int]) -> None:
        """Put an auto-mode control into its manual value, remembering the mode for `unlock()`."""
        if not self.has(cid):
            return  # e.g. a manual-only focus motor: nothing automatic to switch off
        self._saved_modes.setdefault(cid, self._read(cid))
        self._write(cid, manual_value)
        written[cid] = manual_value

    def _set_absolute(self, cid: int, value: int | None, written: dict[int, int]) -> None:
        if not self.has(cid):
            return
        if value is None:
            value = self._read(cid)  # where the auto mode left it, now frozen
        self._check_value(cid, value)
        self._write(cid, value)
        written[cid] = value

    def unlock(self) -> dict[str, int]:
        """Give focus (and exposure / white balance, if locked) back to the camera's auto modes.

        Restores the modes saved by `lock()`; without a previous lock, switches continuous autofocus
        on. Returns the read-back values of the mode controls written.
        """
        modes = dict(self._saved_modes) or (
            {V4L2_CID_FOCUS_AUTO: 1} if self.has(V4L2_CID_FOCUS_AUTO) else {})
        for cid, value in modes.items():
            self._write(cid, value)
        confirmed = self._verify(modes)
        self._saved_modes.clear()
        return confirmed
