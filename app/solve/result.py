"""The solve's output types: what a calibration is, and what the report around it says."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from calibcoach.drivers.lens import CameraModel


@dataclass(frozen=True, slots=True)
class View:
    """One frame's observations as they enter the solver."""

    frame_index: int  # index of the frame in its source
    frame_name: str  # file name for folder sources, "" otherwise
    ids: np.ndarray  # (N,) int32 ChArUco corner ids
    image_points_px: np.ndarray  # (N, 2) float64 detected corners
    object_points_m: np.ndarray  # (N, 3) float64 the same corners on the board, metres
    # Share of an independent view this frame counts for in the intrinsics' covariance: look-alike
    # frames of one hold share their pose-dependent corner errors (blur, print, light at that spot),
    # so a group of k counts 1/k each. The solve itself uses every frame at full weight.
    information_weight: float = 1.0
    timestamp_ns: int | None = None  # the frame's capture time (source clock); None where unknown
    # (N, 2) float64 the same corners fitted to the pattern's point symmetry (coverage/corner_symmetry.py;
    # before it, refined on the checker's edges: coverage/corner_refine.py); None where not computed.
    # The final solve takes these (`as_refined`, unless --corners opencv), the capture's incremental
    # solves OpenCV's.
    refined_px: np.ndarray | None = None
    # (N,) bool: the corners the refinement left as OpenCV gave them (for the symmetry fit: a frame of
    # fewer than 6 corners, too few clean sample pairs, or no converged fit within 0.5 px); set by
    # `as_refined`, None where no refinement ran. They keep the markers' pull and, in a tracked
    # frame, part of the frame before's error, so the final solve weighs them by their own measured
    # variance (`robust.unrefined_corner_weights`).
    unrefined: np.ndarray | None = None
    # (N,) weight of each corner's rows relative to the view's own (`information_weight` and the
    # weighted refinement's view weight): in the weighted refinement, the information and the noise
    # estimate. None: every corner 1.
    corner_weights: np.ndarray | None = None

    def as_refined(self) -> View:
        """This view with its refined corners as its observations (itself where it has none)."""
        if self.refined_px is None:
            return self
        # the refinement returns OpenCV's corner, bit for bit, where it does not refine one
        unrefined = np.all(self.refined_px == self.image_points_px, axis=1)
        return replace(self, image_points_px=self.refined_px, refined_px=None, unrefined=unrefined)

    def rows_weight(self) -> np.ndarray:
        """(N,) each corner's weight in the solve: `information_weight` times its `corner_weights`."""
        base = np.full(self.ids.shape[0], float(self.information_weight))
        return base if self.corner_weights is None else base * self.corner_weights


@dataclass(frozen=True, slots=True)
class DroppedCorner:
    frame_index: int
    corner_id: int
    residual_px: float  # length of the corner's reprojection error when it was dropped


@dataclass(frozen=True, slots=True)
class DroppedFrame:
    frame_index: int
    reason: str  # e.g. "frame RMS 2.31 px is 6.2x the median frame RMS (defocus or motion blur)"


@dataclass(frozen=True, slots=True)
class Calibration:
    """A solved camera model with everything needed to judge it."""

    camera: CameraModel
    rms_px: float  # RMS reprojection error over all kept corners, per coordinate pair (OpenCV's definition)
    views: tuple[View, ...]  # the views the final solve used (outlier corners removed)
    rvecs: np.ndarray  # (V, 3) float64 Rodrigues vectors, T_cam_board
    tvecs: np.ndarray  # (V, 3) float64 metres, T_cam_board
    residuals_px: tuple[np.ndarray, ...]  # per view (N_v, 2) float64, observed - projected
    per_view_rms_px: np.ndarray  # (V,) float64
    intrinsic_names: tuple[str, ...]  # names of the free intrinsic parameters, e.g. ("fx", "fy", "cx", ...)
    intrinsic_covariance: np.ndarray  # (P, P) float64 covariance of the free intrinsics, poses marginalised
    dropped_frames: tuple[DroppedFrame, ...] = ()
    dropped_corners: tuple[DroppedCorner, ...] = ()

    @property
    def intrinsic_std(self) -> np.ndarray:
        """(P,) float64 one-sigma uncertainty of each free intrinsic parameter."""
        return np.sqrt(np.clip(np.diag(self.intrinsic_covariance), 0, None))

    @property
    def corner_count(self) -> int:
        return int(sum(v.ids.size for v in self.views))


@dataclass(frozen=True, slots=True)
class UncertaintyMap:
    """Projection uncertainty over a grid of image points (mrcal's idea, from the solve's covariance)."""

    grid_x_px: np.ndarray  # (GX,) float64 pixel x of grid columns
    grid_y_px: np.ndarray  # (GY,) float64 pixel y of grid rows
    sigma_px: np.ndarray  # (GY, GX) float64 1-sigma worst-direction projection uncertainty
    covered: np.ndarray  # (GY, GX) bool grid points inside the region the board was seen in
    error_px: np.ndarray  # (GY, GX) float64 expected length of the projection error, sqrt(trace(J Sigma J^T))
    error_weight: np.ndarray  # (P, P) float64 W with E^2 = trace(W Sigma) over the covered points

    @property
    def expected_error_px(self) -> float:
        """E, the headline number: RMS over the covered region of the expected projection error (px)."""
        values = self.error_px[self.covered] if self.covered.any() else self.error_px.reshape(-1)
        return float(np.sqrt(np.mean(values**2)))

    def expected_error_where(self, mask: np.ndarray) -> float:
        """RMS of the expected projection error over the grid points `mask` (GY, GX) marks (px); nan for none."""
        values = self.error_px[np.asarray(mask, bool)]
        return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")

    @property
    def p95_covered_px(self) -> float:
        values = self.sigma_px[self.covered] if self.covered.any() else self.sigma_px.reshape(-1)
        return float(np.percentile(values, 95))

    @property
    def p95_px(self) -> float:
        return float(np.percentile(self.sigma_px, 95))


@dataclass(frozen=True, slots=True)
class ExpectedErrors:
    """E two ways, the larger of which the final solve reports: from the model covariance (corners
    independent but for the look-alike discount) and from the scatter between the capture's holds
    (app/solve/hold_jackknife.py), which sees what a hold's frames share."""

    from_model_px: float
    between_holds_px: float = float("nan")  # nan: too few holds, or single-frame ones, to read the scatter from
    holds: int = 0

    @property
    def between_holds_wins(self) -> bool:
        return bool(self.between_holds_px > self.from_model_px)

    def summary(self) -> dict[str, object]:
        return {"from_model_px": self.from_model_px, "between_holds_px": self.between_holds_px, "holds": self.holds,
                "reported": "between holds" if self.between_holds_wins else "model"}


@dataclass(frozen=True, slots=True)
class Verdict:
    """The judgement a user reads first."""

    grade: str  # "excellent" | "good" | "acceptable" | "poor" | "insufficient"
    trusted: bool  # False when coverage or uncertainty is not enough, whatever the RMS says
    rms_grade: str  # the method's table on RMS alone, scaled for resolution
    reasons: tuple[str, ...]  # sentences: what is good, what is missing, what to do
    rms_thresholds_px: tuple[float, float, float] = (0.3, 0.5, 1.0)  # excellent/good/acceptable upper bounds used


@dataclass(frozen=True, slots=True)
class ModelChoice:
    """Why a distortion model was chosen (held-out residuals per candidate)."""

    chosen: str
    candidates: dict[str, float] = field(default_factory=dict)  # model -> held-out RMS px (cross-validation)
    reason: str = ""
