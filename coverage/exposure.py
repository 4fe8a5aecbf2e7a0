"""The camera's exposure time read off the footage, and each frame's smear from it.

A frame smears by its corners' speed times the exposure. The speed is cheap and sure: the corners
of the frames either side, a pixel or so apart. The exposure is what footage from elsewhere never
states, and what one frame's edges show only roughly (`EdgeBlur.along_smear_px`): on a dim 720p
render that smears every motion, frames truly smeared 0.5-1 px read 0.8 px (one in ten over 1.3),
those smeared 1.5-2 px 1.7 px (one in ten over 2.6). Over a capture's hundreds of frames the
edges show the exposure well.

An exposure T of a board moving at v (px/s) widens an edge of unit normal n by a box of length
T |v . n|: its squared gaussian width grows by T^2 (v . n)^2 / 12 (coverage/sharpness.py). A
frame's two edge families (normals n_x, n_y) share the lens's blur, so over the frames of one
camera

    w_x^2 - w_y^2 = c + T^2 (<(v . n_x)^2> - <(v . n_y)^2>) / 12,

<> the mean over the frame's corners and c whatever tells the families apart whatever the motion
(astigmatism, the pixel grid). T^2 is the slope of a least-squares line through the judged frames
(`ExposureReader`), never more than the frame interval (an exposure cannot outlast it). Where too
few frames moved to read it, or the reading is unsure, no frame is judged by it. The widths are
read off the steepest gradients, which a smear longer than the lens blur lowers faster than that
variance model says (up to 1.9x the widening, `sharpness.steepest_gradient_sigma`): the line is
fitted again with each frame's motion weighed by that response at the exposure read so far.

Measured on renders that smear every motion over ~1 px (`smear_step_px` 0.5, the "smooth" cells
of bench/renders.py; bench/exposure_reading.py, bench/results/exposure_reading.md): read on 20 of
21 (careful, shaky, dim, messy, wide, fisheye; one careful render was too unsure), the RMS of the
log error 0.138 (0.163 without the response's correction), 11% short to 58% long (8% short to
64%), +4.5% on average (+9.7%); the worst
are the messy render with an 11 ms exposure (18 ms: its frames moving across one edge family widen
it 3-4x what the smear explains, not understood) and a shaky one (+31%). Standard errors of 2-7%
understate what the model leaves out. On the older renders, which show a smear under ~4 px as a
sharp frame, it reads short or not at all, as their images show. Least squares beat a Huber fit
(on the first dim render 1.23 frame intervals against 1.53, the truth 1.0: Huber discounts the
fast frames that carry the slope). On a synthetic smear of 0-4 px (tests/coverage/test_exposure.py)
it reads 5% long (17% without the correction).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from calibcoach.coverage.detector import Detection, shared_corners
from calibcoach.coverage.sharpness import SAMPLING_FLOOR_PX, EdgeBlur, steepest_gradient_sigma

# Frames whose motion would widen one edge family over the other by at least this much (squared
# gaussian width, px^2) if the exposure lasted the whole frame interval: they carry the slope. A
# 720p board's edges are ~0.5-0.8 px wide (0.25-0.6 px^2); 0.02 px^2 is a motion of ~0.5 px a frame
# across one family and not the other.
_INFORMATIVE_PX2 = 0.02
# So many of them before the footage's own reading counts, and it must be known this well (its
# standard error over itself); otherwise no frame is left out as smeared. The smooth renders gave
# 19-211 such frames and standard errors of 2-5%; the older renders, whose images show only smears
# over ~4 px, 4-25% where read and 29-99% where not (bench/results/smear_filter.md).
MIN_INFORMATIVE_FRAMES = 20
MAX_RELATIVE_ERROR = 0.25
# A corner moving more than this between neighbouring frames is in transit (the scan marks such
# frames by their thumbnails), or the neighbours are independent photos: no speed is read.
MAX_NEIGHBOUR_MOVE_PX = 25.0


def corner_velocities(before: Detection, before_ns: int, after: Detection, after_ns: int) -> np.ndarray | None:
    """(N, 2) px/s of the corners both detections found, from `before` to `after` (None: fewer than 4
    shared, no time between them, or a corner moved more than `MAX_NEIGHBOUR_MOVE_PX`)."""
    dt_s = (after_ns - before_ns) / 1e9
    shared = None if dt_s <= 0 else shared_corners(before, after)
    if shared is None:
        return None
    ia, ib = shared
    moved = after.corners_px[ib].astype(np.float64) - before.corners_px[ia].astype(np.float64)
    if float(np.max(np.abs(moved))) > MAX_NEIGHBOUR_MOVE_PX:
        return None
    return moved / dt_s


def velocities_across(here: tuple[Detection, int], before: tuple[Detection, int] | None,
                      after: tuple[Detection, int] | None) -> np.ndarray | None:
    """The corners' velocities at a frame ((detection, timestamp_ns) `here`) from the frames either
    side of it: across it where both show the board, else the faster one-sided difference there is
    (a neighbour None: not seen, e.g. skipped in transit; None: no side tells)."""
    if before is not None and after is not None:
        across = corner_velocities(before[0], before[1], after[0], after[1])
        if across is not None:
            return across
    sides = [corner_velocities(before[0], before[1], *here) if before is not None else None,
             corner_velocities(*here, after[0], after[1]) if after is not None else None]
    known = [v for v in sides if v is not None]
    return max(known, key=worst_corner_speed_px_s) if known else None


def worst_corner_speed_px_s(velocities: np.ndarray | None) -> float | None:
    """The fastest corner's speed, px/s (None where unknown): what the worst corner smears by, per second of exposure."""
    return None if velocities is None else float(np.sqrt(np.max(np.sum(velocities**2, axis=1))))


@dataclass(frozen=True, slots=True)
class ExposureReading:
    """The exposure as the footage shows it."""

    exposure_s: float | None  # the least-squares reading (None: too few moving frames, or too unsure, to read it)
    informative_frames: int
    relative_error: float  # the reading's standard error over itself (inf where there is none)

    def describe(self) -> str:
        if self.exposure_s is None:
            return (f"exposure unknown ({self.informative_frames} frames moved enough to read it, "
                    f"{MIN_INFORMATIVE_FRAMES} needed, to within {MAX_RELATIVE_ERROR:.0%})")
        return (f"exposure ~{self.exposure_s * 1e3:.0f} ms (+-{self.relative_error:.0%}) read off "
                f"{self.informative_frames} moving frames' edges")


class ExposureReader:
    """Collects (edge widths, corner velocities) of judged frames; `reading()` fits the exposure."""

    def __init__(self) -> None:
        self._widths: list[tuple[float, float]] = []  # (w_x, w_y), px
        self._motion: list[tuple[float, float]] = []  # (<(v.n_x)^2>, <(v.n_y)^2>), px^2/s^2

    def add(self, edges: EdgeBlur, velocities_px_s: np.ndarray | None) -> None:
        if velocities_px_s is None or edges.normals is None:
            return
        wx, wy = edges.across_x_px, edges.across_y_px
        if not (np.isfinite(wx) and np.isfinite(wy)):
            return
        nx, ny = (np.asarray(n, np.float64) for n in edges.normals)
        self._widths.append((wx, wy))
        self._motion.append((float(np.mean((velocities_px_s @ nx) ** 2)), float(np.mean((velocities_px_s @ ny) ** 2))))

    def reading(self, frame_interval_s: float) -> ExposureReading:
        """The exposure fitted so far, for footage `frame_interval_s` apart."""
        interval = float(frame_interval_s)
        widths, motion = np.asarray(self._widths).reshape(-1, 2), np.asarray(self._motion).reshape(-1, 2)
        # per frame interval, so the numbers stay near 1 whatever the frame rate: (v . n)^2 in px^2 a frame^2
        moved = motion * interval * interval
        a = (moved[:, 0] - moved[:, 1]) / 12.0
        y = widths[:, 0] ** 2 - widths[:, 1] ** 2
        informative = int(np.count_nonzero(np.abs(a) >= _INFORMATIVE_PX2))
        unknown = ExposureReading(None, informative, float("inf"))
        if informative < MIN_INFORMATIVE_FRAMES or a.size < MIN_INFORMATIVE_FRAMES + 2:
            return unknown
        fit = _line(a, y)
        # The widths are read off the steepest gradients, which a smear past the lens blur lowers
        # faster than the variance model says (`sharpness.steepest_gradient_sigma`): each frame's
        # motion is weighed by what its smear, at the exposure read so far, does to that measure.
        blur = np.sqrt(widths.min(axis=1) ** 2 + SAMPLING_FLOOR_PX**2)  # the frame's sigma before its smear, as measured
        for _ in range(_RESPONSE_ROUNDS):
            if fit is None or fit[0] <= 0:
                break
            smear = np.sqrt(min(fit[0], 1.0) * moved)  # px, each family's RMS smear at that exposure
            response = _widening_response(blur[:, None], smear)
            fit = _line((moved[:, 0] * response[:, 0] - moved[:, 1] * response[:, 1]) / 12.0, y)
        if fit is None:
            return unknown
        slope, slope_variance = fit
        if slope <= 0:
            return unknown
        # T is the slope's square root: its relative error is half the slope's
        relative = 0.5 * float(np.sqrt(max(slope_variance, 0.0))) / slope
        if relative > MAX_RELATIVE_ERROR:
            return replace(unknown, relative_error=relative)
        return ExposureReading(interval * float(np.sqrt(min(slope, 1.0))), informative, relative)


# Rounds of the response's correction: each changes the exposure less than the one before (over
# 21 smooth renders the third moved it by under 1%).
_RESPONSE_ROUNDS = 4


def _line(a: np.ndarray, y: np.ndarray) -> tuple[float, float] | None:
    """Least-squares y = c + s a: (s, its variance), None where the design is singular."""
    X = np.stack([np.ones_like(a), a], axis=1)
    coefficients, *_ = np.linalg.lstsq(X, y, rcond=None)
    residuals = y - X @ coefficients
    try:
        variance = float(residuals @ residuals) / (a.size - 2) * float(np.linalg.inv(X.T @ X)[1, 1])
    except np.linalg.LinAlgError:
        return None
    return float(coefficients[1]), variance


def _widening_response(blur_px: np.ndarray, smear_px: np.ndarray) -> np.ndarray:
    """How much more a smear widens the measured squared width than L^2 / 12 (1 while it is small
    against the blur, up to 12 / (2 pi) = 1.9 past it)."""
    smear = np.maximum(smear_px, 1e-3)
    widened = steepest_gradient_sigma(blur_px, smear) ** 2 - np.asarray(blur_px) ** 2
    return np.where(smear_px > 1e-3, 12.0 * widened / (smear * smear), 1.0)


class SmearLedger:
    """Which of a capture's frames smeared past a limit: each frame's fastest corner speed, the
    exposure read off the capture (`ExposureReader`), and the frame interval from the timestamps."""

    def __init__(self) -> None:
        self.reader = ExposureReader()
        self._speed_px_s: dict[int, float] = {}  # frame index -> its fastest corner's speed
        self._intervals_s: list[float] = []  # between consecutive frames seen (the latest few)
        self._last: tuple[int, int] | None = None  # (index, timestamp_ns) of the last frame seen

    def saw(self, index: int, timestamp_ns: int) -> None:
        """A frame went by: its time gives the frame interval."""
        if self._last is not None and index > self._last[0] and timestamp_ns > self._last[1]:
            self._intervals_s.append((timestamp_ns - self._last[1]) / 1e9 / (index - self._last[0]))
            del self._intervals_s[:-64]
        self._last = (index, timestamp_ns)

    def frame_interval_s(self) -> float | None:
        return float(np.median(self._intervals_s)) if self._intervals_s else None

    def record(self, index: int, speed_px_s: float | None) -> None:
        """The fastest corner's speed at a frame that may enter the final solve (None: unknown, never counted smeared)."""
        if speed_px_s is not None and np.isfinite(speed_px_s):
            self._speed_px_s[index] = float(speed_px_s)

    def smeared(self, indices: list[int], limit_px: float) -> tuple[set[int], ExposureReading | None]:
        """Those of `indices` whose fastest corner moved more than `limit_px` within the exposure read.

        Where it could not be read, none: the frame interval bounds it, but loosely where it is long
        (a calibcoach recording keeps only the frames its live session judged, 0.2 s apart, of a
        camera exposing for ~30 ms), and a capture too still to show its exposure has few frames a
        smear could touch.
        """
        interval = self.frame_interval_s()
        if interval is None:
            return set(), None
        reading = self.reader.reading(interval)
        if reading.exposure_s is None:
            return set(), reading
        return {i for i in indices if self._speed_px_s.get(i, 0.0) * reading.exposure_s > limit_px}, reading
