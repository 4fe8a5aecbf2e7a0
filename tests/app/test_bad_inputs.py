"""Every command with inputs it cannot use: one line that names the fix, a non-zero exit, no traceback,
and nothing written that looks like a result (issue 11)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from calibcoach.app.cli import main

RESULT_FILES = ("camera_matrix.npy", "dist_coeffs.npy", "calibration.yaml", "camera_info.yaml", "calibration.json")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bad")
    noise = root / "noise"
    noise.mkdir()
    rng = np.random.default_rng(0)
    for i in range(6):
        cv2.imwrite(str(noise / f"{i:03d}.png"), rng.integers(0, 255, (240, 320), dtype=np.uint8))
    toml = root / "board.toml"
    toml.write_text("squares_x = 8.5\nsquares_y = 11\nsquare_mm = 30.01\nmarker_mm = 22.01\ndictionary = 'DICT_5X5_100'\n")
    refused = root / "refused"
    assert main(["calibrate", str(request.config.rootpath / "recordings" / "frontal_webcam720"), "--out", str(refused),
                 "--quiet"]) == 3
    one = root / "one"  # a single good frame: kept, nothing rejected, still too few to solve
    one.mkdir()
    frames = sorted((request.config.rootpath / "recordings" / "demo_webcam720_careful" / "frames").iterdir())
    (one / frames[0].name).write_bytes(frames[0].read_bytes())
    return {"noise": noise, "toml": toml, "refused": refused / "calibration.json", "one": one,
            "demo": request.config.rootpath / "recordings" / "demo_webcam720_careful"}


CASES = [
    # (command line with {placeholders}, what the one line must say)
    ("calibrate {demo} --square-mm 1e300 --marker-mm 7e299", "between 1 mm and 2000 mm"),
    ("calibrate {demo} --board {toml}", "whole number of squares"),
    ("calibrate {demo} --squares 1x11", "at least 2x2"),
    ("calibrate {demo} --marker-mm 40 --square-mm 30", "smaller than the square size"),
    ("calibrate {demo} --max-frames 0", "pass at least 15"),
    ("calibrate {demo} --fov 500", "pass 10-240"),
    ("calibrate {demo} --dictionary DICT_7X7_9", "unknown ArUco dictionary"),
    ("calibrate {tmp}/nowhere", "does not exist"),
    ("calibrate {noise}", "at most a stray ArUco marker"),
    ("calibrate {one}", "only 1 of 1 frames were usable (none rejected: the source held too few frames)"),
    ("scale {refused} --to 640x360", "--accept-partial"),
    ("scale {refused} --crop 0,0,5000,5000 --accept-partial", "crop inside the image"),
    ("scale {tmp}/nothing.json --to 640x360", "does not exist"),
    ("scale {refused} --accept-partial", "--to WxH"),
    ("board --squares 10x11 --dictionary DICT_4X4_50 --out {tmp}/b.png", "larger dictionary"),
    ("focus somewhere --lock", "unknown focus target"),
    ("live --source {tmp}/nowhere", "does not exist"),
]


@pytest.mark.parametrize(("line", "says"), CASES, ids=[c[0].split()[0] + ":" + c[1][:24] for c in CASES])
def test_bad_input_gets_one_line_and_no_result(line: str, says: str, inputs: dict[str, Path], tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    argv = line.format(tmp=tmp_path, **inputs).split()
    if argv[0] in ("calibrate", "live", "scale"):
        argv += ["--out", str(out)] if "--out" not in argv else []
    if argv[0] in ("calibrate", "live"):
        argv += ["--quiet", "--no-viewer"] if argv[0] == "live" else ["--quiet"]
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own refusals (a bad --max-frames, say) exit 2 with usage
        code = exc.code
    err = capsys.readouterr().err
    assert code not in (0, None), err
    assert "Traceback" not in err and "internal error" not in err, err
    assert says in err, err
    lines = [line for line in err.splitlines() if "error" in line]
    assert len(lines) == 1, err  # one line, not a cascade
    written = [p.name for p in out.rglob("*")] if out.exists() else []
    assert not set(written) & set(RESULT_FILES), written
