"""Reading a camera back from any file calibcoach writes, or from OpenCV's and ROS's own files.

Kept apart from the writers in `files.py` (which re-exports `load_camera`) because reading has to
accept more than calibcoach writes: OpenCV's `calibration.cpp` YAML without a model name, ROS
camera_info files wrapped by ROS's Python calibrator, bare .npy pairs from a script.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibcoach.drivers.errors import CalibcoachError
from calibcoach.drivers.lens import COEFF_COUNT, CameraModel

_ROS_TO_MODEL = {"plumb_bob": "pinhole", "rational_polynomial": "rational", "equidistant": "fisheye", "fisheye": "fisheye"}
_COUNT_TO_MODEL = {4: "fisheye", 5: "pinhole", 8: "rational", 12: "rational", 14: "rational"}


def load_camera(path: str | Path, *, image_size: tuple[int, int] | None = None) -> CameraModel:
    """Read a camera written by this module (or by OpenCV / ROS tools) back into a `CameraModel`.

    Accepts `calibration.json`, an OpenCV FileStorage file (.yaml/.yml/.xml; recognised by its
    `%YAML` header or extension), a ROS camera_info YAML, or a folder (or one of its .npy files)
    holding `camera_matrix.npy` + `dist_coeffs.npy`. Where the file carries no image size,
    `image_size` (width, height) supplies it; where it carries no model, the coefficient count
    decides: 4 fisheye, 5 pinhole, 8/12/14 rational (extra thin-prism/tilt terms must be zero).

    Raises:
        CalibcoachError: the path is missing, the format is unknown, or size/model cannot be found.
    """
    path = Path(path)
    if path.suffix == ".npy" or path.is_dir():
        return _load_npy_folder(path.parent if path.suffix == ".npy" else path, image_size)
    if not path.is_file():
        raise CalibcoachError(f"calibration file {path} does not exist; pass a calibration.json, .yaml or output folder")
    text = path.read_text(errors="replace")
    if path.suffix == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CalibcoachError(f"{path} is not valid JSON ({exc})") from None
        if isinstance(data, dict) and "camera_matrix" in data and "dist_coeffs" in data:
            size = data.get("image_size")
            return _camera(path, data.get("model"), data["camera_matrix"], data["dist_coeffs"], size, image_size)
        return _load_filestorage(path, image_size)
    if text.lstrip().startswith("%YAML") or path.suffix == ".xml":
        return _load_filestorage(path, image_size)
    if path.suffix in (".yaml", ".yml") and "camera_matrix:" in text:
        return _load_ros(path, text, image_size)
    raise CalibcoachError(
        f"{path} is not a calibration file calibcoach knows (calibration.json, OpenCV YAML, ROS camera_info YAML, "
        "or a folder with camera_matrix.npy and dist_coeffs.npy)"
    )


def load_trust(path: str | Path) -> tuple[bool, list[str]]:
    """(trusted, reasons) of a calibration file: calibcoach's verdict where the file or a
    calibration.json beside it carries one, "untrusted" in the file name, or a `trusted` key of an
    OpenCV YAML / `calibcoach_trusted` of a ROS camera_info. Files of other tools carry none: trusted.
    """
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    names = [path.name] if not path.is_dir() else [p.name for p in folder.glob("*.npy")]
    if any("untrusted" in name for name in names):
        return False, _reasons_beside(folder)
    candidates = [path] if path.suffix == ".json" else []
    if path.is_dir() or path.suffix == ".npy":
        candidates.append(folder / "calibration.json")
    for candidate in candidates:
        if candidate.is_file():
            try:
                data = json.loads(candidate.read_text(errors="replace"))
            except json.JSONDecodeError:
                continue
            verdict = data.get("verdict") if isinstance(data, dict) else None
            if isinstance(verdict, dict) and "trusted" in verdict:
                return bool(verdict["trusted"]), [str(r) for r in verdict.get("reasons", [])[1:4]]  # [0] is the RMS table
    if path.is_file() and path.suffix in (".yaml", ".yml", ".xml"):
        text = path.read_text(errors="replace")
        if "calibcoach_trusted: false" in text:
            return False, [line.strip("# ").strip() for line in text.splitlines()[1:4] if line.startswith("#")]
        if text.lstrip().startswith("%YAML") or path.suffix == ".xml":
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
            try:
                node = fs.getNode("trusted")
                if not node.empty() and int(node.real()) == 0:
                    return False, _reasons_beside(folder)
            finally:
                fs.release()
    return True, []


def _reasons_beside(folder: Path) -> list[str]:
    note = folder / "UNTRUSTED.txt"
    if note.is_file():
        return [line[2:].strip() for line in note.read_text(errors="replace").splitlines() if line.startswith("- ")][:3]
    return []


def _load_npy_folder(folder: Path, image_size: tuple[int, int] | None) -> CameraModel:
    k_path, d_path = folder / "camera_matrix.npy", folder / "dist_coeffs.npy"
    if not k_path.is_file() and (folder / "camera_matrix_untrusted.npy").is_file():  # --accept-partial's names
        k_path, d_path = folder / "camera_matrix_untrusted.npy", folder / "dist_coeffs_untrusted.npy"
    missing = [p.name for p in (k_path, d_path) if not p.is_file()]
    if missing:
        raise CalibcoachError(f"{folder} has no {' or '.join(missing)}; pass the output folder of a calibcoach run")
    K, D = np.load(k_path), np.load(d_path)
    model, size = None, None
    sidecar = folder / "calibration.json"
    if sidecar.is_file():
        data = json.loads(sidecar.read_text())
        model, size = data.get("model"), data.get("image_size")
    return _camera(folder, model, K, D, size, image_size)


def _load_filestorage(path: Path, image_size: tuple[int, int] | None) -> CameraModel:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        if not fs.isOpened():
            raise CalibcoachError(f"OpenCV cannot parse {path} as a FileStorage file")
        K, D = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
        if K is None or D is None:
            raise CalibcoachError(f"{path} has no camera_matrix / distortion_coefficients matrices")
        model_node, w, h = fs.getNode("distortion_model"), fs.getNode("image_width"), fs.getNode("image_height")
        model = model_node.string() if model_node.isString() else None
        size = (int(w.real()), int(h.real())) if not (w.empty() or h.empty()) else None
    finally:
        fs.release()
    return _camera(path, _ROS_TO_MODEL.get(model, model), K, D, size, image_size)


def _load_ros(path: Path, text: str, image_size: tuple[int, int] | None) -> CameraModel:
    data = parse_simple_yaml(text)
    try:
        K = np.asarray(data["camera_matrix"]["data"], np.float64)
        D = np.asarray(data["distortion_coefficients"]["data"], np.float64)
    except (KeyError, TypeError):
        raise CalibcoachError(f"{path} lacks camera_matrix.data or distortion_coefficients.data of a ROS camera_info") from None
    ros_model = data.get("distortion_model")
    if ros_model is not None and ros_model not in _ROS_TO_MODEL:
        raise CalibcoachError(f"{path}: ROS distortion_model {ros_model!r} is not one of {sorted(_ROS_TO_MODEL)}")
    size = (data["image_width"], data["image_height"]) if "image_width" in data and "image_height" in data else None
    return _camera(path, _ROS_TO_MODEL.get(ros_model), K, D, size, image_size)


def _camera(source: Path, model: str | None, K: Any, D: Any, size: Any, image_size: tuple[int, int] | None) -> CameraModel:
    D = np.asarray(D, np.float64).reshape(-1)
    if model is None:
        model = _COUNT_TO_MODEL.get(D.size)
        if model is None:
            raise CalibcoachError(f"{source}: {D.size} distortion coefficients match no model (4 fisheye, 5 pinhole, 8 rational)")
    if size is None:
        if image_size is None:
            raise CalibcoachError(f"{source} does not record the image size; pass it (image_size=(width, height))")
        size = image_size
    size = (int(size[0]), int(size[1]))
    if image_size is not None and tuple(image_size) != size:
        raise CalibcoachError(f"{source} is for {size[0]}x{size[1]} images, not the {image_size[0]}x{image_size[1]} asked for")
    if model not in COEFF_COUNT:
        raise CalibcoachError(f"{source}: unknown distortion model {model!r}; expected one of {sorted(COEFF_COUNT)}")
    try:
        return CameraModel(model, np.asarray(K, np.float64).reshape(3, 3), D, size)
    except ValueError as exc:
        raise CalibcoachError(f"{source}: {exc}") from None


def parse_simple_yaml(text: str) -> dict[str, Any]:
    """Parse the YAML subset of ROS camera_info files: nested `key: value` maps and `[a, b]` lists.

    Values become int, float, str or lists of numbers; `data: [...]` may span several lines (ROS's
    Python calibrator wraps long matrices). Comments and blank lines are skipped.

    Example:
        >>> parse_simple_yaml("a: 1\\nm:\\n  rows: 1\\n  data: [1.5,\\n    2]\\n")
        {'a': 1, 'm': {'rows': 1, 'data': [1.5, 2]}}
    """
    root: dict[str, Any] = {}
    stack: list[tuple[int, dict[str, Any]]] = [(-1, root)]
    pending = ""
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].rstrip() if not pending else raw.strip()
        if pending:
            pending += " " + line
            if "]" not in line:
                continue
            line, pending = pending, ""
        if not line.strip() or line.lstrip().startswith(("%", "---")):
            continue
        if line.count("[") > line.count("]"):
            pending = line
            continue
        indent = len(line) - len(line.lstrip())
        key, sep, value = line.strip().partition(":")
        if not sep:
            raise CalibcoachError(f"cannot parse YAML line {raw!r}: expected 'key: value'")
        while stack[-1][0] >= indent:
            stack.pop()
        parent = stack[-1][1]
        value = value.strip()
        if value:
            parent[key.strip()] = _scalar_or_list(value)
        else:
            child: dict[str, Any] = {}
            parent[key.strip()] = child
            stack.append((indent, child))
    return root


def _scalar_or_list(value: str) -> Any:
    if value.startswith("["):
        return [_scalar(v.strip()) for v in value.strip("[] ").split(",") if v.strip()]
    return _scalar(value)


def _scalar(value: str) -> Any:
    if len(value) >= 2 and value[0] == value[-1] and value[0] in "'\"":
        return value[1:-1]
    for kind in (int, float):
        try:
            return kind(value)
        except ValueError:
            pass
    return value
