"""The command line on bad input and on real captures: clear one-line errors, honest verdicts."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibcoach.app.cli import main


def run_cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(err: str, *needles: str) -> None:
    lines = [ln for ln in err.splitlines() if ln.startswith("calibcoach: error:")]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_missing_path(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_cli(capsys, "calibrate", str(tmp_path / "nope.mp4"), "--out", str(tmp_path / "o"))
    assert code == 2
    assert_one_line_error(err, "does not exist")


def test_empty_video_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty.mp4").write_bytes(b"")
    code, _, err = run_cli(capsys, "calibrate", str(tmp_path / "empty.mp4"), "--out", str(tmp_path / "o"))
    assert code == 2
    assert_one_line_error(err, "empty")


def test_corrupt_video_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "junk.avi").write_bytes(np.random.default_rng(0).bytes(20000))
    code, _, err = run_cli(capsys, "calibrate", str(tmp_path / "junk.avi"), "--out", str(tmp_path / "o"))
    assert code == 2
    assert_one_line_error(err, "junk.avi")


def test_folder_without_images(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "notes.txt").write_text("x")
    code, _, err = run_cli(capsys, "calibrate", str(tmp_path / "in"), "--out", str(tmp_path / "o"))
    assert code == 2
    assert_one_line_error(err, "no images")


def test_images_without_any_board(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "grey"
    folder.mkdir()
    rng = np.random.default_rng(1)
    for i in range(4):
        cv2.imwrite(str(folder / f"{i}.png"), rng.integers(0, 255, (240, 320), np.uint8))
    code, _, err = run_cli(capsys, "calibrate", str(folder), "--out", str(tmp_path / "o"))
    assert code == 2
    assert_one_line_error(err, "no board corners were found in any of the 4 frames")
    assert not (tmp_path / "o" / "camera_matrix.npy").exists()


def test_wrong_dictionary_on_a_real_capture(shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    video = shared_data / "caliscope_webcam_charuco_4x5" / "video" / "cam_0.mp4"
    code, _, err = run_cli(capsys, "calibrate", str(video), "--out", str(tmp_path / "o"),
                           "--squares", "4x5", "--square-mm", "54", "--marker-mm", "40.5", "--dictionary", "DICT_5X5_100")
    assert code == 2
    assert_one_line_error(err, "DICT_4X4", "--dictionary")


def test_a_real_print_of_another_size_is_measured_from_its_markers(shared_data: Path, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """caliscope's inverted 4x5 print with only its dictionary given (the default 8x11 otherwise)."""
    video = shared_data / "caliscope_webcam_charuco_4x5" / "video" / "cam_0.mp4"
    code, _, err = run_cli(capsys, "calibrate", str(video), "--out", str(tmp_path / "o"), "--quiet", "--no-viewer",
                           "--dictionary", "DICT_4X4_1000")
    assert code == 2
    assert_one_line_error(err, "no corners match a 8x11 squares", "they form the corners of a 4x5 board: pass --squares 4x5")


def test_chessboard_photos_are_not_a_charuco_board(shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_cli(capsys, "calibrate", str(shared_data / "boofcv_sony_hx5v_chess"), "--out", str(tmp_path / "o"))
    assert code == 2
    assert_one_line_error(err, "a plain chessboard (at least 7x5 squares", "calibcoach board --out board.pdf")


def test_inverted_webcam_capture_is_refused_for_poor_coverage(shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = shared_data / "caliscope_webcam_charuco_4x5"
    out = tmp_path / "o"
    code, stdout, err = run_cli(capsys, "calibrate", str(root / "video" / "cam_0.mp4"), "--board", str(root / "charuco.toml"),
                                "--out", str(out), "--quiet")
    assert "inverted print" in err
    assert code == 3
    data = json.loads((out / "calibration.json").read_text())
    assert data["verdict"]["grade"] == "insufficient" and data["verdict"]["trusted"] is False
    assert data["board"]["inverted"] is True
    # E over the whole image a board can reach is recorded beside E over the covered region (23% covered: far above it)
    assert data["uncertainty"]["reachable_error_px"] > 2 * data["uncertainty"]["expected_error_px"] > 0
    # the webcam's exposure, read off its moving frames' edges (12 ms at 6 fps; an indoor webcam's auto
    # exposure runs 8-33 ms), and no frame smeared past the final solve's limit in it
    exposure_ms = float(re.search(r"exposure ~(\d+) ms", data["smear"]["exposure"]).group(1))  # type: ignore[union-attr]
    assert 5 <= exposure_ms <= 33 and data["smear"]["frames_left_out"] == 0
    assert not (out / "camera_matrix.npy").exists()
    assert "no camera files" in stdout
    code, _, _ = run_cli(capsys, "calibrate", str(root / "video" / "cam_0.mp4"), "--board", str(root / "charuco.toml"),
                         "--out", str(out), "--quiet", "--accept-partial")
    assert code == 3
    assert not (out / "camera_matrix.npy").exists()  # under --accept-partial the name says what it is
    K = np.load(out / "camera_matrix_untrusted.npy")
    assert K.shape == (3, 3) and 700 < K[0, 0] < 1100


def test_a_mirrored_webcam_video_is_named_as_mirrored(shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """caliscope's cam_1 is mirrored left to right (its README): the board's ids read as others up to 871, which
    used to be blamed on the square count."""
    root = shared_data / "caliscope_webcam_charuco_4x5"
    code, _, err = run_cli(capsys, "calibrate", str(root / "video" / "cam_1.mp4"), "--board", str(root / "charuco.toml"),
                           "--out", str(tmp_path / "o"), "--quiet", "--no-viewer")
    assert code == 2
    assert_one_line_error(err, "the images are mirrored left to right", "ffmpeg -vf hflip")
    assert "--squares" not in err


def test_machine_vision_photos_match_the_authors_intrinsics(shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "o"
    code, _, _ = run_cli(capsys, "calibrate", str(shared_data / "pycamset_charuco_3cam" / "2"), "--out", str(out), "--quiet",
                         "--squares", "20x20", "--square-mm", "4", "--marker-mm", "3.2", "--dictionary", "DICT_4X4_1000")
    data = json.loads((out / "calibration.json").read_text())
    K = np.array(data["camera_matrix"])
    # authors: fx 2828.19 fy 2837.69 cx 665.72 cy 502.43; the narrow lens leaves cx/cy loose (std ~4 px).
    # The authors' values are an estimate from these same 22 photos, no better determined than
    # ours: the difference's sigma is ~sqrt(2) ours (cx came out 17-20 px off, 3.1-3.5 of those,
    # with OpenCV's corners and with the masked refinement alike).
    assert K[0, 0] == pytest.approx(2828.19, rel=0.01)
    assert K[1, 1] == pytest.approx(2837.69, rel=0.01)
    assert abs(K[0, 2] - 665.72) < 5 * np.sqrt(2) * data["intrinsic_std"]["cx"]
    assert abs(K[1, 2] - 502.43) < 5 * np.sqrt(2) * data["intrinsic_std"]["cy"]
    assert data["model"] == "pinhole"
    assert data["frames_used"] >= 18
    # the board never left the middle of the image: the verdict must not trust it, whatever the RMS
    assert code == 3 and data["verdict"]["trusted"] is False


def test_scale_and_board_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from calibcoach.app.outputs.files import load_camera, write_calibration_json
    from calibcoach.drivers.lens import CameraModel

    camera = CameraModel("pinhole", [[900, 0, 639.5], [0, 900, 359.5], [0, 0, 1]], [-0.1, 0.05, 0, 0, 0], (1280, 720))
    write_calibration_json(tmp_path / "calibration.json", {
        "model": "pinhole", "image_size": [1280, 720], "camera_matrix": camera.camera_matrix, "dist_coeffs": camera.dist_coeffs,
    })
    code, out, _ = run_cli(capsys, "scale", str(tmp_path / "calibration.json"), "--to", "640x360", "--out", str(tmp_path / "s"))
    assert code == 0
    half = load_camera(tmp_path / "s" / "calibration.yaml")
    assert half.fx == pytest.approx(450.0) and half.principal_point == pytest.approx((319.5, 179.5))
    np.testing.assert_allclose(half.dist_coeffs, camera.dist_coeffs)
    code, _, _ = run_cli(capsys, "scale", str(tmp_path / "calibration.json"), "--crop", "100,60,1080,600", "--out", str(tmp_path / "c"))
    assert code == 0
    assert load_camera(tmp_path / "c" / "calibration.yaml").principal_point == pytest.approx((539.5, 299.5))
    code, _, err = run_cli(capsys, "scale", str(tmp_path / "calibration.json"), "--to", "640x480", "--out", str(tmp_path / "x"))
    assert code == 2 and "aspect ratio" in err
    code, out, _ = run_cli(capsys, "board", "--out", str(tmp_path / "board.svg"))
    assert code == 0 and "30.01" in (tmp_path / "board.svg").read_text()


def test_explicit_board_options_override_a_recordings_board_with_a_notice(recordings_dir: Path, tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture[str]) -> None:
    # the recording stores 30.01 / 22.01 mm; a re-measured print says 30.2 / 22.15: that is what must be solved with
    code, _, err = run_cli(capsys, "calibrate", str(recordings_dir / "frontal_webcam720"), "--out", str(tmp_path / "o"), "--quiet",
                           "--square-mm", "30.2", "--marker-mm", "22.15")
    assert "overridden by the command line: square_mm 30.01 -> 30.2, marker_mm 22.01 -> 22.15" in err
    assert "squares 30.2 mm, markers 22.15 mm" in err  # the banner says what is used
    assert json.loads((tmp_path / "o" / "calibration.json").read_text())["board"]["square_mm"] == 30.2


@pytest.mark.parametrize("busy_thread", [False, True])
def test_the_command_leaves_without_teardown_unless_something_still_runs(tmp_path: Path, busy_thread: bool) -> None:
    # `calibcoach` (cli.run) ends the process as soon as main() returns -- output flushed, files
    # closed -- skipping the interpreter's teardown; a thread still running gets the normal exit.
    import subprocess
    import sys

    script = (
        "import atexit, sys, threading, time\n"
        "atexit.register(lambda: print('teardown ran'))\n"
        f"if {busy_thread}: threading.Thread(target=time.sleep, args=(1.0,)).start()\n"
        "from calibcoach.app.cli import run\n"
        f"sys.argv = ['calibcoach', 'board', '--out', {str(tmp_path / 'board.svg')!r}]\n"
        "run()\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "wrote " in done.stdout and (tmp_path / "board.svg").stat().st_size > 0
    assert ("teardown ran" in done.stdout) == busy_thread


@pytest.mark.parametrize("users_value", [None, "2"])
def test_the_command_runs_numpys_blas_on_one_thread_unless_the_user_chose(users_value: str | None) -> None:
    # OpenBLAS's worker threads spin after each call and took CPU from calibcoach's own threads
    # (cli.py); the setting must come before NumPy loads, and a value the user set wins.
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if users_value is not None:
        env["OPENBLAS_NUM_THREADS"] = users_value
    script = ("import os, calibcoach.app.cli, numpy\n"
              "numpy.ones((300, 300)) @ numpy.ones((300, 300))\n"  # a BLAS call large enough to start its threads
              "print(os.environ['OPENBLAS_NUM_THREADS'], len(os.listdir('/proc/self/task')))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, env=env)
    assert done.returncode == 0, done.stderr
    setting, threads = done.stdout.split()
    assert setting == (users_value or "1")
    if users_value is None:
        assert threads == "1", "NumPy's BLAS started threads of its own"


@pytest.mark.parametrize("keep", [True, False])
def test_the_command_reuses_freed_frame_sized_blocks_instead_of_faulting_them_in_again(keep: bool) -> None:
    # glibc gave freed frames at its heap's top back to the kernel, so every frame's arrays came
    # back as ~225 new pages, each faulted in and zeroed (cli.py). Importing the command keeps them
    # for reuse; CALIBCOACH_MALLOPT=0 leaves glibc's defaults (the control that shows the count means it).
    import os
    import platform
    import subprocess
    import sys

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        pytest.skip("the setting is glibc's; other C libraries keep their own policy")
    env = {**os.environ, "CALIBCOACH_MALLOPT": "1" if keep else "0"}
    # A hold's frames wait for its judgement and are then freed together, ten holds of 30 frames.
    script = ("import resource, calibcoach.app.cli, numpy\n"
              "before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
              "for hold in range(10):\n"
              "    frames = [numpy.full((720, 1280), i, numpy.uint8) for i in range(30)]\n"  # written whole, as decoded
              "    del frames\n"
              "print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 300)\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, env=env)
    assert done.returncode == 0, done.stderr
    faults_a_frame = float(done.stdout)  # a 720p grey frame is 225 pages
    if keep:
        assert faults_a_frame < 50, f"{faults_a_frame:.0f} page faults a frame: freed frames were not reused"
    else:
        assert faults_a_frame > 150, f"{faults_a_frame:.0f} page faults a frame with glibc's defaults: the test measures nothing"


@pytest.mark.parametrize("command", ["calibrate", "live"])
@pytest.mark.parametrize(("fov", "model", "distance_m"), [(None, "pinhole", 0.74), ("30", "pinhole", 1.93), ("150", "fisheye", 0.40)])
def test_fov_is_the_lens_the_first_guidance_is_for(command: str, fov: str | None, model: str, distance_m: float) -> None:
    """--fov sets the lens before the first solve: the first pose's range, and an equidistant fisheye from 120 deg.

    The first pose asks for the board at mid range (a frontal board over ~52% of the image height). Told
    0.74 m as for a 70 deg webcam, a person with a 30 deg lens would hold the board where it spans 1.5x
    the image height; at 1.93 m it spans 57%.
    """
    from calibcoach.app.cli import build_parser
    from calibcoach.app.commands import session_settings
    from calibcoach.app.session import CalibrationSession
    from calibcoach.coverage.board import BoardSpec
    from calibcoach.drivers.base import SourceInfo

    source = "recording" if command == "calibrate" else "--source=sim"
    args = build_parser().parse_args([command, source, "--out", "o", *([] if fov is None else ["--fov", fov])])
    settings = session_settings(args, SourceInfo("a video", "video", image_size=(1280, 720)), live=command == "live")
    session = CalibrationSession(BoardSpec(), (1280, 720), settings)
    assert session.camera.model == model and session.detection_lens is session.camera
    target = session.guide.guidance(done=False).target
    assert target is not None and target.distance_m == pytest.approx(distance_m, rel=0.02)


@pytest.mark.parametrize(("lens", "given", "says"), [("tele30", None, "--fov 30"), ("webcam720", None, ""),
                                                      ("webcam720", 72.0, ""), ("fisheye150", None, "--fov 152"),
                                                      ("fisheye150", 150.0, ""), ("webcam720", 150.0, "--fov 68"),
                                                      ("wide720", None, "--fov 89"), ("fisheye110", None, "--fov 88")])
def test_live_suggests_fov_when_the_lens_read_far_from_the_guess(lens: str, given: float | None, says: str) -> None:
    """Said where the solved focal length is 25% or more from the guess's; the value it names silences it."""
    from calibcoach.app.commands import fov_hint
    from calibcoach.app.session_types import lens_guess
    from calibcoach.drivers.lens import CameraModel
    from calibcoach.drivers.sim import LENSES

    # fisheye110: a fisheye model whose equidistant reading, under 120 deg, no --fov gives as a fisheye
    camera = {"tele30": lens_guess((1280, 720), 30.0),
              "fisheye110": CameraModel.from_fov((1280, 720), 110.0, "fisheye")}.get(lens) or LENSES[lens]
    hint = fov_hint(camera, given)
    if not says:
        assert hint == ""
        return
    assert says in hint
    assert fov_hint(camera, float(says.split()[-1])) == ""  # what it suggests fits


def test_unreadable_frames_are_named_then_counted(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "frames"
    folder.mkdir()
    demo = sorted((Path(__file__).parents[2] / "recordings" / "demo_webcam720_careful" / "frames").iterdir())
    for path in demo[:24]:
        (folder / path.name).write_bytes(path.read_bytes())
    for i in range(12):  # sorted after the good frames: indices 24-35
        (folder / f"zz_damaged_{i:02d}.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    _, _, err = run_cli(capsys, "calibrate", str(folder), "--out", str(tmp_path / "o"), "--quiet", "--no-viewer")
    named = [ln for ln in err.splitlines() if ln.startswith("calibcoach: skipped frame")]
    assert named[0] == ("calibcoach: skipped frame 24 (zz_damaged_00.png): file does not decode as an image "
                        "(damaged, truncated, or not really a .png file)")
    assert len(named) == 10
    assert "calibcoach: ... and 2 more frames skipped" in err.splitlines()


def test_detection_threads_default_to_the_usable_cores_and_refuse_nonsense(capsys: pytest.CaptureFixture[str]) -> None:
    import os

    from calibcoach.app.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(["calibrate", "frames", "--out", "out"])
    assert args.workers == min(max(2, len(os.sched_getaffinity(0))), 8)  # the plain loop's detectBoard uses every core too
    assert parser.parse_args(["calibrate", "frames", "--out", "out", "--workers", "3"]).workers == 3
    for bad in ("0", "two"):
        with pytest.raises(SystemExit):
            parser.parse_args(["calibrate", "frames", "--out", "out", "--workers", bad])
        assert "--workers" in capsys.readouterr().err
