"""A results file whose table keeps the rows of renders not rerun (renders come and go from bench/cache)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path


def write_merged(out: Path, preamble: str, header: str, made: list[str], key: Callable[[str], tuple]) -> None:
    """Write `made` into the table under `header` in `out`, replacing the rows with the same `key`.

    What was written before is kept: the text above the table (`preamble` when the file is new),
    the rows of other keys, and the reading below the table (after its first blank line). Rows are
    sorted by `key`.
    """
    before, _, rest = (out.read_text() if out.exists() else preamble).partition(header + "\n")
    old_rows, _, reading = rest.partition("\n\n")
    rerun = {key(line) for line in made}
    kept = [line for line in old_rows.splitlines() if line.startswith("| ") and key(line) not in rerun]
    table = sorted(kept + made, key=key)
    out.write_text(before + header + "\n" + "\n".join(table) + "\n" + ("\n" + reading if reading else ""))
