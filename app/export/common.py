"""What every export shares: the trust rule's names and notices, and exact number formatting.

The trust rule of the project: a refused calibration writes no file another tool would load as a
camera unless the user passes --accept-partial; then each file's name carries "untrusted"
(`untrusted_name`) and, where the format has comments, the file says inside that it is untrusted
and why (`notice_lines`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

from calibcoach.drivers.errors import CalibcoachError


def untrusted_name(name: str) -> str:
    """'cameras.txt' -> 'cameras_untrusted.txt' (the same rule as outputs/report.py)."""
    stem, dot, ext = name.rpartition(".")
    return f"{stem}_untrusted{dot}{ext}" if dot else f"{name}_untrusted"


def file_name(name: str, untrusted_because: Sequence[str]) -> str:
    """`name` for a trusted calibration, its untrusted twin otherwise."""
    return untrusted_name(name) if untrusted_because else name


def notice_lines(untrusted_because: Sequence[str], comment: str = "#") -> list[str]:
    """Comment lines opening an untrusted file: that it is untrusted, and why; [] when trusted."""
    if not untrusted_because:
        return []
    lines = [f"{comment} UNTRUSTED calibration (calibcoach refused it; written because of --accept-partial):"]
    lines += [f"{comment}   {ascii_text(reason)}" for reason in untrusted_because]
    return lines


def ascii_text(text: str) -> str:
    return str(text).encode("ascii", "replace").decode()


def num(x: float) -> str:
    """Shortest repr that reads back to the same float64 (no rounding in any export)."""
    value = float(x)
    if not math.isfinite(value):
        raise CalibcoachError(f"calibration contains a non-finite value ({value}); it cannot be exported")
    return repr(value)


def out_path(out_dir: str | Path, name: str, untrusted_because: Sequence[str]) -> Path:
    return Path(out_dir) / file_name(name, untrusted_because)
