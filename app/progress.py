"""Progress bars for a person at a terminal: frames read of a replay, and the final solve's stages.

Drawn with tqdm on stderr, and only when stderr is a terminal and the run is not `--quiet`;
otherwise nothing here prints, and the plain progress lines (`commands.ProgressLine`), which logs,
tests and CI read, stay exactly as they are.
"""

from __future__ import annotations

import sys
from typing import Any

# What `CalibrationSession.finish` does after the capture, in order (it reports each as it starts);
# the command adds the last.
SOLVE_STAGES = ("frame budget", "model choice", "robust solve", "uncertainty", "verdict", "outputs")


def terminal_bar(*, enabled: bool, **options: Any):
    """A tqdm bar on stderr when `enabled` and stderr is a terminal, else None."""
    if not enabled or not sys.stderr.isatty():
        return None
    from tqdm import tqdm

    return tqdm(file=sys.stderr, dynamic_ncols=True, mininterval=0.1, leave=True, **options)


class SolveStages:
    """The final solve's stages as a bar, used as `with SolveStages(enabled=...) as stages:`.

    `stages(name)` as each stage begins (a callable for `CalibrationSession.finish(on_stage=...)`),
    `stages.say(line)` for a line on stderr that must not tear the bar; leaving the block fills the
    bar to 100%; an exception leaving it clears the bar instead. Does nothing off a terminal or with --quiet.
    """

    def __init__(self, *, enabled: bool) -> None:
        self._bar = terminal_bar(enabled=enabled, total=len(SOLVE_STAGES), desc="solving", unit="stage",
                                 bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} stages, {elapsed}{postfix}")

    def __call__(self, stage: str) -> None:
        if self._bar is None:
            return
        if stage in SOLVE_STAGES:  # the stages before this one are done (some, such as the budget fill, may be skipped)
            self._bar.n = SOLVE_STAGES.index(stage)
        self._bar.set_postfix_str(stage, refresh=False)
        self._bar.refresh()

    def say(self, line: str) -> None:
        """Print `line` on stderr: above the bar on a terminal, as a plain line otherwise."""
        if self._bar is None:
            print(line, file=sys.stderr)
        else:
            self._bar.write(line, file=sys.stderr)

    def __enter__(self) -> SolveStages:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self._bar is None:
            return
        if exc_type is None:
            self._bar.n = len(SOLVE_STAGES)
            self._bar.set_postfix_str("done", refresh=False)
        else:  # the error's own message says what happened: no half-filled bar above it
            self._bar.leave = False
        self._bar.close()
        self._bar = None
