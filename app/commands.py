"""What each CLI command does, between argument parsing (cli.py) and the stages."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from calibcoach.app.progress import SolveStages, terminal_bar
from calibcoach.app.scan_stream import ScanStream
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.base import Frame, FrameSource, SourceInfo
from calibcoach.drivers.errors import CalibcoachError
from calibcoach.drivers.replay import open_source

# The session, the final solve and the outputs (~0.15 s of imports) are imported where they are
# used, so that `calibrate` can start scanning footage before they load (app/scan_stream.py).
if TYPE_CHECKING:
    from calibcoach.app.session import FrameOutcome, Progress, SessionSettings
    from calibcoach.drivers.lens import CameraModel

_SKIPPED_SHOWN = 10  # unreadable frames named one per line at the end of a replay; the rest counted


class ProgressLine:
    """A progress bar of frames read on a terminal (`progress.py`); a line every few seconds otherwise."""

    def __init__(self, total: int | None, *, enabled: bool) -> None:
        self.total = total
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self._last = 0.0
        self._start = time.perf_counter()
        self._last_guidance = ""
        self._bar = terminal_bar(enabled=enabled, total=total or None, desc="reading", unit="frame")

    def __call__(self, outcome: FrameOutcome, frame: Frame) -> None:
        if not self.enabled:
            return
        if self._bar is not None:
            p = outcome.progress
            read = outcome.frame_index + 1  # tracked frames of a hold are not decided one by one: its position, not a count
            if self._bar.total is not None and read > self._bar.total:  # a video whose header undercounts
                self._bar.total = read
            self._bar.update(max(0, read - self._bar.n))
            self._bar.set_postfix_str(f"kept {p.frames_accepted}, coverage {p.coverage * 100:.0f}%, "
                                      f"E {error_words(p)}, last: {outcome.decision.reason}", refresh=False)
            return
        now = time.perf_counter()
        if now - self._last < (0.1 if self.tty else 5.0) and not outcome.progress.done:
            return
        self._last = now
        p = outcome.progress
        fps = p.frames_seen / max(now - self._start, 1e-6)
        of = f"/{self.total}" if self.total else ""
        line = (f"frame {outcome.frame_index + 1}{of}  kept {p.frames_accepted}  coverage {p.coverage * 100:3.0f}%  "
                f"expected error {error_words(p)}  {fps:4.0f} fps  last: {outcome.decision.reason}")
        if self.tty:
            print("\r" + line[:160].ljust(160), end="", file=sys.stderr, flush=True)
        else:
            print(line, file=sys.stderr, flush=True)
        if outcome.guidance.target is not None and outcome.guidance.sentence != self._last_guidance and not self.tty:
            self._last_guidance = outcome.guidance.sentence
            print(f"  next: {outcome.guidance.sentence}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif self.enabled and self.tty:
            print(file=sys.stderr)


def error_words(p: Progress) -> str:
    """'0.041/0.030 px' (E against its target), or '--' before the first solve."""
    if p.expected_error_px is None or p.target_px is None:
        return "--"
    return f"{p.expected_error_px:.3f}/{p.target_px:.3f} px"


def photos_within_budget(args: argparse.Namespace, info: SourceInfo, *, live: bool = False) -> bool:
    """A folder handed to `calibrate` (a set of photos) that fits the frame budget: chosen by a
    person, so every usable photo is kept, and each is detected in full."""
    return not live and info.kind == "folder" and (info.frame_count or 0) <= args.max_frames


def session_settings(args: argparse.Namespace, info: SourceInfo, *, live: bool) -> SessionSettings:
    """The session's settings from the command line; live and replay of its recording must agree."""
    from calibcoach.app.session import SessionSettings
    from calibcoach.coverage.select import SelectorSettings

    photos = not live and info.kind == "folder"  # a folder handed to `calibrate` is a set of photos
    guess = {} if getattr(args, "fov", None) is None else {"hfov_guess_deg": args.fov}
    return SessionSettings(
        **guess,
        model=args.model,
        selector=SelectorSettings(max_frames=args.max_frames, keep_all_usable=photos_within_budget(args, info, live=live)),
        stop_when_done=not args.no_stop,
        use_motion_gate=not photos,
        corners=args.corners,
    )


def fov_hint(camera: CameraModel, given_deg: float | None) -> str:
    """A sentence suggesting --fov for the next capture where the solved lens is far from the guess ("" if not).

    The guess sets the first guidance's ranges (`SessionSettings.hfov_guess_deg`, `lens_guess`): a
    focal length more than 25% from the guess's asks for the board noticeably too near or too far
    at first. The value suggested is the guess with this lens's focal length (`guess_for_focal`: a
    distortion-free lens's field of view, an equidistant one for a fisheye), so passing it silences
    the hint; for a strongly distorted wide lens that is less than its datasheet says.
    """
    from calibcoach.app.session_types import SessionSettings, guess_for_focal, lens_guess

    guess = SessionSettings().hfov_guess_deg if given_deg is None else given_deg
    assumed = lens_guess(camera.image_size, guess).fx
    if not (math.isfinite(camera.fx) and camera.fx > 0) or abs(math.log(camera.fx / assumed)) < math.log(1.25):
        return ""
    same_focal = guess_for_focal(camera.image_size, camera.fx, fisheye=camera.model == "fisheye")
    return (f"the first guidance assumed a {guess:.0f} deg lens (f {assumed:.0f} px) and this one has f {camera.fx:.0f} px; "
            f"pass --fov {same_focal:.0f} next time and it fits the lens from the first frame")


def board_for_source(args: argparse.Namespace, board: BoardSpec, stored: dict | None) -> BoardSpec:
    """The board of a source that carries its own (a recording), with explicit options overriding it.

    Each of --squares, --square-mm, --marker-mm, --dictionary, --legacy, --inverted given on the
    command line replaces that field of the stored board, with a notice; --board replaces it whole.
    """
    if not stored or args.board:
        return board
    values = BoardSpec.from_dict(dict(stored)).to_dict()
    explicit = {"squares_x": board.squares_x if args.squares else None, "squares_y": board.squares_y if args.squares else None,
                "square_mm": args.square_mm, "marker_mm": args.marker_mm,
                "dictionary": board.dictionary if args.dictionary else None,
                "legacy": True if args.legacy else None, "inverted": True if args.inverted else None}
    changed = {k: v for k, v in explicit.items() if v is not None and v != values.get(k)}
    if changed:
        said = ", ".join(f"{k} {values.get(k)!r} -> {v!r}" for k, v in changed.items())
        print(f"calibcoach: the recording's board overridden by the command line: {said}", file=sys.stderr)
    values.update(changed)
    return BoardSpec.from_dict(values)


def calibrate_command(args: argparse.Namespace, board: BoardSpec, *, argv: list[str]) -> int:
    source = open_source(args.source)
    info = source.info
    board = board_for_source(args, board, None if info.board is None else dict(info.board))  # a recording knows its board
    print(f"calibcoach: {info.description}; board {board.describe()}", file=sys.stderr)
    # Footage is scanned from here on, in a process of its own, while the session's modules load
    # (app/scan_stream.py). A small folder of photos is kept whole; a long sequence tracks its held
    # boards unless asked not to.
    scan = ScanStream(source, board, workers=args.workers, every_frame=args.every_frame or photos_within_budget(args, info))
    try:
        return _replay(args, argv, source, board, scan)
    finally:
        scan.close()


def _replay(args: argparse.Namespace, argv: list[str], source: FrameSource, board: BoardSpec, scan: ScanStream) -> int:
    from calibcoach.app.replay import run_replay

    info = source.info
    settings = session_settings(args, info, live=False)
    with open_replay_viewer(args) as viewer:
        progress = ProgressLine(info.frame_count, enabled=not args.quiet)

        def on_outcome(outcome: FrameOutcome, frame: Frame) -> None:
            progress(outcome, frame)
            viewer.log_frame(outcome, frame)

        with source:
            try:
                session, stats = run_replay(source, board, settings, on_outcome=on_outcome, scan=scan)
            finally:
                progress.close()
        return _finish_replay(args, argv, source, info, session, stats, viewer)


def open_viewer(args: argparse.Namespace):
    """The Rerun sink for this run (always saving session.rrd); prints where to look."""
    from calibcoach.app.viewer import Viewer

    viewer = Viewer.open(args.viewer, out_dir=Path(args.out), bind=args.bind, web_port=args.web_port, grpc_port=args.grpc_port)
    if viewer.url:
        print(f"calibcoach: viewer at {viewer.url}", file=sys.stderr)
    if viewer.notice:
        print(f"calibcoach: {viewer.notice}", file=sys.stderr)
    return viewer


def open_replay_viewer(args: argparse.Namespace):
    """A replay that only saves session.rrd logs in a child process (app/viewer_process.py), or on a
    thread of its own where no child can be started; one shown live logs directly."""
    if args.viewer != "none":
        return open_viewer(args)
    from calibcoach.app.scan_process import fork_available
    from calibcoach.app.viewer_process import ProcessViewer
    from calibcoach.app.viewer_thread import BackgroundViewer

    Path(args.out).mkdir(parents=True, exist_ok=True)
    if fork_available():
        return ProcessViewer(Path(args.out))

    def open_saving_only():
        from calibcoach.app.viewer import Viewer  # imported on the logging thread: rerun takes ~0.8 s to load

        return Viewer.open("none", out_dir=Path(args.out))

    return BackgroundViewer(open_saving_only)


def keep_serving(viewer) -> None:
    """After a replay, leave the web viewer up for the person who asked for it, until Ctrl-C."""
    if viewer.url and sys.stdin.isatty():
        print(f"calibcoach: the viewer stays at {viewer.url}; press Ctrl-C to quit", file=sys.stderr)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass


def _finish_replay(args, argv, source, info, session, stats, viewer) -> int:
    from calibcoach.app.outputs.report import write_session_outputs

    if stats.variant_found and stats.variant_found != "standard pattern":
        print(f"calibcoach: detected {stats.variant_found}", file=sys.stderr)
    for skipped in source.skipped[:_SKIPPED_SHOWN]:
        name = f" ({skipped.name})" if skipped.name else ""  # files have names, video frames only their index
        print(f"calibcoach: skipped frame {skipped.index}{name}: {skipped.reason}", file=sys.stderr)
    if len(source.skipped) > _SKIPPED_SHOWN:
        print(f"calibcoach: ... and {len(source.skipped) - _SKIPPED_SHOWN} more frames skipped", file=sys.stderr)
    why_stopped = (
        "interrupted: solving with the frames kept so far" if stats.interrupted
        else "stop rule met (coverage complete, uncertainty on target)" if stats.stopped_early
        else "end of source"
    )
    tracked = (f", {stats.tracked} of them held boards tracked from the frame before (--every-frame detects each anew)"
               if stats.tracked else "")
    print(f"calibcoach: read {stats.frames_read} frames in {stats.seconds:.1f} s ({why_stopped}{tracked}); "
          f"kept {len(session.views)}; solving...", file=sys.stderr)
    viewer.start()  # a saving-only logger (its own process) imports rerun and catches up now, beside the final solve
    with SolveStages(enabled=not args.quiet) as stages:
        result = session.finish(on_stage=stages)
        rejected = ", ".join(f"{n} {reason}" for reason, n in sorted(result.rejections.items(), key=lambda kv: -kv[1])
                             if n and reason != "accepted")
        added, reserve = session.budget_fill
        if result.smeared_left_out:
            stages.say(f"calibcoach: {result.exposure}; {result.smeared_left_out} usable frames left out as smeared over "
                       f"{session.settings.selector.max_solve_smear_px:.1f} px in it")
        stages.say(f"calibcoach: rejected {rejected or 'nothing'}; the final solve also took {added} of {reserve} usable "
                   "frames held in reserve (poses of their own first, then repeats of every hold alike)")
        stages("outputs")
        written = write_session_outputs(
            args.out, result, source_info=info, command_line=argv, accept_partial=args.accept_partial,
            replay_seconds=stats.seconds, frames_read=stats.frames_read, stopped_early=stats.stopped_early,
        )
        viewer.log_result(result, Path(args.out))
    written.append(Path(args.out) / "session.rrd")
    cal, verdict = result.calibration, result.verdict
    K = cal.camera.camera_matrix
    print(
        f"{verdict.grade.upper()}: {cal.camera.model} model, RMS {cal.rms_px:.3f} px on {len(cal.views)} frames, "
        f"fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f}, "
        f"expected error E {result.uncertainty.expected_error_px:.3f} px where the board was seen "
        f"(target {result.target_px:.3f} px), coverage {result.coverage.completeness() * 100:.0f}%"
    )
    for reason in verdict.reasons:
        print(f"  - {reason}")
    print(f"wrote {', '.join(p.name for p in written)} to {args.out}")
    keep_serving(viewer)
    if not verdict.trusted:
        if not args.accept_partial:
            print("no camera files (camera_matrix.npy, dist_coeffs.npy, calibration.yaml, camera_info.yaml) were written: "
                  "a refused calibration must not be loaded as a camera (--accept-partial writes them as *_untrusted)")
        return 3
    return 0


def scale_command(args: argparse.Namespace) -> int:
    from calibcoach.app.outputs.camera_reader import load_trust
    from calibcoach.app.outputs.files import load_camera, write_npy, write_opencv_yaml, write_ros_camera_info

    camera = load_camera(args.calibration)
    trusted, reasons = load_trust(args.calibration)
    if not trusted and not args.accept_partial:
        why = f" ({reasons[0]})" if reasons else ""
        raise CalibcoachError(f"{args.calibration} is a calibration calibcoach refused{why}; capture again, or pass "
                              "--accept-partial to scale it anyway (the outputs are then named *_untrusted)")
    if args.to is None and args.crop is None:
        raise CalibcoachError("scale needs --to WxH and/or --crop x,y,w,h")
    try:
        if args.crop:
            camera = camera.cropped(*args.crop)
        if args.to:
            camera = camera.resized(args.to)
    except ValueError as exc:
        raise CalibcoachError(f"{exc}; pass a crop inside the image and a size of the same aspect") from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    suffix = "" if trusted else "_untrusted"
    extra: dict[str, object] = {"derived_from": str(args.calibration), "trusted": trusted}
    if not trusted:
        extra["untrusted_because"] = reasons or ["the source calibration was not trusted"]
    written = [*write_npy(out, camera, suffix=suffix),
               write_opencv_yaml(out / f"calibration{suffix}.yaml", camera, rms_px=None, extra=extra),
               write_ros_camera_info(out / f"camera_info{suffix}.yaml", camera, camera_name="calibcoach",
                                     untrusted_because=[] if trusted else (reasons or ["the source calibration was not trusted"]))]
    K = camera.camera_matrix
    print(f"{camera.image_size[0]}x{camera.image_size[1]}: fx {K[0, 0]:.3f} fy {K[1, 1]:.3f} cx {K[0, 2]:.3f} cy {K[1, 2]:.3f}; "
          f"distortion unchanged; wrote {', '.join(p.name for p in written)} to {out}")
    return 0


def focus_command(args: argparse.Namespace) -> int:
    """`calibcoach focus TARGET --lock [--position N] | --unlock | --status`, read back every time."""
    if args.position is not None and not args.lock:
        raise CalibcoachError("--position goes with --lock")
    target = args.target
    if target.startswith("visca:"):
        return _focus_visca(args)
    if target.startswith("v4l2:") or target.startswith("/dev/video"):
        return _focus_v4l2(args)
    if target == "depthai" or target.startswith("depthai:"):
        return _focus_depthai(args)
    raise CalibcoachError(f"unknown focus target {target!r}; pass v4l2:/dev/videoN, v4l2:N, depthai[:ID] or visca:PORT[@BAUD]")


def _focus_visca(args: argparse.Namespace) -> int:
    from calibcoach.drivers.visca import ViscaCamera, parse_target

    port, baud = parse_target(args.target)
    with ViscaCamera(port, baud=baud) as camera:
        if args.lock:
            position = camera.lock_focus(args.position)
            print(f"{args.target}: focus locked (manual) at {position} (0x{position:04X}), read back from the camera")
        elif args.unlock:
            camera.unlock_focus()
            print(f"{args.target}: autofocus on, read back from the camera")
        status = camera.status()
    print(f"{args.target}: focus {status['focus_mode']}, focus position {status['focus_position']} "
          f"(0x{status['focus_position']:04X}), zoom position {status['zoom_position']} (0x{status['zoom_position']:04X})")
    return 0


def _focus_v4l2(args: argparse.Namespace) -> int:
    # UVC cameras keep their controls until unplugged, so a lock set here holds for later captures
    from calibcoach.drivers.v4l2 import V4L2FocusControl, open_v4l2_device, parse_v4l2_target

    device = open_v4l2_device(parse_v4l2_target(args.target))
    try:
        control = V4L2FocusControl(device)
        if args.lock:
            print(f"{args.target}: focus locked, read back: {control.lock(args.position)}")
        elif args.unlock:
            print(f"{args.target}: autofocus restored, read back: {control.unlock()}")
        print(f"{args.target}: {control.status()}")
    finally:
        device.close()
    return 0


def _focus_depthai(args: argparse.Namespace) -> int:
    if args.lock or args.unlock:
        raise CalibcoachError(
            "an OAK camera applies focus controls only while a pipeline runs, so a lock cannot outlive this command; "
            "lock it for the capture with `calibcoach live --source depthai --lens-position N` "
            "(`calibcoach focus depthai --status` reads the current lens position)"
        )
    from calibcoach.drivers.oak import DepthAICamera, parse_depthai_target

    with DepthAICamera(parse_depthai_target(args.target)) as camera:
        print(f"{args.target}: {camera.focus.status()}")
    return 0
