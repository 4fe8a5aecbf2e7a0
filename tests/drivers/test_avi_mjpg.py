"""Motion-JPEG AVIs read from their container: the same frames VideoCapture gives, and the odd files.

Files come from cv2.VideoWriter, and where a case needs what it never writes (JPEGs without
Huffman tables, OpenDML's second RIFF chunk, a dropped frame) they are assembled here chunk by chunk.
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from _jpegs import without_huffman_tables

from calibcoach.app.preview import frame_preview_jpeg
from calibcoach.drivers.avi_mjpg import mjpg_index
from calibcoach.drivers.base import SkippedFrame
from calibcoach.drivers.recording import RecordingWriter
from calibcoach.drivers.replay import RecordingSource
from calibcoach.drivers.video_file import VideoFileSource

WIDTH, HEIGHT, FPS = 64, 48, 15


def _textured(i: int) -> np.ndarray:
    """Frame i: smooth colour gradients plus a white square that moves, so decoders' rounding shows and frames differ."""
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    image = np.stack([30 + 2 * x + i, 40 + 3 * y, 100 + x + y], axis=2).astype(np.uint8)
    image[10:20, 5 + 3 * i:15 + 3 * i] = 255
    return image


def _written(path: Path, count: int, fourcc: str = "MJPG") -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), FPS, (WIDTH, HEIGHT))
    if not writer.isOpened():
        pytest.skip(f"this OpenCV build cannot write {fourcc} into {path.suffix}")
    for i in range(count):
        writer.write(_textured(i))
    writer.release()
    return path


def _jpeg(i: int, *, huffman_tables: bool = True) -> bytes:
    data = cv2.imencode(".jpg", _textured(i))[1].tobytes()
    return data if huffman_tables else without_huffman_tables(data)


def _chunk(fourcc: bytes, body: bytes, *, pad: bool = True) -> bytes:
    return fourcc + struct.pack("<I", len(body)) + body + b"\0" * (len(body) % 2 if pad else 0)


def _list(kind: bytes, form: bytes, *chunks: bytes) -> bytes:
    return _chunk(kind, form + b"".join(chunks))


def _avi(frames: list[bytes], *, extension: list[bytes] | None = None, codec: bytes = b"MJPG", pad: bool = True) -> bytes:
    """An AVI of one video stream holding `frames` as '00dc' chunks; `extension`: more in an OpenDML 'AVIX'
    chunk; `pad` False writes odd-sized chunks without the pad byte RIFF asks for, as some writers do."""
    avih = struct.pack("<14I", round(1e6 / FPS), 0, 0, 0x10, len(frames), 0, 1, 0, WIDTH, HEIGHT, 0, 0, 0, 0)
    strh = b"vids" + codec + struct.pack("<IHHIIIIIIIIhhhh", 0, 0, 0, 0, 1, FPS, 0, len(frames), 0, 0xFFFFFFFF, 0,
                                         0, 0, WIDTH, HEIGHT)
    strf = struct.pack("<IiiHH4sIiiII", 40, WIDTH, HEIGHT, 1, 24, codec, WIDTH * HEIGHT * 3, 0, 0, 0, 0)
    header = _list(b"LIST", b"hdrl", _chunk(b"avih", avih), _list(b"LIST", b"strl", _chunk(b"strh", strh), _chunk(b"strf", strf)))
    movi = _list(b"LIST", b"movi", *(_chunk(b"00dc", f, pad=pad) for f in frames))
    data = _list(b"RIFF", b"AVI ", header, movi)
    if extension is not None:
        data += _list(b"RIFF", b"AVIX", _list(b"LIST", b"movi", *(_chunk(b"00dc", f) for f in extension)))
    return data


def _frames(path: Path) -> tuple[VideoFileSource, list]:
    source = VideoFileSource(path)
    with source:
        return source, list(source)


def test_frames_match_videocaptures(tmp_path: Path) -> None:
    path = _written(tmp_path / "clip.avi", 12)
    index = mjpg_index(path)
    assert index is not None and len(index.packets) == 12 and index.fps == FPS and index.image_size == (WIDTH, HEIGHT)
    source, frames = _frames(path)
    capture = cv2.VideoCapture(str(path))
    reference = [capture.read()[1] for _ in range(12)]
    assert [f.index for f in frames] == list(range(12)) and source.skipped == []
    assert source.info.description == f"video file clip.avi ({WIDTH}x{HEIGHT}, {FPS} fps, 12 frames)"
    assert [f.timestamp_ns for f in frames] == pytest.approx([i * 1e9 / FPS for i in range(12)], abs=1e3)
    for frame, expected in zip(frames, reference, strict=True):
        # the luminance alone is decoded; the colour on demand, from the JPEG the frame keeps
        colour = frame.colour()
        assert frame.image.shape == expected.shape[:2] and colour.shape == expected.shape and colour.dtype == np.uint8
        # libjpeg against FFmpeg: another IDCT and colour rounding, a level or so in the grey the
        # detector reads, a little more in colour at the square's sharp edges; never another picture
        assert np.abs(frame.grey().astype(int) - cv2.cvtColor(expected, cv2.COLOR_BGR2GRAY)).mean() < 1.5
        assert np.abs(colour.astype(int) - expected).mean() < 3.0
        # the luminance is libjpeg's colour converted to grey but for rounding, and for where the colour
        # clipped (the saturated square's edges here: up to 6 levels on 1-2% of this small clip's pixels)
        gaps = np.abs(frame.grey().astype(int) - cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))
        assert gaps.mean() < 0.1 and np.mean(gaps > 2) < 0.02
    assert np.abs(frames[0].image.astype(int) - frames[11].image).mean() > 3.0  # the frames themselves differ more


def test_other_codecs_are_read_by_videocapture(tmp_path: Path) -> None:
    path = _written(tmp_path / "clip.mp4", 6, fourcc="mp4v")
    assert mjpg_index(path) is None
    source, frames = _frames(path)
    assert [f.index for f in frames] == list(range(6)) and frames[0].image.shape == (HEIGHT, WIDTH, 3)


def test_jpegs_without_huffman_tables_decode_as_with_them(tmp_path: Path) -> None:
    (tmp_path / "full.avi").write_bytes(_avi([_jpeg(i) for i in range(4)]))
    (tmp_path / "bare.avi").write_bytes(_avi([_jpeg(i, huffman_tables=False) for i in range(4)]))
    assert len(_jpeg(0, huffman_tables=False)) < len(_jpeg(0)) - 300  # the tables are really gone
    _, full = _frames(tmp_path / "full.avi")
    _, bare = _frames(tmp_path / "bare.avi")
    assert len(full) == len(bare) == 4
    assert all(np.array_equal(a.image, b.image) and np.array_equal(a.colour(), b.colour()) for a, b in zip(full, bare, strict=True))


def test_opendml_extension_is_read_after_the_first_riff(tmp_path: Path) -> None:
    path = tmp_path / "long.avi"
    path.write_bytes(_avi([_jpeg(i) for i in range(3)], extension=[_jpeg(i) for i in range(3, 6)]))
    assert len(mjpg_index(path).packets) == 6  # type: ignore[union-attr]
    _, frames = _frames(path)
    expected = [cv2.imdecode(np.frombuffer(_jpeg(i), np.uint8), cv2.IMREAD_COLOR) for i in range(6)]
    assert [f.index for f in frames] == list(range(6))
    assert all(np.array_equal(f.colour(), e) for f, e in zip(frames, expected, strict=True))


def test_a_dropped_frame_or_another_codec_leaves_the_file_to_videocapture(tmp_path: Path) -> None:
    dropped = tmp_path / "dropped.avi"
    dropped.write_bytes(_avi([_jpeg(0), b"", _jpeg(2)]))
    assert mjpg_index(dropped) is None
    other = tmp_path / "other.avi"
    other.write_bytes(_avi([_jpeg(0)], codec=b"XVID"))
    assert mjpg_index(other) is None
    assert mjpg_index(tmp_path / "missing.avi") is None


def test_a_walk_that_loses_its_way_leaves_the_file_to_videocapture(tmp_path: Path) -> None:
    odd = [data + b"\0" * (1 - len(data) % 2) for data in (_jpeg(i) for i in range(5))]  # every chunk odd-sized
    padded, unpadded = tmp_path / "padded.avi", tmp_path / "unpadded.avi"
    padded.write_bytes(_avi(odd))
    unpadded.write_bytes(_avi(odd, pad=False))
    assert len(mjpg_index(padded).packets) == 5  # type: ignore[union-attr]
    # without the pad bytes the chunks after the first are misread: fewer frames than the header counts
    assert mjpg_index(unpadded) is None


def test_a_file_cut_off_inside_a_frame_keeps_the_frames_before_it(tmp_path: Path) -> None:
    path = _written(tmp_path / "clip.avi", 10)
    index = mjpg_index(path)
    offset, length = index.packets[7]  # type: ignore[union-attr]
    path.write_bytes(path.read_bytes()[: offset + length // 2])
    source, frames = _frames(path)
    assert [f.index for f in frames] == list(range(7))
    assert source.skipped == [SkippedFrame(7, "", (
        "the file ends inside frame 7, so it was cut off (copied or recorded incompletely); the frames before it are read"))]


def test_what_a_person_sees_of_an_mjpg_frame_is_in_colour(tmp_path: Path) -> None:
    """Only the grey is decoded for detection; the preview decodes its colour from the JPEG the frame
    keeps (a grey preview would be a wrong picture). A recording of the frame keeps its JPEG byte for
    byte: its replay must detect the same grey to reproduce the session, and the colour stays."""
    size = (1280, 720)
    y, x = np.mgrid[0:size[1], 0:size[0]]
    image = np.stack([x % 256, y % 256, (x + y) % 256], axis=2).astype(np.uint8)  # colour everywhere
    writer = cv2.VideoWriter(str(tmp_path / "colour.avi"), cv2.VideoWriter_fourcc(*"MJPG"), FPS, size)
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG into .avi")
    writer.write(image)
    writer.release()
    _source, (frame,) = _frames(tmp_path / "colour.avi")
    assert frame.image.ndim == 2 and frame.encoded is not None
    preview = cv2.imdecode(np.frombuffer(frame_preview_jpeg(frame), np.uint8), cv2.IMREAD_UNCHANGED)
    shrunk = cv2.resize(frame.colour(), (640, 360), interpolation=cv2.INTER_AREA)
    assert preview.shape == (360, 640, 3) and np.abs(preview.astype(int) - shrunk).mean() < 4.0  # libjpeg's DCT shrink
    with RecordingWriter(tmp_path / "rec", camera_id="file", kind="video", image_size=size, fps=FPS, controls={},
                         board=None) as recording:
        recording.write(frame)
    assert (tmp_path / "rec" / "frames" / "000000.jpg").read_bytes() == frame.encoded
    (recorded,) = list(RecordingSource(tmp_path / "rec"))
    assert np.array_equal(recorded.grey(), frame.grey())  # not the colour's conversion, which rounds otherwise
    assert recorded.image.ndim == 2 and np.array_equal(recorded.colour(), frame.colour())
