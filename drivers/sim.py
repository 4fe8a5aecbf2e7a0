"""The simulated camera: a handheld ChArUco capture rendered through a known lens, with ground truth.

It is the project's ground truth for accuracy tests (the true lens and every true board pose are
known), the source of the README's demo recording, and the benchmark input. It has to look like
real footage, so a tool tuned on it also works on a webcam: perspective and lens distortion are
rendered exactly (`sim_render`), the board moves like a hand holds it (`sim_paths`), and frames
carry motion blur, defocus, vignetting, gamma, sensor noise and, optionally, low light.

The pieces:
- `LENSES`: four lens presets (70 deg webcam, 115 deg wide, 150 deg fisheye, 1080p webcam).
- `handheld_path` (from `sim_paths`): board poses for a "careful", "sloppy" or "frontal" capture.
- `render_board_view` / `BoardRenderer` (from `sim_render`): one image of the board at one pose.
- `SimulatedCamera`: a `FrameSource` that renders a path frame by frame, deterministically.

Example:
    >>> from calibcoach.coverage.board import BoardSpec  # doctest: +SKIP
    >>> camera = LENSES["webcam720"]  # doctest: +SKIP
    >>> poses = handheld_path(camera, BoardSpec(), "careful", seconds=15, fps=10, seed=1)  # doctest: +SKIP
    >>> with SimulatedCamera(camera, BoardSpec(), poses, lens_name="webcam720") as source:  # doctest: +SKIP
    ...     for frame in source:
    ...         ...
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np

from calibcoach.drivers.base import Frame, FrameSource, SourceInfo
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.sim_paths import (
    STYLES,
    Pose,
    Trajectory,
    board_tilt_deg,
    handheld_path,
    handheld_trajectory,
    place_board,
)
from calibcoach.drivers.sim_render import (
    BoardRenderer,
    expose,
    interpolate_pose,
    motion_subframes,
    render_board_view,
)

if TYPE_CHECKING:  # drivers is the bottom layer: the board type is only named, never imported at run time
    from calibcoach.coverage.board import BoardSpec

__all__ = [
    "LENSES",
    "STYLES",
    "BoardRenderer",
    "Pose",
    "SimTruth",
    "SimulatedCamera",
    "Trajectory",
    "board_tilt_deg",
    "handheld_path",
    "handheld_trajectory",
    "place_board",
    "render_board_view",
]


def _lens(model: str, size: tuple[int, int], fx: float, fy: float, cx: float, cy: float, dist: Sequence[float]) -> CameraModel:
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return CameraModel(model, K, np.array(dist, np.float64), size)


# Focal lengths were solved for the field of view (through the edge midpoints, distortion
# included) and rounded; tests/drivers/test_sim.py checks each FOV and that every lens maps the
# whole image one-to-one (unproject -> project round trip, angle increasing to the corners).
# Principal points sit a few pixels off the image centre ((w - 1) / 2, (h - 1) / 2), as on real sensors.
LENSES: dict[str, CameraModel] = {
    # A typical 720p USB webcam: ~70 deg horizontal, mild barrel distortion.
    "webcam720": _lens("pinhole", (1280, 720), 954.0, 953.1, 643.8, 356.8, [-0.12, 0.08, 0.0009, -0.0006, -0.02]),
    # An action-camera-like wide lens, ~115 deg: the rational model's denominator (k4..k6) keeps
    # the profile monotonic out to ~76 deg off axis, beyond the image corners (65 deg).
    "wide720": _lens("rational", (1280, 720), 655.5, 655.0, 636.4, 361.7,
                     [0.6, 0.1, 0.0004, -0.0003, 0.002, 0.95, 0.25, 0.01]),
    # A 150 deg Kannala-Brandt fisheye; the image corners look 86 deg off axis.
    "fisheye150": _lens("fisheye", (1280, 720), 483.8, 483.5, 641.9, 361.1, [0.02, -0.01, 0.002, -0.0005]),
    # A 1080p webcam, ~75 deg horizontal.
    "webcam1080": _lens("pinhole", (1920, 1080), 1292.2, 1291.0, 954.3, 543.4, [-0.08, 0.05, 0.0005, 0.0004, -0.01]),
}

# Exposure: 20 ms under office light; low light doubles it (auto-exposure), so motion smears more,
# up to the frame interval: a camera cannot expose one frame for longer than it takes to deliver it
# (in less light a webcam lowers its frame rate instead, or raises its gain).
EXPOSURE_S = 0.02
LOW_LIGHT_EXPOSURE_FACTOR = 2.0


def effective_exposure_s(exposure_s: float, *, low_light: bool, fps: float | None) -> float:
    """The exposure a frame gets: `exposure_s`, doubled in low light, at most 1 / fps."""
    exposure = float(exposure_s) * (LOW_LIGHT_EXPOSURE_FACTOR if low_light else 1.0)
    return exposure if fps is None else min(exposure, 1.0 / float(fps))


def lens_name_of(camera: CameraModel) -> str:
    """The preset name of `camera`, or "custom" when it is none of `LENSES`."""
    for name, preset in LENSES.items():
        if (preset.model == camera.model and preset.image_size == camera.image_size
                and np.array_equal(preset.camera_matrix, camera.camera_matrix)
                and np.array_equal(preset.dist_coeffs, camera.dist_coeffs)):
            return name
    return "custom"


@dataclass(frozen=True, slots=True)
class SimTruth:
    """What the simulator knows and a calibration has to recover."""

    camera: CameraModel  # the lens every frame was rendered through
    poses: tuple[Pose, ...]  # T_cam_board of every frame, in frame order

    def pose_tuples(self) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """[(index, rvec (3,), tvec (3,) metres)], the shape `recording.write_truth` takes."""
        return [(p.index, p.rvec, p.tvec) for p in self.poses]


class SimulatedCamera(FrameSource):
    """Renders a board path through a lens: a live-camera stand-in with known ground truth.

    Args:
        camera: the lens (one of `LENSES`, or any `CameraModel`, e.g. a preset `.resized(...)`).
        spec: the printed board.
        poses: one Pose per frame (from `handheld_path`); the frame rate comes from their timestamps.
        noise_sigma: sensor noise, 8-bit DN at normal light (x2.5 in low light).
        blur_sigma: Gaussian lens blur in pixels (0.6 ~ a focused webcam; 2+ is visibly out of focus).
        low_light: a dim room: ~1/3 of the brightness after gamma, more noise, twice the exposure time
                (at most the frame interval).
        inverted: white-on-black print.
        legacy: OpenCV's pre-4.6 ChArUco pattern.
        seed: noise seed; frame i draws from `default_rng([seed, i])`, so any frame renders the same
            on its own as in sequence.
        lens_name: used in `camera_id` ("sim:<lens_name>"); default: the preset's name or "custom".
        vignetting: brightness lost at the image corners (0.2 = 20%, typical of small webcam lenses).
        exposure_s: exposure time; motion during it smears the board (sub-frames `smear_step_px` apart, at most 8).
        smear_step_px: image motion between the sub-frames of a smear. At 2 px (the default, which
            the cached renders and tests were made with) each half of the exposure moving up to 2 px
            renders as one sharp sub-frame, so smears under ~4 px at the paper's corners do not show
            at all; 0.5 px renders everything over ~1 px as a smear (~1.5x the render time of a
            handheld 720p capture).
        supersample: samples per pixel along each axis.
        trajectory: the continuous path the poses were sampled from (`handheld_trajectory`); with
            it, motion blur follows the real path, without it the path between frames is taken as
            straight (fine at 30 fps, early blur at move starts at 5 fps).
    """

    def __init__(
        self,
        camera: CameraModel,
        spec: BoardSpec,
        poses: Sequence[Pose],
        *,
        noise_sigma: float = 1.5,
        blur_sigma: float = 0.6,
        low_light: bool = False,
        inverted: bool = False,
        legacy: bool = False,
        seed: int = 0,
        lens_name: str | None = None,
        vignetting: float = 0.2,
        exposure_s: float = EXPOSURE_S,
        supersample: int = 2,
        trajectory: Trajectory | None = None,
        smear_step_px: float = 2.0,
    ) -> None:
        super().__init__()
        if not poses:
            raise ValueError("SimulatedCamera needs at least one pose; make them with handheld_path(...)")
        if smear_step_px <= 0:
            raise ValueError(f"smear_step_px must be > 0, got {smear_step_px}")
        if noise_sigma < 0 or blur_sigma < 0 or exposure_s < 0:
            raise ValueError(f"noise_sigma, blur_sigma and exposure_s must be >= 0, got {noise_sigma}, {blur_sigma}, {exposure_s}")
        self.camera = camera
        self.spec = spec
        self.poses = tuple(poses)
        self.noise_sigma = float(noise_sigma)
        self.blur_sigma = float(blur_sigma)
        self.low_light = bool(low_light)
        self.inverted = bool(inverted)
        self.legacy = bool(legacy)
        self.seed = int(seed)
        self.lens_name = lens_name or lens_name_of(camera)
        self.vignetting = float(vignetting)
        self.exposure_s = effective_exposure_s(exposure_s, low_light=low_light, fps=self.fps if len(self.poses) >= 2 else None)
        self.supersample = int(supersample)
        self.smear_step_px = float(smear_step_px)
        self.trajectory = trajectory
        self._renderer: BoardRenderer | None = None  # built on first use: ~0.5-2 s and ~60 MB at 720p
        self._controls = MappingProxyType({"focus_absolute": 0.0})  # fixed-focus lens, nothing to adjust

    @property
    def fps(self) -> float:
        """Frame rate from the pose timestamps (median interval); 30 for a single pose."""
        if len(self.poses) < 2:
            return 30.0
        dt_ns = np.median(np.diff([p.timestamp_ns for p in self.poses]))
        return float(1e9 / dt_ns)

    @property
    def truth(self) -> SimTruth:
        return SimTruth(self.camera, self.poses)

    @property
    def info(self) -> SourceInfo:
        w, h = self.camera.image_size
        extras = [name for name, on in (("low light", self.low_light), ("inverted", self.inverted),
                                        ("legacy", self.legacy)) if on]
        tail = f", {', '.join(extras)}" if extras else ""
        board = {**self.spec.to_dict(), "legacy": self.legacy, "inverted": self.inverted}
        return SourceInfo(
            description=f"simulated {self.lens_name} camera ({w}x{h}, {self.fps:g} fps, {len(self.poses)} frames{tail})",
            kind="sim",
            camera_id=f"sim:{self.lens_name}",
            image_size=(w, h),
            fps=self.fps,
            frame_count=len(self.poses),
            controls=self._controls,
            board=MappingProxyType(board),
        )

    def _get_renderer(self) -> BoardRenderer:
        if self._renderer is None:
            self._renderer = BoardRenderer(self.camera, self.spec, self.supersample, self.inverted, self.legacy)
        return self._renderer

    def exposure_poses(self, i: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """Sub-frame poses [(rvec (3,), tvec (3,))] of frame i's exposure, for motion blur.

        The exposure is centred on the frame's timestamp, so the truth pose (at the timestamp) is
        the centre of any blur and a blurred frame that is still detected is not biased. Its two
        halves follow the path to the previous and the next pose; sub-frames sit at the midpoints
        of equal time slices (one sub-frame = the truth pose itself), one per `smear_step_px` of
        image motion, at most 8.
        """
        pose = self.poses[i]
        here = (pose.rvec, pose.tvec)
        half_s = self.exposure_s / 2
        if half_s <= 0:
            return [here]
        prev = self.poses[i - 1] if i > 0 else None
        nxt = self.poses[i + 1] if i + 1 < len(self.poses) else None
        dt_prev = (pose.timestamp_ns - prev.timestamp_ns) / 1e9 if prev is not None else 0.0
        dt_next = (nxt.timestamp_ns - pose.timestamp_ns) / 1e9 if nxt is not None else 0.0
        trajectory = self.trajectory

        def at(offset_s: float) -> tuple[np.ndarray, np.ndarray]:
            if trajectory is not None:
                return trajectory.pose_at(pose.timestamp_ns / 1e9 + offset_s) if offset_s else here
            if offset_s < 0 and prev is not None and dt_prev > 0:
                return interpolate_pose(prev.rvec, prev.tvec, *here, 1.0 - min(1.0, -offset_s / dt_prev))
            if offset_s > 0 and nxt is not None and dt_next > 0:
                return interpolate_pose(*here, nxt.rvec, nxt.tvec, min(1.0, offset_s / dt_next))
            return here

        corners = self._get_renderer().paper_corners_m()
        step = self.smear_step_px
        n = min(8, motion_subframes(self.camera, corners, at(-half_s), here, px_per_subframe=step)
                + motion_subframes(self.camera, corners, here, at(half_s), px_per_subframe=step) - 1)
        if n <= 1:
            return [here]
        return [at(-half_s + (j + 0.5) * self.exposure_s / n) for j in range(n)]

    def render(self, i: int) -> np.ndarray:
        """(H, W) uint8 grey image of frame i (the same whether rendered alone or in sequence)."""
        renderer = self._get_renderer()
        radiance = renderer.radiance_exposure(self.exposure_poses(i))
        return expose(radiance, rng=np.random.default_rng([self.seed, i]), blur_sigma_px=self.blur_sigma,
                      noise_sigma_dn=self.noise_sigma, low_light=self.low_light, vignetting=self.vignetting,
                      off_axis_rad=renderer.off_axis_rad)

    def frames(self) -> Iterator[Frame]:
        for i, pose in enumerate(self.poses):
            yield Frame(index=pose.index, timestamp_ns=pose.timestamp_ns, image=self.render(i), controls=self._controls)

    def close(self) -> None:
        self._renderer = None  # drops the texture; the per-camera ray map stays cached in sim_render
