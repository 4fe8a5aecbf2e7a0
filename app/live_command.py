"""`calibcoach live` and `calibcoach devices`: cameras in front of the session (see live.py)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from calibcoach.app.assistant import step_record
from calibcoach.app.commands import (
    board_for_source,
    error_words,
    fov_hint,
    keep_serving,
    open_viewer,
    session_settings,
)
from calibcoach.app.live import LiveStats, PacedSource, run_live
from calibcoach.app.outputs.report import untrusted_name, write_session_outputs
from calibcoach.app.progress import SolveStages
from calibcoach.app.session import FrameOutcome
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.base import Frame, FrameSource
from calibcoach.drivers.errors import CalibcoachError
from calibcoach.drivers.replay import open_source


def open_live_source(args: argparse.Namespace) -> tuple[FrameSource, Any | None]:
    """(source, focus controller or None) for v4l2:..., depthai[:ID] or any replay source (paced)."""
    spec = str(args.source)
    if spec == "auto":
        spec = first_camera() or args.fallback or ""
        if not spec:
            raise CalibcoachError("--source auto found no camera; attach one, or pass --fallback with a recording to run on")
        print(f"calibcoach: --source auto chose {spec}", file=sys.stderr)
    if spec.startswith("v4l2:") or spec.startswith("/dev/video"):
        from calibcoach.drivers.v4l2 import V4L2Camera, parse_v4l2_target

        camera = V4L2Camera(parse_v4l2_target(spec), size=args.size, fps=args.fps)
        return camera, camera.focus
    if spec == "depthai" or spec.startswith("depthai:"):
        from calibcoach.drivers.oak import DepthAICamera, parse_depthai_target

        camera = DepthAICamera(parse_depthai_target(spec), size=args.size or (1920, 1080), fps=args.fps or 30.0,
                               lens_position=args.lens_position)
        return camera, camera.focus
    return PacedSource(open_source(spec), speed=args.speed), None


def first_camera() -> str | None:
    """The first usable camera as a --source spec: V4L2 devices first, then DepthAI; None if none."""
    from calibcoach.drivers.oak import list_depthai_devices
    from calibcoach.drivers.v4l2 import list_v4l2_devices

    for device in list_v4l2_devices():
        if "error" not in device:
            return f"v4l2:{device['path']}"
    for device in list_depthai_devices(timeout_s=2.0):
        return f"depthai:{device['device_id']}"
    return None


def lock_focus(args: argparse.Namespace, source: FrameSource, focus: Any | None) -> dict[str, float]:
    """Lock focus before the first frame counts; returns the controls read back (for drift checks)."""
    if args.focus_control:
        from calibcoach.drivers.visca import ViscaCamera, parse_target

        port, baud = parse_target(args.focus_control)
        with ViscaCamera(port, baud=baud) as camera:
            position = camera.lock_focus(args.lens_position)
        print(f"calibcoach: focus locked through {args.focus_control} at {position} (0x{position:04X}), read back",
              file=sys.stderr)
        return {"visca_focus_position": float(position)}
    if focus is not None:
        try:
            locked = focus.lock(args.lens_position)
        except CalibcoachError as exc:
            if not args.allow_autofocus:
                raise
            print(f"calibcoach: warning: focus not locked ({exc}); continuing because of --allow-autofocus",
                  file=sys.stderr)
            return {}
        # V4L2 reads back several controls (a dict); DepthAI reports one lens position per frame
        values = dict(locked) if isinstance(locked, dict) else {"lens_position": locked}
        print(f"calibcoach: focus locked, read back: {values}", file=sys.stderr)
        return {k: float(v) for k, v in values.items()}
    if source.info.kind in ("v4l2", "depthai") and not args.allow_autofocus:
        raise CalibcoachError(
            "this camera offers no focus control, so focus cannot be locked; pass --focus-control visca:PORT, "
            "or --allow-autofocus if the lens is fixed-focus (an autofocus change invalidates the calibration)"
        )
    print(f"calibcoach: {source.info.kind} source: focus is whatever was captured; nothing to lock", file=sys.stderr)
    return {}


class LiveStatus:
    """One status line for the person at the camera: progress, rate, and what to do next.

    A hint about the capture itself (frames smeared or soft, the board off its spec) gets a line of
    its own, once each time it changes: it is what to fix before following the next pose.
    """

    def __init__(self, *, enabled: bool) -> None:
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self._last = 0.0
        self._said = ""
        self._hinted = ""

    def __call__(self, outcome: FrameOutcome, frame: Frame, stats: LiveStats) -> None:
        if not self.enabled:
            return
        hint = outcome.guidance.hint
        if hint and hint != self._hinted:
            print(("\r" + " " * 200 + "\r" if self.tty else "") + f"calibcoach: {hint}", file=sys.stderr, flush=True)
        self._hinted = hint
        now = time.perf_counter()
        guidance = outcome.guidance.sentence
        if now - self._last < (0.2 if self.tty else 3.0) and guidance == self._said:
            return
        self._last = now
        p = outcome.progress
        line = (f"kept {p.frames_accepted}  coverage {p.coverage * 100:3.0f}%  expected error {error_words(p)}"
                f"  {stats.processed_fps:4.1f} fps  dropped {stats.frames_dropped}  last: {outcome.decision.reason}")
        if self.tty:
            print("\r" + f"{line} | {guidance}"[:200].ljust(200), end="", file=sys.stderr, flush=True)
        else:
            print(line if guidance == self._said else f"{line}\n  next: {guidance}", file=sys.stderr, flush=True)
        self._said = guidance

    def close(self) -> None:
        if self.enabled and self.tty:
            print(file=sys.stderr)


def open_guidance_jsonl(path: Path | None):
    """The --guidance-jsonl file, opened for line-buffered writing (None when not asked for)."""
    if path is None:
        return None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return path.open("w", encoding="utf-8")
    except OSError as exc:
        raise CalibcoachError(f"cannot write --guidance-jsonl {path} ({exc.strerror}); pass a writable path") from None


def live_command(args: argparse.Namespace, board: BoardSpec, *, argv: list[str]) -> int:
    if args.record and args.resume:
        raise CalibcoachError("pass either --record DIR (a new recording) or --resume DIR (continue one), not both")
    source, focus = open_live_source(args)
    info = source.info
    board = board_for_source(args, board, None if info.board is None else dict(info.board))
    print(f"calibcoach: live on {info.description}; board {board.describe()}", file=sys.stderr)
    with source, open_viewer(args) as viewer:
        locked = lock_focus(args, source, focus)
        status = LiveStatus(enabled=not args.quiet)
        steps = open_guidance_jsonl(args.guidance_jsonl)

        def on_outcome(outcome: FrameOutcome, frame: Frame, stats: LiveStats) -> None:
            status(outcome, frame, stats)
            viewer.log_frame(outcome, frame, image=False)  # the capture thread logs every image
            if steps is not None:
                steps.write(json.dumps(step_record(outcome, frame.timestamp_ns)) + "\n")
                steps.flush()  # a program reading along sees each step as it is decided

        try:
            session, stats = run_live(source, board, session_settings(args, info, live=True),
                                      record=args.record, resume=args.resume, locked_controls=locked, on_outcome=on_outcome,
                                      on_capture=viewer.log_preview)
        finally:
            status.close()
            if steps is not None:
                steps.close()
        return _finish_live(args, argv, info, session, stats, locked, viewer)


def _finish_live(args: argparse.Namespace, argv: list[str], info: Any, session: Any, stats: LiveStats,
                 locked: dict[str, float], viewer: Any) -> int:
    why = ("Ctrl-C" if stats.interrupted else "stop rule met"
           if stats.stopped_early else "end of source")
    print(f"calibcoach: processed {stats.frames_processed} frames ({stats.processed_fps:.1f} fps, {stats.frames_dropped} "
          f"dropped by the capture thread) in {stats.seconds:.1f} s: {why}", file=sys.stderr)
    if stats.resumed_frames:
        print(f"calibcoach: {stats.resumed_frames} frames came from the resumed recording", file=sys.stderr)
    if stats.focus_drift:
        print(f"calibcoach: acceptance stopped: {stats.focus_drift}; lock focus again and continue with --resume",
              file=sys.stderr)
    if session is None:
        raise CalibcoachError(f"{info.description} delivered no frames; check the camera and the --source")
    with SolveStages(enabled=not args.quiet) as stages:
        result = session.finish(on_stage=stages)
        stages("outputs")
        written = write_session_outputs(
            args.out, result, source_info=info, command_line=argv, accept_partial=args.accept_partial,
            replay_seconds=stats.seconds, frames_read=stats.frames_processed, stopped_early=stats.stopped_early,
            lens_state={**dict(info.controls), **locked},
        )
    trusted = bool(result.verdict.trusted)
    lens = int(locked["lens_position"]) if "lens_position" in locked else None
    if info.kind == "depthai" and (trusted or args.accept_partial):
        from calibcoach.drivers.oak import write_depthai_calibration

        name = "depthai_calibration.json" if trusted else untrusted_name("depthai_calibration.json")
        written.append(write_depthai_calibration(Path(args.out) / name, result.calibration.camera, lens_position=lens,
                                                 untrusted=not trusted))
    if args.write_to_device and info.kind == "depthai" and trusted:
        from calibcoach.drivers.oak_device import flash_intrinsics

        backup = flash_intrinsics(info.camera_id or None, result.calibration.camera, lens_position=lens,
                                  backup_path=Path(args.out) / "depthai_calibration_before.json")
        print(f"calibcoach: flashed CAM_A intrinsics to the device; its previous calibration is in {backup}")
    elif args.write_to_device:
        # never flashed without a trusted result, --accept-partial or not: the EEPROM outlives this run
        why = "the calibration is not trusted" if not trusted else f"the source is {info.kind}, not a DepthAI camera"
        print(f"calibcoach: --write-to-device flashes trusted DepthAI calibrations only; {why}, nothing was flashed",
              file=sys.stderr)
    viewer.log_result(result, Path(args.out))
    written.append(Path(args.out) / "session.rrd")
    cal = result.calibration
    print(f"{result.verdict.grade.upper()}: {cal.camera.model} model, RMS {cal.rms_px:.3f} px on {len(cal.views)} frames; "
          f"wrote {', '.join(p.name for p in written)} to {args.out}")
    for reason in result.verdict.reasons:
        print(f"  - {reason}")
    hint = fov_hint(cal.camera, args.fov)
    if hint:
        print(f"calibcoach: {hint}", file=sys.stderr)
    keep_serving(viewer)
    return 0 if result.verdict.trusted else 3


def devices_command(args: argparse.Namespace) -> int:
    """Every V4L2 and DepthAI camera with its modes and focus/exposure/white-balance controls."""
    from calibcoach.drivers.oak import list_depthai_devices
    from calibcoach.drivers.v4l2 import list_v4l2_devices

    cameras = [("v4l2", d) for d in list_v4l2_devices()] + [("depthai", d) for d in list_depthai_devices(timeout_s=2.0)]
    if not cameras:
        print("no cameras found (no V4L2 /dev/video* capture device, no DepthAI device)")
        return 0
    for kind, device in cameras:
        name = device.get("path") or device.get("device_id") or device.get("id")
        print(f"{kind}: {name}  {device.get('name') or device.get('card') or ''}")
        for key, value in device.items():
            if key not in ("path", "device_id", "id", "name", "card"):
                print(f"    {key}: {value}")
    return 0
