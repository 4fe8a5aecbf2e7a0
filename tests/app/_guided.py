"""The closed-loop runs of tests/app/test_guided_loop.py, each in a process of its own.

A simulated person following the guidance for a minute or two of capture is ~30-115 s of mostly
one-core Python per run, and five such runs were 40% of the test suite's time. They are
independent, so they run two at a time in spawned worker processes (a fresh interpreter: no
threads or OpenCV pool inherited from the test process), each returning what its test asserts
as plain values.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import replace

import numpy as np

import calibcoach
from calibcoach.app.solve.compare import projection_difference
from calibcoach.app.solve.uncertainty import covered_region_mask
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.sim import LENSES
from calibcoach.drivers.sim_person import SimulatedPerson

BOARD = calibcoach.BoardSpec()
FPS = 8


def _run(lens: str, strategy: str, *, seed: int, max_s: float):
    camera = LENSES[lens]
    assistant = calibcoach.Assistant(board=BOARD, image_size=camera.image_size, model="auto")
    person = SimulatedPerson(camera, BOARD, strategy, seed=seed, fps=FPS)
    run = person.run(assistant.feed, max_s=max_s)
    return camera, assistant, run


def guided(lens: str) -> dict:
    """A person following the guidance on `lens` (seed 11, up to 90 s)."""
    camera, assistant, run = _run(lens, "guided", seed=11, max_s=90.0)
    steps = run.steps
    accepted = {s.frame_index for s in steps if s.accepted}
    # the longest run of holds ending on the same target without a frame accepted
    streak = longest = 0
    previous = None
    for hold in run.holds:
        asked = None if hold.asked is None else (tuple(hold.asked.centre_px), hold.asked.tilt_x_deg, hold.asked.tilt_y_deg)
        registered = any(hold.start_s * FPS - 10 <= i <= hold.end_s * FPS for i in accepted)
        streak = streak + 1 if (asked is not None and asked == previous and not registered) else 1
        longest, previous = max(longest, streak), asked
    outcome = {
        "stopped_at_s": run.stopped_at_s,
        "progress": str(assistant.session.progress()),
        "always_a_target": all(s.guidance.target is not None for s in steps if not s.progress.done),
        "ends_done_without_target": steps[-1].guidance.target is None and steps[-1].progress.done,
        "sentences": sorted({s.guidance.sentence for s in steps if s.guidance.target is not None}),
        "longest_unregistered_repeat": longest,
    }
    result = assistant.finish()
    views = result.session.calibration.views
    estimate = CameraModel(result.model, result.camera_matrix, result.dist_coeffs, camera.image_size)
    mask = covered_region_mask(camera.image_size, [v.image_points_px for v in views], (32, 18))
    outcome.update(trusted=bool(result.verdict.trusted), reasons=list(result.verdict.reasons),
                   truth_px=float(projection_difference(camera, estimate, grid=(32, 18), mask=mask).rms_px),
                   expected_error_px=float(result.expected_error_px))
    return outcome


def lazy() -> dict:
    """A lazy, frontal capture on the webcam (seed 11, 30 s)."""
    _camera, assistant, run = _run("webcam720", "lazy", seed=11, max_s=30.0)
    result = assistant.finish()
    return {"stopped_at_s": run.stopped_at_s, "trusted": bool(result.verdict.trusted), "grade": result.verdict.grade,
            "reasons": list(result.verdict.reasons)}


def noisy() -> dict:
    """The guided webcam run with a poor real webcam's corner noise (0.5 px per coordinate) on its detections."""
    from calibcoach.coverage.detector import CharucoBoardDetector
    from calibcoach.drivers.base import Frame

    camera = LENSES["webcam720"]
    assistant = calibcoach.Assistant(board=BOARD, image_size=camera.image_size)
    detector = CharucoBoardDetector(BOARD)
    rng = np.random.default_rng(5)
    count = 0

    def feed(image: np.ndarray, timestamp_ns: int):
        nonlocal count
        detection = detector.detect(image)
        noise = rng.normal(0, 0.5, detection.corners_px.shape)
        count += 1
        return assistant.feed_detected(Frame(count - 1, timestamp_ns, image),
                                       replace(detection, corners_px=(detection.corners_px + noise).astype(np.float32)))

    run = SimulatedPerson(camera, BOARD, "guided", seed=12, fps=FPS).run(feed, max_s=120.0)
    result = assistant.finish()
    return {"stopped_at_s": run.stopped_at_s, "progress": str(assistant.session.progress()),
            "noise_px": float(result.session.noise_px), "reasons": list(result.verdict.reasons),
            "grade": result.verdict.grade, "rms_grade": result.verdict.rms_grade}


def start_all() -> dict[str, Future]:
    """Every run started on two spawned workers, longest first: name -> its future outcome."""
    pool = ProcessPoolExecutor(max_workers=2, mp_context=multiprocessing.get_context("spawn"))
    jobs = {name: pool.submit(guided, name) for name in ("wide720", "fisheye150", "webcam720")}
    jobs["noisy"] = pool.submit(noisy)
    jobs["lazy"] = pool.submit(lazy)
    pool.shutdown(wait=False)  # the workers finish the queue; each future is waited for by its test
    return jobs
