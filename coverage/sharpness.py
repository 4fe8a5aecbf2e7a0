"""How sharp a frame's board is, and how much it smeared during the exposure: read off the image.

A hand never holds a board perfectly still: between frames it jitters a pixel or two, which is no
harm; what degrades corners is motion *during* the exposure, which smears the image along the
motion. Inter-frame corner speed cannot tell the two apart (it does not know the exposure time),
so the frame itself is measured:

- The chessboard's edges come in two families, along the board's x and y axes. A smear of length
  L along a direction m widens an edge with normal n by a box of length L |m . n|, i.e. adds
  (L |m . n|)^2 / 12 to its squared gaussian width; edges parallel to the motion stay sharp.
- For each family the edge width is estimated from the steepest gradients across it (an edge of
  contrast C blurred by a gaussian of sigma s has a steepest gradient C / (s sqrt(2 pi))).
- The sharper family bounds the lens blur (plus the smear's share across it); the difference of
  squares gives the smear: L >= sqrt(12 |s_a^2 - s_b^2|) (`along_smear_px`). A smear along a
  board diagonal widens both families alike; the excess of the sharper family over the camera's
  own sharpness (the median of the frames kept so far) catches it: L_diag = sqrt(24 (s_min^2 -
  s_own^2)) (`diagonal_smear_px`).

`EdgeBlur.smear_px` is the larger of the two estimates, and `EdgeBlur.widening` how much it
widened the edges against the reference it was measured against. Both are needed: on a soft image
(defocus of 2-3 px, as on real close-range photos) a 4% difference between the families already
reads as a 2-3 px "smear", yet widens the edges by only 4% -- no harm to the corners, and within
the measure's own scatter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

_FAMILY_COS = np.cos(np.radians(20.0))  # a gradient counts for a family within 20 deg of its normal
_MIN_EDGE_PIXELS = 40  # fewer strong-gradient pixels than this in a family: no estimate
SAMPLING_FLOOR_PX = 0.5  # a perfectly sharp edge sampled by pixels still spreads over ~1 px
_erf = np.frompyfunc(math.erf, 1, 1)  # NumPy has no erf; a reading takes a few hundred values


@dataclass(frozen=True, slots=True)
class EdgeBlur:
    """Edge widths of the board's two edge families in one frame (gaussian sigma, px)."""

    across_x_px: float  # edges running along the board's x axis (their normal is across it)
    across_y_px: float  # edges running along the board's y axis
    # the two families' unit normals in the image, ((x, y) of the x family, (x, y) of the y family):
    # how much of a motion widens each (coverage/exposure.py); None where no widths were measured
    normals: tuple[tuple[float, float], tuple[float, float]] | None = None

    @property
    def sharp_px(self) -> float:
        """The sharper family: the lens blur, plus whatever smear reaches it."""
        return min(self.across_x_px, self.across_y_px)

    @property
    def blur_px(self) -> float:
        """The blurrier family: what the corners' worst direction sees."""
        return max(self.across_x_px, self.across_y_px)

    def along_smear_px(self) -> float:
        """Smear seen as a difference between the two edge families, px: L = sqrt(12 |s_a^2 - s_b^2|)."""
        a, b = self.across_x_px, self.across_y_px
        if not (np.isfinite(a) and np.isfinite(b)):
            return float("inf")
        return float(np.sqrt(12.0 * abs(a * a - b * b)))

    def along_widening(self) -> float:
        """The blurrier family's width over the sharper one's (1.0 = alike)."""
        a, b = self.across_x_px, self.across_y_px
        return float(max(a, b) / min(a, b)) if np.isfinite(a) and np.isfinite(b) and min(a, b) > 0 else float("inf")

    def diagonal_smear_px(self, own_sharp_px: float) -> float:
        """Smear along a board diagonal (both families widened alike) against this camera's own
        sharpness (median `sharp_px` of kept frames): L = sqrt(24 (s_min^2 - s_own^2)), px."""
        return float(np.sqrt(24.0 * max(self.sharp_px**2 - own_sharp_px**2, 0.0))) if np.isfinite(self.sharp_px) else float("inf")

    def diagonal_widening(self, own_sharp_px: float) -> float:
        """The sharper family's width over this camera's own sharpness (1.0 = as sharp as usual)."""
        return float(self.sharp_px / own_sharp_px) if own_sharp_px > 0 else float("inf")


def edge_blur(grey: np.ndarray, corners_px: np.ndarray, object_points_m: np.ndarray) -> EdgeBlur:
    """The two edge families' widths around the detected corners.

    Args:
        grey: (H, W) uint8 image.
        corners_px: (N, 2) detected ChArUco corners, N >= 4.
        object_points_m: (N, 3) the same corners on the board (their x, y give the board's axes).
    """
    inf = EdgeBlur(float("inf"), float("inf"))
    pts = np.asarray(corners_px, np.float64).reshape(-1, 2)
    if pts.shape[0] < 4:
        return inf
    H, _ = cv2.findHomography(np.asarray(object_points_m, np.float64)[:, :2], pts)
    if H is None:
        return inf
    x0, y0 = np.floor(pts.min(axis=0)).astype(int)
    x1, y1 = np.ceil(pts.max(axis=0)).astype(int)
    h, w = grey.shape
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1 + 1, w), min(y1 + 1, h)
    if y1 - y0 < 8 or x1 - x0 < 8:
        return inf
    board = grey[y0:y1, x0:x1]
    contrast = percentile_spread(board, 5.0, 95.0)
    if contrast < 10:
        return inf
    # Sobel of the uint8 pixels scaled by 1/8 (a power of two): the same float32 values as Sobel of a
    # float32 copy divided by 8, without the copy or the division
    gx = cv2.Sobel(board, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(board, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    mag = np.sqrt(gx * gx + gy * gy)
    strong = np.flatnonzero(mag > 0.25 * float(upper_percentile(mag, 99.5)))
    if strong.size == 0:
        return inf
    # the board's axes in the image at its centre, from the homography's Jacobian there
    centre = np.asarray(object_points_m, np.float64)[:, :2].mean(axis=0)
    u, v = _image_axes(H, centre)
    normals = {"x": np.array([-u[1], u[0]]), "y": np.array([-v[1], v[0]])}  # normals of edges along x / y
    strong_mag = mag.ravel()[strong]
    ex, ey = gx.ravel()[strong] / strong_mag, gy.ravel()[strong] / strong_mag
    widths = {}
    for name, n in normals.items():
        family = np.abs(ex * n[0] + ey * n[1]) >= _FAMILY_COS
        if np.count_nonzero(family) < _MIN_EDGE_PIXELS:
            widths[name] = float("inf")
            continue
        g_max = float(upper_percentile(strong_mag[family], 95))
        sigma = contrast / (np.sqrt(2 * np.pi) * g_max)
        widths[name] = float(np.sqrt(max(sigma * sigma - SAMPLING_FLOOR_PX**2, 0.0)))
    return EdgeBlur(widths["x"], widths["y"], (tuple(map(float, normals["x"])), tuple(map(float, normals["y"]))))  # type: ignore[arg-type]


def steepest_gradient_sigma(sigma_px: np.ndarray, smear_px: np.ndarray) -> np.ndarray:
    """The sigma `edge_blur` reads (before its sampling floor comes off) for an edge of gaussian blur
    `sigma_px` smeared across it by a box of `smear_px`: the steepest gradient of the two convolved
    is C / L erf(L / (2 sqrt(2) sigma)), so L / (sqrt(2 pi) erf(L / (2 sqrt(2) sigma))).

    While the smear is small against the blur this is sqrt(sigma^2 + L^2 / 12), the variance model
    (2% wider at L = 2 sigma); past the blur the steepest gradient falls as 1 / L, and the squared
    width grows by L^2 / (2 pi), 1.9x what the variance model says.
    """
    sigma = np.asarray(sigma_px, np.float64)
    smear = np.maximum(np.asarray(smear_px, np.float64), 1e-9)
    ratio = smear / (2.0 * np.sqrt(2.0) * sigma)
    return smear / (np.sqrt(2.0 * np.pi) * np.asarray(_erf(ratio), np.float64))


def percentile_spread(values: np.ndarray, low_pct: float, high_pct: float) -> float:
    """np.percentile(values, high_pct) - np.percentile(values, low_pct) of whole grey levels (0-255), exactly.

    The sorted values the percentiles interpolate between are read off the cumulative histogram:
    one counting pass instead of a partial sort per percentile (~10x cheaper on a board's pixels,
    ~15x on a thumbnail; every frame a replay judges pays it).
    """
    flat = np.asarray(values).ravel()
    counts = np.cumsum(np.bincount(flat.astype(np.intp, copy=False), minlength=256))

    def sorted_value(k: int) -> float:  # the k-th smallest value (0-based)
        return float(np.searchsorted(counts, k, side="right"))

    def percentile(pct: float) -> float:
        position = pct / 100.0 * (flat.size - 1)
        below = int(position)
        value = sorted_value(below)
        return value + (sorted_value(min(below + 1, flat.size - 1)) - value) * (position - below)

    return percentile(high_pct) - percentile(low_pct)


# Shares of the maximum tried as the cut above which an upper percentile's values lie, highest first:
# of a careful 720p board's gradient magnitudes (~1.5 x 10^5) a third lie above a quarter of the
# largest (the edges), a fifth above 0.6 of it, which still holds the top 0.5% and 5% the edge
# measure asks for: edge_blur 3.7 -> 2.8 ms on such a frame, the same numbers.
_UPPER_SHARES = (0.6, 0.25)


def upper_percentile(values: np.ndarray, pct: float) -> float:
    """np.percentile(values, pct) of finite values, bit for bit, for an upper percentile (a few % of the values above it).

    np.percentile partially sorts a copy of every value, pinning the smallest and the largest too;
    the edge measure asks for the 99.5th and 95th percentiles of ~10^5 gradients a frame (a third
    of its time). Only the values from the wanted rank up matter, and nearly always they all lie
    above 0.6 of the maximum, else above a quarter of it: those few are partitioned instead, and
    all of them when neither guess holds enough. The index and the interpolation are NumPy's own
    (method "linear"), so the result is the same number.
    """
    flat = np.asarray(values).ravel()
    n = flat.size
    q = pct / 100.0
    virtual = n * q + (1 + q * (1 - 1 - 1)) - 1  # numpy's _compute_virtual_index with alpha = beta = 1
    below = min(max(int(np.floor(virtual)), 0), n - 1)
    above = min(below + 1, n - 1)
    gamma = virtual - below
    top = flat.max()
    for share in _UPPER_SHARES:  # the fewest values that still hold every rank from `below` up
        candidates = flat[flat >= top * share]
        if candidates.size >= n - below:
            break
    else:
        candidates = flat
    skipped = n - candidates.size  # every skipped value is smaller than every candidate
    ranked = np.partition(candidates, [below - skipped, above - skipped])
    a, b = ranked[below - skipped], ranked[above - skipped]
    diff = b - a  # numpy's _lerp: from the nearer end
    return b - diff * (1 - gamma) if gamma >= 0.5 else a + diff * gamma


def _image_axes(H: np.ndarray, board_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit image directions of the board's x and y axes at board point `board_xy` (2,)."""
    x, y = board_xy
    p = H @ np.array([x, y, 1.0])
    du = (H[:2, 0] * p[2] - p[:2] * H[2, 0]) / p[2] ** 2
    dv = (H[:2, 1] * p[2] - p[:2] * H[2, 1]) / p[2] ** 2
    return du / np.linalg.norm(du), dv / np.linalg.norm(dv)
