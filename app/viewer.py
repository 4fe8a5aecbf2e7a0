"""Live and after-the-fact view of a calibration session in Rerun; the only module that logs to rerun.

Why Rerun: the person holding the board needs to see, at a glance and a metre away, the camera
image with the corners found, where the board should go next (a ghost outline plus one sentence),
and how far the session has come. The same stream is always saved to `session.rrd`, so a run
without a screen (mode "none") can be looked at later with `rerun session.rrd`.

Modes:
- "web": a `rerun --serve-web` child process hosts the gRPC proxy and the web viewer, both bound
  to `bind` (127.0.0.1 by default: the SDK's own `serve_web_viewer` cannot choose its bind address
  and listens on every interface). `Viewer.url` is what the caller prints.
- "native": spawns the desktop viewer when a display is available; otherwise saves only and says
  why in `Viewer.notice`.
- "none": saves only.

Each Viewer owns a dedicated `RecordingStream` (never the global one), so several can coexist in
one process. `close()` flushes and disconnects, which writes the .rrd footer `rerun rrd verify`
wants; it is idempotent and safe to call from a `finally` after Ctrl-C.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from urllib.parse import quote

import cv2
import numpy as np
import rerun as rr

from calibcoach.app import viewer_blueprint as paths
from calibcoach.app.preview import frame_preview_jpeg, preview_factor
from calibcoach.app.session import FrameOutcome, SessionResult
from calibcoach.coverage.grid import DISTANCE_CELLS, TILT_CELLS, CoverageMap
from calibcoach.coverage.guidance import Target
from calibcoach.drivers.base import Frame
from calibcoach.drivers.errors import CalibcoachError
from calibcoach.drivers.lens import CameraModel

MODES = ("web", "native", "none")
# JPEG by OpenCV, not rr.Image.compress: 0.9 ms against 6.4 ms for a 960x540 frame on this machine.
_SERVER_START_TIMEOUT_S = 15.0

# Corner colours by the frame's fate (RGB): green kept, grey look-alike, orange hold still, red unusable.
_FATE_COLOURS = {
    "accepted": (40, 200, 60),
    "duplicate": (150, 150, 150),
    "adds nothing": (150, 150, 150),
    "frame limit": (150, 150, 150),
    "moving": (255, 150, 0),
    "blurred": (255, 150, 0),
    "focus drift": (255, 150, 0),
}
_UNUSABLE = (230, 40, 40)  # too few corners, collinear, no board


class ViewerError(CalibcoachError):
    """The viewer could not be started (port taken, rerun executable missing, ...)."""


def _rerun_command() -> list[str]:
    """The rerun binary itself (rerun-sdk bundles it in `rerun_cli`), else the CLI on PATH.

    The `rerun` script in a venv's bin is a Python wrapper that starts the binary as a child:
    starting the binary directly leaves one process to stop, not two.
    """
    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin is not None:
        binary = Path(spec.origin).with_name("rerun.exe" if sys.platform.startswith("win") else "rerun")
        if binary.exists():
            return [str(binary)]
    beside = Path(sys.executable).with_name("rerun")
    if beside.exists():
        return [str(beside)]
    found = shutil.which("rerun")
    return [found] if found else [sys.executable, "-m", "rerun"]


def _wait_for_port(host: str, port: int, process: subprocess.Popen[bytes], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise ViewerError(f"the rerun viewer server exited with code {process.returncode} "
                              f"(is port {port} already in use?)")
        try:
            with socket.create_connection((host, port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise ViewerError(f"the rerun viewer server did not listen on {host}:{port} within {timeout_s:.0f} s")


def ghost_outline_px(camera: CameraModel, target: Target, per_edge: int = 12) -> np.ndarray:
    """(4 * per_edge + 1, 2) float64 closed outline of the board at the target pose, in image pixels.

    The outline's four corners are the target's `outline_px`; points along the edges are projected
    too (through `camera`, the intrinsics the target was made with) so the ghost bends like the board.
    """
    R, _ = cv2.Rodrigues(np.asarray(target.rvec, np.float64).reshape(3))
    corners = np.asarray(target.outline_px, np.float64)
    rays = camera.unproject(corners)
    # the corners' board-frame positions from their camera-frame points on the target's plane
    n, d = R[:, 2], float(R[:, 2] @ np.asarray(target.tvec_m, np.float64))
    pts = rays * (d / (rays @ n))[:, None]
    s = np.linspace(0.0, 1.0, per_edge, endpoint=False)[:, None]
    edges = [pts[k] + s * (pts[(k + 1) % 4] - pts[k]) for k in range(4)]
    outline = camera.project(np.concatenate(edges + [pts[:1]]))
    return np.where(np.isfinite(outline), outline, np.nan)


def _fate_colour(reason: str) -> tuple[int, int, int]:
    return _FATE_COLOURS.get(reason, _UNUSABLE)


class Viewer:
    """One session's Rerun stream: live frames, guidance and progress, then the result."""

    def __init__(self, recording: rr.RecordingStream, rrd_path: Path, *, mode: str, url: str | None = None,
                 notice: str | None = None, server: subprocess.Popen[bytes] | None = None) -> None:
        self.recording = recording
        self.rrd_path = rrd_path
        self.mode = mode
        self.url = url  # web mode: the address to open in a browser (the caller prints it)
        self.notice = notice  # a fallback the caller should tell the person about, e.g. no display
        self._server = server
        self._closed = False
        self._last_log_s: float | None = None  # wall time of the previous log_frame, for processed fps
        self._last_progress: tuple | None = None  # last (accepted, coverage, p95) logged
        self._fps: float | None = None
        self._last_guidance: tuple[object, ...] | None = None
        self._last_target: float | None = None

    # --- opening and closing ----------------------------------------------------------------------
    @classmethod
    def open(cls, mode: str, *, out_dir: Path, bind: str = "127.0.0.1", web_port: int = 9090,
             grpc_port: int = 9876, application_id: str = "calibcoach") -> Viewer:
        """Start the stream: always saving `out_dir/session.rrd`, plus serving or spawning per `mode`."""
        if mode not in MODES:
            raise ViewerError(f"unknown viewer mode {mode!r}; use one of {', '.join(MODES)}")
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        rrd_path = out_dir / "session.rrd"
        rec = rr.RecordingStream(application_id, send_properties=False)
        blueprint = paths.session_blueprint()
        file_sink = rr.FileSink(str(rrd_path))
        host = "127.0.0.1" if bind in ("0.0.0.0", "::") else bind
        proxy = f"rerun+http://{host}:{grpc_port}/proxy"
        if mode == "web":
            cmd = [*_rerun_command(), "--serve-web", "--bind", bind, "--port", str(grpc_port),
                   "--web-viewer-port", str(web_port)]
            with tempfile.TemporaryFile() as errors:  # the server's log, only read if it fails to start
                server = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                          stderr=errors, start_new_session=True)
                try:
                    _wait_for_port(host, grpc_port, server, _SERVER_START_TIMEOUT_S)
                    _wait_for_port(host, web_port, server, _SERVER_START_TIMEOUT_S)
                except ViewerError as exc:
                    _stop(server)
                    errors.seek(0)
                    tail = errors.read().decode(errors="replace").strip().splitlines()[-3:]
                    raise ViewerError(f"{exc}: {' | '.join(tail)}") from None
                except BaseException:
                    _stop(server)
                    raise
            rec.set_sinks(rr.GrpcSink(url=proxy), file_sink, default_blueprint=blueprint)
            url = f"http://{host}:{web_port}/?url={quote(proxy, safe='')}"
            return cls(rec, rrd_path, mode=mode, url=url, server=server)
        if mode == "native":
            notice = None
            if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
                notice = f"no display found (DISPLAY is not set): not opening the viewer; open {rrd_path} later with `rerun`"
            else:
                try:
                    rec.spawn(port=grpc_port, connect=False)
                except Exception as exc:  # noqa: BLE001 - any spawn failure means: save only
                    notice = f"could not start the Rerun viewer ({exc}); saving to {rrd_path} only"
            if notice is None:
                rec.set_sinks(rr.GrpcSink(url=proxy), file_sink, default_blueprint=blueprint)
            else:
                rec.set_sinks(file_sink, default_blueprint=blueprint)
            return cls(rec, rrd_path, mode=mode, notice=notice)
        rec.set_sinks(file_sink, default_blueprint=blueprint)
        return cls(rec, rrd_path, mode=mode)

    def start(self) -> None:
        """Nothing to catch up on: this viewer logs each frame as it comes (see BackgroundViewer.start)."""

    def close(self) -> None:
        """Flush, disconnect (writes the .rrd footer) and stop the web server; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        try:
            self.recording.flush(timeout_sec=10.0)
        finally:
            try:
                self.recording.disconnect()
            finally:
                if self._server is not None:
                    _stop(self._server)
                    self._server = None

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- live ---------------------------------------------------------------------------------
    def log_preview(self, frame: Frame) -> None:
        """Log a captured frame's image only, on capture_time: the live view at the camera's own rate.

        Called from the capture thread for every frame the camera delivers, so the picture stays
        fluid while detection handles fewer frames per second (1080p on two cores); the overlays
        of processed frames follow a frame or two behind. Rerun's time is per thread, so this does
        not disturb the processing thread's timeline.
        """
        self.recording.set_time("capture_time", duration=frame.timestamp_ns * 1e-9)
        self._log_image(frame)

    def _log_image(self, frame: Frame, jpeg: bytes | None = None) -> None:
        jpeg = frame_preview_jpeg(frame) if jpeg is None else jpeg
        if jpeg is not None:
            self.recording.log(paths.IMAGE, rr.EncodedImage(contents=jpeg, media_type="image/jpeg"))

    def log_frame(self, outcome: FrameOutcome, frame: Frame, *, image: bool = True, jpeg: bytes | None = None) -> None:
        """Log one processed frame: preview image, corners by fate, decision, guidance, progress.

        The image goes out every frame (it is the live view) unless `image` is False because the
        capture thread logs previews itself; the coverage boxes and the guidance only when they
        change, since latest-at queries keep showing the last value. Coverage is read from the
        session's own map on the outcome, so custom requirements show as they are. A replay logs
        the same things for all its frames at once (`app/viewer_columns.py`).
        """
        rec = self.recording
        rec.set_time("frame", sequence=frame.index)
        rec.set_time("capture_time", duration=frame.timestamp_ns * 1e-9)
        scale = 1.0 / preview_factor(frame.image_size[0])
        if image:
            self._log_image(frame, jpeg)  # `jpeg`: its preview, already encoded (the frame may hold no pixels then)
        text, level, colour = decision_line(outcome, frame)
        corners = outcome.detection.corners_px
        if corners.shape[0]:
            rec.log(paths.CORNERS, rr.Points2D(corners.astype(np.float32) * scale, colors=colour, radii=CORNER_RADIUS,
                                               labels=[outcome.decision.reason], show_labels=False))
        else:
            rec.log(paths.CORNERS, rr.Points2D(np.zeros((0, 2), np.float32)))
        axes = pose_axes_px(outcome, scale)
        if axes is not None:
            rec.log(paths.AXES, rr.LineStrips2D(axes, colors=AXIS_COLOURS, radii=AXIS_RADIUS, draw_order=AXIS_ORDER)
                    if axes else rr.LineStrips2D([]))
        rec.log(paths.DECISIONS, rr.TextLog(text, level=level, color=colour))
        self.log_changes(outcome, frame, now_s=time.perf_counter())
        arrow = target_arrow_px(outcome, scale)
        if arrow is CLEAR:
            rec.log(paths.TARGET_ARROW, rr.Clear(recursive=False))
        elif arrow is not None:
            rec.log(paths.TARGET_ARROW, rr.Arrows2D(origins=[arrow[0]], vectors=[arrow[1]], colors=[ARROW_COLOUR],
                                                    radii=ARROW_RADIUS, draw_order=ARROW_ORDER))

    def log_changes(self, outcome: FrameOutcome, frame: Frame, *, now_s: float) -> None:
        """What a processed frame logs only when it changed: coverage (on a kept frame), the ghost
        board and its sentence, progress; and the processed frame rate (`now_s`: when the frame was
        processed, perf_counter seconds), every 10th frame. The frame's time must be set."""
        scale = 1.0 / preview_factor(frame.image_size[0])
        if outcome.decision.accepted:
            self._log_coverage(outcome.coverage, frame, scale)
        self._log_guidance(outcome, frame.image_size, scale)
        rec = self.recording
        p = outcome.progress
        if self._last_log_s is not None and now_s > self._last_log_s:
            # frames the pipeline processed per second, smoothed over ~10 frames
            rate = 1.0 / (now_s - self._last_log_s)
            self._fps = rate if self._fps is None else 0.9 * self._fps + 0.1 * rate
            if frame.index % 10 == 0:
                rec.log(paths.PROCESSED_FPS, rr.Scalars(self._fps))
        self._last_log_s = now_s
        # Each log call costs ~0.1 ms; the progress values change only when a frame is kept or a solve
        # ran, and a time series holds its last value in between.
        progress = (p.frames_accepted, round(p.coverage, 4), p.expected_error_px)
        if progress != self._last_progress:
            self._last_progress = progress
            rec.log(paths.ACCEPTED, rr.Scalars(float(p.frames_accepted)))
            rec.log(paths.COVERAGE_PCT, rr.Scalars(100.0 * p.coverage))
            if p.expected_error_px is not None and p.target_px is not None:  # the target beside every E point: a line
                rec.log(paths.EXPECTED_ERROR, rr.Scalars(p.expected_error_px))
                rec.log(paths.ERROR_TARGET, rr.Scalars(p.target_px))

    def _log_coverage(self, coverage: CoverageMap, frame: Frame, scale: float) -> None:
        """Region cells as boxes over the preview: red (empty) to green (requirement met)."""
        fill = coverage.region_fill()
        rows, cols = fill.shape
        w, h = frame.image_size
        cw, ch = w * scale / cols, h * scale / rows
        r, c = np.mgrid[0:rows, 0:cols]
        mins = np.stack([c.ravel() * cw, r.ravel() * ch], axis=1)
        f = fill.ravel()
        colours = np.stack([255 * (1 - f), 200 * f, np.full_like(f, 40), np.full_like(f, 200)], axis=1).astype(np.uint8)
        self.recording.log(paths.COVERAGE, rr.Boxes2D(mins=mins, sizes=np.tile([cw, ch], (f.size, 1)), colors=colours,
                                                      labels=[f"{v * 100:.0f}%" for v in f], radii=1.0,
                                                      show_labels=False, draw_order=5.0))
        # tilt and distance requirements, one bar each, 1.0 = met (the order is TILT_CELLS then DISTANCE_CELLS)
        req = coverage.requirements
        bars = [min(coverage.tilt_counts[c] / req.views_per_tilt_cell, 1.0) for c in TILT_CELLS]
        bars += [min(coverage.distance_counts[c] / req.views_per_distance_cell, 1.0) for c in DISTANCE_CELLS]
        self.recording.log(paths.TILT_DISTANCE, rr.BarChart(np.asarray(bars, np.float32)))

    def _log_guidance(self, outcome: FrameOutcome, size: tuple[int, int], scale: float) -> None:
        """The ghost board where the board should go and the sentence beside it, when the target changes.

        The ghost is the chessboard's outline at the target pose, projected through the current
        intrinsics (perspective and tilt as the person will see the board there), drawn along
        its edges so a fisheye bows it as it bows the board. The arrow to it: `target_arrow_px`.
        """
        g = outcome.guidance
        target = g.target
        rec = self.recording
        key = (g.sentence, g.hint, None if target is None else tuple(np.round(target.outline_px.reshape(-1), 1)))
        if key != self._last_guidance:
            self._last_guidance = key
            hint = f"\n\n**{g.hint}**" if g.hint else ""
            rec.log(paths.GUIDANCE, rr.TextDocument(f"## {g.sentence}\n\n{g.why}{hint}", media_type=rr.MediaType.MARKDOWN))
            if target is None:
                rec.log(paths.TARGET, rr.Clear(recursive=False))
            else:
                ghost = ghost_outline_px(outcome.camera, target) * scale
                rec.log(paths.TARGET, rr.LineStrips2D([ghost.astype(np.float32)], colors=[(0, 200, 255)], radii=3.0,
                                                      labels=[g.sentence], show_labels=True, draw_order=10.0))

    # --- the end -------------------------------------------------------------------------------
    def log_result(self, result: SessionResult, out_dir: Path) -> None:
        """Log the report: verdict, per-frame errors, residual vectors and the report's pictures.

        The pictures are the PNGs the report already wrote to `out_dir` when present (no second
        render); missing ones are drawn here with the same functions.
        """
        rec = self.recording
        cal = result.calibration
        rec.set_time("frame", sequence=max(result.frames_seen - 1, 0))
        rec.log(paths.VERDICT, rr.TextDocument(_verdict_markdown(result), media_type=rr.MediaType.MARKDOWN))
        indices = np.array([v.frame_index for v in cal.views], dtype=np.float64)
        rec.log(paths.PER_FRAME_RMS, rr.BarChart(np.asarray(cal.per_view_rms_px, np.float64), abscissa=indices))
        points = np.concatenate([v.image_points_px for v in cal.views]).astype(np.float32)
        residuals = np.concatenate(cal.residuals_px).astype(np.float32)
        w, h = cal.camera.image_size
        magnify = _arrow_magnification(residuals, w)
        rec.log(f"{paths.RESIDUALS}/frame", rr.LineStrips2D([[[0, 0], [w, 0], [w, h], [0, h], [0, 0]]],
                                                            colors=[(120, 120, 120)], radii=1.0))
        rec.log(paths.RESIDUALS, rr.Arrows2D(origins=points, vectors=residuals * magnify, colors=(230, 60, 40), radii=0.8,
                                             labels=[f"residuals x{magnify:g}"], show_labels=False))
        out_dir = Path(out_dir)
        for entity, name in paths.REPORT_IMAGES.items():
            png = out_dir / name
            if png.exists():
                rec.log(entity, rr.EncodedImage(path=png))
                continue
            picture = _render_picture(name, result)
            if picture is not None:
                ok, data = cv2.imencode(".png", picture)
                if ok:
                    rec.log(entity, rr.EncodedImage(contents=data.tobytes(), media_type="image/png"))


# What every processed frame logs, shared by `Viewer.log_frame` and a replay's columns (app/viewer_columns.py).
CORNER_RADIUS = 3.0
AXIS_COLOURS = [(230, 40, 40), (40, 200, 40), (60, 90, 255)]  # the board's x, y and z (towards the camera)
AXIS_RADIUS, AXIS_ORDER = 2.0, 20.0
ARROW_COLOUR, ARROW_RADIUS, ARROW_ORDER = (0, 200, 255), 2.0, 11.0
CLEAR = object()  # `target_arrow_px`: no target or no pose, the arrow is cleared


def decision_line(outcome: FrameOutcome, frame: Frame) -> tuple[str, str, tuple[int, int, int]]:
    """The decisions log's line for a frame: (text, level, its fate's colour)."""
    decision = outcome.decision
    text = f"frame {frame.index}: {decision.reason}" + (f" ({decision.detail})" if decision.detail else "")
    colour = _fate_colour(decision.reason)
    level = "INFO" if decision.accepted else "WARN" if colour != _UNUSABLE else "DEBUG"
    return text, level, colour


def pose_axes_px(outcome: FrameOutcome, scale: float) -> list[np.ndarray] | None:
    """The board's x, y and z axes from the pose estimate, as three (2, 2) float32 preview-pixel strips;
    [] without a pose, None where they do not project (nothing is logged then)."""
    pose = outcome.pose
    if pose is None:
        return []
    obj = outcome.detection.object_points_m.astype(np.float64)
    origin = obj.mean(axis=0)
    length = 0.5 * float(np.ptp(obj[:, 0]) + np.ptp(obj[:, 1])) / 2 or 0.05
    ends = origin + np.array([[0, 0, 0], [length, 0, 0], [0, length, 0], [0, 0, -length]])
    px = outcome.camera.project(ends, pose.rvec, pose.tvec) * scale
    if not np.all(np.isfinite(px)):
        return None
    return [np.stack([px[0], px[k]]).astype(np.float32) for k in (1, 2, 3)]


def target_arrow_px(outcome: FrameOutcome, scale: float) -> tuple[np.ndarray, np.ndarray] | object | None:
    """(origin, vector) in preview pixels of the arrow from the board's centre now to the target's;
    `CLEAR` without a target or a pose; None when the board's centre is unknown (nothing is logged)."""
    target = outcome.guidance.target
    if target is None or outcome.pose is None:
        return CLEAR
    here = outcome.board_centre_px
    if here is None:
        return None
    there = np.asarray(target.centre_px, np.float64)
    return np.asarray(here, np.float64) * scale, (there - here) * scale


def _stop(server: subprocess.Popen[bytes]) -> None:
    """Stop the web server child (its own process group, started by us), politely then firmly."""
    if server.poll() is not None:
        return
    try:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=5)
    except (ProcessLookupError, subprocess.TimeoutExpired):
        if server.poll() is None:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait(timeout=5)


def _arrow_magnification(residuals: np.ndarray, width: int) -> float:
    """A round factor that makes the 95th-percentile residual about 2% of the image width long."""
    if residuals.size == 0:
        return 1.0
    p95 = float(np.percentile(np.linalg.norm(residuals, axis=1), 95))
    if p95 <= 0:
        return 1.0
    raw = 0.02 * width / p95
    step = 10 ** np.floor(np.log10(raw))
    return float(max(1.0, step * min((1, 2, 5, 10), key=lambda m: abs(m * step - raw))))


def _verdict_markdown(result: SessionResult) -> str:
    v, cal = result.verdict, result.calibration
    w, h = cal.camera.image_size
    lines = [
        f"# {v.grade.upper()}{'' if v.trusted else ' (not trusted)'}",
        "",
        f"- **RMS reprojection error:** {cal.rms_px:.3f} px ({v.rms_grade} on RMS alone)",
        f"- **Frames:** {len(cal.views)} used of {result.frames_seen} seen",
        f"- **Model:** {cal.camera.model} ({result.model_choice.reason})" if result.model_choice.reason
        else f"- **Model:** {cal.camera.model}",
        f"- **Image:** {w}x{h}",
        f"- **Expected projection error E (covered region):** {result.uncertainty.expected_error_px:.3f} px "
        f"(target {result.target_px:.3f} px; corner noise {result.noise_px:.3f} px)",
        f"- **Coverage:** {100 * result.coverage.completeness():.0f}%",
        "",
        "## Why",
        "",
        *(f"- {reason}" for reason in v.reasons),
    ]
    return "\n".join(lines)


def _render_picture(name: str, result: SessionResult) -> np.ndarray | None:
    """Draw one report picture the report did not write (same functions as the report)."""
    from calibcoach.app.outputs import pictures

    cal = result.calibration
    size = cal.camera.image_size
    if name == "coverage.png":
        return pictures.coverage_picture(size, [v.image_points_px for v in cal.views], result.coverage.region_counts,
                                         required=float(result.coverage.requirements.corners_per_region_cell))
    if name == "residuals.png":
        return pictures.residual_map_picture(size, np.concatenate([v.image_points_px for v in cal.views]),
                                             np.concatenate(cal.residuals_px))
    if name == "uncertainty.png":
        return pictures.uncertainty_picture(result.uncertainty, target_px=result.target_px, image_size=size)
    if name == "per_frame_errors.png":
        return pictures.per_frame_error_picture([v.frame_name or str(v.frame_index) for v in cal.views],
                                                cal.per_view_rms_px)
    if name == "board_residuals.png" and result.residual_structure is not None and result.residual_structure.board.judged:
        return pictures.board_pattern_picture(result.residual_structure, result.board)
    if name == "undistorted_check.png" and result.check_image is not None:
        return pictures.undistorted_check_picture(result.check_image, cal.camera)
    return None
