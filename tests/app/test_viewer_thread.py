"""Replays log to Rerun in a child process (or on a thread of their own): the saved session is complete, in order, and a
logger that fails neither hangs the replay nor goes unreported."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest
import rerun.chunk as rrc

from calibcoach.app.cli import main
from calibcoach.app.viewer import ViewerError
from calibcoach.app.viewer_thread import BackgroundViewer


def test_calibrate_saves_every_processed_frame_in_order(recordings_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    main(["calibrate", str(recordings_dir / "frontal_webcam720"), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    read = int(err.split("calibcoach: read ")[1].split(" frames")[0])
    rrd = out / "session.rrd"
    beside = Path(sys.executable).with_name("rerun")
    verify = subprocess.run([str(beside), "rrd", "verify", str(rrd)], capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr
    frames: list[int] = []
    for chunk in rrc.RrdReader(str(rrd)).stream().to_chunks():
        if chunk.entity_path.lstrip("/") == "camera/image":
            frames += chunk.to_record_batch().column("frame").to_pylist()
    assert len(frames) == read == 20
    assert frames == sorted(frames)
    assert any(c.entity_path.lstrip("/") == "report/verdict" for c in rrc.RrdReader(str(rrd)).stream().to_chunks())


def test_a_logger_that_cannot_open_never_blocks_the_replay_and_is_reported() -> None:
    def cannot_open():
        raise ViewerError("cannot write session.rrd: disk full")

    viewer = BackgroundViewer(cannot_open)
    for _ in range(100):  # more than the queue holds: a dead logger must not make the replay wait for ever
        viewer.log_result(None, Path("."))  # type: ignore[arg-type]
    with pytest.raises(ViewerError, match="disk full"):
        viewer.close()
    viewer.close()  # idempotent once closed


def test_a_logging_child_that_fails_is_reported_and_never_blocks_the_replay(tmp_path: Path) -> None:
    from calibcoach.app.viewer_process import LoggerError, ProcessViewer

    blocked = tmp_path / "not_a_folder"
    blocked.write_text("a file where session.rrd's folder should be")
    viewer = ProcessViewer(blocked)
    viewer.start()  # the child tries to open blocked/session.rrd and fails
    for _ in range(100):  # more than a pipe holds: a dead child must not make the replay wait for ever
        viewer.log_result(None, Path("."))  # type: ignore[arg-type]
    with pytest.raises(LoggerError, match="session.rrd"):
        viewer.close()
    viewer.close()  # idempotent once closed


def test_the_logging_child_runs_in_a_session_of_its_own_deaf_to_ctrl_c(tmp_path: Path) -> None:
    # Ctrl-C reaches the replay's whole process group; the child writing session.rrd must not die
    # of it mid-file (the replay goes on to solve with what it kept, and closes the log after).
    import os
    import signal

    from calibcoach.app.viewer_process import ProcessViewer

    viewer = ProcessViewer(tmp_path)
    viewer.start()  # forks: the child logs what it holds, then waits for the result on its pipe
    child = viewer._child
    assert child is not None and child > 0

    def sigint_ignored() -> bool:
        status = Path(f"/proc/{child}/status").read_text().splitlines()
        return bool(int(next(line for line in status if line.startswith("SigIgn:")).split()[1], 16) & (1 << (signal.SIGINT - 1)))

    deadline = time.monotonic() + 10.0  # the child sets itself up right after the fork
    while not (os.getsid(child) == child and sigint_ignored()) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert os.getsid(child) == child != os.getsid(0)
    assert sigint_ignored()
    viewer.close()
    verify = subprocess.run([str(Path(sys.executable).with_name("rerun")), "rrd", "verify", str(tmp_path / "session.rrd")],
                            capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr


def test_the_logging_child_is_forked_with_the_viewer_and_imports_rerun_at_the_lowest_priority(tmp_path: Path) -> None:
    # It imports rerun while the replay reads, in the CPU the replay leaves idle (nice 19), rather
    # than beside the final solve; a replay killed before its frames were sent leaves no session.rrd.
    import os

    from calibcoach.app.viewer_process import ProcessViewer

    viewer = ProcessViewer(tmp_path)
    child = viewer._child
    assert child is not None and child > 0  # forked before any frame was logged or start() was called
    nice = int(Path(f"/proc/{child}/stat").read_text().rsplit(")", 1)[1].split()[16])
    deadline = time.monotonic() + 10.0  # it lowers its priority right after the fork
    while nice != 19 and time.monotonic() < deadline:
        time.sleep(0.01)
        nice = int(Path(f"/proc/{child}/stat").read_text().rsplit(")", 1)[1].split()[16])
    assert nice == 19
    os.close(viewer._to_child)  # the pipe closes before any frames came, as when the replay is killed
    viewer._to_child = None
    _pid, status = os.waitpid(child, 0)
    assert os.waitstatus_to_exitcode(status) == 0
    assert not (tmp_path / "session.rrd").exists()
    viewer._closed = True
