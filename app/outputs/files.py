"""Calibration files other tools read: numpy arrays, OpenCV FileStorage YAML, ROS camera_info, JSON.

Each writer targets one consumer and uses that consumer's own conventions, so the file can be used
without calibcoach:
- `camera_matrix.npy` / `dist_coeffs.npy`: the arrays in the shapes OpenCV's calibration calls
  return them -- (1, N) for pinhole and rational (`calibrateCamera`), (4, 1) for fisheye
  (`cv2.fisheye.calibrate`) -- so `cv2.undistort(img, K, D)` or `cv2.fisheye.undistortImage(img, K, D)`
  take them as loaded;
- `calibration.yaml`: OpenCV FileStorage written by `cv2.FileStorage` itself, the keys of OpenCV's
  `calibration.cpp` sample plus `distortion_model`, so C++ and Python OpenCV read it back;
- `camera_info.yaml`: the ROS camera_info format of `camera_calibration` / `camera_info_manager`;
- `calibration.json`: everything the run knew (verdict, coverage, uncertainty, the command line), so a
  result can be traced and rerun (mrcal writes the command line into every model for the same reason).

All writes are atomic (a temporary file in the same folder, then `os.replace`): an interrupted run
never leaves half a calibration behind. `load_camera` (in camera_reader.py, re-exported here) reads
any of these back into a `CameraModel`.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import secrets
from collections.abc import Iterable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

import calibcoach
from calibcoach.app.outputs.camera_reader import load_camera, parse_simple_yaml
from calibcoach.app.solve.result import Calibration, ModelChoice, UncertaintyMap, Verdict
from calibcoach.coverage.board import BoardSpec
from calibcoach.drivers.errors import CalibcoachError
from calibcoach.drivers.lens import ROS_DISTORTION_NAME, CameraModel

DIST_COEFF_NAMES = {
    "pinhole": ("k1", "k2", "p1", "p2", "k3"),
    "rational": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "fisheye": ("k1", "k2", "k3", "k4"),
}
EXACT_JSON_KEYS = ("camera_matrix", "dist_coeffs")  # written at full float precision in calibration.json
__all__ = [  # load_camera / parse_simple_yaml live in camera_reader.py; the pipeline imports them from here
    "EXACT_JSON_KEYS",
    "atomic_write_bytes",
    "calibration_payload",
    "load_camera",
    "opencv_dist_layout",
    "parse_simple_yaml",
    "ros_camera_name",
    "write_calibration_json",
    "write_npy",
    "write_opencv_yaml",
    "write_ros_camera_info",
]
_FS_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


# --- atomic writes ------------------------------------------------------------------------------


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write `data` to `path` through a temporary file in the same folder and `os.replace`.

    Readers see either the old file or the complete new one, never a partial write. Parent folders
    are created; the file gets the usual permissions (0o666 less the umask), unlike `mkstemp`'s 0o600.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary_name(path)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _temporary_name(path: Path) -> Path:
    """A hidden sibling of `path` with the same extension (OpenCV picks its format from it)."""
    return path.with_name(f".{path.stem}.{secrets.token_hex(6)}.tmp{path.suffix}")


def opencv_dist_layout(camera: CameraModel) -> np.ndarray:
    """Distortion coefficients shaped as OpenCV's calibration returns them for the camera's model.

    Returns:
        (1, 5) or (1, 8) float64 for pinhole / rational (`cv2.calibrateCamera`), (4, 1) float64 for
        fisheye (`cv2.fisheye.calibrate`).
    """
    d = np.asarray(camera.dist_coeffs, np.float64)
    return d.reshape(-1, 1) if camera.model == "fisheye" else d.reshape(1, -1)


# --- writers --------------------------------------------------------------------------------------


def write_npy(out_dir: str | Path, camera: CameraModel, *, suffix: str = "") -> tuple[Path, Path]:
    """Write `camera_matrix.npy` (3, 3) and `dist_coeffs.npy` in OpenCV's layout (see module docstring).

    `suffix` goes before the extension (`camera_matrix_untrusted.npy`): an .npy file cannot say
    inside that it is untrusted, so its name must.

    The image size and model are not in these files; `load_camera` takes them from a
    `calibration.json` beside them, or from its `image_size` argument and the coefficient count.

    Returns:
        The two paths written.
    """
    out_dir = Path(out_dir)
    paths = []
    for name, array in ((f"camera_matrix{suffix}.npy", camera.camera_matrix), (f"dist_coeffs{suffix}.npy", opencv_dist_layout(camera))):
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(array, dtype=np.float64))
        paths.append(atomic_write_bytes(out_dir / name, buf.getvalue()))
    return paths[0], paths[1]


def write_opencv_yaml(
    path: str | Path, camera: CameraModel, *, rms_px: float | None, extra: Mapping[str, Any] | None = None
) -> Path:
    """Write an OpenCV FileStorage file with `cv2.FileStorage`, so OpenCV (C++ or Python) reads it back.

    Keys: `calibration_time` (UTC ISO 8601), `image_width`, `image_height`, `camera_matrix`,
    `distortion_coefficients` (OpenCV's layout, see `opencv_dist_layout`), `distortion_model`
    ("pinhole" | "rational" | "fisheye"), `avg_reprojection_error` (px; left out when `rms_px` is None,
    e.g. for a camera rescaled from another calibration, which has no error of its own), then `extra`: ints, floats,
    bools (as 0/1), strings, numeric arrays or lists (as matrices), lists of strings, nested dicts.
    The path's extension picks the format as in OpenCV (.yaml/.yml, .xml, .json).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary_name(path if path.suffix else path.with_suffix(".yaml"))
    try:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        if not fs.isOpened():
            raise CalibcoachError(f"cannot write {path}: OpenCV could not open a file there; pass a writable --out folder")
        try:
            fs.write("calibration_time", datetime.now(UTC).isoformat(timespec="seconds"))
            fs.write("image_width", int(camera.image_size[0]))
            fs.write("image_height", int(camera.image_size[1]))
            fs.write("camera_matrix", camera.camera_matrix)
            fs.write("distortion_coefficients", opencv_dist_layout(camera))
            fs.write("distortion_model", camera.model)
            if rms_px is not None:
                fs.write("avg_reprojection_error", float(rms_px))
            _fs_write_map(fs, extra or {})
        finally:
            fs.release()
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _fs_write_map(fs: cv2.FileStorage, values: Mapping[str, Any]) -> None:
    for key, value in values.items():
        if not _FS_KEY.match(str(key)):
            raise CalibcoachError(f"OpenCV YAML key {key!r} is not a valid FileStorage name (letters, digits, underscore)")
        _fs_write(fs, str(key), value)


def _fs_write(fs: cv2.FileStorage, key: str, value: Any) -> None:
    if isinstance(value, Mapping):
        fs.startWriteStruct(key, cv2.FileNode_MAP)
        _fs_write_map(fs, value)
        fs.endWriteStruct()
    elif isinstance(value, bool | np.bool_):
        fs.write(key, int(value))
    elif isinstance(value, int | np.integer):
        fs.write(key, int(value))
    elif isinstance(value, float | np.floating):
        fs.write(key, float(value))
    elif isinstance(value, str):
        fs.write(key, value)
    elif isinstance(value, list | tuple) and all(isinstance(v, str) for v in value):
        fs.startWriteStruct(key, cv2.FileNode_SEQ)
        for v in value:
            fs.write("", v)
        fs.endWriteStruct()
    else:
        array = np.asarray(value, dtype=np.float64)
        fs.write(key, array.reshape(1, -1) if array.ndim <= 1 else array.reshape(array.shape[0], -1))


def ros_camera_name(name: str) -> str:
    """`name` made valid for camera_info_manager, which accepts letters, digits and underscores only.

    Example:
        >>> ros_camera_name("OAK-D Lite/rgb")
        'OAK_D_Lite_rgb'
    """
    clean = re.sub(r"[^A-Za-z0-9_]", "_", name.strip())
    return clean or "camera"


def write_ros_camera_info(path: str | Path, camera: CameraModel, *, camera_name: str,
                          untrusted_because: Sequence[str] = ()) -> Path:
    """Write a ROS camera_info YAML in the layout `camera_calibration` and `camera_info_manager` write.

    `distortion_model` is plumb_bob (5 coefficients), rational_polynomial (8) or equidistant (the 4
    Kannala-Brandt coefficients, which image_proc feeds to `cv2.fisheye`). The rectification matrix
    is the identity and the projection matrix is [K | 0]: a monocular camera rectified to its own K.
    Numbers are written at full precision, always with a decimal point, so YAML 1.1 readers (PyYAML,
    which `camera_info_manager_py` uses) parse them as floats. `camera_name` goes through
    `ros_camera_name`. With `untrusted_because`, the file opens with comment lines saying so and
    why, and carries `calibcoach_trusted: false` (ROS's parsers ignore keys they do not know).
    """
    K = camera.camera_matrix
    P = np.hstack([K, np.zeros((3, 1))])
    d = camera.dist_coeffs
    lines = [
        f"image_width: {int(camera.image_size[0])}",
        f"image_height: {int(camera.image_size[1])}",
        f"camera_name: {ros_camera_name(camera_name)}",
        *_ros_matrix("camera_matrix", K),
        f"distortion_model: {ROS_DISTORTION_NAME[camera.model]}",
        *_ros_matrix("distortion_coefficients", d.reshape(1, -1)),
        *_ros_matrix("rectification_matrix", np.eye(3)),
        *_ros_matrix("projection_matrix", P),
        "",
    ]
    if untrusted_because:
        notice = ["# UNTRUSTED calibration (calibcoach refused it; written because of --accept-partial):"]
        notice += [f"#   {reason.encode('ascii', 'replace').decode()}" for reason in untrusted_because]
        lines = notice + lines[:-1] + ["calibcoach_trusted: false", ""]
    return atomic_write_bytes(path, "\n".join(lines).encode("ascii"))


def _ros_matrix(name: str, m: np.ndarray) -> list[str]:
    data = ", ".join(_yaml_float(x) for x in np.asarray(m, np.float64).reshape(-1))
    return [f"{name}:", f"  rows: {m.shape[0]}", f"  cols: {m.shape[1]}", f"  data: [{data}]"]


def _yaml_float(x: float) -> str:
    """Shortest round-trip repr with a '.' in the mantissa (YAML 1.1 reads '1e-05' as a string)."""
    if not math.isfinite(x):
        raise CalibcoachError(f"calibration contains a non-finite value ({x}); it cannot be written to camera_info")
    text = repr(float(x))
    mantissa, _, exponent = text.partition("e")
    if "." not in mantissa:
        mantissa += ".0"
    return f"{mantissa}e{'' if exponent.startswith('-') else '+'}{exponent.lstrip('+')}" if exponent else mantissa


# --- calibration.json ---------------------------------------------------------------------------


def calibration_payload(
    calibration: Calibration,
    *,
    verdict: Verdict,
    model_choice: ModelChoice | None,
    uncertainty: UncertaintyMap | None,
    coverage_summary: Mapping[str, Any],
    board: BoardSpec,
    source: Mapping[str, Any],
    command_line: Iterable[str],
    lens_state: Mapping[str, Any],
) -> dict[str, Any]:
    """Everything `calibration.json` records about one solve, as plain Python/numpy values.

    The camera comes first (what other tools need), then how good it is (verdict, per-frame errors,
    what was dropped, uncertainty), then how to reproduce it (board, source, command line, version,
    the lens controls that were locked). `write_calibration_json` turns numpy values into JSON.
    """
    cam = calibration.camera
    n_views = len(calibration.views)
    shapes = {"per_view_rms_px": calibration.per_view_rms_px.shape[0], "rvecs": len(calibration.rvecs), "tvecs": len(calibration.tvecs)}
    bad = {k: v for k, v in shapes.items() if v != n_views}
    if bad:
        raise ValueError(f"calibration has {n_views} views but {bad} entries; the solve produced inconsistent arrays")
    frames = [
        {
            "index": int(view.frame_index),
            "name": view.frame_name,
            "rms_px": float(calibration.per_view_rms_px[i]),
            "corners": int(view.ids.size),
            "rvec": np.asarray(calibration.rvecs[i]).reshape(3),
            "tvec_m": np.asarray(calibration.tvecs[i]).reshape(3),
        }
        for i, view in enumerate(calibration.views)
    ]
    std = calibration.intrinsic_std
    return {
        "model": cam.model,
        "image_size": [int(cam.image_size[0]), int(cam.image_size[1])],
        "camera_matrix": cam.camera_matrix,
        "dist_coeffs": cam.dist_coeffs.reshape(-1),
        "dist_coeff_names": list(DIST_COEFF_NAMES[cam.model]),
        "ros_distortion_model": ROS_DISTORTION_NAME[cam.model],
        "rms_px": float(calibration.rms_px),
        "frames_used": n_views,
        "corners_used": calibration.corner_count,
        "verdict": {
            "grade": verdict.grade,
            "trusted": bool(verdict.trusted),
            "rms_grade": verdict.rms_grade,
            "rms_thresholds_px": list(verdict.rms_thresholds_px),
            "reasons": list(verdict.reasons),
        },
        "intrinsic_std": {name: float(std[i]) for i, name in enumerate(calibration.intrinsic_names)},
        "uncertainty": None
        if uncertainty is None
        else {
            "expected_error_px": uncertainty.expected_error_px,
            "p95_px": uncertainty.p95_px,
            "p95_covered_px": uncertainty.p95_covered_px,
            "max_px": float(np.max(uncertainty.sigma_px)),
        },
        "model_choice": None
        if model_choice is None
        else {"chosen": model_choice.chosen, "candidates": dict(model_choice.candidates), "reason": model_choice.reason},
        "coverage": dict(coverage_summary),
        "frames": frames,
        "dropped_frames": [{"frame_index": int(d.frame_index), "reason": d.reason} for d in calibration.dropped_frames],
        "dropped_corners": [
            {"frame_index": int(d.frame_index), "corner_id": int(d.corner_id), "residual_px": float(d.residual_px)}
            for d in calibration.dropped_corners
        ],
        "board": board.to_dict(),
        "source": dict(source),
        "lens_state": dict(lens_state),
        "command_line": [str(a) for a in command_line],
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "calibcoach_version": calibcoach.__version__,
    }


def write_calibration_json(
    path: str | Path,
    payload: Mapping[str, Any],
    *,
    significant_digits: int = 6,
    exact_keys: Iterable[str] = EXACT_JSON_KEYS,
) -> Path:
    """Write `payload` as readable JSON, atomically.

    numpy arrays and scalars become lists and numbers; floats are rounded to `significant_digits`
    (6 digits keep a residual to 1e-6 px relative, and keep the file readable) except under a key
    in `exact_keys` (the camera matrix and distortion), which is written at full precision so that
    `load_camera` gives back the solved camera exactly. NaN and infinity become `null`. Lists of
    numbers stay on one line and small records (one frame, one dropped corner) take one line each.
    """
    exact = frozenset(exact_keys)
    tree = _jsonable(payload, significant_digits, exact, keep=False)
    return atomic_write_bytes(path, (_dump(tree, 0) + "\n").encode("utf-8"))


def _jsonable(value: Any, digits: int, exact: frozenset[str], *, keep: bool) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v, digits, exact, keep=keep or str(k) in exact) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, list | tuple | set | frozenset):
        items = sorted(value) if isinstance(value, set | frozenset) else value
        return [_jsonable(v, digits, exact, keep=keep) for v in items]
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            return None
        return value if keep or value == 0 else float(f"{value:.{digits}g}")
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"calibration.json cannot hold a {type(value).__name__} ({value!r}); convert it in the payload")


def _dump(value: Any, depth: int) -> str:
    flat = not isinstance(value, dict | list) or all(
        not isinstance(v, dict | list) or (isinstance(v, list) and all(not isinstance(x, dict | list) for x in v))
        for v in (value.values() if isinstance(value, dict) else value)
    )
    if flat:  # encoded whole only here: encoding every level whole first costs the file's depth times over
        inline = json.dumps(value, ensure_ascii=False)
        if not isinstance(value, dict) or len(inline) + 2 * depth <= 150:
            return inline
    pad, inner = "  " * depth, "  " * (depth + 1)
    if isinstance(value, dict):
        body = ",\n".join(f"{inner}{json.dumps(k, ensure_ascii=False)}: {_dump(v, depth + 1)}" for k, v in value.items())
        return "{\n" + body + "\n" + pad + "}"
    return "[\n" + ",\n".join(inner + _dump(v, depth + 1) for v in value) + "\n" + pad + "]"
