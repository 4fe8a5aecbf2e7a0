"""Focus and zoom control of Sony VISCA cameras over a serial line (PTZ and block cameras).

Cameras whose video arrives through a capture card cannot be focused through the video path; most
PTZ and block cameras take Sony VISCA commands on an RS-232/RS-422 port instead. Calibration needs
the focus fixed (every focus change alters the intrinsics), so `ViscaCamera.lock_focus` switches
the camera to manual focus, optionally drives it to a position, and reads both back to prove it.

Protocol (8N1, usually 9600 baud; every packet ends with the terminator 0xFF):
- Commands start with 0x80 + address (0x81 for camera 1), then 01, a category and the command:
  focus manual `81 01 04 38 03 FF`, focus auto `81 01 04 38 02 FF`,
  focus direct `81 01 04 48 0p 0q 0r 0s FF`, zoom direct `81 01 04 47 0p 0q 0r 0s FF`,
  where p q r s are the four nibbles of a 16-bit position, most significant first.
- Inquiries have 09 in place of 01: focus mode `81 09 04 38 FF`, focus position `81 09 04 48 FF`,
  zoom position `81 09 04 47 FF`.
- Replies start with 0x80 + (address << 4) (0x90 for camera 1); the low nibble y of the second byte
  is the socket. A command gets an ACK `90 4y FF`, then a completion `90 5y FF` once done. An inquiry
  gets one answer `90 50 ... FF`: `02` auto / `03` manual for the focus mode, `0p 0q 0r 0s` for a
  position. Errors are `90 6y EE FF`; `ERROR_CODES` decodes EE.
Replies are read byte by byte up to the terminator; bytes before a reply header (line noise, a
reply that arrived too late) are skipped, and a reply may arrive split across several reads.
"""

from __future__ import annotations

import time

import serial

from calibcoach.drivers.errors import CalibcoachError

ERROR_CODES = {
    0x01: "message length error",
    0x02: "syntax error",
    0x03: "command buffer full",
    0x04: "command cancelled",
    0x05: "no socket (to be cancelled)",
    0x41: "command not executable",
}
FOCUS_MODES = {0x02: "auto", 0x03: "manual"}
DEFAULT_BAUD = 9600
_MAX_PACKET = 16  # VISCA packets are at most 16 bytes; anything longer is noise, not a reply


class FocusControlError(CalibcoachError):
    """The camera's focus or zoom could not be set or confirmed over VISCA."""


def _hex(data: bytes) -> str:
    return " ".join(f"{b:02X}" for b in data)


def _nibbles(value: int) -> bytes:
    """A 16-bit value as four bytes 0p 0q 0r 0s, most significant nibble first."""
    return bytes((value >> shift) & 0x0F for shift in (12, 8, 4, 0))


def _from_nibbles(data: bytes) -> int:
    value = 0
    for b in data:
        value = (value << 4) | (b & 0x0F)
    return value


def parse_target(spec: str) -> tuple[str, int]:
    """Split "visca:/dev/ttyUSB0@9600" (or "visca:/dev/ttyUSB0", 9600 baud) into (port, baud)."""
    prefix = "visca:"
    if not spec.startswith(prefix):
        raise FocusControlError(
            f"focus target {spec!r} is not a VISCA target; write it as visca:PORT[@BAUD], "
            f"e.g. visca:/dev/ttyUSB0@9600")
    port, sep, baud_text = spec[len(prefix):].partition("@")
    if not port:
        raise FocusControlError(
            f"focus target {spec!r} names no serial port; write it as visca:PORT[@BAUD], "
            f"e.g. visca:/dev/ttyUSB0@9600")
    if not sep:
        return port, DEFAULT_BAUD
    if not baud_text.isdigit() or int(baud_text) <= 0:
        raise FocusControlError(
            f"focus target {spec!r} has baud rate {baud_text!r}, which is not a positive whole number; "
            f"VISCA cameras use 9600 (the default), 19200, 38400 or 115200")
    return port, int(baud_text)


class ViscaCamera:
    """One VISCA camera on a serial port; use as a context manager or call `close()`."""

    def __init__(self, port: str, *, baud: int = DEFAULT_BAUD, address: int = 1, timeout_s: float = 1.0):
        if not 1 <= address <= 7:
            raise FocusControlError(f"VISCA address {address} is out of range; cameras use 1..7 (usually 1)")
        self.port, self.baud, self.address, self.timeout_s = port, baud, address, timeout_s
        self._reply_header = 0x80 + (address << 4)
        try:
            self._serial = serial.Serial(port, baud, bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                                         stopbits=serial.STOPBITS_ONE, timeout=timeout_s)
        except (serial.SerialException, ValueError) as exc:
            raise FocusControlError(
                f"cannot open VISCA serial port {port} at {baud} baud: {exc}; check the port name "
                f"(ls /dev/ttyUSB* /dev/ttyACM*) and that your user may open it (group dialout)") from exc

    def __enter__(self) -> ViscaCamera:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        self._serial.close()

    # --- packets -------------------------------------------------------------------------------

    def _packet(self, kind: int, body: bytes) -> bytes:
        return bytes((0x80 + self.address, kind)) + body + b"\xff"

    def _read_reply(self, sent: bytes) -> bytes:
        """The next reply packet (header .. FF); noise before a header is skipped."""
        deadline = time.monotonic() + self.timeout_s
        packet = bytearray()
        while True:
            byte = self._serial.read(1)
            if not byte or time.monotonic() > deadline:
                raise FocusControlError(
                    f"VISCA camera on {self.port}: sent {_hex(sent)} but got no reply within "
                    f"{self.timeout_s:g} s; check the cable (RS-232/RS-422 wiring, TX/RX swapped), the "
                    f"baud rate ({self.baud}), the VISCA address ({self.address}) and that the camera "
                    f"is powered on")
            if byte[0] == self._reply_header:
                packet.clear()  # a header never occurs inside a reply: restart on it (drops a torn reply)
            elif not packet:
                continue  # noise or a stale tail before a reply header
            packet += byte
            if byte == b"\xff":
                return bytes(packet)
            if len(packet) >= _MAX_PACKET:
                packet.clear()  # no terminator: resynchronise on the next header

    def _raise_if_error(self, reply: bytes, sent: bytes) -> None:
        if reply[1] & 0xF0 == 0x60 and len(reply) >= 4:
            meaning = ERROR_CODES.get(reply[2], f"unknown error code 0x{reply[2]:02X}")
            raise FocusControlError(
                f"VISCA camera on {self.port} rejected {_hex(sent)}: {meaning} (reply {_hex(reply)}); "
                f"check that this camera model supports the command and that no other controller "
                f"is sending commands at the same time")

    def _command(self, body: bytes) -> None:
        """Send a command (`81 01 ...`) and wait for its ACK `90 4y FF` and completion `90 5y FF`."""
        sent = self._packet(0x01, body)
        self._serial.reset_input_buffer()
        self._serial.write(sent)
        while True:
            reply = self._read_reply(sent)
            self._raise_if_error(reply, sent)
            if reply[1] & 0xF0 == 0x50:
                return  # completion (some cameras skip the ACK)
            # ACK (0x4y) or anything unrelated: keep waiting for the completion

    def _inquire(self, body: bytes) -> bytes:
        """Send an inquiry (`81 09 ...`) and return the payload of its answer `90 50 ... FF`."""
        sent = self._packet(0x09, body)
        self._serial.reset_input_buffer()
        self._serial.write(sent)
        while True:
            reply = self._read_reply(sent)
            self._raise_if_error(reply, sent)
            if reply[1] == 0x50 and len(reply) > 3:
                return reply[2:-1]

    # --- focus and zoom ------------------------------------------------------------------------

    def focus_mode(self) -> str:
        payload = self._inquire(b"\x04\x38")
        if len(payload) != 1 or payload[0] not in FOCUS_MODES:
            raise FocusControlError(
                f"VISCA camera on {self.port} answered the focus-mode inquiry with {_hex(payload)}, "
                f"expected 02 (auto) or 03 (manual); is this a VISCA camera?")
        return FOCUS_MODES[payload[0]]

    def _position(self, category: bytes, what: str) -> int:
        payload = self._inquire(category)
        if len(payload) != 4:
            raise FocusControlError(
                f"VISCA camera on {self.port} answered the {what}-position inquiry with {_hex(payload)}, "
                f"expected four nibbles 0p 0q 0r 0s; is this a VISCA camera?")
        return _from_nibbles(payload)

    def focus_position(self) -> int:
        return self._position(b"\x04\x48", "focus")

    def zoom_position(self) -> int:
        return self._position(b"\x04\x47", "zoom")

    def set_zoom(self, position: int) -> None:
        """Zoom direct `81 01 04 47 0p 0q 0r 0s FF`."""
        self._command(b"\x04\x47" + _nibbles(_check_position(position, "zoom")))

    def lock_focus(self, position: int | None = None) -> int:
        """Manual focus, at `position` if given (else where it is); returns the confirmed position."""
        if position is not None:
            _check_position(position, "focus")
        self._command(b"\x04\x38\x03")
        if position is not None:
            self._command(b"\x04\x48" + _nibbles(position))
        mode = self.focus_mode()
        if mode != "manual":
            raise FocusControlError(
                f"VISCA camera on {self.port} acknowledged manual focus but still reports {mode} focus; "
                f"check that the camera is not in a menu or a preset that forces auto focus")
        actual = self.focus_position()
        if position is not None and actual != position:
            raise FocusControlError(
                f"VISCA camera on {self.port} ignored the focus position: asked for 0x{position:04X}, "
                f"camera reports 0x{actual:04X}; check the camera's focus range for this zoom "
                f"(positions outside it are clamped) and that one-push AF is not running")
        return actual

    def unlock_focus(self) -> None:
        """Back to auto focus, confirmed by reading the mode back."""
        self._command(b"\x04\x38\x02")
        mode = self.focus_mode()
        if mode != "auto":
            raise FocusControlError(
                f"VISCA camera on {self.port} acknowledged auto focus but still reports {mode} focus")

    def status(self) -> dict[str, object]:
        """{"focus_mode": "manual" | "auto", "focus_position": int, "zoom_position": int}."""
        return {"focus_mode": self.focus_mode(), "focus_position": self.focus_position(),
                "zoom_position": self.zoom_position()}


def _check_position(position: int, what: str) -> int:
    if isinstance(position, bool) or not isinstance(position, int) or not 0 <= position <= 0xFFFF:
        raise FocusControlError(
            f"{what} position {position!r} is out of range: VISCA positions are whole numbers "
            f"0..65535 (0x0000..0xFFFF); most cameras use a smaller range, see the camera's manual")
    return position
