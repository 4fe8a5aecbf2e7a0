"""RecordingWriter -> RecordingSource round trips, crash-cut recordings, resume, and ground truth."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from _jpegs import without_huffman_tables

from calibcoach.drivers.base import Frame, SkippedFrame
from calibcoach.drivers.errors import SourceError
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.png_fast import decode_png
from calibcoach.drivers.recording import RecordingWriter, read_truth, write_truth
from calibcoach.drivers.replay import RecordingSource, open_source

SIZE = (40, 30)  # (width, height) pixels
BOARD = {"squares_x": 8, "squares_y": 11, "square_mm": 30.01, "marker_mm": 22.01,
         "dictionary": "DICT_5X5_100", "legacy": False, "inverted": False}


def _frames(indices: list[int], *, grey: bool = False, seed: int = 0) -> list[Frame]:
    """Random-noise frames (noise so that any lossy step would show), focus rising with the index."""
    rng = np.random.default_rng(seed)
    shape = (SIZE[1], SIZE[0]) if grey else (SIZE[1], SIZE[0], 3)
    return [Frame(index=i, timestamp_ns=1_000_000 * i, image=rng.integers(0, 256, shape, dtype=np.uint8),
                  controls={"focus_absolute": 30 + i, "exposure_time_s": 0.01}) for i in indices]


def _writer(folder: Path, **kwargs) -> RecordingWriter:
    return RecordingWriter(folder, camera_id="sim:webcam720", kind="sim", image_size=SIZE, fps=30.0,
                           controls={"focus_absolute": 30, "focus_automatic_continuous": 0}, board=BOARD, **kwargs)


@pytest.mark.parametrize("grey", [False, True])
def test_round_trip_pixels_controls_board(tmp_path: Path, grey: bool) -> None:
    written = _frames([0, 1, 3, 4], grey=grey)  # index 2 was dropped by the camera: the gap must survive
    with _writer(tmp_path / "rec") as writer:
        assert [writer.write(f) for f in written] == [0, 1, 3, 4]
    session = json.loads((tmp_path / "rec" / "session.json").read_text())
    assert session["complete"] is True and len(session["frames"]) == 4
    assert session["frames"][2] == {"index": 3, "file": "frames/000003.png", "timestamp_ns": 3_000_000,
                                    "controls": {"focus_absolute": 33, "exposure_time_s": 0.01}}

    source = open_source(tmp_path / "rec")
    assert isinstance(source, RecordingSource)
    info = source.info
    assert (info.kind, info.camera_id, info.image_size, info.fps, info.frame_count) == (
        "recording", "sim:webcam720", SIZE, 30.0, 4)
    assert dict(info.controls) == {"focus_absolute": 30, "focus_automatic_continuous": 0}
    assert dict(info.board) == BOARD
    read = list(source)
    assert source.skipped == []
    assert [f.index for f in read] == [0, 1, 3, 4]
    assert [f.name for f in read] == ["000000.png", "000001.png", "000003.png", "000004.png"]
    for before, after in zip(written, read, strict=True):
        assert after.image.shape == before.image.shape and after.image.dtype == np.uint8
        assert np.array_equal(after.image, before.image)
        assert after.timestamp_ns == before.timestamp_ns
        assert dict(after.controls) == dict(before.controls)


@pytest.mark.parametrize("grey", [False, True])
def test_recorded_frames_replay_through_the_fast_png_decoder(tmp_path: Path, grey: bool) -> None:
    """A recording's PNGs are Sub-filtered, the rows drivers/png_fast.py undoes without libpng."""
    written = _frames([0, 1], grey=grey, seed=3)
    with _writer(tmp_path / "rec") as writer:
        for frame in written:
            writer.write(frame)
    for frame in written:
        data = (tmp_path / "rec" / "frames" / f"{frame.index:06d}.png").read_bytes()
        decoded = decode_png(data)
        assert decoded is not None, "a recorded frame fell back to libpng: its rows are not all Sub-filtered"
        assert np.array_equal(decoded, frame.image)


def _crash_cut_copy(tmp_path: Path) -> Path:
    """Write 5 frames, copy the folder before close() (what a crash leaves), then damage the copy."""
    with _writer(tmp_path / "rec") as writer:
        for frame in _frames([0, 1, 2, 3, 4]):
            writer.write(frame)
        shutil.copytree(tmp_path / "rec", tmp_path / "crashed")
    crashed = tmp_path / "crashed"
    log = crashed / "frames.jsonl"
    text = log.read_text()
    log.write_text(text[: len(text) - 20])  # the crash hit while appending frame 4's line
    (crashed / "frames" / "000001.png").unlink()
    return crashed


def test_crash_cut_recording_replays_what_was_written(tmp_path: Path) -> None:
    crashed = _crash_cut_copy(tmp_path)
    assert json.loads((crashed / "session.json").read_text())["complete"] is False
    source = open_source(crashed)
    assert source.info.frame_count == 4  # frame 4's cut line is ignored
    assert source.info.description == "recording crashed (sim:webcam720, 40x30, 4 frames, cut off before it was closed)"
    read = list(source)
    assert [f.index for f in read] == [0, 2, 3]
    assert np.array_equal(read[1].image, _frames([0, 1, 2, 3, 4])[2].image)
    assert source.skipped == [SkippedFrame(1, "000001.png", "file is missing")]


def test_resume_continues_numbering_after_a_crash(tmp_path: Path) -> None:
    crashed = _crash_cut_copy(tmp_path)
    with _writer(crashed, append=True) as writer:
        assert writer.frame_count == 4
        assert [writer.write(f) for f in _frames([0, 1], seed=1)] == [4, 5]  # after the last listed index, 3
    lines = (crashed / "frames.jsonl").read_text().splitlines()
    assert [json.loads(line)["index"] for line in lines] == [0, 1, 2, 3, 4, 5]  # the cut line is gone
    source = open_source(crashed)
    assert [f.index for f in source] == [0, 2, 3, 4, 5]
    assert source.skipped == [SkippedFrame(1, "000001.png", "file is missing")]


def _camera_jpeg(index: int) -> Frame:
    """A frame as an MJPG camera delivers it: the JPEG's luminance, the JPEG kept (drivers/v4l2.py);
    frame 1 without Huffman tables, as many webcams send them."""
    y, x = np.mgrid[0:SIZE[1], 0:SIZE[0]]
    colour = np.stack([5 * x + index, 7 * y, 3 * (x + y)], axis=2).astype(np.uint8)
    jpeg = cv2.imencode(".jpg", colour)[1].tobytes()
    if index == 1:
        jpeg = without_huffman_tables(jpeg)
        assert b"\xff\xc4" not in jpeg[:jpeg.index(b"\xff\xda")]
    grey = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    return Frame(index, 1_000_000 * index, grey, controls={"focus_absolute": 30}, encoded=jpeg)


def test_a_cameras_jpeg_is_recorded_as_it_came_and_replays_as_the_session_saw_it(tmp_path: Path) -> None:
    """Resumed after PNG frames, an MJPG camera's frames are recorded as their JPEGs: the replay gives
    the luminance detected live (not the colour's conversion to grey, which rounds otherwise) and
    the colour for what a person sees, also of a JPEG without Huffman tables; a damaged JPEG is
    skipped with its reason."""
    with _writer(tmp_path / "rec") as writer:
        writer.write(_frames([0], grey=True)[0])
    jpegs = [_camera_jpeg(i) for i in (0, 1, 2)]  # a resumed stream counts from 0 again
    with _writer(tmp_path / "rec", append=True) as writer:
        assert [writer.write(f) for f in jpegs] == [1, 2, 3]
    files = [e["file"] for e in json.loads((tmp_path / "rec" / "session.json").read_text())["frames"]]
    assert files == ["frames/000000.png", "frames/000001.jpg", "frames/000002.jpg", "frames/000003.jpg"]
    assert [(tmp_path / "rec" / f).read_bytes() for f in files[1:]] == [f.encoded for f in jpegs]
    assert not list((tmp_path / "rec" / "frames").glob(".*"))  # no temporary file left behind
    (tmp_path / "rec" / "frames" / "000003.jpg").write_bytes(jpegs[2].encoded[:40])  # cut short
    source = open_source(tmp_path / "rec")
    read = list(source)
    assert [f.index for f in read] == [0, 1, 2]
    assert read[0].encoded is None and read[0].image.ndim == 2
    for replayed, live in zip(read[1:], jpegs[:2], strict=True):
        assert replayed.encoded == live.encoded and np.array_equal(replayed.image, live.image)
        assert np.array_equal(replayed.colour(), cv2.imdecode(np.frombuffer(live.encoded, np.uint8), cv2.IMREAD_COLOR))
    assert [s.index for s in source.skipped] == [3]
    assert source.skipped[0].reason.startswith("file does not decode as an image")


def test_writer_refuses_a_folder_holding_a_recording(tmp_path: Path) -> None:
    with _writer(tmp_path / "rec") as writer:
        writer.write(_frames([0])[0])
    with pytest.raises(SourceError, match=r"already holds a recording; pass another folder, or --resume to add frames"):
        _writer(tmp_path / "rec")
    assert len(json.loads((tmp_path / "rec" / "session.json").read_text())["frames"]) == 1  # untouched


def test_resume_refuses_a_different_resolution(tmp_path: Path) -> None:
    _writer(tmp_path / "rec").close()
    with pytest.raises(SourceError, match=r"was recorded at 40x30 but the camera now delivers 80x60"):
        RecordingWriter(tmp_path / "rec", camera_id="sim:webcam720", kind="sim", image_size=(80, 60), fps=30.0,
                        controls={}, board=None, append=True)


def test_writer_rejects_frames_of_another_size(tmp_path: Path) -> None:
    with _writer(tmp_path / "rec") as writer, pytest.raises(ValueError, match=r"frame 0 is 20x10 uint8"):
        writer.write(Frame(0, 0, np.zeros((10, 20), np.uint8)))


def test_recording_without_frames_is_an_error(tmp_path: Path) -> None:
    _writer(tmp_path / "rec").close()
    with pytest.raises(SourceError, match=r"lists no usable frames"):
        open_source(tmp_path / "rec")


def test_newer_format_version_is_refused(tmp_path: Path) -> None:
    (tmp_path / "session.json").write_text(json.dumps({"format": "calibcoach-recording", "version": 2}))
    with pytest.raises(SourceError, match=r"is recording format version 2 but this calibcoach reads version 1"):
        open_source(tmp_path)


def test_truth_round_trip_is_exact(tmp_path: Path) -> None:
    camera = CameraModel("rational", np.array([[900.5, 0, 639.25], [0, 901.0, 359.75], [0, 0, 1]]),
                         np.array([-0.31, 0.12, 1e-4, -2e-4, 0.01, 0.02, 0.003, 1e-3]), (1280, 720))
    poses = [(0, np.array([0.1, -0.2, 0.3]), np.array([0.05, -0.02, 0.6])),
             (7, np.array([[-0.4], [0.0], [1.0 / 3.0]]), np.array([[0.0], [0.1], [1.25]]))]  # (3, 1) accepted
    write_truth(tmp_path, camera, poses)
    truth = read_truth(tmp_path)
    assert truth.camera.model == "rational" and truth.camera.image_size == (1280, 720)
    assert np.array_equal(truth.camera.camera_matrix, camera.camera_matrix)
    assert np.array_equal(truth.camera.dist_coeffs, camera.dist_coeffs)
    assert [p[0] for p in truth.poses] == [0, 7]
    for (_, rvec, tvec), (_, rvec_read, tvec_read) in zip(poses, truth.poses, strict=True):
        assert rvec_read.shape == (3,) and np.array_equal(rvec_read, rvec.reshape(3))
        assert np.array_equal(tvec_read, tvec.reshape(3))


def test_read_truth_without_file(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match=r"holds no truth\.json; only simulated sessions carry ground truth"):
        read_truth(tmp_path)
