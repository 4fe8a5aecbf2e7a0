"""The coverage map: which image regions, tilts and ranges the accepted frames have shown.

Three axes, each a set of cells with a requirement:
- image region: a grid over the image (corners and edges are where distortion lives, so the outer
  ring weighs more); a cell is met when enough corner observations have landed in it. Only cells
  a board can be seen in are required: `reachable` marks them (from the candidate poses'
  virtual views, so a fisheye's black corners, beyond 90 deg off axis, are not asked for);
- tilt: frontal, each of the four tilt directions beyond 20 deg, and a steep view (>= 35 deg) about
  each axis -- tilted views separate focal length from distance, which frontal views cannot;
- range: the distance from the camera to the board's centre, from its pose -- near and far as
  `candidates.Ranges` defines them for this board and lens (mid-range views count for the rest). Not the visible footprint: a board
  held close at the image edge shows few corners but is still near, as the person holding it knows.
Completeness is the weighted share of requirements met; `gain` says how much a candidate frame
would add, which is what frame selection is built on.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calibcoach.coverage.candidates import Ranges, cell_index, region_cell_counts
from calibcoach.coverage.detector import Detection
from calibcoach.coverage.pose import BoardPose

TILT_STEER_DEG = 20.0  # a view counts for a tilt direction from here on
TILT_STEEP_DEG = 35.0  # "steep" views: the method asks for 30-60 deg
TILT_DIRECTIONS = ("top_away", "bottom_away", "left_away", "right_away")
TILT_CELLS = ("frontal", *TILT_DIRECTIONS, "steep_x", "steep_y")
# Ranges required: far and near (each counted from its limit, `Ranges.far_min_m` / `near_max_m`).
# Mid-range views count for regions and tilts but are no requirement of their own: what separates
# focal length from distance is the spread between near and far, and a person's "near" and "far"
# differ from calibcoach's representative ranges by more than the mid band is wide.
DISTANCE_CELLS = ("far", "near")
TILT_HISTOGRAM_EDGES_DEG = (-90.0, -45.0, -30.0, -15.0, 15.0, 30.0, 45.0, 90.0)
_AXIS_WEIGHTS = {"region": 0.5, "tilt": 0.3, "distance": 0.2}


def tilt_cells(tilt_deg: float, tilt_x_deg: float, tilt_y_deg: float) -> tuple[str, ...]:
    """The tilt cells a view at this tilt (angle to the line of sight, and about each image axis) counts for."""
    cells: list[str] = []
    if tilt_deg < 15.0:
        cells.append("frontal")
    if tilt_x_deg >= TILT_STEER_DEG:
        cells.append("top_away")
    if tilt_x_deg <= -TILT_STEER_DEG:
        cells.append("bottom_away")
    if tilt_y_deg >= TILT_STEER_DEG:
        cells.append("right_away")
    if tilt_y_deg <= -TILT_STEER_DEG:
        cells.append("left_away")
    if abs(tilt_x_deg) >= TILT_STEEP_DEG:
        cells.append("steep_x")
    if abs(tilt_y_deg) >= TILT_STEEP_DEG:
        cells.append("steep_y")
    return tuple(cells)


@dataclass(frozen=True, slots=True)
class CoverageRequirements:
    corners_per_region_cell: int = 10  # corner observations that make a region cell "seen"
    views_per_tilt_cell: int = 2
    views_per_distance_cell: int = 2


@dataclass(frozen=True, slots=True)
class Contribution:
    """What one frame would add to the map."""

    region_counts: np.ndarray  # (rows, cols) float64 corners this frame puts in each cell
    tilt_cells: tuple[str, ...]
    distance_cell: str | None
    tilt_x_deg: float
    tilt_y_deg: float
    has_pose: bool = True  # False: the frame's pose was unknown, so tilts and range are not counted


def region_grid_shape(image_size: tuple[int, int]) -> tuple[int, int]:
    """(rows, cols) of the region grid: about square cells, 6 across a 16:9 image, 5 across 4:3."""
    w, h = image_size
    aspect = w / h
    cols = 6 if aspect >= 1.5 else 5
    rows = max(3, int(np.ceil(cols / aspect - 0.05)))
    return rows, cols


class CoverageMap:
    """Accumulates accepted frames' contributions; says what is complete and what is missing."""

    def __init__(self, image_size: tuple[int, int], requirements: CoverageRequirements | None = None, *,
                 ranges: Ranges, reachable: np.ndarray | None = None) -> None:
        self.image_size = image_size
        self.requirements = requirements or CoverageRequirements()
        self.ranges = ranges
        self.rows, self.cols = region_grid_shape(image_size)
        # (rows, cols) bool: cells a board can be seen in on this lens; all of them until told otherwise
        self.reachable = np.ones((self.rows, self.cols), bool) if reachable is None else np.asarray(reachable, bool)
        if self.reachable.shape != (self.rows, self.cols):
            raise ValueError(f"reachable must be ({self.rows}, {self.cols}), got {self.reachable.shape}")
        self.region_counts = np.zeros((self.rows, self.cols))  # (rows, cols) corner observations
        self.tilt_counts = dict.fromkeys(TILT_CELLS, 0)
        self.distance_counts = dict.fromkeys(DISTANCE_CELLS, 0)
        self.tilt_x_history: list[float] = []
        self.tilt_y_history: list[float] = []
        self.footprints: list[float] = []
        ring = np.ones((self.rows, self.cols))
        ring[0, :] = ring[-1, :] = ring[:, 0] = ring[:, -1] = 2.0  # edges: twice the weight of the inside
        for r, c in ((0, 0), (0, -1), (-1, 0), (-1, -1)):
            ring[r, c] = 3.0  # corners: where distortion is strongest and hardest to reach
        self._ring = ring
        self.region_weights = np.where(self.reachable, ring, 0.0) / max(float(np.where(self.reachable, ring, 0.0).sum()), 1e-12)

    # --- what a frame would add ---------------------------------------------------------------
    def contribution(self, detection: Detection, pose: BoardPose | None) -> Contribution:
        seen = None if pose is None else (pose.tilt_deg, pose.tilt_x_deg, pose.tilt_y_deg, pose.distance_m)
        return self.contributions([detection.corners_px], [seen])[0]

    def contributions(self, corner_sets: Sequence[np.ndarray],
                      poses: Sequence[tuple[float, float, float, float] | None]) -> list[Contribution]:
        """`contribution` of many frames at once (the candidate poses are ranked by hundreds).

        Args:
            corner_sets: per frame (N, 2) corner pixels.
            poses: per frame (tilt, tilt_x, tilt_y, distance_m) as `BoardPose` has them, or None (no pose).
        """
        counts = region_cell_counts(corner_sets, self.image_size, (self.rows, self.cols)).astype(np.float64)
        made = []
        for region_counts, pose in zip(counts, poses, strict=True):
            if pose is None:
                made.append(Contribution(region_counts, (), None, 0.0, 0.0, has_pose=False))
                continue
            tilt, tx, ty, distance_m = pose
            cell = self.ranges.cell(distance_m)
            made.append(Contribution(region_counts, tilt_cells(tilt, tx, ty), cell if cell in DISTANCE_CELLS else None, tx, ty))
        return made

    def gain(self, c: Contribution, *, region_only: bool = False) -> float:
        """How much of the unmet requirements this frame would fill, 0..1 of the whole map.

        `region_only` scores the image regions alone: a look-alike of a kept frame must not fill
        the "second view" of a tilt or distance cell, which asks for another view, not a copy.
        """
        return float(self.gains([c], region_only=region_only)[0])

    def gains(self, contributions: Sequence[Contribution], *, region_only: bool = False) -> np.ndarray:
        """`gain` of each contribution on its own, (K,) float64."""
        req = self.requirements
        need = req.corners_per_region_cell
        if not contributions:
            return np.zeros(0)
        before = np.minimum(self.region_counts / need, 1.0)
        after = np.minimum((self.region_counts + np.stack([c.region_counts for c in contributions])) / need, 1.0)
        region = np.sum((after - before) * self.region_weights, axis=(1, 2))
        if region_only:
            return _AXIS_WEIGHTS["region"] * region
        tilt = np.array([sum(1.0 for cell in c.tilt_cells if self.tilt_counts[cell] < req.views_per_tilt_cell)
                         for c in contributions]) / (len(TILT_CELLS) * req.views_per_tilt_cell)
        distance = np.array([1.0 if c.distance_cell is not None and self.distance_counts[c.distance_cell] < req.views_per_distance_cell
                             else 0.0 for c in contributions]) / (len(DISTANCE_CELLS) * req.views_per_distance_cell)
        return _AXIS_WEIGHTS["region"] * region + _AXIS_WEIGHTS["tilt"] * tilt + _AXIS_WEIGHTS["distance"] * distance

    def add(self, c: Contribution, footprint: float | None = None) -> None:
        self.region_counts += c.region_counts
        for cell in c.tilt_cells:
            self.tilt_counts[cell] += 1
        if c.distance_cell is not None:
            self.distance_counts[c.distance_cell] += 1
        if c.has_pose:
            self.tilt_x_history.append(c.tilt_x_deg)
            self.tilt_y_history.append(c.tilt_y_deg)
        if footprint is not None:
            self.footprints.append(footprint)

    # --- state --------------------------------------------------------------------------------
    def region_fill(self) -> np.ndarray:
        """(rows, cols) float64 in 0..1: how far each region cell is towards its requirement."""
        return np.minimum(self.region_counts / self.requirements.corners_per_region_cell, 1.0)

    def region_met(self) -> np.ndarray:
        """(rows, cols) bool: cells that meet their requirement or need none (no board can be seen there)."""
        return (self.region_fill() >= 1.0) | ~self.reachable

    def axis_completeness(self) -> dict[str, float]:
        req = self.requirements
        region = float(np.sum(self.region_fill() * self.region_weights))
        tilt = float(np.mean([min(self.tilt_counts[c] / req.views_per_tilt_cell, 1.0) for c in TILT_CELLS]))
        distance = float(np.mean([min(self.distance_counts[c] / req.views_per_distance_cell, 1.0) for c in DISTANCE_CELLS]))
        return {"region": region, "tilt": tilt, "distance": distance}

    def completeness(self) -> float:
        """Weighted share of all requirements met, 0..1."""
        parts = self.axis_completeness()
        return float(sum(_AXIS_WEIGHTS[k] * v for k, v in parts.items()))

    def is_complete(self) -> bool:
        return self.completeness() >= 0.999

    def reachable_at(self, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
        """(len(y_px), len(x_px)) bool: which points of a pixel grid lie in a region cell a board can be seen in."""
        w, h = self.image_size
        return self.reachable[np.ix_(cell_index(y_px, h, self.rows), cell_index(x_px, w, self.cols))]

    def missing_regions(self) -> list[tuple[int, int, float]]:
        """(row, col, fill) of region cells below their requirement, the most important first."""
        fill = self.region_fill()
        cells = [(r, c, float(fill[r, c])) for r in range(self.rows) for c in range(self.cols)
                 if fill[r, c] < 1.0 and self.reachable[r, c]]
        return sorted(cells, key=lambda t: (-(1.0 - t[2]) * self.region_weights[t[0], t[1]], t[0], t[1]))

    def missing_tilts(self) -> list[str]:
        return [c for c in TILT_CELLS if self.tilt_counts[c] < self.requirements.views_per_tilt_cell]

    def missing_distances(self) -> list[str]:
        return [c for c in DISTANCE_CELLS if self.distance_counts[c] < self.requirements.views_per_distance_cell]

    def tilt_histograms(self) -> dict[str, np.ndarray]:
        """Signed tilt histograms (views per bin of TILT_HISTOGRAM_EDGES_DEG) about each axis."""
        edges = np.asarray(TILT_HISTOGRAM_EDGES_DEG)
        return {
            "tilt_x": np.histogram(self.tilt_x_history, bins=edges)[0],
            "tilt_y": np.histogram(self.tilt_y_history, bins=edges)[0],
        }

    def summary(self) -> dict[str, object]:
        """A JSON-ready account of the map, for calibration.json and the viewer."""
        parts = self.axis_completeness()
        return {
            "completeness": round(self.completeness(), 4),
            "complete": self.is_complete(),
            "axes": {k: round(v, 4) for k, v in parts.items()},
            "region_grid": [self.rows, self.cols],
            "region_fill": np.round(self.region_fill(), 3).tolist(),
            "region_corner_counts": self.region_counts.astype(int).tolist(),
            "region_reachable": self.reachable.tolist(),
            "range_limits_m": {"near_max": round(self.ranges.near_max_m, 3), "far_min": round(self.ranges.far_min_m, 3)},
            "tilt_views": dict(self.tilt_counts),
            "distance_views": dict(self.distance_counts),
            "tilt_histogram_edges_deg": list(TILT_HISTOGRAM_EDGES_DEG),
            "tilt_histograms": {k: v.tolist() for k, v in self.tilt_histograms().items()},
            "missing": {
                "regions": [[r, c] for r, c, _ in self.missing_regions()],
                "tilts": self.missing_tilts(),
                "distances": self.missing_distances(),
            },
        }
