"""The recording format (docs/recording-format.md): writing it, and parsing its JSON for the reader.

A recording is a folder that replays exactly like the camera it came from, so a session can be
re-run through the pipeline, debugged and turned into a test. It has to survive a crash mid-capture
(the laptop sleeps, the USB camera drops out): every frame is a whole file (a PNG, or the camera's
JPEG as it came) renamed into place before its line is appended and fsynced to `frames.jsonl`, so
whatever was written before the crash is readable afterwards. `session.json` only receives the full
frame list on a clean `close()`.

This module owns the format; `calibcoach.drivers.replay.RecordingSource` turns a parsed recording
into frames. `write_truth` / `read_truth` store the simulator's ground truth beside its recordings.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from calibcoach.drivers.base import Frame, SkippedFrame
from calibcoach.drivers.errors import SourceError
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.png_fast import encode_png

FORMAT_NAME = "calibcoach-recording"
FORMAT_VERSION = 1
SESSION_FILE = "session.json"
FRAMES_LOG = "frames.jsonl"
FRAMES_DIR = "frames"
TRUTH_FILE = "truth.json"


@dataclass(frozen=True, slots=True)
class SessionContents:
    """A parsed recording: its header and the frame entries it lists, PNGs not yet read."""

    header: Mapping[str, Any]  # session.json without its "frames" list
    entries: tuple[Mapping[str, Any], ...]  # {"index", "file", "timestamp_ns", "controls"}, index increasing
    problems: tuple[SkippedFrame, ...]  # entries that could not be used, with reasons
    complete: bool  # True when the writer closed cleanly (entries from session.json)


def read_session(folder: str | Path) -> SessionContents:
    """Parse `folder`'s session.json and its frame list (session.json if complete, else frames.jsonl).

    Raises `SourceError` when session.json is missing, not JSON, or not a version-1 recording.
    Bad frame entries do not raise: they come back in `problems` (a truncated last line of
    frames.jsonl, the normal trace of a crash, is dropped silently as the format prescribes).
    """
    folder = Path(folder)
    session_path = folder / SESSION_FILE
    if not session_path.is_file():
        raise SourceError(f"{folder} holds no {SESSION_FILE}, so it is not a calibcoach recording; pass a recording folder")
    try:
        session = json.loads(session_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SourceError(
            f"{session_path} is not valid JSON ({exc}); the recording header is damaged, so restore it "
            "from a backup or record the session again"
        ) from None
    fmt = session.get("format") if isinstance(session, dict) else None
    if fmt != FORMAT_NAME:
        raise SourceError(
            f"{session_path} is not a calibcoach recording (format {fmt!r}, expected {FORMAT_NAME!r}); pass a "
            f"folder recorded by calibcoach, or move {SESSION_FILE} aside to read the folder as plain images"
        )
    version = session.get("version")
    if version != FORMAT_VERSION:
        raise SourceError(
            f"{session_path} is recording format version {version!r} but this calibcoach reads version "
            f"{FORMAT_VERSION}; open it with the calibcoach version that recorded it"
        )
    _check_header(session, session_path)
    complete = session.get("complete") is True and isinstance(session.get("frames"), list)
    if complete:
        raw = [(f"{SESSION_FILE} frames[{i}]", entry) for i, entry in enumerate(session["frames"])]
        entries, problems = _validate_entries(raw)
    else:
        entries, problems = _validate_entries(_read_frames_log(folder / FRAMES_LOG))
    header = {key: value for key, value in session.items() if key != "frames"}
    return SessionContents(header, tuple(entries), tuple(problems), complete)


class RecordingWriter:
    """Writes frames as a recording folder that `RecordingSource` replays.

    Indices: the PNG of a frame is named by `frame.index` (its stream index, gaps included), so a
    replay reproduces the live stream's numbering. With `append=True` (resume) the new frames are
    numbered after the existing ones: index = last recorded index + 1 + frame.index.

    Example:
        >>> with RecordingWriter(tmp, camera_id="sim:webcam720", kind="sim", image_size=(1280, 720),
        ...                      fps=30.0, controls={}, board=None) as writer:  # doctest: +SKIP
        ...     writer.write(frame)
    """

    def __init__(
        self,
        folder: str | Path,
        *,
        camera_id: str,
        kind: str,
        image_size: tuple[int, int],
        fps: float | None,
        controls: Mapping[str, float],
        board: Mapping[str, Any] | None,
        append: bool = False,
        locked_controls: Mapping[str, float] | None = None,
    ) -> None:
        self.folder = Path(folder)
        self.image_size = (int(image_size[0]), int(image_size[1]))  # (width, height) pixels
        if min(self.image_size) <= 0:
            raise ValueError(f"image_size must be positive (width, height), got {image_size}")
        self._entries: list[dict[str, Any]] = []
        self._index_offset = 0  # added to frame.index; non-zero when appending
        self._last_index = -1
        self._closed = False
        board_dict = None if board is None else dict(board)
        holds_recording = (self.folder / SESSION_FILE).exists() or (self.folder / FRAMES_LOG).exists()
        if holds_recording and not append:
            raise SourceError(
                f"{self.folder} already holds a recording; pass another folder, or --resume to add frames to it"
            )
        if holds_recording:
            self._header = self._resume(board_dict)
        else:
            self._header = {
                "format": FORMAT_NAME,
                "version": FORMAT_VERSION,
                "created": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
                "complete": False,
                "camera": {"id": camera_id, "kind": kind, "image_size": list(self.image_size),
                           "fps": None if fps is None else float(fps)},
                "controls": _plain_controls(controls),
                "board": board_dict,
                # what focus was locked at (read back): a replay watches the frames' reports against it
                "locked_controls": _plain_controls(locked_controls or {}),
                "events": [],  # e.g. {"kind": "focus_drift", "frame_index": ...}, written when they happen
            }
        (self.folder / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        _write_json_atomic(self.folder / SESSION_FILE, self._header)
        self._log = open(self.folder / FRAMES_LOG, "a", encoding="utf-8")  # closed in close()

    def _resume(self, board: dict[str, Any] | None) -> dict[str, Any]:
        """Load the existing recording, check it matches, and rewrite frames.jsonl without a cut line."""
        contents = read_session(self.folder)
        header = dict(contents.header)
        recorded_size = tuple(header["camera"]["image_size"])
        if recorded_size != self.image_size:
            raise SourceError(
                f"{self.folder} was recorded at {recorded_size[0]}x{recorded_size[1]} but the camera now delivers "
                f"{self.image_size[0]}x{self.image_size[1]}; pass another folder instead of resuming this one"
            )
        if board is not None and not _same_board(header.get("board"), board):
            raise SourceError(
                f"{self.folder} was recorded with board {header['board']} but this session uses {board}; "
                "pass another folder instead of resuming this one"
            )
        header["board"] = _settled_board(header.get("board"), board)
        header["complete"] = False
        self._entries = [dict(entry) for entry in contents.entries]
        if self._entries:
            self._last_index = int(self._entries[-1]["index"])
            self._index_offset = self._last_index + 1
        # A crash can leave a half-written last line; appending after it would corrupt the next one.
        lines = "".join(json.dumps(entry) + "\n" for entry in self._entries)
        _write_text_atomic(self.folder / FRAMES_LOG, lines)
        return header

    @property
    def frame_count(self) -> int:
        """Frames listed so far, including the ones an appended recording already held."""
        return len(self._entries)

    def write(self, frame: Frame) -> int:
        """Save one frame (a PNG, or a camera's JPEG as it came), then log it; returns the index it was recorded under."""
        if self._closed:
            raise ValueError(f"recording {self.folder} is closed")
        if frame.image.dtype != np.uint8 or frame.image_size != self.image_size:
            raise ValueError(
                f"frame {frame.index} is {frame.image_size[0]}x{frame.image_size[1]} {frame.image.dtype}, but the "
                f"recording holds {self.image_size[0]}x{self.image_size[1]} uint8 images"
            )
        index = self._index_offset + int(frame.index)
        if index <= self._last_index:
            raise ValueError(f"frame index {index} does not follow the last recorded index {self._last_index}")
        # A frame delivered as a JPEG (an MJPG camera's, an MJPG file's or a JPEG folder's) whose
        # `image` is its luminance is kept as that JPEG, byte for byte: the replay decodes the same
        # luminance from it (RecordingSource), so it detects what the session detected, and the colour
        # stays. A 720p MJPG frame of the bench's is then 33-75 KB written as it came, where its colour
        # as a PNG took 324-817 KB (and 26-48 ms in OpenCV's encoder, more than a core at 30 fps).
        # Any other frame is its `image`, losslessly as a PNG whose rows drivers/png_fast.py decodes
        # fastest on replay (`encode_png`: 7-11 ms a 720p BGR frame).
        suffix = "png" if frame.encoded is None else "jpg"
        relative = f"{FRAMES_DIR}/{index:06d}.{suffix}"
        final_path = self.folder / relative
        temp_path = final_path.with_name(f".{index:06d}.tmp.{suffix}")
        try:
            temp_path.write_bytes(encode_png(frame.image) if frame.encoded is None else frame.encoded)
        except OSError as exc:
            raise SourceError(f"could not write {temp_path} ({exc.strerror}); check free disk space and write "
                              "permission") from exc
        os.replace(temp_path, final_path)
        entry = {"index": index, "file": relative, "timestamp_ns": int(frame.timestamp_ns),
                 "controls": _plain_controls(frame.controls)}
        self._log.write(json.dumps(entry) + "\n")
        self._log.flush()
        os.fsync(self._log.fileno())
        self._entries.append(entry)
        self._last_index = index
        return index

    def note_event(self, event: Mapping[str, Any]) -> None:
        """Store an event of the live session (a focus drift, say) in session.json, at once and atomically.

        The header is rewritten now rather than at close, so a crash right after a drift still leaves it
        in the recording for the replay to apply."""
        self._header = {**self._header, "events": [*self._header.get("events", []), dict(event)]}
        _write_json_atomic(self.folder / SESSION_FILE, self._header)

    def close(self) -> None:
        """Write the full frame list into session.json and mark the recording complete."""
        if self._closed:
            return
        self._closed = True
        self._log.close()
        _write_json_atomic(self.folder / SESSION_FILE, {**self._header, "complete": True, "frames": self._entries})

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        # Closing on an exception too is deliberate: Ctrl-C is how a capture normally ends, and every
        # listed frame is already a whole file, so the frame list is accurate either way.
        self.close()


def _same_board(recorded: Mapping[str, Any] | None, now: Mapping[str, Any]) -> bool:
    """Whether two board descriptions agree; None (not yet settled, e.g. legacy or inverted print) agrees with any value."""
    if recorded is None:
        return True
    return all(recorded.get(k) is None or now.get(k) is None or recorded.get(k) == now.get(k)
               for k in recorded.keys() | now.keys())


def _settled_board(recorded: Mapping[str, Any] | None, now: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """The recorded board with what has been settled since filled in."""
    if recorded is None or now is None:
        return None if recorded is None and now is None else dict(recorded or now or {})
    return {k: recorded.get(k) if recorded.get(k) is not None else now.get(k) for k in recorded.keys() | now.keys()}


@dataclass(frozen=True, slots=True)
class Truth:
    """A simulated session's ground truth: the camera that rendered it and every frame's board pose."""

    camera: CameraModel
    poses: tuple[tuple[int, np.ndarray, np.ndarray], ...]  # (index, rvec (3,) float64, tvec (3,) float64 m), T_cam_board


def write_truth(folder: str | Path, camera: CameraModel, poses: Sequence[tuple[int, Any, Any]]) -> None:
    """Store the true camera model and board poses (T_cam_board, metres) as `folder`/truth.json."""
    payload = {
        "camera": {
            "model": camera.model,
            "camera_matrix": camera.camera_matrix.tolist(),
            "dist_coeffs": camera.dist_coeffs.tolist(),
            "image_size": list(camera.image_size),
        },
        "poses": [
            {"index": int(index), "rvec": np.asarray(rvec, np.float64).reshape(3).tolist(),
             "tvec": np.asarray(tvec, np.float64).reshape(3).tolist()}
            for index, rvec, tvec in poses
        ],
    }
    Path(folder).mkdir(parents=True, exist_ok=True)
    _write_json_atomic(Path(folder) / TRUTH_FILE, payload)


def read_truth(folder: str | Path) -> Truth:
    """Load `folder`/truth.json written by `write_truth` (floats round-trip exactly through JSON)."""
    path = Path(folder) / TRUTH_FILE
    if not path.is_file():
        raise SourceError(f"{folder} holds no {TRUTH_FILE}; only simulated sessions carry ground truth")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        cam = data["camera"]
        camera = CameraModel(cam["model"], np.array(cam["camera_matrix"], np.float64),
                             np.array(cam["dist_coeffs"], np.float64), tuple(cam["image_size"]))
        poses = tuple((int(p["index"]), np.array(p["rvec"], np.float64).reshape(3),
                       np.array(p["tvec"], np.float64).reshape(3)) for p in data["poses"])
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as exc:
        raise SourceError(f"{path} is damaged ({exc}); re-run the simulation to regenerate it") from None
    return Truth(camera, poses)


# --- helpers ----------------------------------------------------------------------------------


def _check_header(session: dict[str, Any], session_path: Path) -> None:
    camera = session.get("camera")
    size = camera.get("image_size") if isinstance(camera, dict) else None
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
        raise SourceError(
            f"{session_path} has no valid camera.image_size (found {size!r}); the header is damaged, so restore "
            "it from a backup or record the session again"
        )


def _read_frames_log(path: Path) -> list[tuple[str, Any]]:
    """frames.jsonl as (where, parsed-or-exception) pairs; a cut-off last line is dropped."""
    if not path.is_file():
        return []
    lines = path.read_bytes().split(b"\n")
    cut_last = lines[-1] != b""  # a complete file ends with a newline, leaving b"" after the split
    out: list[tuple[str, Any]] = []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            out.append((f"{FRAMES_LOG} line {number}", json.loads(line)))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            if cut_last and number == len(lines):
                continue  # the line a crash interrupted: it never named a frame (format rule)
            out.append((f"{FRAMES_LOG} line {number}", exc))
    return out


def _validate_entries(raw: list[tuple[str, Any]]) -> tuple[list[dict[str, Any]], list[SkippedFrame]]:
    """Keep entries with the format's fields and strictly increasing indices; report the rest."""
    entries: list[dict[str, Any]] = []
    problems: list[SkippedFrame] = []
    last_index = -1
    for where, entry in raw:
        reason = _entry_problem(entry)
        index = entry.get("index", -1) if isinstance(entry, dict) else -1
        if reason is None and index <= last_index:
            reason = f"index {index} does not follow the previous index {last_index}"
        if reason is not None:
            # Index -1 when the entry has none: the frame cannot be placed in the stream.
            problems.append(SkippedFrame(index if isinstance(index, int) else -1, where, reason))
            continue
        entries.append({"index": index, "file": entry["file"], "timestamp_ns": entry["timestamp_ns"],
                        "controls": dict(entry.get("controls") or {})})
        last_index = index
    return entries, problems


def _entry_problem(entry: Any) -> str | None:
    if isinstance(entry, Exception):
        return f"not valid JSON ({entry})"
    if not isinstance(entry, dict):
        return f"expected a JSON object, found {type(entry).__name__}"
    for key in ("index", "timestamp_ns"):
        if not isinstance(entry.get(key), int) or isinstance(entry.get(key), bool):
            return f"{key!r} is missing or not an integer"
    file = entry.get("file")
    if not isinstance(file, str) or not file or Path(file).is_absolute() or ".." in Path(file).parts:
        return f"'file' must be a path inside the recording folder, found {file!r}"
    if not isinstance(entry.get("controls", {}), dict):
        return "'controls' is not a JSON object"
    return None


def _plain_controls(controls: Mapping[str, Any]) -> dict[str, int | float]:
    """Controls as JSON-ready numbers (numpy scalars -> Python; ints stay ints, e.g. focus_absolute 30)."""
    out: dict[str, int | float] = {}
    for key, value in controls.items():
        value = value.item() if isinstance(value, np.generic) else value
        out[str(key)] = int(value) if isinstance(value, bool | int) else float(value)
    return out


def _write_json_atomic(path: Path, payload: Any) -> None:
    _write_text_atomic(path, json.dumps(payload, indent=2) + "\n")


def _write_text_atomic(path: Path, text: str) -> None:
    """Write to a temporary sibling, fsync, rename: readers see the old file or the new one, never half."""
    temp = path.with_name(f".{path.name}.tmp")
    with open(temp, "w", encoding="utf-8") as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temp, path)
