"""Progress: a tqdm bar of frames read and of the solve's stages on a terminal, the plain lines elsewhere."""

from __future__ import annotations

import fcntl
import os
import pty
import re
import select
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest

from calibcoach.app.cli import main
from calibcoach.app.progress import SOLVE_STAGES

FRONTAL = "frontal_webcam720"  # 20 frames, read to the end in ~2 s (refused: exit 3, still a full run)
# Every line `calibrate` writes on stderr without a terminal, as it did before the bar existed.
PLAIN_LINES = (
    r"calibcoach: recording frontal_webcam720 \(.*\); board .*",
    r"frame \d+/20  kept \d+  coverage +\d+%  expected error (--|\d+\.\d{3}/\d+\.\d{3} px) +\d+ fps  last: [a-z ]+",
    r"  next: .+",
    r"calibcoach: read 20 frames in \d+\.\d s \(end of source\); kept \d+; solving\.\.\.",
    r"calibcoach: rejected .+; the final solve also took \d+ of \d+ usable frames held in reserve \(poses of their own first, then repeats of every hold alike\)",
)


def run_on_a_terminal(args: list[str], *, timeout_s: float = 120.0) -> tuple[int, str, str]:
    """Run the CLI with stderr on a pseudo-terminal (120 columns); (exit code, terminal text, stdout)."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    env = {**os.environ, "PYTHONIOENCODING": "utf-8"}
    env.pop("CALIBCOACH_DEBUG", None)
    process = subprocess.Popen([sys.executable, "-m", "calibcoach.app", *args], stdin=subprocess.DEVNULL,
                               stdout=subprocess.PIPE, stderr=slave, env=env)
    os.close(slave)
    received = b""
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            ready, _, _ = select.select([master], [], [], 0.2)
            if ready:
                try:
                    chunk = os.read(master, 65536)
                except OSError:  # EIO: the child closed the terminal
                    break
                if not chunk:
                    break
                received += chunk
            elif process.poll() is not None:
                break
        else:
            process.kill()
            pytest.fail(f"the CLI did not finish in {timeout_s} s")
        stdout = process.stdout.read().decode()
        code = process.wait(timeout=10)
    finally:
        os.close(master)
        process.stdout.close()
    return code, received.decode("utf-8", errors="replace"), stdout


def test_a_terminal_gets_progress_bars_of_frames_read_and_solve_stages(recordings_dir: Path, tmp_path: Path) -> None:
    code, terminal, stdout = run_on_a_terminal(["calibrate", str(recordings_dir / FRONTAL), "--out", str(tmp_path / "o")])
    assert code == 3, terminal  # the frontal capture is refused, after a full run
    assert "█" in terminal and "|" in terminal  # tqdm's bar
    assert re.search(r"reading: 100%\|█+\| 20/20 \[", terminal), terminal[-2000:]  # frames read of the frame count
    assert re.search(r"solving: 100%\|█+\| 6/6 stages, .*done", terminal), terminal[-2000:]
    for stage in SOLVE_STAGES[1:]:
        assert stage in terminal
    assert "kept " in terminal and "coverage" in terminal  # the status rides on the bar
    assert not re.search(r"^frame \d+/20  kept", terminal.replace("\r", "\n"), flags=re.M)  # no plain lines on a terminal
    # the lines that are not progress still come through, untorn
    assert "calibcoach: rejected " in terminal and "calibcoach: read 20 frames" in terminal
    assert stdout.startswith("INSUFFICIENT: ") and "report.html" in stdout  # the verdict on stdout, as ever


def test_quiet_draws_no_bar_on_a_terminal(recordings_dir: Path, tmp_path: Path) -> None:
    code, terminal, _ = run_on_a_terminal(["calibrate", str(recordings_dir / FRONTAL), "--out", str(tmp_path / "o"), "--quiet"])
    assert code == 3
    assert "%|" not in terminal and "█" not in terminal and "frame 1/20" not in terminal
    assert "calibcoach: rejected " in terminal


def test_without_a_terminal_the_plain_lines_are_unchanged(recordings_dir: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", str(recordings_dir / FRONTAL), "--out", str(tmp_path / "o")]) == 3
    err = capsys.readouterr().err
    assert "█" not in err and "%|" not in err and "\r" not in err
    lines = err.splitlines()
    for line in lines:
        assert any(re.fullmatch(p, line) for p in PLAIN_LINES), f"unexpected stderr line {line!r}"
    assert re.fullmatch(PLAIN_LINES[1], lines[1]) and lines[1].startswith("frame 1/20  kept 1  ")
    assert re.fullmatch(PLAIN_LINES[3], lines[-2]) and re.fullmatch(PLAIN_LINES[4], lines[-1])
