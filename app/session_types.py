"""What a calibration session takes and gives: settings, per-frame outcome, progress, the result.

Split from `session.py`, which holds the behaviour; these are the frozen values that cross into
the replay and live loops, the viewer, the outputs and the embedding API.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from calibcoach.app.solve.residual_structure import ResidualStructure
from calibcoach.app.solve.result import Calibration, ExpectedErrors, ModelChoice, UncertaintyMap, Verdict
from calibcoach.coverage.board import BoardSpec
from calibcoach.coverage.detector import Detection
from calibcoach.coverage.grid import CoverageMap, CoverageRequirements
from calibcoach.coverage.guidance import Guidance
from calibcoach.coverage.pose import BoardPose
from calibcoach.coverage.select import Decision, SelectorSettings
from calibcoach.drivers.lens import CameraModel

FISHEYE_GUESS_DEG = 120.0  # a field-of-view guess this wide is taken as a fisheye (model_choice's fisheye limit)


def lens_guess(image_size: tuple[int, int], hfov_deg: float) -> CameraModel:
    """The lens before the first solve: the field-of-view guess, as an equidistant fisheye from
    `FISHEYE_GUESS_DEG` on (a pinhole cannot reach 90 deg off axis at all; on the rendered 150 deg
    lens the equidistant guess's 489 px against the true 484)."""
    return CameraModel.from_fov(image_size, hfov_deg, "fisheye" if hfov_deg >= FISHEYE_GUESS_DEG else "pinhole")


def guess_for_focal(image_size: tuple[int, int], fx: float, *, fisheye: bool) -> float:
    """The field-of-view guess whose `lens_guess` has focal length `fx` (px): `lens_guess` inverted.

    Two guesses can share a focal length, an equidistant fisheye's and a distortion-free lens's;
    the fisheye's is taken for a `fisheye` lens where `lens_guess` reads it as one (from
    `FISHEYE_GUESS_DEG` on), else the distortion-free one, which it reads as such below that.
    """
    half_width = image_size[0] / 2.0
    equidistant = math.degrees(2.0 * half_width / fx)
    distortion_free = math.degrees(2.0 * math.atan(half_width / fx))
    if fisheye and equidistant >= FISHEYE_GUESS_DEG:
        return equidistant
    return distortion_free if distortion_free < FISHEYE_GUESS_DEG else equidistant


@dataclass(frozen=True, slots=True)
class SessionSettings:
    model: str = "auto"  # "auto" | "pinhole" | "rational" | "fisheye"
    selector: SelectorSettings = field(default_factory=SelectorSettings)
    # The lens before the first solve (--fov): poses, ranges and candidates, and the fisheye-aware re-detection
    # (an equidistant fisheye from 120 deg on). 70 deg: a webcam; a wrong guess costs only the first frames' guidance.
    hfov_guess_deg: float = 70.0
    stop_when_done: bool = True
    error_target_px: float | None = None  # stop rule's E target; None = derived from the corner noise (verdict.py)
    coverage: CoverageRequirements = field(default_factory=CoverageRequirements)
    use_motion_gate: bool = True  # off for folders of independent photos
    # Most frames in the final solve: the diverse frames kept live (at most `selector.max_frames`)
    # plus the sharp, still repeats of their holds and poses the live selection passed over.
    # Repeats average each pose's corner noise: on held-out renders (bench/heldout.py) the 60
    # frames alone left the true error at 2-5x what every sharp frame of the same capture gives
    # (0.07-0.12 -> 0.022-0.031 px on a 784-frame 720p capture), and 400 frames solve in ~2.5 s.
    solve_frames: int = 400
    # The final solve's corners: "masked" (OpenCV's fitted to the pattern's point symmetry:
    # coverage/corner_symmetry.py; named for the masked refinement, coverage/corner_refine.py, that
    # it replaced) or "opencv" (as detectBoard returned them).
    # The capture's own incremental solves take OpenCV's either way (the guidance's E was measured so),
    # and so does the final solve through a lens of 90 deg or more, or a fisheye (`refines_corners`).
    corners: str = "masked"


@dataclass(frozen=True, slots=True)
class Progress:
    frames_seen: int
    frames_accepted: int
    coverage: float  # 0..1, of what this lens can show
    expected_error_px: float | None  # E over the covered region; None before the first incremental solve
    target_px: float | None  # the stop rule's E target; None until the corner noise is measured
    uncertainty_p95_px: float | None  # secondary: p95 of the worst-direction sigma over the covered region
    best_next_cut: float | None  # relative cut of E the current target would bring
    rejections: dict[str, int]
    done: bool
    stop_reason: str = ""  # why the stop rule fired, once it has


@dataclass(frozen=True, slots=True)
class FrameOutcome:
    frame_index: int
    frame_name: str
    detection: Detection
    pose: BoardPose | None
    decision: Decision
    blur_px: float | None
    motion_px_s: float | None
    guidance: Guidance
    progress: Progress
    camera: CameraModel  # the intrinsics the pose was estimated with (the bootstrap guess before any solve)
    coverage: CoverageMap  # the session's live map (shared, not a copy: read it before the next frame)
    board_centre_px: np.ndarray | None = None  # (2,) float64 where the board's centre is in this frame (from the pose)


@dataclass(frozen=True, slots=True)
class SessionResult:
    calibration: Calibration
    model_choice: ModelChoice
    uncertainty: UncertaintyMap
    verdict: Verdict
    coverage: CoverageMap  # rebuilt from the final solve's poses
    board: BoardSpec  # with the print's legacy/inverted settled
    rejections: dict[str, int]
    frames_seen: int
    check_image: np.ndarray | None  # one accepted frame, for the undistortion check picture
    noise_px: float  # corner noise per coordinate the final solve measured (dof-corrected RMS)
    target_px: float  # the E target the verdict judged against
    stop_reason: str  # why the capture ended ("" when the source simply ran out)
    # residual patterns fixed to the board or to the image (None: not tested, e.g. a result built in a test)
    residual_structure: ResidualStructure | None = None
    # E over every image point a board can be seen in, covered or not: what short coverage is judged on
    reachable_error_px: float = float("nan")
    # usable frames the final solve left out as smeared, and the exposure they were judged by (coverage/exposure.py)
    smeared_left_out: int = 0
    exposure: str = ""
    # E from the model covariance and from the scatter between holds; the uncertainty above has the larger
    expected_errors: ExpectedErrors | None = None
