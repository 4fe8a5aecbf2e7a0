"""Calibration files: shapes other tools expect, exact round trips, and readable errors."""

from __future__ import annotations

import json
import re
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibcoach.app.outputs import files
from calibcoach.app.outputs.files import (
    calibration_payload,
    load_camera,
    parse_simple_yaml,
    write_calibration_json,
    write_npy,
    write_opencv_yaml,
    write_ros_camera_info,
)
from calibcoach.app.solve.result import (
    Calibration,
    DroppedCorner,
    DroppedFrame,
    ModelChoice,
    UncertaintyMap,
    Verdict,
    View,
)
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.errors import CalibcoachError
from calibcoach.drivers.lens import CameraModel

SIZE = (1920, 1080)
# Values with many significant digits, a skew term and a tiny coefficient: anything lossy shows up.
K = np.array([[1234.5678901234567, 0.0123456789, 959.87654321], [0.0, 1233.2109876543, 541.123456789], [0.0, 0.0, 1.0]])
DIST = {
    "pinhole": [-0.3123456789012345, 0.1234567890123, 1.234567e-05, -0.000987654321, -0.0234567891],
    "rational": [2.1, 13.4567, 1e-05, -0.0002, 8.765, 2.5, 14.25, 9.125],
    "fisheye": [0.0512345678901, -0.0123456789, 0.00234567, -3.4567e-07],
}
ROS_NAMES = {"pinhole": "plumb_bob", "rational": "rational_polynomial", "fisheye": "equidistant"}
YAML11_FLOAT = re.compile(r"^[-+]?[0-9]+\.[0-9]*([eE][-+][0-9]+)?$")  # PyYAML's float, which camera_info_manager_py uses


def camera(model: str) -> CameraModel:
    return CameraModel(model, K, np.array(DIST[model]), SIZE)


def assert_same_camera(a: CameraModel, b: CameraModel) -> None:
    assert a.model == b.model
    assert a.image_size == b.image_size
    np.testing.assert_allclose(a.camera_matrix, b.camera_matrix, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.dist_coeffs, b.dist_coeffs, rtol=0, atol=1e-9)


# --- numpy --------------------------------------------------------------------------------------


@pytest.mark.parametrize(("model", "shape"), [("pinhole", (1, 5)), ("rational", (1, 8)), ("fisheye", (4, 1))])
def test_npy_has_opencv_shapes_and_works_in_opencv_directly(tmp_path: Path, model: str, shape: tuple[int, int]) -> None:
    k_path, d_path = write_npy(tmp_path, camera(model))
    K_loaded, D_loaded = np.load(k_path), np.load(d_path)
    assert (k_path.name, d_path.name) == ("camera_matrix.npy", "dist_coeffs.npy")
    assert K_loaded.shape == (3, 3) and K_loaded.dtype == np.float64
    assert D_loaded.shape == shape and D_loaded.dtype == np.float64
    np.testing.assert_array_equal(D_loaded.reshape(-1), DIST[model])
    pixel = np.array([[[1700.0, 900.0]]])
    if model == "fisheye":
        undistorted = cv2.fisheye.undistortPoints(pixel, K_loaded, D_loaded)
    else:
        undistorted = cv2.undistortPoints(pixel, K_loaded, D_loaded)
    ray = camera(model).unproject(pixel.reshape(1, 2))[0]
    np.testing.assert_allclose(undistorted.reshape(2), ray[:2] / ray[2], atol=1e-3)  # the arrays mean the same lens


# --- round trips --------------------------------------------------------------------------------


def _write(fmt: str, folder: Path, cam: CameraModel) -> tuple[Path, dict]:
    if fmt == "opencv_yaml":
        return write_opencv_yaml(folder / "calibration.yaml", cam, rms_px=0.25, extra={}), {}
    if fmt == "ros":
        return write_ros_camera_info(folder / "camera_info.yaml", cam, camera_name="cam0"), {}
    if fmt == "json":
        payload = {"model": cam.model, "image_size": list(cam.image_size), "camera_matrix": cam.camera_matrix, "dist_coeffs": cam.dist_coeffs}
        return write_calibration_json(folder / "calibration.json", payload), {}
    if fmt == "npy_with_json":
        write_npy(folder, cam)
        write_calibration_json(folder / "calibration.json", {"model": cam.model, "image_size": list(cam.image_size)})
        return folder, {}
    write_npy(folder, cam)  # "npy_only": the size comes from the caller, the model from the coefficient count
    return folder, {"image_size": SIZE}


@pytest.mark.parametrize("fmt", ["opencv_yaml", "ros", "json", "npy_with_json", "npy_only"])
@pytest.mark.parametrize("model", ["pinhole", "rational", "fisheye"])
def test_every_format_round_trips_every_model(tmp_path: Path, model: str, fmt: str) -> None:
    cam = camera(model)
    path, kwargs = _write(fmt, tmp_path, cam)
    assert_same_camera(load_camera(path, **kwargs), cam)


def test_npy_file_path_reads_its_folder(tmp_path: Path) -> None:
    k_path, _ = write_npy(tmp_path, camera("fisheye"))
    assert_same_camera(load_camera(k_path, image_size=SIZE), camera("fisheye"))


# --- OpenCV YAML --------------------------------------------------------------------------------


def test_opencv_yaml_reads_back_in_filestorage_with_every_key(tmp_path: Path) -> None:
    extra = {"frames_used": 42, "coverage": 0.875, "board": {"squares_x": 8, "dictionary": "DICT_5X5_100"}, "models": ["pinhole", "rational"], "trusted": True}
    path = write_opencv_yaml(tmp_path / "calibration.yaml", camera("rational"), rms_px=0.3125, extra=extra)
    assert path.read_text().startswith("%YAML")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        created = datetime.fromisoformat(fs.getNode("calibration_time").string())
        assert created.tzinfo is not None and abs((datetime.now(UTC) - created).total_seconds()) < 60
        assert (int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real())) == SIZE
        np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), K)
        assert fs.getNode("distortion_coefficients").mat().shape == (1, 8)
        assert fs.getNode("distortion_model").string() == "rational"
        assert fs.getNode("avg_reprojection_error").real() == 0.3125
        assert fs.getNode("frames_used").isInt() and int(fs.getNode("frames_used").real()) == 42
        assert fs.getNode("coverage").real() == 0.875
        assert fs.getNode("board").getNode("dictionary").string() == "DICT_5X5_100"
        assert [fs.getNode("models").at(i).string() for i in range(fs.getNode("models").size())] == ["pinhole", "rational"]
        assert int(fs.getNode("trusted").real()) == 1
    finally:
        fs.release()


def test_opencv_yaml_of_a_rescaled_camera_has_no_reprojection_error(tmp_path: Path) -> None:
    cam = camera("pinhole").resized((960, 540))
    path = write_opencv_yaml(tmp_path / "c.yaml", cam, rms_px=None, extra={"derived_from": "run1/calibration.json"})
    assert "avg_reprojection_error" not in path.read_text()
    assert "derived_from: " in path.read_text()
    assert_same_camera(load_camera(path), cam)


def test_opencv_yaml_rejects_keys_filestorage_cannot_hold(tmp_path: Path) -> None:
    with pytest.raises(CalibcoachError, match="frames used"):
        write_opencv_yaml(tmp_path / "c.yaml", camera("pinhole"), rms_px=0.2, extra={"frames used": 3})
    assert list(tmp_path.iterdir()) == []  # the half-written temporary file is gone


def test_yaml_from_opencv_sample_without_model_or_size_needs_the_size(tmp_path: Path) -> None:
    path = tmp_path / "out_camera_data.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.array(DIST["pinhole"]).reshape(5, 1))  # calibration.cpp writes a column
    fs.release()
    with pytest.raises(CalibcoachError, match=r"does not record the image size; pass it"):
        load_camera(path)
    assert_same_camera(load_camera(path, image_size=SIZE), camera("pinhole"))


# --- ROS ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", ["pinhole", "rational", "fisheye"])
def test_ros_camera_info_has_camera_calibration_layout(tmp_path: Path, model: str) -> None:
    path = write_ros_camera_info(tmp_path / "camera_info.yaml", camera(model), camera_name="OAK-D Lite/rgb")
    text = path.read_text()
    top_keys = [line.split(":")[0] for line in text.splitlines() if line and not line.startswith(" ")]
    assert top_keys == [
        "image_width", "image_height", "camera_name", "camera_matrix", "distortion_model",
        "distortion_coefficients", "rectification_matrix", "projection_matrix",
    ]  # fmt: skip
    data = parse_simple_yaml(text)
    n = len(DIST[model])
    assert (data["image_width"], data["image_height"], data["camera_name"]) == (1920, 1080, "OAK_D_Lite_rgb")
    assert data["distortion_model"] == ROS_NAMES[model]
    assert data["distortion_coefficients"]["rows"] == 1 and data["distortion_coefficients"]["cols"] == n
    assert data["distortion_coefficients"]["data"] == DIST[model]
    assert (data["camera_matrix"]["rows"], data["camera_matrix"]["cols"]) == (3, 3)
    assert data["rectification_matrix"]["data"] == np.eye(3).reshape(-1).tolist()
    assert (data["projection_matrix"]["rows"], data["projection_matrix"]["cols"]) == (3, 4)
    np.testing.assert_array_equal(np.reshape(data["projection_matrix"]["data"], (3, 4)), np.hstack([K, np.zeros((3, 1))]))
    numbers = re.findall(r"data: \[(.*)\]", text)
    assert len(numbers) == 4
    assert all(YAML11_FLOAT.match(x.strip()) for row in numbers for x in row.split(","))


def test_ros_reader_accepts_camera_calibration_wrapped_rows(tmp_path: Path) -> None:
    # As ROS's Python calibrator writes it: numpy's array2string wraps long rows onto indented lines.
    text = """image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [ 423.12345,    0.     ,  318.5    ,
            0.     ,  423.5    ,  240.25   ,
            0.     ,    0.     ,    1.     ]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.321000, 0.110000, 0.000500, -0.000200, 0.000000]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1., 0., 0., 0., 1., 0., 0., 0., 1.]
projection_matrix:
  rows: 3
  cols: 4
  data: [423.1, 0., 318.5, 0., 0., 423.5, 240.25, 0., 0., 0., 1., 0.]
"""
    path = tmp_path / "ost.yaml"
    path.write_text(text)
    cam = load_camera(path)
    assert cam.model == "pinhole" and cam.image_size == (640, 480)
    np.testing.assert_array_equal(cam.camera_matrix, [[423.12345, 0, 318.5], [0, 423.5, 240.25], [0, 0, 1]])
    np.testing.assert_array_equal(cam.dist_coeffs, [-0.321, 0.11, 0.0005, -0.0002, 0.0])


def test_yaml_float_always_has_a_decimal_point() -> None:
    assert [files._yaml_float(v) for v in (1e-05, 2.0, 1e20, -3.5e-7, 0.0)] == ["1.0e-05", "2.0", "1.0e+20", "-3.5e-07", "0.0"]


# --- calibration.json ---------------------------------------------------------------------------


def _calibration() -> Calibration:
    cam = camera("pinhole")
    corners = BoardSpec().corner_points_m()
    views = tuple(
        View(frame_index=i * 10, frame_name=f"frame_{i:03d}.png", ids=np.arange(n, dtype=np.int32),
             image_points_px=np.zeros((n, 2)), object_points_m=corners[:n])
        for i, n in enumerate((70, 35, 12))
    )  # fmt: skip
    return Calibration(
        camera=cam,
        rms_px=0.123456789,
        views=views,
        rvecs=np.array([[0.1, 0.2, 0.3], [0.0, -0.1, 0.0], [0.3, 0.0, 0.1]]),
        tvecs=np.array([[0.01, 0.02, 0.7], [0.0, 0.0, 0.5], [-0.1, 0.05, 1.2]]),
        residuals_px=tuple(np.zeros((v.ids.size, 2)) for v in views),
        per_view_rms_px=np.array([0.11, 0.2, float("nan")]),
        intrinsic_names=("fx", "fy", "cx", "cy", "k1"),
        intrinsic_covariance=np.diag([4.0, 4.0, 0.25, 0.25, 1e-6]),
        dropped_frames=(DroppedFrame(frame_index=50, reason="frame RMS 2.31 px is 6.2x the median"),),
        dropped_corners=(DroppedCorner(frame_index=10, corner_id=7, residual_px=1.987654321),),
    )


def _payload() -> dict:
    sigma = np.array([[0.1, 0.2], [0.3, 0.9]])
    return calibration_payload(
        _calibration(),
        verdict=Verdict(grade="good", trusted=True, rms_grade="excellent", reasons=("Coverage is complete.",)),
        model_choice=ModelChoice(chosen="pinhole", candidates={"pinhole": 0.2, "rational": 0.21}, reason="simplest within 5 %"),
        uncertainty=UncertaintyMap(np.array([0.0, 1919.0]), np.array([0.0, 1079.0]), sigma, np.array([[True, True], [True, False]]),
                                   error_px=sigma * 1.2, error_weight=np.eye(2)),
        coverage_summary={"completeness": 0.93, "missing_regions": [[0, 5]]},
        board=BoardSpec(),
        source={"kind": "folder", "path": "/data/run1"},
        command_line=["calibcoach", "calibrate", "/data/run1", "--square-mm", "30.01"],
        lens_state={"focus_absolute": 120, "autofocus": False},
    )


def test_calibration_json_records_everything_and_rounds_for_reading(tmp_path: Path) -> None:
    path = write_calibration_json(tmp_path / "calibration.json", _payload())
    data = json.loads(path.read_text())
    assert data["model"] == "pinhole" and data["image_size"] == [1920, 1080]
    assert data["camera_matrix"] == K.tolist()  # exact: full precision under camera_matrix
    assert data["dist_coeffs"] == DIST["pinhole"]
    assert data["rms_px"] == 0.123457  # rounded to 6 significant digits
    assert (data["frames_used"], data["corners_used"]) == (3, 117)
    assert [(f["index"], f["name"], f["corners"]) for f in data["frames"]] == [(0, "frame_000.png", 70), (10, "frame_001.png", 35), (20, "frame_002.png", 12)]
    assert data["frames"][2]["rms_px"] is None  # NaN is not JSON; it becomes null
    assert data["frames"][0]["tvec_m"] == [0.01, 0.02, 0.7]
    assert data["verdict"] == {"grade": "good", "trusted": True, "rms_grade": "excellent", "rms_thresholds_px": [0.3, 0.5, 1.0], "reasons": ["Coverage is complete."]}
    assert data["dropped_frames"] == [{"frame_index": 50, "reason": "frame RMS 2.31 px is 6.2x the median"}]
    assert data["dropped_corners"] == [{"frame_index": 10, "corner_id": 7, "residual_px": 1.98765}]
    assert data["uncertainty"]["max_px"] == 0.9
    assert data["uncertainty"]["p95_covered_px"] == pytest.approx(0.29, abs=1e-6)
    assert data["uncertainty"]["expected_error_px"] == pytest.approx(1.2 * np.sqrt((0.01 + 0.04 + 0.09) / 3), abs=1e-6)
    assert data["intrinsic_std"] == {"fx": 2.0, "fy": 2.0, "cx": 0.5, "cy": 0.5, "k1": 0.001}
    assert data["model_choice"]["candidates"] == {"pinhole": 0.2, "rational": 0.21}
    assert data["board"] == BoardSpec().to_dict()
    assert data["coverage"]["missing_regions"] == [[0, 5]]
    assert data["command_line"][-1] == "30.01" and data["source"]["kind"] == "folder"
    assert data["lens_state"] == {"focus_absolute": 120, "autofocus": False}
    assert data["calibcoach_version"] == metadata.version("calibcoach")
    assert datetime.fromisoformat(data["created"]).utcoffset().total_seconds() == 0
    assert_same_camera(load_camera(path), camera("pinhole"))


def test_calibration_json_is_compact_and_written_atomically(tmp_path: Path) -> None:
    path = tmp_path / "calibration.json"
    path.write_text("old")
    write_calibration_json(path, _payload())
    lines = path.read_text().splitlines()
    assert any(line.strip().startswith('{"index": 10, "name": "frame_001.png"') for line in lines)  # one frame, one line
    assert '  "dist_coeffs": [-0.3123456789012345, ' in path.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.json"]  # no temporary left over


def test_calibration_json_refuses_values_json_cannot_hold(tmp_path: Path) -> None:
    with pytest.raises(TypeError, match="cannot hold a complex"):
        write_calibration_json(tmp_path / "c.json", {"x": 1j})
    assert not (tmp_path / "c.json").exists()


def test_payload_rejects_inconsistent_calibration() -> None:
    cal = _calibration()
    broken = Calibration(**{name: getattr(cal, name) for name in Calibration.__dataclass_fields__} | {"rvecs": cal.rvecs[:2]})
    with pytest.raises(ValueError, match="3 views but {'rvecs': 2}"):
        calibration_payload(broken, verdict=Verdict("poor", False, "poor", ()), model_choice=None, uncertainty=None,
                            coverage_summary={}, board=BoardSpec(), source={}, command_line=[], lens_state={})  # fmt: skip


# --- loader errors and model inference ----------------------------------------------------------


def test_load_camera_errors_say_what_to_pass(tmp_path: Path) -> None:
    with pytest.raises(CalibcoachError, match=r"does not exist; pass a calibration.json"):
        load_camera(tmp_path / "missing.yaml")
    with pytest.raises(CalibcoachError, match=r"has no camera_matrix.npy or dist_coeffs.npy"):
        load_camera(tmp_path)
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(CalibcoachError, match="not a calibration file calibcoach knows"):
        load_camera(tmp_path / "notes.txt")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(CalibcoachError, match="is not valid JSON"):
        load_camera(tmp_path / "bad.json")
    path = write_ros_camera_info(tmp_path / "ci.yaml", camera("pinhole"), camera_name="c")
    with pytest.raises(CalibcoachError, match=r"is for 1920x1080 images, not the 640x480 asked for"):
        load_camera(path, image_size=(640, 480))


@pytest.mark.parametrize(("coefficients", "model"), [(4, "fisheye"), (5, "pinhole"), (8, "rational"), (14, "rational")])
def test_npy_model_follows_the_coefficient_count(tmp_path: Path, coefficients: int, model: str) -> None:
    np.save(tmp_path / "camera_matrix.npy", K)
    np.save(tmp_path / "dist_coeffs.npy", np.r_[0.1, -0.05, np.zeros(coefficients - 2)].reshape(1, -1))
    cam = load_camera(tmp_path, image_size=SIZE)
    assert cam.model == model and cam.dist_coeffs[:2].tolist() == [0.1, -0.05]


def test_npy_with_unusable_coefficients_is_refused(tmp_path: Path) -> None:
    np.save(tmp_path / "camera_matrix.npy", K)
    np.save(tmp_path / "dist_coeffs.npy", np.ones((1, 14)))  # thin-prism and tilt terms calibcoach cannot represent
    with pytest.raises(CalibcoachError, match="rational model takes 8 distortion coefficients, got 14"):
        load_camera(tmp_path, image_size=SIZE)
    np.save(tmp_path / "dist_coeffs.npy", np.ones((1, 6)))
    with pytest.raises(CalibcoachError, match="6 distortion coefficients match no model"):
        load_camera(tmp_path, image_size=SIZE)


# --- refused calibrations (issue 11) ------------------------------------------------------------

def _camera_files(folder: Path) -> list[str]:
    """What a downstream tool would load as a camera: .npy matrices, OpenCV YAML, ROS camera_info."""
    return sorted(p.name for p in folder.iterdir() if p.suffix in (".npy", ".yaml", ".yml") or p.name.startswith("depthai"))


def test_a_refused_capture_writes_no_camera_file_and_scale_refuses_it(recordings_dir: Path, tmp_path: Path) -> None:
    from calibcoach.app.cli import main

    out = tmp_path / "refused"
    out.mkdir()
    (out / "camera_info.yaml").write_text("stale: from an earlier run\n")  # an earlier run's camera must go too
    assert main(["calibrate", str(recordings_dir / "frontal_webcam720"), "--out", str(out), "--quiet"]) == 3
    assert _camera_files(out) == []
    assert json.loads((out / "calibration.json").read_text())["verdict"]["trusted"] is False
    assert main(["scale", str(out / "calibration.json"), "--to", "640x360", "--out", str(tmp_path / "s")]) == 2
    assert not (tmp_path / "s").exists() or _camera_files(tmp_path / "s") == []


def test_accept_partial_writes_untrusted_names_that_say_so_inside(recordings_dir: Path, tmp_path: Path) -> None:
    from calibcoach.app.cli import main
    from calibcoach.app.outputs.camera_reader import load_trust

    out = tmp_path / "partial"
    assert main(["calibrate", str(recordings_dir / "frontal_webcam720"), "--out", str(out), "--quiet", "--accept-partial"]) == 3
    names = _camera_files(out)
    assert names == ["calibration_untrusted.yaml", "camera_info_untrusted.yaml", "camera_matrix_untrusted.npy",
                     "dist_coeffs_untrusted.npy"]
    fs = cv2.FileStorage(str(out / "calibration_untrusted.yaml"), cv2.FILE_STORAGE_READ)
    assert int(fs.getNode("trusted").real()) == 0 and fs.getNode("untrusted_because").size() >= 2
    fs.release()
    ros = (out / "camera_info_untrusted.yaml").read_text()
    assert ros.startswith("# UNTRUSTED calibration") and "calibcoach_trusted: false" in ros
    assert "Coverage is only" in (out / "UNTRUSTED.txt").read_text()
    for path in (out / "calibration.json", out / "calibration_untrusted.yaml", out / "camera_info_untrusted.yaml", out):
        assert load_trust(path)[0] is False, path
    assert main(["scale", str(out / "calibration.json"), "--to", "640x360", "--out", str(tmp_path / "s"), "--accept-partial"]) == 0
    assert _camera_files(tmp_path / "s") == ["calibration_untrusted.yaml", "camera_info_untrusted.yaml",
                                             "camera_matrix_untrusted.npy", "dist_coeffs_untrusted.npy"]
