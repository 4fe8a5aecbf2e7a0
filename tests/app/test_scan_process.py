"""The scan in a child process: the same frames and decisions as in process, errors and early stops
reach the parent, nothing is left running or allocated."""

from __future__ import annotations

import multiprocessing
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibcoach.app.replay import run_replay
from calibcoach.app.scan_process import ChildScan, fork_available
from calibcoach.app.session import SessionSettings
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.select import SelectorSettings
from calibcoach.drivers.replay import ImageFolderSource, open_source

pytestmark = pytest.mark.skipif(not fork_available(), reason="the scan runs in a child process only where fork exists")


def _folder(recordings_dir: Path, folder: Path, frames: int = 60, *, colour: bool = False) -> Path:
    """The demo capture's first frames as a plain image folder (footage: scanned with tracking);
    `colour`: as BGR frames whose channels differ, so that their grey is a real conversion."""
    folder.mkdir()
    for index in range(frames):
        grey = cv2.imread(str(recordings_dir / "demo_webcam720_careful" / "frames" / f"{index:06d}.png"), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(folder / f"{index:04d}.png"), cv2.merge([grey, cv2.add(grey, 9), cv2.subtract(grey, 7)]) if colour else grey)
    return folder


def _decisions(recordings_dir: Path, folder: Path, *, in_child: bool) -> list[tuple]:
    got: list[tuple] = []
    settings = SessionSettings(selector=SelectorSettings(max_frames=8), stop_when_done=False)
    session, stats = run_replay(ImageFolderSource(folder), BoardSpec(), settings, in_child=in_child,
                                on_outcome=lambda o, f: got.append((o.frame_index, o.decision.accepted, o.decision.reason,
                                                                    o.detection.corners_px.tobytes(), f.image.sum())))
    return [*got, ("tracked", stats.tracked, "variant", stats.variant_found, "seen", session.frames_seen,
                   "reserve", len(session._reserve))]


def test_a_child_scan_decides_every_frame_as_the_scan_in_process(recordings_dir: Path, tmp_path: Path) -> None:
    folder = _folder(recordings_dir, tmp_path / "frames")
    in_child = _decisions(recordings_dir, folder, in_child=True)
    in_process = _decisions(recordings_dir, folder, in_child=False)
    assert len(in_child) > 20 and in_child[-1][1] > 0  # frames were judged, some tracked
    assert in_child == in_process  # same frames, same pixels, same corners, same decisions and counts


def test_an_error_in_the_child_is_raised_in_the_parent() -> None:
    def failing():
        raise ValueError("frame 3 is damaged")
        yield  # pragma: no cover - makes this a generator

    with ChildScan(failing, 64, state=lambda: None, apply_state=lambda _s: None) as scan, \
            pytest.raises(ValueError, match="frame 3 is damaged"):
        list(scan)


def test_a_child_that_dies_is_reported_not_waited_for() -> None:
    def dying():
        os._exit(9)
        yield  # pragma: no cover

    with ChildScan(dying, 64, state=lambda: None, apply_state=lambda _s: None) as scan, \
            pytest.raises(RuntimeError, match="exit code 9"):
        list(scan)


def _shared_mappings() -> list[str]:
    """This process's shared anonymous mappings (how Linux lists them), empty where /proc is missing."""
    maps = Path("/proc/self/maps")
    return [line for line in maps.read_text().splitlines() if "/dev/zero" in line] if maps.exists() else []


def test_stopping_early_ends_the_child_and_frees_the_ring(recordings_dir: Path, tmp_path: Path) -> None:
    from calibcoach.app.scan import Seen
    from calibcoach.coverage.detector import Detection
    from calibcoach.drivers.base import Frame

    def endless():
        index = 0
        while True:  # far more frames than the ring holds: the child blocks until the parent reads
            yield Seen(Frame(index, index, np.full((4, 4), index % 256, np.uint8)), Detection.empty(), None, None)
            index += 1

    mappings_before = _shared_mappings()
    named_before = set(os.listdir("/dev/shm")) if os.path.isdir("/dev/shm") else set()
    states = []
    scan = ChildScan(endless, 16, state=lambda: "running", apply_state=states.append)
    stream = iter(scan)
    first = [next(stream) for _ in range(100)]
    assert [int(s.frame.image[0, 0]) for s in first] == [i % 256 for i in range(100)]  # in order, pixels intact
    assert states == ["running"] * 100
    if Path("/proc/self/maps").exists():
        assert len(_shared_mappings()) == len(mappings_before) + 1  # the ring, while the scan runs
    scan.close()  # what the replay does at its stop rule
    assert multiprocessing.active_children() == []
    assert _shared_mappings() == mappings_before  # the ring is unmapped
    named_after = set(os.listdir("/dev/shm")) if os.path.isdir("/dev/shm") else set()
    assert named_after <= named_before  # nothing named was ever left behind


def test_a_child_scan_starts_after_opencv_ran_its_own_threads(recordings_dir: Path, tmp_path: Path) -> None:
    # A process that used OpenCV's thread pool (a bench detecting with two threads first) forks the
    # scan: the child must not touch the pool whose threads stayed behind (it hung once). Run in a
    # fresh interpreter, so this test's own process state does not decide it, with a deadline.
    import subprocess
    import sys
    import textwrap

    folder = _folder(recordings_dir, tmp_path / "frames", frames=20)
    script = textwrap.dedent(f"""
        import cv2, numpy as np
        cv2.setNumThreads(2)
        cv2.GaussianBlur(np.zeros((2000, 2000), np.float32), (31, 31), 5)  # the pool's threads start
        from calibcoach.app.replay import run_replay
        from calibcoach.coverage.board import BoardSpec
        from calibcoach.drivers.replay import ImageFolderSource
        session, stats = run_replay(ImageFolderSource({str(folder)!r}), BoardSpec())
        print("read", stats.frames_read)
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "read 20" in done.stdout


def test_a_started_scan_closed_unread_ends_its_child_and_frees_the_ring(recordings_dir: Path, tmp_path: Path) -> None:
    # `calibrate` starts the scan before the session's modules load; an error in between (a viewer
    # port taken, Ctrl-C) closes a scan nobody read: its child must end and its ring be unmapped.
    from calibcoach.app.scan_stream import ScanStream

    folder = _folder(recordings_dir, tmp_path / "frames", frames=12)
    mappings_before = _shared_mappings()
    scan = ScanStream(ImageFolderSource(folder), BoardSpec())
    assert scan.in_child and [p.name for p in multiprocessing.active_children()] == ["calibcoach-scan"]
    scan.close()
    scan.close()  # idempotent
    assert multiprocessing.active_children() == []
    assert _shared_mappings() == mappings_before


def test_calibrate_starts_scanning_footage_before_the_session_loads(recordings_dir: Path, tmp_path: Path) -> None:
    # The start of a replay ran on one core while the session's modules loaded; the scan's process
    # now starts first. In a fresh interpreter, so that no earlier test has imported the session.
    import subprocess
    import sys
    import textwrap

    folder = _folder(recordings_dir, tmp_path / "frames", frames=12)
    script = textwrap.dedent(f"""
        import sys
        from calibcoach.app import cli, scan_stream
        started = []
        class Watched(scan_stream.ScanStream):
            def __init__(self, *args, **kwargs):
                super().__init__(*args, **kwargs)
                started.append((self.in_child, "calibcoach.app.session" in sys.modules))
        scan_stream.ScanStream = Watched
        import calibcoach.app.commands as commands
        commands.ScanStream = Watched
        code = cli.main(["calibrate", {str(folder)!r}, "--out", {str(tmp_path / "out")!r}, "--quiet", "--accept-partial"])
        print("started", started, "code", code, "session loaded", "calibcoach.app.session" in sys.modules)
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "started [(True, False)]" in done.stdout  # forked, before the session's modules were imported
    assert "session loaded True" in done.stdout  # ... which the replay then loaded and ran


def test_a_colour_frame_the_session_only_tracks_crosses_in_grey(recordings_dir: Path, tmp_path: Path) -> None:
    # Tracked frames are judged in grey, so the child sends the grey it made (a third of the bytes);
    # decided frames keep their colour for previews, and the grey the child made of them comes
    # along (the session judges in grey); frames skipped in transit are only counted and cross
    # without pixels. The pixels are the replay's own grey conversion, so the decisions are those
    # of the scan in process.
    from calibcoach.app.scan_stream import ScanStream

    folder = _folder(recordings_dir, tmp_path / "colour", frames=40, colour=True)
    with ScanStream(ImageFolderSource(folder), BoardSpec()) as in_child:
        crossed = list(in_child)
    with ScanStream(ImageFolderSource(folder), BoardSpec(), in_child=False) as in_process:
        local = list(in_process)
    tracked = [s for s in crossed if s.tracked_from is not None]
    assert tracked and len(tracked) < len(crossed)  # both kinds are there
    assert any(s.skipped for s in crossed)  # ... and frames skipped in transit
    for child, here in zip(crossed, local, strict=True):
        assert child.frame.index == here.frame.index and child.tracked_from == here.tracked_from
        if child.skipped:
            assert child.frame.image.size == 0 and child.frame.timestamp_ns == here.frame.timestamp_ns
        elif child.tracked_from is not None:
            assert child.frame.image.ndim == 2 and np.array_equal(child.frame.image, here.frame.grey())
        else:  # with the grey the child made of it, so the session does not convert it again
            assert child.frame.image.ndim == 3 and np.array_equal(child.frame.image, here.frame.image)
            assert child.frame.grey_made is not None and np.array_equal(child.frame.grey_made, here.frame.grey())
        assert np.array_equal(child.detection.corners_px, here.detection.corners_px)
    colour_decisions = _decisions(recordings_dir, folder, in_child=True)
    assert colour_decisions == _decisions(recordings_dir, folder, in_child=False)  # frames, corners, decisions, counts


def test_an_mjpg_videos_frames_cross_as_grey_with_their_jpeg(recordings_dir: Path, tmp_path: Path) -> None:
    """Of an MJPG video only the luminance is decoded (drivers/avi_mjpg.py): the frames the session
    judges cross from the scan with their JPEG, so what a person sees of them is in colour: the
    previews it logs and the check picture of the result."""
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (1280, 720))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG into .avi")
    for index in range(40):
        grey = cv2.imread(str(recordings_dir / "demo_webcam720_careful" / "frames" / f"{index:06d}.png"), cv2.IMREAD_GRAYSCALE)
        writer.write(cv2.merge([grey, cv2.add(grey, 9), cv2.subtract(grey, 7)]))
    writer.release()
    judged: list[tuple[int, bool, int]] = []
    settings = SessionSettings(selector=SelectorSettings(max_frames=8), stop_when_done=False)
    session, _stats = run_replay(open_source(path), BoardSpec(), settings,
                                 on_outcome=lambda o, f: judged.append((f.image.ndim, f.encoded is not None, f.colour().ndim)))
    assert judged and set(judged) == {(2, True, 3)}
    assert session.finish().check_image.ndim == 3
