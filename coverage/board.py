"""The calibration target: a ChArUco board described by its measured sizes.

The solver treats these sizes as truth, so they should be the printed board's measured values,
not the nominal ones (the method's board measures 30.01 mm squares and 22.01 mm markers).
"""

from __future__ import annotations

import tomllib
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibcoach.drivers.errors import BoardError

DICTIONARY_NAMES = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
# Sizes a printed board's squares and markers can have: below 1 mm no camera resolves the bits of
# a marker at a focusable distance; above 2 m it is a wall, not a board (and OpenCV's board
# geometry overflows long before 1e300 mm).
MIN_SIZE_MM = 1.0
MAX_SIZE_MM = 2000.0


def dictionary_id(name: str) -> int:
    """OpenCV's id for a dictionary name; accepts "DICT_5X5_100", "5x5_100" or "5X5_100".

    Example:
        >>> dictionary_id("5x5_100") == cv2.aruco.DICT_5X5_100
        True
    """
    key = name.strip().upper()
    if not key.startswith("DICT_"):
        key = "DICT_" + key
    value = getattr(cv2.aruco, key, None)
    if not isinstance(value, int):
        raise BoardError(
            f"unknown ArUco dictionary {name!r}; pass one of {', '.join(DICTIONARY_NAMES)} (e.g. --dictionary DICT_5X5_100)"
        )
    return value


@dataclass(frozen=True, slots=True)
class BoardSpec:
    """A ChArUco board: counts in squares, sizes in millimetres as measured on the print."""

    squares_x: int = 8  # squares along the board's width
    squares_y: int = 11  # squares along the board's height
    square_mm: float = 30.01  # measured chessboard square side
    marker_mm: float = 22.01  # measured ArUco marker side
    dictionary: str = "DICT_5X5_100"
    legacy: bool | None = None  # OpenCV < 4.6 pattern; None = detect automatically
    inverted: bool | None = None  # white-on-black print; None = detect automatically

    def __post_init__(self) -> None:
        for name in ("squares_x", "squares_y"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating) \
                    or not float(value).is_integer():
                raise BoardError(f"{name} must be a whole number of squares, got {value!r}: count the squares along the "
                                 f"board's {'width' if name == 'squares_x' else 'height'} (e.g. --squares 8x11)")
            object.__setattr__(self, name, int(value))
        if self.squares_x < 2 or self.squares_y < 2:
            raise BoardError(f"a ChArUco board needs at least 2x2 squares, got {self.squares_x}x{self.squares_y}")
        for name in ("square_mm", "marker_mm"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating) \
                    or not np.isfinite(value) or not MIN_SIZE_MM <= float(value) <= MAX_SIZE_MM:
                flag = "--square-mm" if name == "square_mm" else "--marker-mm"
                raise BoardError(f"{name.replace('_mm', '')} size {value!r} mm is not a printed board's: measure it on the "
                                 f"print and pass it in millimetres ({flag}, between {MIN_SIZE_MM:g} mm and {MAX_SIZE_MM:g} mm)")
            object.__setattr__(self, name, float(value))
        if not isinstance(self.dictionary, str):
            raise BoardError(f"dictionary must be a name such as DICT_5X5_100, got {self.dictionary!r}")
        if not 0 < self.marker_mm < self.square_mm:
            raise BoardError(
                f"marker size {self.marker_mm} mm must be positive and smaller than the square size {self.square_mm} mm"
            )
        dictionary_id(self.dictionary)
        object.__setattr__(self, "dictionary", "DICT_" + self.dictionary.strip().upper().removeprefix("DICT_"))
        markers_needed = (self.squares_x * self.squares_y) // 2
        size = cv2.aruco.getPredefinedDictionary(dictionary_id(self.dictionary)).bytesList.shape[0]
        if markers_needed > size:
            raise BoardError(
                f"a {self.squares_x}x{self.squares_y} board needs {markers_needed} markers but {self.dictionary} has only {size}; "
                "pass a larger dictionary"
            )

    @property
    def corner_count(self) -> int:
        """Inner chessboard corners, the ChArUco corners a full view shows."""
        return (self.squares_x - 1) * (self.squares_y - 1)

    @property
    def size_mm(self) -> tuple[float, float]:
        """Outer size of the chessboard area (width, height) in millimetres."""
        return self.squares_x * self.square_mm, self.squares_y * self.square_mm

    def cv_board(self, *, legacy: bool | None = None) -> cv2.aruco.CharucoBoard:
        """The OpenCV board in metres; `legacy` overrides the spec's pattern choice."""
        board = cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y),
            self.square_mm / 1000.0,
            self.marker_mm / 1000.0,
            cv2.aruco.getPredefinedDictionary(dictionary_id(self.dictionary)),
        )
        use_legacy = self.legacy if legacy is None else legacy
        board.setLegacyPattern(bool(use_legacy))
        return board

    def corner_points_m(self) -> np.ndarray:
        """(corner_count, 3) float64 board-frame coordinates of every ChArUco corner, in metres."""
        return np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def describe(self) -> str:
        extras = []
        if self.legacy:
            extras.append("legacy pattern")
        if self.inverted:
            extras.append("inverted print")
        tail = f" ({', '.join(extras)})" if extras else ""
        return (
            f"{self.squares_x}x{self.squares_y} squares, {self.dictionary}, "
            f"squares {self.square_mm:g} mm, markers {self.marker_mm:g} mm{tail}"
        )

    def with_detected(self, *, legacy: bool, inverted: bool) -> BoardSpec:
        return replace(self, legacy=legacy, inverted=inverted)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BoardSpec:
        """Build from our own keys, or from caliscope's charuco.toml keys (columns, rows, ...)."""
        try:
            if "columns" in data and "squares_x" not in data:
                return _from_caliscope(data)
            known = {k: data[k] for k in cls.__dataclass_fields__ if k in data}
            unknown = sorted(set(data) - set(cls.__dataclass_fields__))
            if unknown:
                raise BoardError(
                    f"board file has unknown keys {unknown}; expected squares_x, squares_y, square_mm, marker_mm, "
                    "dictionary, legacy, inverted"
                )
            return cls(**known)
        except TypeError as exc:
            raise BoardError(f"board description is malformed ({exc})") from None

    @classmethod
    def from_toml(cls, path: str | Path) -> BoardSpec:
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise BoardError(f"board file {path} does not exist; pass --board with a TOML file or --squares/--square-mm") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise BoardError(f"board file {path} is not valid TOML ({exc})") from None
        return cls.from_dict(data.get("board", data))


def _from_caliscope(data: dict[str, Any]) -> BoardSpec:
    square_cm = data.get("square_size_override_cm")
    if square_cm is None:
        raise BoardError("caliscope board file without square_size_override_cm: pass the measured square size with --square-mm")
    square_mm = float(square_cm) * 10.0
    return BoardSpec(
        squares_x=int(data["columns"]),
        squares_y=int(data["rows"]),
        square_mm=square_mm,
        marker_mm=square_mm * float(data.get("aruco_scale", 0.75)),
        dictionary=str(data.get("dictionary", "DICT_4X4_50")),
        inverted=bool(data.get("inverted", False)),
    )
