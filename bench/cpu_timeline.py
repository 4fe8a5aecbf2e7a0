"""Where a replay's CPU goes, process by process, over time: `calibcoach calibrate` watched from /proc.

A replay runs in three processes (the replay itself, the scan's child: app/scan_process.py, and
session.rrd's writer: app/viewer_process.py). Profilers see one process, and Python's own clocks
one thread; this samples every process of the command's tree from /proc every 20 ms, so it shows
whether both cores are busy (the read), or only one (the time after it), and which process holds
them. Prints, per 0.25 s, the CPU seconds each process used in it, then each one's total.

    .venv/bin/python bench/cpu_timeline.py FOLDER_OR_VIDEO [--step 0.25]

Nothing is written; bench/results/replay_speed.md quotes its runs.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

_TICKS = os.sysconf("SC_CLK_TCK")


def tree(root: int) -> list[int]:
    """`root` and every process below it (gone ones are skipped)."""
    found = [root]
    try:
        for thread in os.listdir(f"/proc/{root}/task"):
            with open(f"/proc/{root}/task/{thread}/children") as children:
                for child in children.read().split():
                    found += tree(int(child))
    except OSError:
        pass
    return found


def cpu_and_nice(pid: int) -> tuple[float, int] | None:
    """User + system CPU of a process so far and its nice value (None once it is gone)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / _TICKS, int(fields[16])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="a folder of images or a video file")
    parser.add_argument("--step", type=float, default=0.25, help="seconds per printed row")
    args = parser.parse_args()
    if not Path("/proc/self/stat").exists():
        raise SystemExit("cpu_timeline: needs Linux's /proc")
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        command = subprocess.Popen([sys.executable, "-m", "calibcoach.app", "calibrate", str(args.source), "--out", out, "--quiet"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        samples: list[tuple[float, dict[int, float]]] = []
        niced: set[int] = set()
        while command.poll() is None:
            now = {}
            for pid in tree(command.pid):
                if (read := cpu_and_nice(pid)) is not None:
                    now[pid] = read[0]
                    if read[1] > 0:
                        niced.add(pid)
            samples.append((time.perf_counter() - start, now))
            time.sleep(0.02)
        wall = time.perf_counter() - start
        said = command.stderr.read() if command.stderr else ""
    pids = sorted({pid for _t, row in samples for pid in row})
    # the replay forks the scan's child, then session.rrd's writer, which lowers itself to nice 19
    names = {pid: "replay" if pid == command.pid else "rrd writer" if pid in niced else "scan" for pid in pids}
    print(f"wall {wall:.2f} s; {said.strip().splitlines()[-1] if said.strip() else ''}")
    print("t, s   " + " ".join(f"{names[p]:>12s}" for p in pids))
    last = dict.fromkeys(pids, 0.0)
    edge = args.step
    for t, row in samples:
        if t < edge:
            continue
        print(f"{t:5.2f}  " + " ".join(f"{row.get(p, last[p]) - last[p]:12.2f}" for p in pids))
        last = {p: row.get(p, last[p]) for p in pids}
        edge += args.step
    totals = {p: max((row[p] for _t, row in samples if p in row), default=0.0) for p in pids}
    print("total  " + " ".join(f"{totals[p]:12.2f}" for p in pids) + f"   (all: {sum(totals.values()):.2f} s of CPU)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
