"""The `calibcoach` command line. The only place that prints errors and chooses exit codes.

Exit codes: 0 success, 2 a problem the user can fix (the message says how), 3 a calibration was
computed but is not trustworthy (coverage or uncertainty insufficient), 130 interrupted.
"""

from __future__ import annotations

import argparse
import ctypes
import multiprocessing
import os
import sys
import threading
from pathlib import Path

# NumPy's OpenBLAS starts a worker thread per core that spins for a while after every BLAS call.
# calibcoach's matrices are small (9-15 intrinsics, 6-parameter poses), and it keeps both cores
# busy with threads and processes of its own, so those spins only took CPU from them: a replay
# of a 784-frame folder used 0.28 s less CPU (9.27 -> 8.99 s) and ran 1.5% faster (6 paired
# runs, all faster) with one BLAS thread, with the same results to 1e-9 on five renders. Set
# before NumPy loads (OpenBLAS reads it once); a value the user set is kept.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _keep_freed_frames_for_reuse() -> None:
    """Let glibc's malloc keep freed frame-sized blocks for reuse instead of giving them back.

    A replay allocates a few frame-sized arrays a frame (the inflated rows and the decoded image in
    the scan's process, each frame's copy out of the shared ring here), 0.9 MB each at 720p grey,
    and frees them in bursts (a hold's frames once it is judged). glibc gives freed memory at the
    top of its heap back to the kernel once a few MB are free there, and maps larger blocks anew,
    so those frames kept coming back as fresh pages, each faulted in and zeroed by the kernel
    (225 a frame). Blocks under 32 MB now come from the heap and up to 256 MB of it is kept once
    freed: a 784-frame 720p replay made ~104,000 page faults instead of ~184,000, its processes
    used ~0.2 s less system time, and it ran 2-4% faster (paired runs; same decisions and cameras)
    for ~25 MB more peak memory. Set before NumPy and OpenCV allocate; forked children inherit it.
    CALIBCOACH_MALLOPT=0 leaves glibc's own policy (a small device that needs the memory back).
    Linux only, and a no-op where the C library ignores it (musl).
    """
    if os.environ.get("CALIBCOACH_MALLOPT") == "0" or not sys.platform.startswith("linux"):
        return
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):
        return
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
    mallopt(m_mmap_threshold, 32 << 20)  # glibc's largest on 64-bit: blocks up to it come from the heap
    mallopt(m_trim_threshold, 256 << 20)


_keep_freed_frames_for_reuse()

from calibcoach.coverage.board import BoardSpec  # noqa: E402 - after the BLAS setting above
from calibcoach.drivers.errors import BoardError, CalibcoachError  # noqa: E402


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 1280x720, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"sizes must be positive, got {text!r}")
    return w, h


def _whole_number(text: str, example: str) -> int:
    """An option's whole number, or argparse's error naming what was expected (`example`: "60 frames")."""
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number such as {example}, got {text!r}") from None


def _frame_budget(text: str) -> int:
    """--max-frames: a calibration needs at least MIN_VIEWS_TO_STOP distinct frames to be trusted."""
    value = _whole_number(text, "60 frames")
    if value < 15:
        raise argparse.ArgumentTypeError(f"{value} frames cannot make a trusted calibration; pass at least 15 (default 60)")
    return value


def usable_cores() -> int:
    """The cores this process may run on (its affinity mask where the OS has one, e.g. under taskset or a container)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def _workers(text: str) -> int:
    """--workers: the scan's detection threads; each holds a detector and a frame (~1 MB at 720p)."""
    value = _whole_number(text, "2 threads")
    if not 1 <= value <= 64:
        raise argparse.ArgumentTypeError(f"{value} detection threads: pass 1 to 64 (default: the {usable_cores()} usable cores)")
    return value


_FOV_HELP = ("the lens's rough horizontal field of view in degrees, from its datasheet: the guidance and the fisheye-aware "
             "re-detection start from it until the first solve (default 70; 120 or more: a fisheye)")


def _field_of_view(text: str) -> float:
    """--fov: a lens's horizontal field of view in degrees, as a datasheet gives it."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected the lens's horizontal field of view in degrees such as 150, got {text!r}") from None
    if not 10.0 <= value <= 240.0:
        raise argparse.ArgumentTypeError(f"{value:g} deg is no lens's horizontal field of view; pass 10-240 (a fisheye: 120 or more)")
    return value


def _crop(text: str) -> tuple[int, int, int, int]:
    try:
        x, y, w, h = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected x,y,width,height such as 0,60,1280,600, got {text!r}") from None
    return x, y, w, h


def add_board_arguments(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("board (default: 8x11 squares, DICT_5X5_100, 30.01 mm squares, 22.01 mm markers)")
    g.add_argument("--board", type=Path, help="TOML file describing the board (squares_x, squares_y, square_mm, marker_mm, dictionary)")
    g.add_argument("--squares", type=_size, help="squares across x down, e.g. 8x11")
    g.add_argument("--square-mm", type=float, help="measured square side in mm")
    g.add_argument("--marker-mm", type=float, help="measured marker side in mm")
    g.add_argument("--dictionary", help="ArUco dictionary, e.g. DICT_5X5_100")
    g.add_argument("--legacy", action="store_true", default=None, help="board printed by OpenCV < 4.6 (default: detected)")
    g.add_argument("--inverted", action="store_true", default=None, help="white-on-black print (default: detected)")


def add_viewer_arguments(parser: argparse.ArgumentParser, *, default: str) -> None:
    g = parser.add_argument_group("viewer (the session is always saved as session.rrd in --out)")
    g.add_argument("--viewer", choices=("web", "native", "none"), default=default,
                   help=f"web: serve Rerun's web viewer and print its URL; native: the desktop viewer (default {default})")
    g.add_argument("--no-viewer", dest="viewer", action="store_const", const="none", help="same as --viewer none")
    g.add_argument("--bind", default="127.0.0.1", help="address the web viewer listens on (default 127.0.0.1)")
    g.add_argument("--web-port", type=int, default=9090, help="web viewer port (default 9090)")
    g.add_argument("--grpc-port", type=int, default=9876, help="Rerun data port (default 9876)")


def board_from_args(args: argparse.Namespace) -> BoardSpec:
    base = BoardSpec.from_toml(args.board) if args.board else BoardSpec()
    values = base.to_dict()
    if args.squares:
        values["squares_x"], values["squares_y"] = args.squares
    if args.square_mm is not None:
        values["square_mm"] = args.square_mm
        if args.marker_mm is None and not args.board:
            raise BoardError("--square-mm without --marker-mm: pass the measured marker size too (e.g. --marker-mm 22.01)")
    if args.marker_mm is not None:
        values["marker_mm"] = args.marker_mm
    if args.dictionary:
        values["dictionary"] = args.dictionary
    if args.legacy:
        values["legacy"] = True
    if args.inverted:
        values["inverted"] = True
    return BoardSpec.from_dict(values)


def add_corner_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--corners", choices=("masked", "opencv"), default="masked",
                        help="corners of the final solve: OpenCV's fitted to the checker pattern's point symmetry "
                             "(default, named for the masked refinement it replaced; a lens of 90 deg or more, or a fisheye, "
                             "keeps OpenCV's), or OpenCV's as detected")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="calibcoach",
        description="Camera calibration capture assistant: guides a ChArUco capture and calibrates when the data is good enough.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    cal = sub.add_parser("calibrate", help="calibrate from a video file, a folder of images or a calibcoach recording")
    cal.add_argument("source", help="video file (.avi/.mp4/.mkv), folder of images, or recording folder")
    cal.add_argument("--out", type=Path, required=True, help="output folder")
    cal.add_argument("--model", choices=("auto", "pinhole", "rational", "fisheye"), default="auto",
                     help="distortion model (auto: field of view + cross-validation)")
    cal.add_argument("--accept-partial", action="store_true",
                     help="write camera_matrix.npy/dist_coeffs.npy even when coverage or uncertainty is insufficient")
    cal.add_argument("--fov", type=_field_of_view, metavar="DEG", help=_FOV_HELP)
    cal.add_argument("--max-frames", type=_frame_budget, default=60, help="most frames kept for the solve (default 60)")
    cal.add_argument("--no-stop", action="store_true", help="read the whole source even after the stop rule is met")
    # The plain loop's detectBoard runs on every core (OpenCV's own threads); the scan's detections
    # run one per thread with OpenCV single-threaded, so they take as many threads as there are cores
    # -- up to 8: the scan runs at least 8 frames ahead (drivers/base.py `frames_ahead`), not more.
    cal.add_argument("--workers", type=_workers, default=min(max(2, usable_cores()), 8),
                     help="detection threads of a replay's scan (default: the usable cores, 2 to 8)")
    cal.add_argument("--every-frame", action="store_true",
                     help="detect each frame of a video or folder in full instead of tracking a held board from the frame "
                          "before (a board in transit is judged by the scene's change either way; see the README's held-frame scan)")
    add_corner_argument(cal)
    cal.add_argument("--quiet", action="store_true", help="no progress line")
    add_viewer_arguments(cal, default="none")
    add_board_arguments(cal)

    sc = sub.add_parser("scale", help="adapt a calibration to a resized and/or cropped image")
    sc.add_argument("calibration", type=Path, help="calibration.json, calibration.yaml, camera_info.yaml or a folder of .npy files")
    sc.add_argument("--to", type=_size, help="new image size after a uniform resize, e.g. 640x360")
    sc.add_argument("--crop", type=_crop, help="crop x,y,width,height applied BEFORE the resize")
    sc.add_argument("--out", type=Path, required=True, help="output folder")
    sc.add_argument("--accept-partial", action="store_true",
                    help="scale a calibration calibcoach refused (outputs are named *_untrusted)")

    lv = sub.add_parser("live", help="guide a live capture (camera, or a file paced like one) until calibrated")
    lv.add_argument("--source", required=True,
                    help="v4l2:/dev/videoN | v4l2:N | depthai[:ID] | a video, folder or recording | auto (the first camera found)")
    lv.add_argument("--fallback", help="with --source auto: what to run when no camera is attached (e.g. a recording)")
    lv.add_argument("--out", type=Path, required=True, help="output folder")
    lv.add_argument("--record", type=Path, help="record the session here as it happens (crash-safe)")
    lv.add_argument("--guidance-jsonl", type=Path,
                    help="write every step (decision, guidance sentence and target, progress) here as JSON lines")
    lv.add_argument("--resume", type=Path, help="continue a recorded session (crashed, stopped or unplugged)")
    add_viewer_arguments(lv, default="web")
    lv.add_argument("--size", type=_size, help="capture resolution, e.g. 1920x1080")
    lv.add_argument("--fps", type=float, help="capture frame rate")
    lv.add_argument("--speed", type=float, default=1.0, help="replay sources: play this many times faster than recorded")
    lv.add_argument("--focus-control", help="lock focus through a VISCA camera: visca:PORT[@BAUD]")
    lv.add_argument("--lens-position", type=lambda t: int(t, 0), help="focus position to lock at (default: keep the current one)")
    lv.add_argument("--allow-autofocus", action="store_true", help="run on a camera whose focus cannot be locked")
    lv.add_argument("--model", choices=("auto", "pinhole", "rational", "fisheye"), default="auto")
    lv.add_argument("--accept-partial", action="store_true", help="write the .npy files even when not trusted")
    lv.add_argument("--fov", type=_field_of_view, metavar="DEG", help=_FOV_HELP)
    lv.add_argument("--max-frames", type=_frame_budget, default=60, help="most frames kept for the solve (default 60)")
    lv.add_argument("--no-stop", action="store_true", help="keep capturing after the stop rule is met")
    lv.add_argument("--write-to-device", action="store_true",
                    help="DepthAI: also flash the result into the camera's EEPROM (the old calibration is backed up)")
    add_corner_argument(lv)
    lv.add_argument("--quiet", action="store_true", help="no status line")
    add_board_arguments(lv)

    ex = sub.add_parser("export", help="write an earlier calibration for another tool (COLMAP, Kalibr, mrcal, Isaac Sim, ...)")
    ex.add_argument("calibration", type=Path, help="calibration.json, or the output folder holding it")
    ex.add_argument("--to", required=True, choices=("colmap", "kalibr", "mrcal", "isaac", "mujoco", "blender", "ros", "opencv"),
                    help="target tool (see the README's 'Taking the calibration elsewhere')")
    ex.add_argument("--out", type=Path, help="output folder (default: the calibration's folder)")
    ex.add_argument("--accept-partial", action="store_true",
                    help="export a calibration calibcoach refused (files named *_untrusted, the reasons inside)")

    sub.add_parser("devices", help="list V4L2 and DepthAI cameras with their modes and focus/exposure controls")

    fc = sub.add_parser("focus", help="lock, unlock or show a camera's focus (visca:PORT[@BAUD])")
    fc.add_argument("target", help="visca:/dev/ttyUSB0[@9600] (V4L2 and DepthAI targets come with live capture)")
    action = fc.add_mutually_exclusive_group(required=True)
    action.add_argument("--lock", action="store_true", help="manual focus, kept where it is unless --position")
    action.add_argument("--unlock", action="store_true", help="back to autofocus")
    action.add_argument("--status", action="store_true", help="print focus mode and positions")
    fc.add_argument("--position", type=lambda t: int(t, 0), help="focus position for --lock (decimal or 0x hex)")

    bd = sub.add_parser("board", help="write the board at true physical scale (PDF, SVG or PNG)")
    bd.add_argument("--out", type=Path, required=True, help="board.pdf, board.svg or board.png")
    bd.add_argument("--dpi", type=int, default=300, help="PNG resolution (default 300)")
    add_board_arguments(bd)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.command == "calibrate":
            from calibcoach.app.commands import calibrate_command

            return calibrate_command(args, board_from_args(args), argv=sys.argv if argv is None else ["calibcoach", *argv])
        if args.command == "scale":
            from calibcoach.app.commands import scale_command

            return scale_command(args)
        if args.command == "live":
            from calibcoach.app.live_command import live_command

            return live_command(args, board_from_args(args), argv=sys.argv if argv is None else ["calibcoach", *argv])
        if args.command == "export":
            from calibcoach.app.export.targets import export_command

            return export_command(args)
        if args.command == "devices":
            from calibcoach.app.live_command import devices_command

            return devices_command(args)
        if args.command == "focus":
            from calibcoach.app.commands import focus_command

            return focus_command(args)
        if args.command == "board":
            from calibcoach.app.outputs.board_print import write_board

            spec = board_from_args(args)
            write_board(args.out, spec, **({"dpi": args.dpi} if args.out.suffix.lower() == ".png" else {}))
            print(f"wrote {args.out}: {spec.describe()} -- print at 100% (actual size), then measure a square and a marker")
            return 0
    except CalibcoachError as exc:
        print(f"calibcoach: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("calibcoach: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:  # a path that cannot be read or written: the input's problem, said in one line
        where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
        print(f"calibcoach: error: {exc.strerror or exc}{where}; check the path and its permissions", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - every command's errors end here, as one line
        if os.environ.get("CALIBCOACH_DEBUG"):
            raise
        print(f"calibcoach: internal error: {type(exc).__name__}: {exc} -- please report it with the command line; "
              "CALIBCOACH_DEBUG=1 shows the traceback", file=sys.stderr)
        return 1
    parser.error(f"unknown command {args.command}")
    return 2


def run() -> None:
    """The `calibcoach` command: `main()`, then the process ends at once.

    A Python process that has loaded OpenCV, NumPy and the session's data takes ~0.05 s to tear
    itself down (modules, caches, arrays freed one by one), time a replay's user waits for after
    the last line was printed. Everything a command writes is closed by the time `main` returns,
    so the process leaves without that teardown -- unless something is still running (a thread,
    a child process), which then gets the normal exit that waits for it.
    """
    code = main()
    if threading.active_count() == 1 and not multiprocessing.active_children():
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        except (OSError, ValueError):  # a reader that went away, a closed stream: nothing more to say
            pass
        os._exit(code)
    raise SystemExit(code)


if __name__ == "__main__":
    run()
