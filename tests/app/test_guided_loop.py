"""The guidance loop closed: a simulated person follows `calibcoach.Assistant` at default settings.

Issue 9's promise, tested the way an embedding program uses calibcoach: whoever does what the
guidance says gets an automatic stop and a trusted calibration, on a webcam, a wide (rational)
lens and a fisheye; the words always agree with the target they describe; an unregistered pose
is not asked for three times running; a lazy, frontal capture is refused. The multi-seed,
multi-hand figures are in bench/guided.py; these are single seeds, one per lens.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

import calibcoach
from calibcoach.coverage.candidates import candidate_poses, ranges_for
from calibcoach.coverage.guidance import COLUMN_WORDS, ROW_WORDS, sentence_for, zone
from calibcoach.coverage.virtual_view import BoardGeometry
from calibcoach.drivers.lens import CameraModel
from calibcoach.drivers.sim import LENSES

BOARD = calibcoach.BoardSpec()
TRUTH_LIMIT_PX = {"webcam720": 0.05, "wide720": 0.1, "fisheye150": 0.1}  # issue 9's bar, over the covered region


# --- words and targets agree (no rendering) -----------------------------------------------------

_ZONE_OF_WORDS = {
    "the centre": (2, 1), "left of centre": (1, 1), "right of centre": (3, 1), "the left edge": (0, 1), "the right edge": (4, 1),
    "the top centre": (2, 0), "the bottom centre": (2, 2), "the top-left corner": (0, 0), "the top-right corner": (4, 0),
    "the bottom-left corner": (0, 2), "the bottom-right corner": (4, 2), "the upper left": (1, 0),
    "the upper right": (3, 0), "the lower left": (1, 2), "the lower right": (3, 2),
}


def parse(sentence: str) -> dict:
    """Read a guidance sentence back: image zone, tilt per edge (signed degrees), range (m)."""
    m = re.fullmatch(r"Board (?:to )?(?P<where>.+?), (?P<tilt>facing the camera|.+?), (?P<range>[0-9.]+) m away\.", sentence)
    assert m, sentence
    tilts = {"x": 0.0, "y": 0.0}
    if m["tilt"] != "facing the camera":
        for edge, deg in re.findall(r"(top|bottom|left|right) edge(?: tilted away)? ~(\d+)°", m["tilt"]):
            axis, sign = {"top": ("x", 1), "bottom": ("x", -1), "right": ("y", 1), "left": ("y", -1)}[edge]
            tilts[axis] = sign * float(deg)
        assert any(tilts.values()), sentence
    return {"zone": _ZONE_OF_WORDS[m["where"]], "tilt_x": tilts["x"], "tilt_y": tilts["y"], "range": float(m["range"])}


@pytest.mark.parametrize("lens", ["webcam720", "wide720", "fisheye150"])
def test_every_candidate_sentence_says_what_its_target_is(lens: str) -> None:
    from calibcoach.app.guide import target_of
    from calibcoach.app.solve.next_view import RankedPose

    camera = LENSES[lens]
    geometry = BoardGeometry.of(BOARD)
    candidates = candidate_poses(camera, geometry, ranges_for(camera, geometry))
    assert len(candidates) > 100
    zones = set()
    for cand in candidates:
        target = target_of(RankedPose(cand, 0.1, 0.0, 0.1), camera, geometry.centre_m)
        said = parse(sentence_for(target, camera.image_size))
        assert said["zone"] == zone(target.centre_px, camera.image_size)
        assert said["tilt_x"] == pytest.approx(target.tilt_x_deg, abs=2.5)  # said to the nearest 5 deg
        assert said["tilt_y"] == pytest.approx(target.tilt_y_deg, abs=2.5)
        assert said["range"] == pytest.approx(target.distance_m, abs=0.05)
        # the target's pose puts the board's centre where the words say, at the range they say
        centre_cam = cv2_rotate(target.rvec, geometry.centre_m) + target.tvec_m
        assert np.linalg.norm(centre_cam) == pytest.approx(target.distance_m, rel=1e-6)
        assert camera.project(centre_cam.reshape(1, 3))[0] == pytest.approx(target.centre_px, abs=1e-3)
        zones.add(said["zone"])
    # every zone has a name of its own; all are asked for where a board can register there (a
    # 150 deg fisheye's image corners lie ~80 deg off axis, where the markers squeeze below reading)
    assert len(zones) == len(COLUMN_WORDS) * len(ROW_WORDS) or (lens == "fisheye150" and len(zones) >= 11)


def cv2_rotate(rvec: np.ndarray, point: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(rvec, np.float64))[0] @ point


def test_regions_beyond_a_fisheyes_image_circle_are_not_required() -> None:
    # a 190 deg circular fisheye on a 16:9 sensor: the image corners are black, no board is ever there
    circular = CameraModel("fisheye", [[300.0, 0, 639.5], [0, 300.0, 359.5], [0, 0, 1]], [0.0, 0.0, 0.0, 0.0], (1280, 720))
    session = calibcoach.Assistant(board=BOARD, image_size=(1280, 720), model="fisheye").session
    session.camera = circular
    session._candidates_camera = None
    session._refresh_lens()
    reachable = session.selector.coverage.reachable
    assert not reachable[0, 0] and not reachable[-1, -1] and not reachable[0, -1] and not reachable[-1, 0]
    assert reachable[1:-1, 1:-1].sum() >= 6  # the middle of the image circle is asked for
    assert not session.selector.coverage.is_complete()


def test_candidate_poses_are_rebuilt_only_when_the_lens_moved_by_a_share_of_the_image() -> None:
    """A narrow lens seen in the middle moves its image corners by pixels from solve to solve; the candidates
    (whose Jacobians the ranking takes from the current lens anyway) are rebuilt beyond 1% of the diagonal."""
    session = calibcoach.Assistant(board=BOARD, image_size=(1280, 720), model="pinhole").session
    base = CameraModel("pinhole", [[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]], np.zeros(5), (1280, 720))
    session.camera = base
    session._candidates_camera = None
    session._refresh_lens()
    built = session._candidates
    for focal, rebuilt in ((912.0, False), (935.0, True)):  # edges move ~9 px, then ~23 px (limit 14.7 px at 720p)
        session.camera = CameraModel("pinhole", [[focal, 0, 640], [0, focal, 360], [0, 0, 1]], np.zeros(5), (1280, 720))
        session._refresh_lens()
        assert (session._candidates is not built) == rebuilt


@pytest.mark.parametrize(("squares", "need"), [((4, 5), 6), ((5, 7), 6), ((6, 8), 8)])
def test_a_small_board_gets_targets_and_every_region_of_an_ordinary_lens(squares, need) -> None:
    """A board with fewer corners than the default's quarter (16) is asked for a quarter of itself (at least the
    method's 6) in a target, and a region cell is reachable when a seventh of it lands there: caliscope's 4 x 5
    board (12 corners) had no candidate pose at all, so no guidance, and no region ever counted."""
    from calibcoach.coverage.candidates import target_corners

    board = calibcoach.BoardSpec(squares_x=squares[0], squares_y=squares[1], square_mm=54.0, marker_mm=40.5,
                                 dictionary="DICT_4X4_1000")
    assert target_corners(board.corner_count) == need
    session = calibcoach.Assistant(board=board, image_size=(1280, 720), model="pinhole").session
    session.camera = CameraModel.from_fov((1280, 720), 70.0)
    session._candidates_camera = None
    session._refresh_lens()
    assert len(session._candidates) > 100
    assert min(c.view.corner_count for c in session._candidates) >= need
    assert session.selector.coverage.reachable.all()
    session._rank()
    assert session.guide.best is not None  # the first target: the board facing the camera at the centre


# --- the closed loop ----------------------------------------------------------------------------
# Each run is a minute or two of simulated capture; they run two at a time in worker processes
# (tests/app/_guided.py), started with the first test that needs them.


@pytest.fixture(scope="module")
def runs() -> dict:
    import _guided

    return _guided.start_all()


@pytest.mark.slow
@pytest.mark.parametrize("lens", ["webcam720", "wide720", "fisheye150"])
def test_a_person_following_the_guidance_gets_an_automatic_trusted_stop(lens: str, runs: dict) -> None:
    run = runs[lens].result()
    assert run["stopped_at_s"] is not None and run["stopped_at_s"] <= 90.0, run["progress"]
    assert run["always_a_target"]  # never "keep moving"
    assert run["ends_done_without_target"]
    for sentence in run["sentences"]:
        parse(sentence)  # every instruction names a place, a tilt (or facing) and a range
    # the same target never comes back at the end of three holds in a row without a frame accepted
    assert run["longest_unregistered_repeat"] < 3
    assert run["trusted"], run["reasons"]
    assert run["truth_px"] <= TRUTH_LIMIT_PX[lens]
    # E is honest: the true error lies within the band bench/guided.py measured (README). With the
    # corners fitted to the pattern's symmetry the webcam's true error fell to 0.001-0.005 px, and E
    # (the scatter between holds, ~0.005) is up to ~4.5x above it: truth / E 0.23-1.01 over the 10
    # webcam runs of bench/results/guided_symmetry.md, 0.22 on this test's seed 11 (0.30-2.14 before)
    assert 0.15 < run["truth_px"] / run["expected_error_px"] < 2.5


@pytest.mark.slow
def test_a_lazy_frontal_capture_is_refused(runs: dict) -> None:
    run = runs["lazy"].result()
    assert run["stopped_at_s"] is None  # nothing it shows completes the coverage
    assert not run["trusted"] and run["grade"] == "insufficient"
    assert any("Coverage is only" in r for r in run["reasons"])


@pytest.mark.slow
def test_a_noisy_webcam_finishes_too_and_the_verdict_names_the_noise(runs: dict) -> None:
    # corner noise of a poor real webcam (0.5 px per coordinate: compression, rolling shutter, dim
    # light), put onto the detected corners of rendered frames: the stop must still fire by itself
    run = runs["noisy"].result()
    assert run["stopped_at_s"] is not None and run["stopped_at_s"] <= 120.0, run["progress"]
    assert run["noise_px"] == pytest.approx(0.5, rel=0.25)
    assert any("What limits it: corner noise" in r for r in run["reasons"]), run["reasons"]
    assert run["grade"] in ("acceptable", "poor") and run["rms_grade"] != "excellent"
