"""Rendering a printed ChArUco board through a distorted lens, by inverse mapping (ray casting).

Why inverse mapping: the simulator is the ground truth for accuracy tests, so each image pixel must
show exactly what the lens model says it sees. Every pixel's unit ray comes from
`CameraModel.unproject` (precomputed once per camera); per pose the rays are intersected with the
board plane and the board texture is sampled where they land. Forward warping (projecting the
texture into the image) cannot follow a fisheye's curvature inside one square and leaves holes.

The pipeline for one frame:
1. `BoardRenderer.radiance`: rays of a supersampled grid (s x s per pixel) hit the plane
   z = 0 of the board frame (`p_cam = R p_board + t`, origin at the outer corner of the top-left
   square, the frame of `cv_board().getChessboardCorners()`); the paper is sampled from a mip
   pyramid of `generateImage` (level chosen from the footprint of each ray, blended trilinearly);
   misses, back-side hits and everything beyond the paper show a fixed cluttered background.
   The s x s samples are averaged with INTER_AREA, which keeps the pixel-centre convention
   (pixel (0, 0) is the centre of the top-left pixel): output pixel i averages supersampled
   pixels s*i .. s*i+s-1 whose mean centre is (i + 0.5) s - 0.5, exactly where
   `CameraModel.resized` puts pixel i. Motion blur averages several such renders.
2. `expose`: vignetting, defocus blur, exposure (low light), sRGB-like gamma, sensor noise, uint8.

All radiance is linear and relative: 1.0 is white paper under full light, before exposure.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np
from scipy.interpolate import RectBivariateSpline

from calibcoach.drivers.lens import CameraModel

if TYPE_CHECKING:  # drivers is the bottom layer: the board type is only named, never imported at run time
    from calibcoach.coverage.board import BoardSpec

# Printed-board reflectances (linear): laser toner is not perfectly black, office paper not 1.0.
INK_REFLECTANCE = 0.05
PAPER_REFLECTANCE = 0.85
# Texture resolution: 128 texels per square keeps level-0 texels smaller than a supersampled pixel
# for any board that fills less than ~2x the image height, so magnification is rare.
TEXTURE_PX_PER_SQUARE = 128
MIP_LEVELS = 7  # 128, 64, ..., 2 texels per square; a square below 2 px is not detectable anyway
# Light from above and behind the camera (camera frame, pointing from the board to the light).
_LIGHT_DIR = np.array([0.25, -0.7, -1.0]) / np.linalg.norm([0.25, -0.7, -1.0])
_AMBIENT = 0.6  # share of the light that does not depend on the board's orientation
# Ray-map construction: exact unprojection on a coarse grid, bicubic spline in between. The spline's
# error is below 3e-8 rad (1e-4 px at f = 2500 px) for all presets; exact unprojection of every
# supersampled pixel of a 720p image would take ~8 s instead of ~0.3 s.
_RAY_GRID_STEP_PX = 8
# sRGB-like transfer: webcams deliver gamma-encoded values, which lifts printed black to ~60 DN.
_GAMMA = 1.0 / 2.2
LOW_LIGHT_GAIN = 0.1  # linear signal scale: white paper drops from ~225 to ~80 DN after gamma
LOW_LIGHT_NOISE_SCALE = 2.5  # the analogue gain that lifts the dark signal lifts read noise too
_REMAP_ROW = 1024  # texture lookups per row of a remap map (remap caps maps at 32767 rows)


@dataclass(frozen=True, slots=True)
class _RayMap:
    """Per-pixel rays of one camera at one supersampling, shared by every renderer of that camera."""

    rays: np.ndarray  # (3, Hs*Ws) float32 unit rays (x, y, z rows), camera frame, row-major over the grid
    pixel_angle_rad: np.ndarray  # (Hs*Ws,) float32 angular size of one supersampled pixel
    size: tuple[int, int]  # (Ws, Hs) supersampled image size
    off_axis_rad: np.ndarray  # (H, W) float32 angle of each output pixel's ray from the optical axis


def _camera_key(camera: CameraModel) -> tuple:
    return (camera.model, camera.camera_matrix.tobytes(), camera.dist_coeffs.tobytes(), camera.image_size)


@functools.lru_cache(maxsize=4)  # a 720p x2 map is ~60 MB; tests and the recording script reuse a few cameras
def _ray_map(key: tuple, supersample: int) -> _RayMap:
    """The rays of the camera `_camera_key` describes, on its grid supersampled s x s per pixel.

    The supersampled grid is `camera.resized((W s, H s))`, whose pixel i sits at (i + 0.5) / s - 0.5
    in output pixels: the INTER_AREA average of s x s of them is centred on the output pixel.
    """
    model, k_bytes, d_bytes, size = key
    camera = CameraModel(model, np.frombuffer(k_bytes).reshape(3, 3), np.frombuffer(d_bytes), size)
    hi = camera.resized((size[0] * supersample, size[1] * supersample))
    rays = _spline_rays(hi)  # (Hs, Ws, 3) float64
    # Angular pixel size: geometric mean of the ray steps along x and y (the last step repeated at the end).
    dx = np.linalg.norm(np.diff(rays, axis=1, append=2 * rays[:, -1:] - rays[:, -2:-1]), axis=2)
    dy = np.linalg.norm(np.diff(rays, axis=0, append=2 * rays[-1:] - rays[-2:-1]), axis=2)
    angle = np.sqrt(dx * dy)
    off_axis_hi = np.arccos(np.clip(rays[..., 2], -1.0, 1.0)).astype(np.float32)
    off_axis = cv2.resize(off_axis_hi, size, interpolation=cv2.INTER_AREA)
    ws, hs = hi.image_size
    return _RayMap(
        rays=np.ascontiguousarray(rays.reshape(-1, 3).T, dtype=np.float32),
        pixel_angle_rad=angle.reshape(-1).astype(np.float32),
        size=(ws, hs),
        off_axis_rad=off_axis,
    )


def _spline_rays(camera: CameraModel) -> np.ndarray:
    """(H, W, 3) float64 unit rays of every pixel: exact on a coarse grid, bicubic in between."""
    w, h = camera.image_size
    step = _RAY_GRID_STEP_PX
    xs = np.arange(-2 * step, w + 2 * step, step, dtype=np.float64)  # 2 knots beyond each edge
    ys = np.arange(-2 * step, h + 2 * step, step, dtype=np.float64)
    gx, gy = np.meshgrid(xs, ys)
    coarse = camera.unproject(np.stack([gx.ravel(), gy.ravel()], axis=1)).reshape(ys.size, xs.size, 3)
    px_x, px_y = np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)
    rays = np.stack([RectBivariateSpline(ys, xs, coarse[..., k], kx=3, ky=3)(px_y, px_x) for k in range(3)], axis=2)
    return rays / np.linalg.norm(rays, axis=2, keepdims=True)


def _background(size: tuple[int, int], seed: int) -> np.ndarray:
    """(H, W) float32 radiance of a static room behind the board (fixed camera, fixed scene).

    Smooth shading at two scales and a dozen furniture-like rectangles (shelves, posters, a monitor)
    whose edges are softened because the room is out of focus behind the board: enough edges and
    dark quads for spurious ArUco candidates, none of them a valid marker. It is kept free of fine
    texture on purpose: sensor noise already fills every pixel, and fine texture would double the
    size of the bundled recordings' PNGs without making detection any harder.
    """
    w, h = size
    # Drawn at a quarter of the size and scaled up: nothing in it is sharper than ~4 px, and
    # blurring 14 full-size layers would dominate the renderer's set-up time.
    wq, hq = max(8, w // 4), max(8, h // 4)
    rng = np.random.default_rng(seed)
    img = np.full((hq, wq), 0.35, np.float32)
    for cells, amplitude in ((4, 0.12), (14, 0.07)):  # lighting across the room, then mid-size clutter
        grid = rng.normal(0.0, amplitude, (max(2, cells * h // w), cells)).astype(np.float32)
        img += cv2.resize(grid, (wq, hq), interpolation=cv2.INTER_CUBIC)
    for _ in range(14):
        x0, y0 = rng.uniform(-0.1, 1.0) * wq, rng.uniform(-0.1, 1.0) * hq
        rw, rh = rng.uniform(0.05, 0.35) * wq, rng.uniform(0.05, 0.35) * hq
        patch = np.zeros((hq, wq), np.float32)
        cv2.rectangle(patch, (int(x0), int(y0)), (int(x0 + rw), int(y0 + rh)), 1.0, thickness=-1)
        img += cv2.GaussianBlur(patch, (0, 0), 0.004 * wq + 0.5) * np.float32(rng.uniform(-0.18, 0.22))
    return np.clip(cv2.resize(img, (w, h), interpolation=cv2.INTER_LINEAR), 0.04, 0.8)


def pose_matrix(rvec: np.ndarray) -> np.ndarray:
    """(3,) Rodrigues vector -> (3, 3) float64 rotation."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
    return R


def interpolate_pose(rvec_a, tvec_a, rvec_b, tvec_b, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """The pose `fraction` (0..1) of the way from a to b: slerp of R, linear t. Returns (3,), (3,)."""
    Ra, Rb = pose_matrix(rvec_a), pose_matrix(rvec_b)
    step, _ = cv2.Rodrigues(Rb @ Ra.T)  # relative rotation as an axis-angle vector
    R = pose_matrix(step.reshape(3) * fraction) @ Ra
    rvec, _ = cv2.Rodrigues(R)
    t = (1 - fraction) * np.asarray(tvec_a, np.float64).reshape(3) + fraction * np.asarray(tvec_b, np.float64).reshape(3)
    return rvec.reshape(3), t


class BoardRenderer:
    """Renders one printed board through one camera; holds the ray map and the board texture.

    At 1280x720 with supersample 2 the ray map costs ~1.2 s and ~60 MB once per camera (cached
    across renderers); a renderer on a cached camera builds in ~0.02 s, and each sub-frame of
    `radiance_exposure` costs ~0.1 s.

    Args:
        camera: the lens and image size to render through.
        spec: the board; its `cv_board(legacy=...)` draws the print.
        supersample: samples per pixel along each axis (2 = 4 samples), averaged with INTER_AREA.
        inverted: white-on-black print (every texel of the paper, margin included, is 1 - value).
        legacy: draw OpenCV's pre-4.6 pattern (differs from the new one for an even row count).
        background_seed: seed of the static background clutter.
        print_warp: a print off its spec: maps (x, y) arrays on the paper (board frame, metres) to
            the spec's (x, y) of what is printed there (None: printed exactly to spec).

    Example:
        >>> from calibcoach.coverage.board import BoardSpec  # doctest: +SKIP
        >>> renderer = BoardRenderer(LENSES["webcam720"], BoardSpec())  # doctest: +SKIP
        >>> image = expose(renderer.radiance(rvec, tvec), rng=np.random.default_rng(0))  # doctest: +SKIP
    """

    def __init__(
        self,
        camera: CameraModel,
        spec: BoardSpec,
        supersample: int = 2,
        inverted: bool = False,
        legacy: bool = False,
        *,
        background_seed: int = 0,
        print_warp: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> None:
        if supersample < 1 or int(supersample) != supersample:
            raise ValueError(f"supersample must be a positive integer, got {supersample}")
        self.camera = camera
        self.spec = spec
        self.supersample = int(supersample)
        self.inverted = bool(inverted)
        self.legacy = bool(legacy)
        self._rays = _ray_map(_camera_key(camera), self.supersample)
        self._background = _background(self._rays.size, background_seed).reshape(-1)  # (Hs*Ws,) float32
        self.square_m = spec.square_mm / 1000.0
        self._texels_per_m = TEXTURE_PX_PER_SQUARE / self.square_m
        self._margin_m = self.square_m  # white paper around the chessboard: one square on each side
        self._print_warp = print_warp
        self._levels = self._texture_pyramid()

    @property
    def off_axis_rad(self) -> np.ndarray:
        """(H, W) float32 angle between each output pixel's ray and the optical axis (for vignetting)."""
        return self._rays.off_axis_rad

    def paper_corners_m(self) -> np.ndarray:
        """(4, 3) float64 corners of the paper (chessboard area plus margin) in the board frame."""
        m = self._margin_m
        w = self.spec.squares_x * self.square_m
        h = self.spec.squares_y * self.square_m
        return np.array([[-m, -m, 0], [w + m, -m, 0], [w + m, h + m, 0], [-m, h + m, 0]], np.float64)

    def _texture_pyramid(self) -> list[np.ndarray]:
        """Reflectance mip levels of the paper, each (Ht / 2^k, Wt / 2^k) float32.

        Level 0 places the chessboard exactly at texel edges: square j spans texels
        [margin + 128 j, margin + 128 (j + 1)), which `generateImage` reproduces exactly when the
        image is (squares + 2) x 128 texels with a 128-texel margin (checked by the tests).
        """
        pps = TEXTURE_PX_PER_SQUARE
        size = ((self.spec.squares_x + 2) * pps, (self.spec.squares_y + 2) * pps)
        board = self.spec.cv_board(legacy=self.legacy)
        img = board.generateImage(size, marginSize=pps, borderBits=1).astype(np.float32) / 255.0
        if self.inverted:
            img = 1.0 - img  # paper black, squares and marker bits white
        level = INK_REFLECTANCE + (PAPER_REFLECTANCE - INK_REFLECTANCE) * img
        levels = [level]
        for _ in range(MIP_LEVELS - 1):  # sizes stay even: 128 * (squares + 2) / 2^6 is an integer
            level = cv2.resize(level, (level.shape[1] // 2, level.shape[0] // 2), interpolation=cv2.INTER_AREA)
            levels.append(level)
        return levels

    def brightness(self, rvec: np.ndarray) -> float:
        """Lambertian light on the paper at orientation rvec (3,): frontal ~0.9, turned away 0.6.

        One factor per pose multiplies the paper's reflectance; the background is not affected.
        """
        facing = -pose_matrix(rvec)[:, 2]  # the printed side's normal: -z of the board frame
        return _AMBIENT + (1 - _AMBIENT) * max(0.0, float(facing @ _LIGHT_DIR))

    def radiance_hi(self, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        """(Hs, Ws) float32 linear radiance at the supersampled resolution, for T_cam_board (rvec, tvec)."""
        R = pose_matrix(rvec)
        t = np.asarray(tvec, np.float64).reshape(3)
        out = self._background.copy()
        ws, hs = self._rays.size
        plane_offset = float(R[:, 2] @ t)  # n . t: distance of the plane from the camera centre along n
        if plane_offset <= 0:
            return out.reshape(hs, ws)  # the camera is behind the board: only its back is visible
        # ray . n for every ray (N,). Written out per component: a BLAS (N, 3) @ (3, 3) product
        # takes ~0.6 s here against ~0.03 s for the three multiply-adds.
        rx, ry, rz = self._rays.rays
        Rf = R.astype(np.float32)
        denom = rx * Rf[0, 2] + ry * Rf[1, 2] + rz * Rf[2, 2]
        idx = np.flatnonzero(denom > 1e-6)  # rays that meet the printed (front) side; <= 0: parallel or back
        rx, ry, rz, denom = rx[idx], ry[idx], rz[idx], denom[idx]
        dist = np.float32(plane_offset) / denom  # (n,) distance along the ray to the plane, metres
        offset = R.T @ t  # board-frame coordinates of the camera centre are -offset
        x_m = dist * (rx * Rf[0, 0] + ry * Rf[1, 0] + rz * Rf[2, 0]) - np.float32(offset[0])
        y_m = dist * (rx * Rf[0, 1] + ry * Rf[1, 1] + rz * Rf[2, 1]) - np.float32(offset[1])
        corners = self.paper_corners_m()
        inside = (x_m >= corners[0, 0]) & (x_m <= corners[1, 0]) & (y_m >= corners[0, 1]) & (y_m <= corners[2, 1])
        idx, x_m, y_m, dist, denom = idx[inside], x_m[inside], y_m[inside], dist[inside], denom[inside]
        if idx.size == 0:
            return out.reshape(hs, ws)
        # Texels per supersampled pixel at level 0: the ray's footprint on the plane, stretched by
        # 1/sqrt(cos incidence) (geometric mean of the stretched and unstretched directions).
        footprint = dist * self._rays.pixel_angle_rad[idx] * np.float32(self._texels_per_m) / np.sqrt(denom)
        level = np.clip(np.log2(np.maximum(footprint, 1.0)), 0.0, MIP_LEVELS - 1.0)
        if self._print_warp is not None:
            x_m, y_m = (np.asarray(a, np.float32) for a in self._print_warp(x_m, y_m))
        # Level-0 texel-edge coordinates; level k's pixel-centre coordinate is edge / 2^k - 0.5.
        u0 = (x_m + np.float32(self._margin_m)) * np.float32(self._texels_per_m)
        v0 = (y_m + np.float32(self._margin_m)) * np.float32(self._texels_per_m)
        values = np.empty(idx.size, np.float32)
        base = np.floor(level).astype(np.int32)
        for k in np.unique(base):
            sel = np.flatnonzero(base == k)
            low = self._sample(k, u0[sel], v0[sel])
            if k + 1 < MIP_LEVELS:
                frac = level[sel] - k
                low = low * (1 - frac) + self._sample(k + 1, u0[sel], v0[sel]) * frac
            values[sel] = low
        out[idx] = values * np.float32(self.brightness(rvec))
        return out.reshape(hs, ws)

    def _sample(self, k: int, u0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        """Bilinear texture lookup at level k for (n,) level-0 edge coordinates; returns (n,) float32."""
        scale = np.float32(1.0 / (1 << int(k)))
        n = u0.size
        # remap wants maps below 32767 rows and columns: lay the n lookups out as rows of 1024.
        rows = -(-n // _REMAP_ROW)
        map_x = np.zeros(rows * _REMAP_ROW, np.float32)
        map_y = np.zeros(rows * _REMAP_ROW, np.float32)
        map_x[:n] = u0 * scale - np.float32(0.5)
        map_y[:n] = v0 * scale - np.float32(0.5)
        sampled = cv2.remap(self._levels[k], map_x.reshape(rows, _REMAP_ROW), map_y.reshape(rows, _REMAP_ROW),
                            cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return sampled.reshape(-1)[:n]

    def radiance(self, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
        """(H, W) float32 linear radiance at the output resolution, the board frozen at (rvec, tvec)."""
        return self.radiance_exposure([(rvec, tvec)])

    def radiance_exposure(self, poses: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """(H, W) float32 mean radiance over sub-frame poses [(rvec (3,), tvec (3,)), ...]: motion blur.

        The supersampled renders are summed first and downsampled once (the average is linear).
        """
        if len(poses) == 0:
            raise ValueError("radiance_exposure needs at least one (rvec, tvec) pose")
        acc = self.radiance_hi(*poses[0])
        for rvec, tvec in poses[1:]:
            acc += self.radiance_hi(rvec, tvec)
        w, h = self.camera.image_size
        return cv2.resize(acc / np.float32(len(poses)), (w, h), interpolation=cv2.INTER_AREA)


def motion_subframes(camera: CameraModel, points_m: np.ndarray, pose_a, pose_b, *, px_per_subframe: float = 2.0,
                     max_subframes: int = 8) -> int:
    """Sub-frames needed to smear the motion a -> b: one per `px_per_subframe` of image motion, capped.

    `points_m` (N, 3) board-frame points (e.g. the paper corners); `pose_a`, `pose_b` are
    (rvec, tvec) pairs. Points that are not in front of the camera at both poses are ignored.
    The cap (8) bounds the cost; beyond ~16 px of motion the board is a smear the detector rejects.
    """
    pts_a = _to_camera(points_m, *pose_a)
    pts_b = _to_camera(points_m, *pose_b)
    front = (pts_a[:, 2] > 1e-3) & (pts_b[:, 2] > 1e-3)
    if not np.any(front):
        return 1
    motion = np.linalg.norm(camera.project(pts_b[front]) - camera.project(pts_a[front]), axis=1)
    motion_px = float(np.max(motion)) if np.all(np.isfinite(motion)) else 0.0
    return int(np.clip(np.ceil(motion_px / px_per_subframe), 1, max_subframes))


def _to_camera(points_m: np.ndarray, rvec, tvec) -> np.ndarray:
    return points_m @ pose_matrix(rvec).T + np.asarray(tvec, np.float64).reshape(1, 3)


def expose(
    radiance: np.ndarray,
    *,
    rng: np.random.Generator,
    blur_sigma_px: float = 0.0,
    noise_sigma_dn: float = 0.0,
    low_light: bool = False,
    vignetting: float = 0.0,
    off_axis_rad: np.ndarray | None = None,
) -> np.ndarray:
    """Turn (H, W) float32 linear radiance into the (H, W) uint8 grey image a webcam would deliver.

    Order follows the light: vignetting and defocus act on light in the lens, the exposure gain
    (x0.1 in low light) at the sensor, then sRGB-like gamma encoding, additive Gaussian noise in
    output DN (x2.5 in low light, the analogue gain lifts read noise too), rounding and clipping.

    Args:
        radiance: (H, W) float32, 1.0 = white paper in full light.
        rng: noise source (seeded by the caller for determinism).
        blur_sigma_px: Gaussian defocus blur, output pixels; 0 = sharp.
        noise_sigma_dn: sensor noise standard deviation in 8-bit digital numbers at normal light.
        low_light: dim scene: darker, noisier.
        vignetting: brightness lost at the most off-axis pixel (0.2 = corners 20% darker),
            quadratic in the ray's angle; needs `off_axis_rad` (H, W) float32.
    Returns:
        (H, W) uint8 image.
    """
    img = radiance.astype(np.float32, copy=True)
    if vignetting > 0:
        if off_axis_rad is None:
            raise ValueError("vignetting needs off_axis_rad, the (H, W) angle of every pixel's ray")
        rel = off_axis_rad / max(float(off_axis_rad.max()), 1e-9)
        img *= 1.0 - np.float32(vignetting) * rel * rel
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), float(blur_sigma_px), borderType=cv2.BORDER_REFLECT)
    gain = LOW_LIGHT_GAIN if low_light else 1.0
    dn = 255.0 * np.power(np.clip(img * np.float32(gain), 0.0, 1.0), np.float32(_GAMMA))
    sigma = noise_sigma_dn * (LOW_LIGHT_NOISE_SCALE if low_light else 1.0)
    if sigma > 0:
        dn = dn + rng.normal(0.0, sigma, dn.shape).astype(np.float32)
    return np.clip(np.rint(dn), 0, 255).astype(np.uint8)


def render_board_view(
    camera: CameraModel,
    spec: BoardSpec,
    rvec: np.ndarray,
    tvec: np.ndarray,
    *,
    supersample: int = 2,
    inverted: bool = False,
    legacy: bool = False,
    blur_sigma_px: float = 0.0,
    noise_sigma_dn: float = 0.0,
    low_light: bool = False,
    vignetting: float = 0.0,
    motion_from: tuple[np.ndarray, np.ndarray] | None = None,
    seed: int = 0,
    print_warp: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
) -> np.ndarray:
    """One (H, W) uint8 grey image of the board at T_cam_board = (rvec (3,), tvec (3,) metres).

    A one-shot convenience over `BoardRenderer` + `expose` (the ray map is cached per camera,
    the texture is rebuilt per call). `motion_from` = (rvec0, tvec0): blur along the motion from
    that pose, with as many sub-frames as the image motion needs (2 px each, at most 8).
    Defaults give a clean image: no blur, no noise, no vignetting. `print_warp`: see `BoardRenderer`.

    Example:
        >>> image = render_board_view(LENSES["webcam720"], BoardSpec(), rvec, tvec)  # doctest: +SKIP
        >>> image.shape, image.dtype  # doctest: +SKIP
        ((720, 1280), dtype('uint8'))
    """
    renderer = BoardRenderer(camera, spec, supersample, inverted, legacy, print_warp=print_warp)
    poses = [(rvec, tvec)]
    if motion_from is not None:
        n = motion_subframes(camera, renderer.paper_corners_m(), motion_from, (rvec, tvec))
        if n > 1:  # the exposure runs from motion_from to (rvec, tvec), both ends included
            poses = [interpolate_pose(*motion_from, rvec, tvec, j / (n - 1)) for j in range(n)]
    radiance = renderer.radiance_exposure(poses)
    return expose(radiance, rng=np.random.default_rng(seed), blur_sigma_px=blur_sigma_px,
                  noise_sigma_dn=noise_sigma_dn, low_light=low_light, vignetting=vignetting,
                  off_axis_rad=renderer.off_axis_rad)
