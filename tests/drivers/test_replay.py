"""Replay sources on real files written with cv2 into tmp_path: order, decoding, skips and error text."""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibcoach.drivers.base import SkippedFrame
from calibcoach.drivers.errors import SourceError
from calibcoach.drivers.replay import ImageFolderSource, RecordingSource, open_source
from calibcoach.drivers.video_file import VideoFileSource

WIDTH, HEIGHT = 64, 48  # pixels; small so the whole file runs in well under a second


def _grey_level(i: int) -> int:
    return 20 + 20 * i  # a flat frame per index: JPEG keeps a flat level within +-2


def _write_avi(path: Path, count: int, fps: float = 15.0) -> Path:
    """An MJPG .avi whose frame i is a flat (HEIGHT, WIDTH, 3) image of level _grey_level(i)."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (WIDTH, HEIGHT))
    assert writer.isOpened()
    for i in range(count):
        writer.write(np.full((HEIGHT, WIDTH, 3), _grey_level(i), np.uint8))
    writer.release()
    return path


def _damage_video_frames(path: Path, indices: list[int]) -> None:
    """Zero the start of the chosen frames' JPEG data (from the SOI marker), as a bad disk sector would."""
    data = bytearray(path.read_bytes())
    starts = [m.start() for m in re.finditer(b"\xff\xd8\xff", data)]  # one JPEG SOI per MJPG frame
    for i in indices:
        data[starts[i]:starts[i] + 200] = bytes(200)
    path.write_bytes(bytes(data))


def _write_image(path: Path, level: int, size: tuple[int, int] = (WIDTH, HEIGHT), grey: bool = False) -> Path:
    shape = (size[1], size[0]) if grey else (size[1], size[0], 3)
    assert cv2.imwrite(str(path), np.full(shape, level, np.uint8))
    return path


# --- image folders ---------------------------------------------------------------------------


def test_folder_natural_case_insensitive_order_and_clock(tmp_path: Path) -> None:
    for i, name in enumerate(["cal10.png", "cal2.png", "cal1.png", "CAL3.PNG", "cal20.jpg"]):
        _write_image(tmp_path / name, 10 * i)
    (tmp_path / "notes.txt").write_text("not an image")
    _write_image(tmp_path / "._cal0.png", 0)  # macOS resource-fork file: hidden, ignored
    source = open_source(tmp_path)
    assert isinstance(source, ImageFolderSource)
    frames = list(source)
    assert [f.name for f in frames] == ["cal1.png", "cal2.png", "CAL3.PNG", "cal10.png", "cal20.jpg"]
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert [f.timestamp_ns for f in frames] == [0, 33_333_333, 66_666_667, 100_000_000, 133_333_333]
    assert source.info.fps is None and source.info.frame_count == 5 and source.info.kind == "folder"
    assert source.info.image_size == (WIDTH, HEIGHT)
    assert source.skipped == []


def test_folder_with_fps_uses_it_for_timestamps(tmp_path: Path) -> None:
    for i in range(3):
        _write_image(tmp_path / f"f{i}.png", i)
    source = ImageFolderSource(tmp_path, fps=10.0)
    assert [f.timestamp_ns for f in source] == [0, 100_000_000, 200_000_000]
    assert source.info.fps == 10.0


def test_grey_jpeg_stays_two_dimensional_and_colour_is_bgr(tmp_path: Path) -> None:
    _write_image(tmp_path / "a.jpg", 128, grey=True)
    colour = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    colour[:, :, 2] = 200  # red in BGR
    cv2.imwrite(str(tmp_path / "b.png"), colour)
    grey_frame, colour_frame = list(open_source(tmp_path))
    assert grey_frame.image.shape == (HEIGHT, WIDTH) and grey_frame.image.dtype == np.uint8
    assert abs(int(grey_frame.image.mean()) - 128) <= 2
    assert colour_frame.image.shape == (HEIGHT, WIDTH, 3)
    assert colour_frame.image[0, 0].tolist() == [0, 0, 200]


def test_a_colour_jpegs_luminance_is_decoded_and_its_colour_on_demand(tmp_path: Path) -> None:
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    colour = np.stack([x * 4 % 256, y * 5 % 256, (x + y) * 3 % 256], axis=2).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "a.jpg"), colour, [cv2.IMWRITE_JPEG_QUALITY, 95])
    _write_image(tmp_path / "b.png", 90)  # a PNG beside it is decoded whole, as before
    jpeg, png = list(open_source(tmp_path))
    decoded = cv2.imread(str(tmp_path / "a.jpg"), cv2.IMREAD_COLOR)
    assert jpeg.image.shape == (HEIGHT, WIDTH) and jpeg.encoded is not None and np.array_equal(jpeg.colour(), decoded)
    assert np.abs(jpeg.grey().astype(int) - cv2.cvtColor(decoded, cv2.COLOR_BGR2GRAY)).mean() < 0.2  # rounding and clipping
    assert png.encoded is None and np.array_equal(png.colour(), png.image)


def test_corrupt_and_empty_files_are_skipped_with_reasons(tmp_path: Path) -> None:
    _write_image(tmp_path / "img1.png", 10)
    (tmp_path / "img2.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))  # PNG signature, no image
    (tmp_path / "img3.jpg").write_bytes(b"")
    _write_image(tmp_path / "img4.png", 40)
    source = open_source(tmp_path)
    frames = list(source)
    assert [(f.index, f.name) for f in frames] == [(0, "img1.png"), (3, "img4.png")]
    assert [(s.index, s.name) for s in source.skipped] == [(1, "img2.png"), (2, "img3.jpg")]
    assert "does not decode as an image" in source.skipped[0].reason
    assert source.skipped[1].reason == "file is empty (0 bytes)"


def test_size_mismatch_is_skipped_against_the_folders_resolution(tmp_path: Path) -> None:
    _write_image(tmp_path / "a.png", 10)
    _write_image(tmp_path / "b.png", 20, size=(32, 24))
    _write_image(tmp_path / "c.png", 30)
    source = open_source(tmp_path)
    assert [f.name for f in source] == ["a.png", "c.png"]
    assert source.skipped == [SkippedFrame(1, "b.png", (
        "image is 32x24 but 2 of the 3 images are 64x48; all images must share one camera resolution"))]


def test_a_stray_image_sorted_first_does_not_disqualify_the_rest(tmp_path: Path) -> None:
    # a screenshot or a thumbnail named so that it sorts first, among a camera's JPEG and PNG frames
    _write_image(tmp_path / "0_thumb.jpg", 10, size=(32, 24))
    for i in range(1, 4):
        _write_image(tmp_path / f"{i}.jpg", 20 * i)
    _write_image(tmp_path / "4.png", 90)
    source = open_source(tmp_path)
    assert source.info.image_size == (WIDTH, HEIGHT)
    assert [f.name for f in source] == ["1.jpg", "2.jpg", "3.jpg", "4.png"]
    assert source.skipped == [SkippedFrame(0, "0_thumb.jpg", (
        f"image is 32x24 but 4 of the 5 images are {WIDTH}x{HEIGHT}; all images must share one camera resolution"))]


def test_without_sizes_in_the_headers_the_first_image_sets_the_resolution(tmp_path: Path) -> None:
    _write_image(tmp_path / "a.bmp", 10, size=(32, 24))
    _write_image(tmp_path / "b.bmp", 20)
    _write_image(tmp_path / "c.bmp", 30)
    source = open_source(tmp_path)
    assert [f.name for f in source] == ["a.bmp"]
    assert source.skipped[0].reason == ("image is 64x48 but the first image (a.bmp) is 32x24; all images must share "
                                        "one camera resolution")


def test_empty_folder_error_names_extensions(tmp_path: Path) -> None:
    with pytest.raises(SourceError) as err:
        open_source(tmp_path)
    assert str(err.value) == (
        f"{tmp_path} holds no images (looked for .png, .jpg, .jpeg, .tif, .tiff, .bmp, .webp); it is empty; "
        "pass the folder that holds the calibration images")


def test_folder_of_text_files_error_says_what_is_there(tmp_path: Path) -> None:
    for i in range(12):
        (tmp_path / f"log{i}.txt").write_text("x")
    (tmp_path / "cam0").mkdir()
    _write_image(tmp_path / "cam0" / "a.png", 1)
    with pytest.raises(SourceError, match=r"it contains 12 \.txt files and 1 folder; pass the folder that "
                                          r"holds the images, e.g. .*cam0$"):
        open_source(tmp_path)


def test_folder_with_a_video_points_at_the_video(tmp_path: Path) -> None:
    _write_avi(tmp_path / "take1.avi", 2)
    with pytest.raises(SourceError, match=r"it contains 1 \.avi file; pass the video file itself, e.g. .*take1\.avi$"):
        open_source(tmp_path)


# --- paths that are not sources ----------------------------------------------------------------


def test_nonexistent_path(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match=r"nope\.avi does not exist; pass a video file, a folder of images"):
        open_source(tmp_path / "nope.avi")


def test_single_image_file_asks_for_its_folder(tmp_path: Path) -> None:
    image = _write_image(tmp_path / "cal1.png", 5)
    with pytest.raises(SourceError, match=r"is a single image; pass the folder that holds the images instead"):
        open_source(image)


def test_live_spec_points_to_live_command() -> None:
    with pytest.raises(SourceError, match=r"live cameras are opened by `calibcoach live --source v4l2:/dev/video0`"):
        open_source("v4l2:/dev/video0")
    with pytest.raises(SourceError, match=r"'depthai' is a live camera"):
        open_source("depthai")


def test_zero_byte_video(tmp_path: Path) -> None:
    (tmp_path / "empty.mp4").write_bytes(b"")
    with pytest.raises(SourceError, match=r"empty\.mp4 is empty \(0 bytes\)"):
        open_source(tmp_path / "empty.mp4")


def test_garbage_named_mp4(tmp_path: Path) -> None:
    path = tmp_path / "clip.mp4"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(SourceError, match=r"OpenCV cannot open .*clip\.mp4 as a video .*ffmpeg .* or pass a folder"):
        open_source(path)


def test_video_without_a_decodable_frame(tmp_path: Path) -> None:
    path = _write_avi(tmp_path / "dead.avi", 4)
    _damage_video_frames(path, [0, 1, 2, 3])
    with pytest.raises(SourceError, match=r"opens as a video but none of its first 25 frames decodes"):
        open_source(path)


def test_bad_session_json_and_wrong_format(tmp_path: Path) -> None:
    (tmp_path / "session.json").write_text('{"format": "calibcoach-recording", ')
    with pytest.raises(SourceError, match=r"session\.json is not valid JSON .*restore it from a backup"):
        open_source(tmp_path)
    (tmp_path / "session.json").write_text(json.dumps({"format": "other-tool", "version": 3}))
    with pytest.raises(SourceError, match=r"is not a calibcoach recording \(format 'other-tool'"):
        open_source(tmp_path)


# --- videos ----------------------------------------------------------------------------------


def test_video_round_trip(tmp_path: Path) -> None:
    source = open_source(_write_avi(tmp_path / "clip.avi", 12, fps=15.0))
    assert isinstance(source, VideoFileSource)
    assert (source.info.kind, source.info.image_size, source.info.fps, source.info.frame_count) == (
        "video", (WIDTH, HEIGHT), 15.0, 12)
    assert source.info.description == "video file clip.avi (64x48, 15 fps, 12 frames)"
    with source:
        frames = list(source)
    assert [f.index for f in frames] == list(range(12))
    # an MJPG AVI's frames are decoded to their grey, their colour on demand (drivers/avi_mjpg.py)
    assert all(f.image.shape == (HEIGHT, WIDTH) and f.colour().shape == (HEIGHT, WIDTH, 3) for f in frames)
    assert [round(float(f.image.mean())) for f in frames] == pytest.approx([_grey_level(i) for i in range(12)], abs=2)
    assert [f.timestamp_ns for f in frames] == pytest.approx([i * 1e9 / 15 for i in range(12)], abs=1e3)
    assert source.skipped == []
    assert len(list(source)) == 12 and source.skipped == []  # reopening rewinds


def test_a_rotation_tag_is_reported_not_applied(tmp_path: Path) -> None:
    # a phone's portrait video: frames stored landscape, the MP4 track header says "show turned 90 deg"
    writer = cv2.VideoWriter(str(tmp_path / "plain.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (WIDTH, HEIGHT))
    assert writer.isOpened()
    image = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    image[:, : WIDTH // 4] = 255  # a bright band on the stored frame's left
    for _ in range(6):
        writer.write(image)
    writer.release()
    data = bytearray((tmp_path / "plain.mp4").read_bytes())
    matrix = data.find(b"tkhd") + 44  # version-0 tkhd: its 3x3 display matrix follows 40 bytes of fields
    assert struct.unpack(">9i", data[matrix : matrix + 36]) == (0x10000, 0, 0, 0, 0x10000, 0, 0, 0, 0x40000000)
    data[matrix : matrix + 36] = struct.pack(">9i", 0, 0x10000, 0, -0x10000, 0, 0, 0, 0, 0x40000000)
    (tmp_path / "portrait.mp4").write_bytes(bytes(data))
    assert cv2.VideoCapture(str(tmp_path / "portrait.mp4")).read()[1].shape == (WIDTH, HEIGHT, 3)  # what FFmpeg would do
    source = open_source(tmp_path / "portrait.mp4")
    assert source.info.image_size == (WIDTH, HEIGHT)
    assert "players show it turned 90 deg: the calibration is for the stored frames" in source.info.description
    frames = list(source)
    assert len(frames) == 6 and all(f.image.shape == (HEIGHT, WIDTH, 3) for f in frames)
    assert frames[0].image[:, : WIDTH // 4 - 2].mean() > 200 and frames[0].image[:, WIDTH // 2 :].mean() < 40
    assert "turned" not in open_source(tmp_path / "plain.mp4").info.description


def test_video_frame_damaged_mid_stream_is_skipped(tmp_path: Path) -> None:
    path = _write_avi(tmp_path / "clip.avi", 10, fps=10.0)
    _damage_video_frames(path, [4])
    source = open_source(path)
    frames = list(source)
    assert [f.index for f in frames] == [0, 1, 2, 3, 5, 6, 7, 8, 9]
    assert frames[4].timestamp_ns == pytest.approx(500_000_000, abs=1e3)  # the container clock, not a shifted one
    assert source.skipped == [SkippedFrame(4, "", "frame could not be decoded (damaged video data)")]


def test_video_with_damaged_tail_stops_and_says_why(tmp_path: Path) -> None:
    path = _write_avi(tmp_path / "clip.avi", 10)
    _damage_video_frames(path, [5, 6, 7, 8, 9])
    source = VideoFileSource(path, max_consecutive_failures=3)
    assert [f.index for f in source] == [0, 1, 2, 3, 4]
    assert source.skipped == [SkippedFrame(5, "", (
        "frames 5-7 failed to decode in a row, so reading stopped; the header announces 10 frames, "
        "the rest of the file is damaged"))]


def test_open_source_picks_recording_for_folder_with_session(tmp_path: Path) -> None:
    from calibcoach.drivers.base import Frame
    from calibcoach.drivers.recording import RecordingWriter

    with RecordingWriter(tmp_path / "rec", camera_id="sim:t", kind="sim", image_size=(WIDTH, HEIGHT),
                         fps=30.0, controls={}, board=None) as writer:
        writer.write(Frame(0, 0, np.zeros((HEIGHT, WIDTH), np.uint8)))
    assert isinstance(open_source(tmp_path / "rec"), RecordingSource)
