"""COLMAP, Kalibr and mrcal exports: each file read back the way its tool reads it, projections compared."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from calibcoach.app.export.sfm import write_colmap, write_kalibr, write_mrcal
from calibcoach.app.outputs.camera_reader import parse_simple_yaml
from calibcoach.drivers.errors import CalibcoachError
from calibcoach.drivers.lens import CameraModel

SIZE = (1280, 720)
K = np.array([[912.3456789, 0.0, 641.2345], [0.0, 915.6789, 357.8912], [0.0, 0.0, 1.0]])
DIST = {
    "pinhole": [-0.291, 0.087, 0.00041, -0.00063, -0.0123],
    "pinhole_no_k3": [-0.291, 0.087, 0.00041, -0.00063, 0.0],
    "rational": [0.41, -0.12, 0.0004, -0.0006, 0.011, 0.72, -0.08, 0.03],
    "fisheye": [0.061, -0.013, 0.0021, -0.0004],
}
TOLERANCE_PX = 0.01


def camera(kind: str) -> CameraModel:
    model = "pinhole" if kind.startswith("pinhole") else kind
    return CameraModel(model, K, np.array(DIST[kind]), SIZE)


def points_over_image(cam: CameraModel, n: int = 25) -> np.ndarray:
    """3D points (camera frame) whose images cover the whole frame, corners included, at 0.5..3 m."""
    w, h = cam.image_size
    u, v = np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, n))
    rays = cam.unproject(np.stack([u.ravel(), v.ravel()], axis=1))
    depth = np.linspace(0.5, 3.0, rays.shape[0])
    return rays / rays[:, 2:3] * depth[:, None]


# --- COLMAP: parse cameras.txt as COLMAP documents it, project with models.h's formulas ----------------


def parse_colmap_cameras(path: Path) -> dict[int, tuple[str, int, int, list[float]]]:
    cameras = {}
    for line in path.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        cam_id, model, width, height, *params = line.split()
        cameras[int(cam_id)] = (model, int(width), int(height), [float(p) for p in params])
    return cameras


def colmap_img_from_cam(model: str, params: list[float], pts: np.ndarray) -> np.ndarray:
    """OpenCVCameraModel / FullOpenCVCameraModel / OpenCVFisheyeCameraModel::ImgFromCam (models.h)."""
    f1, f2, c1, c2, *extra = params
    u, v = pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2]
    u2, uv, v2 = u * u, u * v, v * v
    r2 = u2 + v2
    if model == "OPENCV":
        k1, k2, p1, p2 = extra
        radial = k1 * r2 + k2 * r2 * r2
        du = u * radial + 2 * p1 * uv + p2 * (r2 + 2 * u2)
        dv = v * radial + 2 * p2 * uv + p1 * (r2 + 2 * v2)
    elif model == "FULL_OPENCV":
        k1, k2, p1, p2, k3, k4, k5, k6 = extra
        r4, r6 = r2 * r2, r2 * r2 * r2
        radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
        du = u * radial + 2 * p1 * uv + p2 * (r2 + 2 * u2) - u
        dv = v * radial + 2 * p2 * uv + p1 * (r2 + 2 * v2) - v
    elif model == "OPENCV_FISHEYE":
        k1, k2, k3, k4 = extra
        r = np.sqrt(r2)
        theta = np.arctan(r)
        t2 = theta * theta
        thetad = theta * (1 + k1 * t2 + k2 * t2**2 + k3 * t2**3 + k4 * t2**4)
        du, dv = u * thetad / r - u, v * thetad / r - v
    else:
        raise AssertionError(f"unexpected COLMAP model {model}")
    return np.stack([f1 * (u + du) + c1, f2 * (v + dv) + c2], axis=1)


@pytest.mark.parametrize(("kind", "colmap_model"), [("pinhole", "FULL_OPENCV"), ("pinhole_no_k3", "OPENCV"),
                                                    ("rational", "FULL_OPENCV"), ("fisheye", "OPENCV_FISHEYE")])
def test_colmap_projects_like_the_calibration(tmp_path: Path, kind: str, colmap_model: str) -> None:
    cam = camera(kind)
    (path,) = write_colmap(tmp_path, cam)
    assert path.name == "cameras.txt"
    model, width, height, params = parse_colmap_cameras(path)[1]
    assert (model, width, height) == (colmap_model, *SIZE)
    assert params[2:4] == pytest.approx([K[0, 2] + 0.5, K[1, 2] + 0.5], abs=1e-12)  # COLMAP's pixel centres
    pts = points_over_image(cam)
    colmap_px = colmap_img_from_cam(model, params, pts)
    error = np.max(np.linalg.norm(colmap_px - 0.5 - cam.project(pts), axis=1))
    assert error < TOLERANCE_PX, f"COLMAP {model} misses by {error:.2e} px"
    # without the +0.5 every point would be half a pixel off: the test sees the convention
    assert np.max(np.linalg.norm(colmap_px - cam.project(pts), axis=1)) > 0.7


# --- Kalibr: the camchain keys, projected with aslam's radtan / equidistant formulas ------------------


def kalibr_project(cam0: dict, pts: np.ndarray) -> np.ndarray:
    fu, fv, pu, pv = cam0["intrinsics"]
    x, y = pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2]
    d = cam0["distortion_coeffs"]
    if cam0["distortion_model"] == "radtan":
        k1, k2, p1, p2 = d
        mx2, my2, mxy = x * x, y * y, x * y
        rho2 = mx2 + my2
        rad = k1 * rho2 + k2 * rho2 * rho2
        x, y = x + x * rad + 2 * p1 * mxy + p2 * (rho2 + 2 * mx2), y + y * rad + 2 * p2 * mxy + p1 * (rho2 + 2 * my2)
    elif cam0["distortion_model"] == "equidistant":
        k1, k2, k3, k4 = d
        r = np.sqrt(x * x + y * y)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + k1 * t2 + k2 * t2**2 + k3 * t2**3 + k4 * t2**4)
        scale = np.where(r > 1e-8, theta_d / np.maximum(r, 1e-300), 1.0)
        x, y = x * scale, y * scale
    else:
        raise AssertionError(cam0["distortion_model"])
    return np.stack([fu * x + pu, fv * y + pv], axis=1)


@pytest.mark.parametrize(("kind", "distortion_model"), [("pinhole_no_k3", "radtan"), ("fisheye", "equidistant")])
def test_kalibr_camchain_is_exact_where_kalibr_has_the_model(tmp_path: Path, kind: str, distortion_model: str) -> None:
    cam = camera(kind)
    (path,) = write_kalibr(tmp_path, cam)
    cam0 = parse_simple_yaml(path.read_text())["cam0"]
    assert set(cam0) == {"camera_model", "intrinsics", "distortion_model", "distortion_coeffs", "resolution", "rostopic"}
    assert (cam0["camera_model"], cam0["distortion_model"], cam0["resolution"]) == ("pinhole", distortion_model, list(SIZE))
    pts = points_over_image(cam)
    error = np.max(np.linalg.norm(kalibr_project(cam0, pts) - cam.project(pts), axis=1))
    assert error < TOLERANCE_PX, f"Kalibr {distortion_model} misses by {error:.2e} px"


def test_kalibr_refits_a_small_k3_and_says_how_far_off_it_is(tmp_path: Path) -> None:
    d = np.array(DIST["pinhole"])
    d[4] = -0.002
    cam = CameraModel("pinhole", K, d, SIZE)
    (path,) = write_kalibr(tmp_path, cam)
    text = path.read_text()
    claimed = float(text.split("worst deviation ")[1].split(" px")[0])
    pts = points_over_image(cam, 41)
    error = np.max(np.linalg.norm(kalibr_project(parse_simple_yaml(text)["cam0"], pts) - cam.project(pts), axis=1))
    assert 0 < error < 0.5 and error <= claimed + 0.01


def test_kalibr_refuses_what_it_cannot_hold(tmp_path: Path) -> None:
    with pytest.raises(CalibcoachError, match="no rational"):
        write_kalibr(tmp_path, camera("rational"))
    with pytest.raises(CalibcoachError, match="no k3"):
        write_kalibr(tmp_path, camera("pinhole"))  # k3 = -0.0123 cannot be refitted within 0.5 px
    assert list(tmp_path.iterdir()) == []


# --- mrcal: read back by Debian's python3-mrcal ------------------------------------------------------

_MRCAL_PROJECT = """
import json, sys
import numpy as np
import mrcal
args = json.load(sys.stdin)
model = mrcal.cameramodel(args["path"])
lensmodel, intrinsics = model.intrinsics()
print(json.dumps({"lensmodel": lensmodel, "imagersize": [int(v) for v in model.imagersize()],
                  "px": mrcal.project(np.array(args["points"]), lensmodel, intrinsics).tolist()}))
"""


def _system_mrcal() -> str:
    python = "/usr/bin/python3"
    if not Path(python).is_file() or shutil.which(python) is None:
        pytest.skip("/usr/bin/python3 is absent, so Debian's python3-mrcal cannot be run (apt-get install python3-mrcal)")
    probe = subprocess.run([python, "-c", "import mrcal"], capture_output=True, env=_clean_env(), check=False)
    if probe.returncode != 0:
        pytest.skip("/usr/bin/python3 has no mrcal module: apt-get install -y python3-mrcal (.ci/run does)")
    return python


def _clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}


@pytest.mark.parametrize(("kind", "lensmodel"), [("pinhole", "LENSMODEL_OPENCV5"), ("rational", "LENSMODEL_OPENCV8")])
@pytest.mark.parametrize("untrusted", [False, True])
def test_mrcal_reads_the_cameramodel_and_projects_the_same(tmp_path: Path, kind: str, lensmodel: str, untrusted: bool) -> None:
    python = _system_mrcal()
    cam = camera(kind)
    because = ["Coverage is only 40 %."] if untrusted else []
    (path,) = write_mrcal(tmp_path, cam, untrusted_because=because)
    assert path.name == ("camera_untrusted.cameramodel" if untrusted else "camera.cameramodel")
    assert path.read_text().startswith("# UNTRUSTED") == untrusted
    pts = points_over_image(cam)
    run = subprocess.run([python, "-c", _MRCAL_PROJECT], input=json.dumps({"path": str(path), "points": pts.tolist()}),
                         capture_output=True, text=True, env=_clean_env(), check=False, timeout=120)
    assert run.returncode == 0, run.stderr
    answer = json.loads(run.stdout)
    assert answer["lensmodel"] == lensmodel and answer["imagersize"] == list(SIZE)
    error = np.max(np.linalg.norm(np.array(answer["px"]) - cam.project(pts), axis=1))
    assert error < TOLERANCE_PX, f"mrcal {lensmodel} misses by {error:.2e} px"


def test_mrcal_refuses_a_fisheye_with_the_reason(tmp_path: Path) -> None:
    with pytest.raises(CalibcoachError, match="no Kannala-Brandt"):
        write_mrcal(tmp_path, camera("fisheye"))
    assert list(tmp_path.iterdir()) == []
