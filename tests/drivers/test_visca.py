"""ViscaCamera against a simulated Sony VISCA camera on a real pseudo-terminal."""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Iterator

import pytest

from calibcoach.drivers.visca import FocusControlError, ViscaCamera, parse_target


class FakeVisca:
    """A VISCA camera (address 1) playing on the master end of a pty, in a thread."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.focus_mode = 0x02  # auto
        self.focus_position = 0x1000
        self.zoom_position = 0x0400
        self.error_code: int | None = None  # answer every packet with 90 60 EE FF
        self.silent = False
        self.ignore_focus_direct = False
        self.split = False  # write replies one byte at a time with small delays
        self.garbage = b""  # bytes written before every reply
        self.received: list[bytes] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        assert not self._thread.is_alive()

    def _run(self) -> None:
        buffer = bytearray()
        while not self._stop.is_set():
            if not select.select([self.fd], [], [], 0.01)[0]:
                continue
            buffer += os.read(self.fd, 64)
            while b"\xff" in buffer:
                end = buffer.index(b"\xff") + 1
                packet, buffer = bytes(buffer[:end]), buffer[end:]
                self.received.append(packet)
                self._answer(packet)

    def _send(self, *replies: bytes) -> None:
        data = self.garbage + b"".join(replies)
        if not self.split:
            os.write(self.fd, data)
            return
        for byte in data:
            os.write(self.fd, bytes([byte]))
            time.sleep(0.002)

    def _answer(self, packet: bytes) -> None:
        if self.silent:
            return
        if self.error_code is not None:
            self._send(bytes([0x90, 0x60, self.error_code, 0xFF]))
            return
        kind, body = packet[1], packet[2:-1]
        if kind == 0x09:
            value = {b"\x04\x38": bytes([self.focus_mode]), b"\x04\x48": _nib(self.focus_position),
                     b"\x04\x47": _nib(self.zoom_position)}.get(body)
            if value is None:
                self._send(b"\x90\x60\x02\xff")
            else:
                self._send(b"\x90\x50" + value + b"\xff")
            return
        if body in (b"\x04\x38\x02", b"\x04\x38\x03"):
            self.focus_mode = body[2]
        elif body[:2] == b"\x04\x48" and len(body) == 6:
            if not self.ignore_focus_direct:
                self.focus_position = _unnib(body[2:])
        elif body[:2] == b"\x04\x47" and len(body) == 6:
            self.zoom_position = _unnib(body[2:])
        else:
            self._send(b"\x90\x60\x02\xff")
            return
        self._send(b"\x90\x41\xff", b"\x90\x51\xff")


def _nib(value: int) -> bytes:
    return bytes((value >> s) & 0xF for s in (12, 8, 4, 0))


def _unnib(data: bytes) -> int:
    return (data[0] << 12) | (data[1] << 8) | (data[2] << 4) | data[3]


@pytest.fixture
def pty_camera() -> Iterator[tuple[FakeVisca, str]]:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    fake = FakeVisca(master)
    try:
        yield fake, os.ttyname(slave)
    finally:
        fake.stop()
        os.close(slave)
        os.close(master)


def test_lock_focus_at_a_position_sends_the_nibbles_and_reads_back(pty_camera) -> None:
    fake, port = pty_camera
    with ViscaCamera(port) as cam:
        assert cam.lock_focus(10844) == 0x2A5C
        assert cam.status() == {"focus_mode": "manual", "focus_position": 0x2A5C, "zoom_position": 0x0400}
    assert fake.received[:2] == [bytes.fromhex("81 01 04 38 03 FF"), bytes.fromhex("81 01 04 48 02 0A 05 0C FF")]
    assert fake.received[2:4] == [bytes.fromhex("81 09 04 38 FF"), bytes.fromhex("81 09 04 48 FF")]
    assert (fake.focus_mode, fake.focus_position) == (0x03, 0x2A5C)


def test_lock_focus_without_position_keeps_the_current_one(pty_camera) -> None:
    fake, port = pty_camera
    with ViscaCamera(port) as cam:
        assert cam.lock_focus(None) == 0x1000
    assert fake.focus_mode == 0x03
    assert not any(p[1:4] == b"\x01\x04\x48" for p in fake.received)


def test_unlock_focus_returns_to_auto(pty_camera) -> None:
    fake, port = pty_camera
    with ViscaCamera(port) as cam:
        cam.lock_focus(0x0123)
        cam.unlock_focus()
        assert cam.status()["focus_mode"] == "auto"
    assert fake.received[-5] == bytes.fromhex("81 01 04 38 02 FF")


def test_zoom_direct_and_status(pty_camera) -> None:
    fake, port = pty_camera
    with ViscaCamera(port) as cam:
        cam.set_zoom(0x4000)
        assert cam.status() == {"focus_mode": "auto", "focus_position": 0x1000, "zoom_position": 0x4000}
    assert fake.received[0] == bytes.fromhex("81 01 04 47 04 00 00 00 FF")


def test_syntax_error_reply_is_decoded(pty_camera) -> None:
    fake, port = pty_camera
    fake.error_code = 0x02
    with ViscaCamera(port) as cam, pytest.raises(FocusControlError, match="syntax error") as info:
        cam.lock_focus(100)
    assert "81 01 04 38 03 FF" in str(info.value)


def test_not_executable_reply_is_decoded(pty_camera) -> None:
    fake, port = pty_camera
    fake.error_code = 0x41
    with ViscaCamera(port) as cam, pytest.raises(FocusControlError, match="command not executable"):
        cam.unlock_focus()


def test_silent_camera_times_out_with_what_to_check(pty_camera) -> None:
    fake, port = pty_camera
    fake.silent = True
    start = time.monotonic()
    with ViscaCamera(port, timeout_s=1.0) as cam, pytest.raises(FocusControlError) as info:
        cam.lock_focus(None)
    assert time.monotonic() - start < 1.5
    message = str(info.value)
    for part in ("no reply within 1 s", port, "81 01 04 38 03 FF", "cable", "baud", "address", "powered"):
        assert part in message


def test_camera_ignoring_the_position_names_both_values(pty_camera) -> None:
    fake, port = pty_camera
    fake.ignore_focus_direct = True
    fake.focus_position = 0x2A00
    with ViscaCamera(port) as cam, pytest.raises(FocusControlError, match="asked for 0x2A5C, camera reports 0x2A00"):
        cam.lock_focus(0x2A5C)


@pytest.mark.parametrize("split, garbage", [(True, b""), (False, b"\x00\x13\x37\xff"), (True, b"\x42\xff\x07"), (False, b"\x90\x13")])
def test_split_and_noisy_replies_still_parse(pty_camera, split: bool, garbage: bytes) -> None:
    fake, port = pty_camera
    fake.split, fake.garbage = split, garbage
    with ViscaCamera(port) as cam:
        assert cam.lock_focus(0xBEEF) == 0xBEEF
        assert cam.status()["focus_mode"] == "manual"


@pytest.mark.parametrize("position", [-1, 0x10000, 1.5, True])
def test_out_of_range_position_is_rejected_before_sending(pty_camera, position) -> None:
    fake, port = pty_camera
    with ViscaCamera(port) as cam, pytest.raises(FocusControlError, match="out of range"):
        cam.lock_focus(position)
    time.sleep(0.03)
    assert fake.received == []


def test_missing_port_is_a_clear_error() -> None:
    with pytest.raises(FocusControlError, match="cannot open VISCA serial port /dev/nonexistent-visca"):
        ViscaCamera("/dev/nonexistent-visca")


@pytest.mark.parametrize("spec, expected", [
    ("visca:/dev/ttyUSB0@9600", ("/dev/ttyUSB0", 9600)),
    ("visca:/dev/ttyUSB0", ("/dev/ttyUSB0", 9600)),
    ("visca:COM3@38400", ("COM3", 38400)),
])
def test_parse_target(spec: str, expected: tuple[str, int]) -> None:
    assert parse_target(spec) == expected


@pytest.mark.parametrize("spec, message", [
    ("/dev/ttyUSB0", "not a VISCA target"),
    ("visca:", "names no serial port"),
    ("visca:@9600", "names no serial port"),
    ("visca:/dev/ttyUSB0@fast", "not a positive whole number"),
    ("visca:/dev/ttyUSB0@0", "not a positive whole number"),
    ("visca:/dev/ttyUSB0@", "not a positive whole number"),
])
def test_parse_target_rejects_bad_specs(spec: str, message: str) -> None:
    with pytest.raises(FocusControlError, match=message):
        parse_target(spec)


def test_focus_command_locks_at_10844_and_reads_back(pty_camera, capsys) -> None:
    # the whole CLI path: `calibcoach focus visca:PORT --lock --position 10844`
    from calibcoach.app.cli import main

    fake, port = pty_camera
    assert main(["focus", f"visca:{port}@9600", "--lock", "--position", "10844"]) == 0
    out = capsys.readouterr().out
    assert "focus locked (manual) at 10844 (0x2A5C)" in out and "focus manual, focus position 10844" in out
    assert fake.focus_mode == 0x03 and fake.focus_position == 0x2A5C
    assert main(["focus", f"visca:{port}", "--unlock"]) == 0
    assert fake.focus_mode == 0x02
    capsys.readouterr()
    assert main(["focus", "v4l2:0", "--status"]) == 2  # no /dev/video0 on this machine: a clear error, no traceback
    assert "cannot open camera /dev/video0" in capsys.readouterr().err
    assert main(["focus", "depthai", "--lock"]) == 2
    assert "--lens-position" in capsys.readouterr().err
