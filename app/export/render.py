"""Renderers with an ideal pinhole camera: MuJoCo and Blender, plus the maps that add the real lens.

Neither MuJoCo's camera nor Blender's perspective camera can hold lens distortion, so both are
written as an ideal pinhole `K_ideal` (same image size and principal point as the real camera, focal
lengths scaled by `s` <= 1 so that the real image's whole field fits in the render), and
`ideal_to_real_map_x.npy` / `ideal_to_real_map_y.npy` (float32, real image size) turn that render
into the real camera's distorted image:

    real = cv2.remap(rendered, map_x, map_y, cv2.INTER_LINEAR)

Direction: for every pixel of the REAL (distorted) image, the map holds where its ray lands in the
IDEAL render -- the inverse of what `cv2.initUndistortRectifyMap` returns (that one maps each
undistorted pixel to its place in the distorted image). It is computed with `CameraModel.unproject`
(exact to a micropixel) and K_ideal; rays beyond 70 deg off axis (fisheye lenses) cannot reach a
pinhole render and are set to -1 (remap's border). Exact up to float32 storage (~1e-4 px) and bilinear
interpolation; what is approximated is the render itself, sampled at the ideal camera's resolution.

MuJoCo `<camera>` (mujoco_camera.xml): `resolution="W H"`, `sensorsize` (length units; without it
MuJoCo ignores the intrinsics and uses `fovy`), `focalpixel="fx fy"` and `principalpixel` (offset of
the principal point from the image centre, x right and y *down* the image: MuJoCo's frustum is
[(W/2 - px) .. (W/2 + px)] left/right and [(H/2 - py) .. (H/2 + py)] below/above the axis,
engine_vis_visualize.c getFrustum), so px = (W - 1) / 2 - cx and py = cy - (H - 1) / 2 in OpenCV's
pixels. `focal`/`principal` in length units are left out (MuJoCo refuses both forms at once), and so
is `fovy`. MuJoCo stores the intrinsics as 32-bit floats (~1e-4 px). The camera looks down its -z
axis with y up: OpenCV's camera frame is MuJoCo's turned 180 deg about x.

Blender (blender_camera.py, run with `blender --python`): `sensor_fit = 'HORIZONTAL'`,
`sensor_width` 36 mm, `lens = fx_ideal * 36 / W` mm, `shift_x`, `shift_y` in units of the fitted
sensor dimension -- the width here; with sensor_fit 'AUTO' it is the larger one, which is why the
script does not leave it to AUTO -- from u0 = (W - 1) / 2 - shift_x * W and v0 = (H - 1) / 2 +
shift_y * W / (pixel_aspect_y / pixel_aspect_x), and fy != fx through the pixel aspect.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from calibcoach.app.export.common import ascii_text, notice_lines, num, out_path
from calibcoach.app.outputs.files import atomic_write_bytes
from calibcoach.drivers.lens import CameraModel

MAX_OFF_AXIS_DEG = 70.0  # a pinhole render cannot hold rays near 90 deg; fisheye beyond this maps to -1
BLENDER_SENSOR_WIDTH_MM = 36.0
MUJOCO_PIXEL_PITCH = 3e-6  # length units per pixel for sensorsize (metres in most models); any value works


def ideal_camera(camera: CameraModel) -> CameraModel:
    """The distortion-free pinhole a renderer should use: same size and principal point, focal
    lengths scaled down until every ray of the real image (up to MAX_OFF_AXIS_DEG) lands inside."""
    w, h = camera.image_size
    cx, cy = camera.principal_point
    u = np.concatenate([np.linspace(-0.5, w - 0.5, 200), np.full(200, w - 0.5), np.linspace(-0.5, w - 0.5, 200), np.full(200, -0.5)])
    v = np.concatenate([np.full(200, -0.5), np.linspace(-0.5, h - 0.5, 200), np.full(200, h - 0.5), np.linspace(-0.5, h - 0.5, 200)])
    rays = camera.unproject(np.stack([u, v], axis=1))
    rays = rays[rays[:, 2] > np.cos(np.radians(MAX_OFF_AXIS_DEG))]
    x, y = rays[:, 0] / rays[:, 2], rays[:, 1] / rays[:, 2]
    limits = [1.0]
    with np.errstate(divide="ignore", invalid="ignore"):
        for n, f, c, size in ((x, camera.fx, cx, w), (y, camera.fy, cy, h)):
            room = np.where(n > 0, (size - 0.5 - c) / (f * n), (-0.5 - c) / (f * n))
            limits.append(float(np.min(room[np.abs(n) > 1e-12], initial=1.0)))
    s = min(limits)
    K = camera.camera_matrix.copy()
    K[0, 0] *= s
    K[1, 1] *= s
    K[0, 1] *= s
    return CameraModel("pinhole", K, np.zeros(5), camera.image_size)


def ideal_to_real_maps(camera: CameraModel, ideal: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y) float32 (H, W): for each real pixel, where its ray is in the ideal render."""
    w, h = camera.image_size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = camera.unproject(np.stack([u.ravel(), v.ravel()], axis=1))
    ok = rays[:, 2] > np.cos(np.radians(MAX_OFF_AXIS_DEG))
    z = np.where(ok, rays[:, 2], 1.0)
    K = ideal.camera_matrix
    mx = K[0, 0] * rays[:, 0] / z + K[0, 1] * rays[:, 1] / z + K[0, 2]
    my = K[1, 1] * rays[:, 1] / z + K[1, 2]
    mx, my = np.where(ok, mx, -1.0), np.where(ok, my, -1.0)
    return mx.reshape(h, w).astype(np.float32), my.reshape(h, w).astype(np.float32)


def write_maps(out_dir: str | Path, camera: CameraModel, ideal: CameraModel, untrusted_because: Sequence[str]) -> list[Path]:
    paths = []
    for name, array in zip(("ideal_to_real_map_x.npy", "ideal_to_real_map_y.npy"), ideal_to_real_maps(camera, ideal), strict=True):
        buffer = io.BytesIO()
        np.save(buffer, array)
        paths.append(atomic_write_bytes(out_path(out_dir, name, untrusted_because), buffer.getvalue()))
    return paths


# --- MuJoCo -------------------------------------------------------------------------------------


def mujoco_attributes(ideal: CameraModel) -> dict[str, str]:
    w, h = ideal.image_size
    cx, cy = ideal.principal_point
    return {
        "resolution": f"{w} {h}",
        "sensorsize": f"{num(w * MUJOCO_PIXEL_PITCH)} {num(h * MUJOCO_PIXEL_PITCH)}",
        "focalpixel": f"{num(ideal.fx)} {num(ideal.fy)}",
        "principalpixel": f"{num((w - 1) / 2.0 - cx)} {num(cy - (h - 1) / 2.0)}",
    }


def write_mujoco(out_dir: str | Path, camera: CameraModel, *, untrusted_because: Sequence[str] = (),
                 name: str = "calibcoach_camera") -> list[Path]:
    ideal = ideal_camera(camera)
    scale = ideal.fx / camera.fx
    notice = [f"<!-- {line[2:]} -->" for line in notice_lines(untrusted_because)]
    attrs = " ".join(f'{k}="{v}"' for k, v in mujoco_attributes(ideal).items())
    lines = [
        *notice,
        f"<!-- calibcoach {camera.model} calibration as a MuJoCo camera. MuJoCo's camera is an ideal pinhole and",
        "     cannot hold lens distortion: this is the real camera without its distortion, focal lengths x "
        f"{scale:.6f} so the whole real field fits; turn a render into the real image with",
        "     cv2.remap(render, np.load('ideal_to_real_map_x.npy'), np.load('ideal_to_real_map_y.npy'), cv2.INTER_LINEAR).",
        "     Set pos and xyaxes/quat yourself: MuJoCo cameras look down -z with y up (OpenCV's frame turned 180 deg about x). -->",
        f'<camera name="{ascii_text(name)}" mode="fixed" {attrs}/>',
        "",
    ]
    xml = atomic_write_bytes(out_path(out_dir, "mujoco_camera.xml", untrusted_because), "\n".join(lines).encode("ascii"))
    return [xml, *write_maps(out_dir, camera, ideal, untrusted_because)]


# --- Blender ------------------------------------------------------------------------------------


def blender_settings(ideal: CameraModel) -> dict[str, float | int | str]:
    w, h = ideal.image_size
    cx, cy = ideal.principal_point
    ratio = ideal.fx / ideal.fy  # pixel_aspect_y / pixel_aspect_x, Blender keeps both >= 1
    aspect_x, aspect_y = (1.0, ratio) if ratio >= 1 else (1.0 / ratio, 1.0)
    return {
        "RESOLUTION_X": w, "RESOLUTION_Y": h, "PIXEL_ASPECT_X": aspect_x, "PIXEL_ASPECT_Y": aspect_y,
        "SENSOR_FIT": "HORIZONTAL", "SENSOR_WIDTH_MM": BLENDER_SENSOR_WIDTH_MM,
        "LENS_MM": ideal.fx * BLENDER_SENSOR_WIDTH_MM / w,
        "SHIFT_X": ((w - 1) / 2.0 - cx) / w,
        "SHIFT_Y": (cy - (h - 1) / 2.0) * ratio / w,
    }


_BLENDER = '''"""calibcoach {model} calibration as a Blender camera: blender scene.blend --python blender_camera.py

Blender's perspective camera is an ideal pinhole: the lens distortion is not in it. Render, then
    real = cv2.remap(render, np.load("ideal_to_real_map_x.npy"), np.load("ideal_to_real_map_y.npy"), cv2.INTER_LINEAR)
Focal lengths are the real ones x {scale:.6f}, so that the whole real field fits in the render.
"""

import bpy

CAMERA_OBJECT = None  # None: the scene's active camera
TRUSTED = {trusted!r}
{settings}

scene = bpy.context.scene
camera = (bpy.data.objects[CAMERA_OBJECT] if CAMERA_OBJECT else scene.camera).data
scene.render.resolution_x = RESOLUTION_X
scene.render.resolution_y = RESOLUTION_Y
scene.render.resolution_percentage = 100
scene.render.pixel_aspect_x = PIXEL_ASPECT_X
scene.render.pixel_aspect_y = PIXEL_ASPECT_Y
camera.type = "PERSP"
camera.lens_unit = "MILLIMETERS"
camera.sensor_fit = SENSOR_FIT
camera.sensor_width = SENSOR_WIDTH_MM
camera.lens = LENS_MM
camera.shift_x = SHIFT_X
camera.shift_y = SHIFT_Y
if not TRUSTED:
    print("WARNING: calibcoach refused this calibration (written because of --accept-partial)")
'''


def write_blender(out_dir: str | Path, camera: CameraModel, *, untrusted_because: Sequence[str] = ()) -> list[Path]:
    ideal = ideal_camera(camera)
    settings = "\n".join(f"{k} = {v!r}" if isinstance(v, str | int) else f"{k} = {num(v)}"
                         for k, v in blender_settings(ideal).items())
    text = _BLENDER.format(model=camera.model, scale=ideal.fx / camera.fx, trusted=not untrusted_because, settings=settings)
    if untrusted_because:
        text = "\n".join(notice_lines(untrusted_because)) + "\n" + text
    script = atomic_write_bytes(out_path(out_dir, "blender_camera.py", untrusted_because), text.encode("ascii"))
    return [script, *write_maps(out_dir, camera, ideal, untrusted_because)]
