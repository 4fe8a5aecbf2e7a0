"""The model-choice rule on stand-in solves (exact held-out errors, fields of view, failures), and a
half's re-solve without its inconsistent view. Fast: these run first in the mutation test.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_model_choice import CASES, views_of

import calibcoach.app.solve.model_choice as mc
from calibcoach.app.solve.model_choice import candidate_order, choose_model, estimate_hfov_deg
from calibcoach.drivers.errors import CalibrationError

from _synthetic import SIZE, observe, random_poses

# --- the decision rule, on stand-in solves with known held-out errors ------------------------------
# The solves in test_model_choice.py are real; these replace them (module attributes, looked up at call time) so the
# rule itself -- which views solve, which score, which model wins by how much -- is checked exactly.


def stand_in(monkeypatch, scores: dict[str, float], *, hfov: float = 100.0, failing=()):
    """choose_model with `estimate_hfov_deg` -> hfov and each model's held-out RMS = scores[model] on either half.

    Returns the log of (model, solved-on frame indices, scored-on frame indices)."""
    log = []

    def solve_half(views, image_size, model, warm=None, cold_pinhole=None):
        if model in failing:
            raise CalibrationError("stand-in failure")
        return (model, tuple(v.frame_index for v in views))

    def held_out(solved, views):
        model, solved_on = solved
        log.append((model, solved_on, tuple(v.frame_index for v in views)))
        return scores[model]

    monkeypatch.setattr(mc, "estimate_hfov_deg", lambda views, size, warm=None: hfov)
    monkeypatch.setattr(mc, "_solve_half", solve_half)
    monkeypatch.setattr(mc, "held_out_rms", held_out)
    return log


def test_each_model_is_solved_on_one_half_and_scored_on_the_other(monkeypatch) -> None:
    log = stand_in(monkeypatch, {"rational": 0.3, "fisheye": 0.3, "pinhole": 0.3})
    views = views_of("webcam720", 0, n=9)
    choice = choose_model(views, SIZE)
    assert choice.chosen == "rational" and list(choice.candidates) == ["rational", "fisheye", "pinhole"]
    assert len(log) == 6
    odd, even = (1, 3, 5, 7), (0, 2, 4, 6, 8)
    for model in choice.candidates:
        assert sorted((s, t) for m, s, t in log if m == model) == sorted([(odd, even), (even, odd)])


def test_eight_views_are_enough_to_cross_validate(monkeypatch) -> None:
    stand_in(monkeypatch, {"pinhole": 0.3, "rational": 0.3}, hfov=60.0)
    assert choose_model(views_of("webcam720", 0, n=8), SIZE).candidates == {"pinhole": 0.3, "rational": 0.3}


def test_the_two_halves_combine_as_an_rms(monkeypatch) -> None:
    log = stand_in(monkeypatch, {"pinhole": 0.0, "rational": 0.0})
    halves = {}
    monkeypatch.setattr(mc, "held_out_rms", lambda solved, views: halves.setdefault(solved[1], 0.3 if len(halves) else 0.4))
    choice = choose_model(views_of("webcam720", 0, n=8), SIZE)
    assert log == [] and choice.candidates["pinhole"] == pytest.approx(np.sqrt((0.3**2 + 0.4**2) / 2))


@pytest.mark.parametrize(("simple", "chosen"), [
    (1.0, "pinhole"), (1.0 * 1.05 + 0.005, "pinhole"), (1.054, "pinhole"), (1.056, "rational"), (1.2, "rational"),
])
def test_the_simplest_model_within_five_percent_of_the_best_wins(monkeypatch, simple: float, chosen: str) -> None:
    stand_in(monkeypatch, {"pinhole": simple, "rational": 1.0, "fisheye": 0.999 if chosen == "rational" else 2.0},
             hfov=85.0)
    choice = choose_model(views_of("webcam720", 0, n=8), SIZE)
    assert choice.chosen == chosen, choice.reason
    assert choice.reason.startswith("~85 deg horizontal field of view")


def test_the_margin_has_a_floor_for_tiny_errors(monkeypatch) -> None:
    """0.005 px on top of the 5%: at 0.02 px held-out error a model 0.004 px worse is as good."""
    stand_in(monkeypatch, {"pinhole": 0.0249, "rational": 0.02}, hfov=60.0)
    assert choose_model(views_of("webcam720", 0, n=8), SIZE).chosen == "pinhole"
    stand_in(monkeypatch, {"pinhole": 0.0262, "rational": 0.02}, hfov=60.0)
    assert choose_model(views_of("webcam720", 0, n=8), SIZE).chosen == "rational"


def test_a_model_that_cannot_be_solved_scores_infinite(monkeypatch) -> None:
    stand_in(monkeypatch, {"fisheye": 0.3, "rational": 0.3}, hfov=150.0, failing=("fisheye",))
    choice = choose_model(views_of("webcam720", 0, n=8), SIZE)
    assert choice.chosen == "rational" and choice.candidates == {"fisheye": float("inf"), "rational": 0.3}
    stand_in(monkeypatch, {}, hfov=150.0, failing=("fisheye", "rational"))
    with pytest.raises(CalibrationError, match="no distortion model could be solved"):
        choose_model(views_of("webcam720", 0, n=8), SIZE)


@pytest.mark.parametrize(("hfov", "chosen"), [(119.9, "pinhole"), (120.0, "fisheye"), (150.0, "fisheye")])
def test_too_few_views_fisheye_from_120_deg(monkeypatch, hfov: float, chosen: str) -> None:
    stand_in(monkeypatch, {}, hfov=hfov)
    choice = choose_model(views_of("webcam720", 0, n=7), SIZE)
    assert choice.chosen == chosen and choice.candidates == {}


class _Raw:
    def __init__(self, rms_px: float, hfov: float) -> None:
        self.rms_px = rms_px
        self.camera = type("Cam", (), {"field_of_view_deg": lambda _self: (hfov, hfov * 0.6)})()


def fake_solves(monkeypatch, answers: dict):
    """`solve` answering (rms, hfov) per model, or raising for models not in `answers`; returns the models tried."""
    tried = []

    def solve(views, image_size, model, **kw):
        tried.append(model)
        if model not in answers:
            raise CalibrationError("stand-in failure")
        return _Raw(*answers[model])

    monkeypatch.setattr(mc, "solve", solve)
    return tried


@pytest.mark.parametrize(("answers", "hfov", "tried"), [
    ({"pinhole": (0.3, 70.0)}, 70.0, ["pinhole"]),  # a narrow lens the pinhole fits: no fisheye solve
    ({"pinhole": (0.99, 79.0), "fisheye": (0.1, 150.0)}, 79.0, ["pinhole"]),
    ({"pinhole": (1.01, 79.0), "fisheye": (0.1, 150.0)}, 150.0, ["pinhole", "fisheye"]),  # fits too loosely
    ({"pinhole": (0.3, 80.5), "fisheye": (0.1, 150.0)}, 150.0, ["pinhole", "fisheye"]),  # too wide to be sure
    ({"pinhole": (0.3, 85.0), "fisheye": (0.4, 150.0)}, 85.0, ["pinhole", "fisheye"]),  # the lower RMS wins
    ({"pinhole": (3.0, 100.0), "fisheye": (3.0, 150.0)}, 100.0, ["pinhole", "fisheye"]),  # a tie: the first
    ({"fisheye": (0.4, 150.0)}, 150.0, ["pinhole", "fisheye"]),  # pinhole failed
    ({"pinhole": (0.3, float("nan")), "fisheye": (2.0, 150.0)}, 150.0, ["pinhole", "fisheye"]),  # no finite FOV
    ({"pinhole": (0.3, 0.5), "fisheye": (2.0, 150.0)}, 150.0, ["pinhole", "fisheye"]),  # no lens is that narrow
    ({"pinhole": (0.3, 1.5)}, 1.5, ["pinhole"]),  # a long telephoto is
    ({"pinhole": (2.0, 100.0), "fisheye": (0.3, 260.0)}, 100.0, ["pinhole", "fisheye"]),  # nor that wide
    ({"pinhole": (2.0, 100.0), "fisheye": (0.3, 249.0)}, 249.0, ["pinhole", "fisheye"]),
])
def test_estimated_field_of_view_takes_the_better_fitting_solve(monkeypatch, answers, hfov, tried) -> None:
    log = fake_solves(monkeypatch, answers)
    assert estimate_hfov_deg([], SIZE) == hfov
    assert log == tried


def test_without_any_solve_the_field_of_view_is_taken_as_an_ordinary_lens(monkeypatch) -> None:
    fake_solves(monkeypatch, {})
    hfov = estimate_hfov_deg([], SIZE)
    assert candidate_order(hfov) == ["pinhole", "rational"]  # the simplest candidates, no fisheye
    fake_solves(monkeypatch, {"pinhole": (0.3, float("inf")), "fisheye": (0.3, float("nan"))})
    assert estimate_hfov_deg([], SIZE) == hfov


def _view_rms_ratio(views, bad: int) -> float:
    from calibcoach.app.solve.calibrate import reprojection_residuals, solve

    raw = solve(views, SIZE, "pinhole")
    rms = [np.sqrt(np.mean(np.sum(r**2, axis=1))) for r in reprojection_residuals(raw.camera, views, raw.rvecs, raw.tvecs)]
    return float(rms[bad] / np.median(rms)), float(rms[bad])


@pytest.mark.parametrize(("noise", "bad_noise", "dropped", "n"), [
    (0.2, 3.0, True, 8),  # 14x the median view: a misdetection
    (0.2, 0.7, True, 8),  # ~3.5x
    (0.2, 0.4, False, 8),  # ~2.5x: within the scatter of views
    (0.02, 0.2, False, 8),  # 10x the median, but under half a pixel: never a reason to drop a view
    (0.2, 3.0, True, 4),  # the three views left are enough to solve again
])
def test_a_half_is_solved_without_its_clearly_inconsistent_view(noise: float, bad_noise: float, dropped: bool,
                                                                n: int) -> None:
    from calibcoach.app.solve.calibrate import solve
    from calibcoach.app.solve.model_choice import _solve_half

    views = views_of("webcam720", 0, n=n, noise_px=noise)
    rng = np.random.default_rng(1)
    views[2] = replace(views[2], image_points_px=views[2].image_points_px + rng.normal(0, bad_noise, (70, 2)))
    ratio, rms = _view_rms_ratio(views, 2)
    assert (ratio > 3.0 and rms > 0.5) is dropped, (ratio, rms)
    expected = solve(views[:2] + views[3:] if dropped else views, SIZE, "pinhole").camera
    got = _solve_half(views, SIZE, "pinhole")
    np.testing.assert_allclose(got.camera_matrix, expected.camera_matrix, atol=0.02)
    np.testing.assert_allclose(got.dist_coeffs, expected.dist_coeffs, atol=1e-4)


@pytest.mark.parametrize("lens", ["webcam720", "fisheye150"])
def test_the_held_out_pose_refinement_converges_from_a_rough_start(lens: str) -> None:
    """Gauss-Newton on the pose alone, from 0.05 rad and 10% off, lands on the true pose of a noise-free view."""
    camera, placement, _, _ = CASES[lens]
    (r, t), = random_poses(camera, 1, np.random.default_rng(7), **placement)
    view = observe(camera, [(r, t)])[0]
    rvec, tvec = mc._refine_pose(camera, view, r + 0.05, t * 1.1)
    np.testing.assert_allclose(rvec, r, atol=1e-8)
    np.testing.assert_allclose(tvec, t, atol=1e-8)


@pytest.mark.parametrize(("hfov", "n", "likely"), [(60.0, 8, "pinhole"), (100.0, 8, "rational"), (150.0, 8, "fisheye"),
                                                   (100.0, 5, "pinhole"), (150.0, 5, "fisheye")])
def test_the_likely_model_is_named_before_the_cross_validation(monkeypatch, hfov: float, n: int, likely: str) -> None:
    """The session starts the likely model's final solve on being told (app/session_finish.py); it must be
    told before any half is solved, and name the model chosen whenever that is within the margin."""
    log = stand_in(monkeypatch, {"pinhole": 0.3, "rational": 0.3, "fisheye": 0.3}, hfov=hfov)
    told = []
    choice = choose_model(views_of("webcam720", 0, n=n), SIZE, on_likely=lambda model: told.append((model, len(log))))
    assert told == [(likely, 0)]
    assert choice.chosen == likely
