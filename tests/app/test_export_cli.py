"""`calibcoach export` and board_poses.json from a real run: the trust rule, one-line errors, numbers intact."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibcoach.app.cli import main

K = [[912.3456789, 0.0, 641.2345], [0.0, 915.6789, 357.8912], [0.0, 0.0, 1.0]]


def run_cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def one_line_error(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.startswith("calibcoach: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def write_calibration(folder: Path, *, model: str = "pinhole", trusted: bool = True) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    dist = {"pinhole": [-0.29, 0.087, 0.0004, -0.0006, 0.0], "rational": [0.41, -0.12, 0.0004, -0.0006, 0.011, 0.72, -0.08, 0.03],
            "fisheye": [0.06, -0.013, 0.002, -0.0004]}[model]
    data = {"model": model, "image_size": [1280, 720], "camera_matrix": K, "dist_coeffs": dist,
            "verdict": {"grade": "good" if trusted else "insufficient", "trusted": trusted,
                        "reasons": ["RMS table", "Coverage is only 40 % of the image."] if not trusted else ["RMS table"]}}
    path = folder / "calibration.json"
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize(("target", "files"), [
    ("colmap", ["cameras.txt"]), ("kalibr", ["camchain.yaml"]), ("mrcal", ["camera.cameramodel"]),
    ("isaac", ["isaac_apply_camera.py", "isaac_camera.usda"]),
    ("mujoco", ["ideal_to_real_map_x.npy", "ideal_to_real_map_y.npy", "mujoco_camera.xml"]),
    ("blender", ["blender_camera.py", "ideal_to_real_map_x.npy", "ideal_to_real_map_y.npy"]),
    ("ros", ["camera_info.yaml"]), ("opencv", ["calibration.yaml", "camera_matrix.npy", "dist_coeffs.npy"]),
])
def test_export_every_target_from_a_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str], target: str, files: list[str]) -> None:
    write_calibration(tmp_path / "run")
    code, out, _ = run_cli(capsys, "export", str(tmp_path / "run"), "--to", target, "--out", str(tmp_path / "x"))
    assert code == 0 and out.startswith("wrote ")
    assert sorted(p.name for p in (tmp_path / "x").iterdir()) == files


def test_export_writes_beside_the_calibration_by_default_with_its_numbers(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_calibration(tmp_path / "run")
    assert run_cli(capsys, "export", str(path), "--to", "colmap")[0] == 0
    line = (tmp_path / "run" / "cameras.txt").read_text().splitlines()[-1].split()
    assert line[:4] == ["1", "OPENCV", "1280", "720"]
    np.testing.assert_array_equal([float(v) for v in line[4:8]], [K[0][0], K[1][1], K[0][2] + 0.5, K[1][2] + 0.5])
    from calibcoach.app.export.targets import export_camera
    from calibcoach.app.outputs.camera_reader import load_camera

    cam = load_camera(path)  # ros/opencv go through the existing writers and read back exactly
    export_camera(cam, "opencv", tmp_path / "o")
    np.testing.assert_array_equal(load_camera(tmp_path / "o" / "calibration.yaml").camera_matrix, cam.camera_matrix)


def test_export_refuses_an_untrusted_calibration_unless_accepted(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_calibration(tmp_path / "run", trusted=False)
    code, _, err = run_cli(capsys, "export", str(tmp_path / "run"), "--to", "colmap", "--out", str(tmp_path / "x"))
    assert code == 2 and "--accept-partial" in one_line_error(err) and "Coverage is only 40 %" in err
    assert not (tmp_path / "x").exists()
    code, out, _ = run_cli(capsys, "export", str(tmp_path / "run"), "--to", "colmap", "--out", str(tmp_path / "x"), "--accept-partial")
    assert code == 0 and "UNTRUSTED" in out
    assert [p.name for p in (tmp_path / "x").iterdir()] == ["cameras_untrusted.txt"]
    text = (tmp_path / "x" / "cameras_untrusted.txt").read_text()
    assert text.startswith("# UNTRUSTED calibration") and "Coverage is only 40 %" in text
    assert run_cli(capsys, "export", str(tmp_path / "run"), "--to", "kalibr", "--out", str(tmp_path / "x"), "--accept-partial")[0] == 0
    assert (tmp_path / "x" / "camchain_untrusted.yaml").read_text().startswith("# UNTRUSTED")


@pytest.mark.parametrize(("args", "says"), [
    (["--to", "kalibr"], "Kalibr has no rational"),
    (["--to", "mrcal"], None),
])
def test_export_errors_are_one_line_naming_the_fix(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str],
                                                   says: str | None) -> None:
    write_calibration(tmp_path / "rat", model="rational")
    write_calibration(tmp_path / "fish", model="fisheye")
    if says:
        code, _, err = run_cli(capsys, "export", str(tmp_path / "rat"), *args)
        assert code == 2 and says in one_line_error(err)
    code, _, err = run_cli(capsys, "export", str(tmp_path / "fish"), "--to", "mrcal")
    assert code == 2 and "no Kannala-Brandt" in one_line_error(err)
    code, _, err = run_cli(capsys, "export", str(tmp_path / "nothing"), "--to", "colmap")
    assert code == 2 and "does not exist" in one_line_error(err)
    (tmp_path / "empty").mkdir()
    code, _, err = run_cli(capsys, "export", str(tmp_path / "empty"), "--to", "colmap")
    assert code == 2 and "no calibration.json" in one_line_error(err)


def test_a_run_writes_board_poses_under_the_trust_rule(recordings_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "partial"
    assert main(["calibrate", str(recordings_dir / "frontal_webcam720"), "--out", str(out), "--quiet", "--accept-partial"]) == 3
    assert not (out / "board_poses.json").exists()
    poses = json.loads((out / "board_poses_untrusted.json").read_text())
    calibration = json.loads((out / "calibration.json").read_text())
    assert poses["trusted"] is False and poses["untrusted_because"]
    assert len(poses["frames"]) == calibration["frames_used"]
    for pose, frame in zip(poses["frames"], calibration["frames"], strict=True):
        assert pose["index"] == frame["index"] and pose["name"] == frame["name"]
        np.testing.assert_allclose(pose["tvec_m"], frame["tvec_m"], rtol=1e-5, atol=1e-9)
        assert isinstance(pose["timestamp_ns"], int)
    stamps = [p["timestamp_ns"] for p in poses["frames"]]
    assert len(set(stamps)) == len(stamps)
    capsys.readouterr()
    refused = tmp_path / "refused"
    refused.mkdir()
    (refused / "board_poses.json").write_text("{}")  # an earlier run's poses must go with its camera
    assert main(["calibrate", str(recordings_dir / "frontal_webcam720"), "--out", str(refused), "--quiet"]) == 3
    assert not any(p.name.startswith("board_poses") for p in refused.iterdir())
