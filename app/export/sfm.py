"""Structure-from-motion, visual-inertial and expert calibration tools: COLMAP, Kalibr, mrcal.

COLMAP `cameras.txt` (one line `CAMERA_ID MODEL WIDTH HEIGHT PARAMS...`, parameter order of
`colmap/src/colmap/sensor/models.h`):
- pinhole -> `OPENCV` (fx, fy, cx, cy, k1, k2, p1, p2) when k3 is 0, else `FULL_OPENCV` (OPENCV has
  no k3; FULL_OPENCV with k4 = k5 = k6 = 0 is the same 5-term model): exact.
- rational -> `FULL_OPENCV` (fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6): exact.
- fisheye -> `OPENCV_FISHEYE` (fx, fy, cx, cy, k1, k2, k3, k4): exact (theta = atan(r), as cv2.fisheye).
- Pixel convention: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), OpenCV at (0, 0),
  so cx and cy are written +0.5 (models.h: "the upper left pixel center has coordinate (0.5, 0.5)").

Kalibr camchain YAML (`cam0: camera_model, intrinsics [fu, fv, pu, pv], distortion_model,
distortion_coeffs, resolution`), pixel centres at integers as in OpenCV:
- fisheye -> `pinhole` + `equidistant` [k1, k2, k3, k4]: exact (Kalibr's equidistant is cv2.fisheye's).
- pinhole with k3 = 0 -> `pinhole` + `radtan` [k1, k2, p1, p2]: exact.
- pinhole with k3 != 0 -> radtan has no k3: k1, k2, p1, p2 are refitted by least squares to the
  model's projections over the whole image; approximated, the file states the worst deviation,
  and a fit worse than 0.5 px anywhere in the image is refused.
- rational -> refused: Kalibr has no rational (k4..k6 denominator) model, and a radtan fit of a
  lens that needs one is wrong where it matters most (the wide corners).

mrcal `.cameramodel` (mrcal's Python-literal format, read by `mrcal.cameramodel(path)`):
- pinhole -> `LENSMODEL_OPENCV5` (fx, fy, cx, cy, k1, k2, p1, p2, k3): exact.
- rational -> `LENSMODEL_OPENCV8` (... k3, k4, k5, k6): exact.
- fisheye -> refused: mrcal 2.2 has no Kannala-Brandt model (its lens models are PINHOLE,
  STEREOGRAPHIC, LONLAT, LATLON, OPENCV4/5/8/12, CAHVOR(E) and SPLINED_STEREOGRAPHIC); fitting a
  splined model needs mrcal's own solver, so calibcoach does not pretend to.
- extrinsics are the identity (rt_cam_ref = 0): the model is the camera on its own.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from calibcoach.app.export.common import ascii_text, notice_lines, num, out_path
from calibcoach.app.outputs.files import atomic_write_bytes
from calibcoach.drivers.errors import CalibcoachError
from calibcoach.drivers.lens import CameraModel

KALIBR_MAX_FIT_PX = 0.5  # a radtan refit worse than this somewhere in the image is refused
COLMAP_PIXEL_SHIFT = 0.5  # COLMAP's top-left pixel centre is (0.5, 0.5); OpenCV's is (0, 0)


# --- COLMAP -------------------------------------------------------------------------------------


def colmap_camera(camera: CameraModel) -> tuple[str, list[float]]:
    """(COLMAP model name, its parameters in COLMAP's order and pixel convention)."""
    fx, fy = camera.fx, camera.fy
    cx, cy = (c + COLMAP_PIXEL_SHIFT for c in camera.principal_point)
    d = [float(v) for v in camera.dist_coeffs]
    if camera.model == "fisheye":
        return "OPENCV_FISHEYE", [fx, fy, cx, cy, *d]
    if camera.model == "pinhole" and d[4] == 0.0:
        return "OPENCV", [fx, fy, cx, cy, *d[:4]]
    full = d + [0.0] * (8 - len(d))  # pinhole: k4 = k5 = k6 = 0
    return "FULL_OPENCV", [fx, fy, cx, cy, *full]


def write_colmap(out_dir: str | Path, camera: CameraModel, *, untrusted_because: Sequence[str] = ()) -> list[Path]:
    _check_skew(camera, "COLMAP")
    model, params = colmap_camera(camera)
    w, h = camera.image_size
    lines = [
        *notice_lines(untrusted_because),
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        "# Number of cameras: 1",
        f"# written by calibcoach from a {camera.model} model; cx, cy are OpenCV's + 0.5 (COLMAP's pixel centres)",
        f"1 {model} {w} {h} " + " ".join(num(p) for p in params),
        "",
    ]
    return [atomic_write_bytes(out_path(out_dir, "cameras.txt", untrusted_because), "\n".join(lines).encode("ascii"))]


# --- Kalibr -------------------------------------------------------------------------------------


def kalibr_distortion(camera: CameraModel) -> tuple[str, list[float], float]:
    """(Kalibr distortion_model, distortion_coeffs, worst deviation in px of the written model)."""
    if camera.model == "rational":
        raise CalibcoachError(
            "Kalibr has no rational (8-coefficient) distortion model, only radtan (4) and equidistant; "
            "recalibrate with --model pinhole or --model fisheye to export to Kalibr, or use --to colmap/mrcal/ros"
        )
    d = [float(v) for v in camera.dist_coeffs]
    if camera.model == "fisheye":
        return "equidistant", d, 0.0
    if d[4] == 0.0:
        return "radtan", d[:4], 0.0
    model, coeffs, worst = _fit_radtan(camera)
    if worst > KALIBR_MAX_FIT_PX:
        raise CalibcoachError(
            f"Kalibr's radtan model has no k3 and this lens needs it: the best k1 k2 p1 p2 miss the calibration by "
            f"{worst:.2f} px somewhere in the image (more than {KALIBR_MAX_FIT_PX} px); export --to colmap/mrcal/ros, "
            "which hold k3, or recalibrate the lens with Kalibr itself"
        )
    return model, coeffs, worst


def _fit_radtan(camera: CameraModel) -> tuple[str, list[float], float]:
    """k1, k2, p1, p2 fitted to the 5-term model's projections over the image (linear least squares)."""
    w, h = camera.image_size
    u, v = np.meshgrid(np.linspace(-0.5, w - 0.5, 41), np.linspace(-0.5, h - 0.5, 31))
    rays = camera.unproject(np.stack([u.ravel(), v.ravel()], axis=1))
    x, y = rays[:, 0] / rays[:, 2], rays[:, 1] / rays[:, 2]
    target = camera.project(rays)
    r2 = x * x + y * y
    fx, fy = camera.fx, camera.fy
    cx, cy = camera.principal_point
    # u = cx + fx * (x + x (k1 r2 + k2 r4) + 2 p1 x y + p2 (r2 + 2 x^2)), v likewise: linear in (k1, k2, p1, p2)
    a_u = np.stack([fx * x * r2, fx * x * r2**2, fx * 2 * x * y, fx * (r2 + 2 * x * x)], axis=1)
    a_v = np.stack([fy * y * r2, fy * y * r2**2, fy * (r2 + 2 * y * y), fy * 2 * x * y], axis=1)
    b_u, b_v = target[:, 0] - cx - fx * x, target[:, 1] - cy - fy * y
    coeffs = np.linalg.lstsq(np.vstack([a_u, a_v]), np.concatenate([b_u, b_v]), rcond=None)[0]
    fitted = CameraModel("pinhole", camera.camera_matrix, np.append(coeffs, 0.0), camera.image_size)
    worst = float(np.max(np.linalg.norm(fitted.project(rays) - target, axis=1)))
    return "radtan", [float(c) for c in coeffs], worst


def write_kalibr(out_dir: str | Path, camera: CameraModel, *, untrusted_because: Sequence[str] = (),
                 rostopic: str = "/cam0/image_raw") -> list[Path]:
    _check_skew(camera, "Kalibr")
    model, coeffs, worst = kalibr_distortion(camera)
    cx, cy = camera.principal_point
    w, h = camera.image_size
    note = (f"# approximated: Kalibr's radtan has no k3; k1 k2 p1 p2 refitted, worst deviation {worst:.4f} px over the image"
            if worst else "# exact: the same model and coefficients as the calibration")
    lines = [
        *notice_lines(untrusted_because),
        f"# Kalibr camchain written by calibcoach from a {camera.model} model",
        note,
        "cam0:",
        "  camera_model: pinhole",
        f"  intrinsics: [{num(camera.fx)}, {num(camera.fy)}, {num(cx)}, {num(cy)}]",
        f"  distortion_model: {model}",
        f"  distortion_coeffs: [{', '.join(num(c) for c in coeffs)}]",
        f"  resolution: [{w}, {h}]",
        f"  rostopic: {ascii_text(rostopic)}",
        "",
    ]
    return [atomic_write_bytes(out_path(out_dir, "camchain.yaml", untrusted_because), "\n".join(lines).encode("ascii"))]


# --- mrcal --------------------------------------------------------------------------------------

MRCAL_LENSMODEL = {"pinhole": "LENSMODEL_OPENCV5", "rational": "LENSMODEL_OPENCV8"}


def write_mrcal(out_dir: str | Path, camera: CameraModel, *, untrusted_because: Sequence[str] = ()) -> list[Path]:
    if camera.model not in MRCAL_LENSMODEL:
        raise CalibcoachError(
            "mrcal 2.2 has no Kannala-Brandt (cv2.fisheye) lens model, so a fisheye calibration cannot be written "
            "as a .cameramodel without refitting it in mrcal itself (LENSMODEL_SPLINED_STEREOGRAPHIC); "
            "export --to kalibr/colmap/ros instead, or calibrate the lens with mrcal-calibrate-cameras"
        )
    _check_skew(camera, "mrcal")
    cx, cy = camera.principal_point
    intrinsics = [camera.fx, camera.fy, cx, cy, *camera.dist_coeffs]
    w, h = camera.image_size
    lines = [
        *notice_lines(untrusted_because),
        f"# generated by calibcoach from a {camera.model} model (OpenCV's coefficients, unchanged)",
        "{",
        f"    'lensmodel':  '{MRCAL_LENSMODEL[camera.model]}',",
        "    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....",
        f"    'intrinsics': [ {', '.join(num(v) for v in intrinsics)} ],",
        "    # extrinsics are rt_fromref",
        "    'extrinsics': [ 0.0, 0.0, 0.0, 0.0, 0.0, 0.0 ],",
        f"    'imagersize': [ {w}, {h} ],",
        "}",
        "",
    ]
    return [atomic_write_bytes(out_path(out_dir, "camera.cameramodel", untrusted_because), "\n".join(lines).encode("ascii"))]


def _check_skew(camera: CameraModel, tool: str) -> None:
    if abs(camera.camera_matrix[0, 1]) > 1e-9 * camera.fx:
        raise CalibcoachError(f"{tool} has no skew term and this camera matrix has one ({camera.camera_matrix[0, 1]:g}); "
                              "calibrate without skew (calibcoach's default) to export it")
