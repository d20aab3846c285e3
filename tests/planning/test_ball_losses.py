"""The outlook with the detector's losses (``planning/ball_losses.py``) against its definition
computed the slow way: every found/lost pattern of the seen balls, each weighted by its own
probability (2^n terms), with the same per-pattern model (``predict_error``)."""

from __future__ import annotations

import itertools
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from analytic_head import PH

from monotracker.planning import predict
from monotracker.planning.camera_poses import camera_pose
from monotracker.planning.candidates import sample_candidates, skin_normals_under
from monotracker.planning.prediction import outlook_with_losses as loss_outlook
from monotracker.planning.prediction import predict_error


@pytest.fixture(scope="module")
def setup(problem):
    cands = sample_candidates(problem, spacing_mm=20.0)
    pose = camera_pose(PH.view_direction_lps, 450.0, PH.fiducial_centres_lps.mean(axis=0), cands.skin)
    C = PH.fiducial_centres_lps
    N = skin_normals_under(problem.head, C, problem.radius_mm)
    seen = predict(problem, pose.T_ct_cam, C, N, full=False).visibility.seen
    assert seen.sum() >= 7
    return problem, pose.T_ct_cam, C, seen


def _by_every_pattern(problem, T, C, seen, q):
    idx = np.flatnonzero(seen)
    trusted = pose = 0.0
    for found in itertools.product((False, True), repeat=len(idx)):
        found = np.array(found)
        w = float(np.prod(np.where(found, q, 1.0 - q)))
        keep = np.zeros(len(C), bool)
        keep[idx[found]] = True
        e = predict_error(problem, T, C, keep)
        if e is not None:
            pose += w
            trusted += w * e.trusted
    return trusted, pose


@pytest.mark.parametrize("q", [0.55, 0.85])
def test_the_outlook_is_the_average_over_every_pattern_of_found_balls(setup, q):
    problem, T, C, seen = setup
    seen = seen.copy()
    seen[np.flatnonzero(seen)[6:]] = False          # 6 seen balls: 64 patterns, exact
    want_t, want_p = _by_every_pattern(problem, T, C, seen, q)
    got = loss_outlook(problem, T, C, seen, q, per_count=64, min_weight=0.0)
    assert got.trusted == pytest.approx(want_t, abs=1e-9)
    assert got.pose == pytest.approx(want_p, abs=1e-9)
    assert got.expected_found == pytest.approx(6 * q)
    assert 0.0 < got.trusted < want_p <= 1.0 + 1e-12   # some patterns lose the pose, fewer are trusted


def test_sampled_subsets_stay_close_to_the_exact_average(setup):
    """With every seen ball (8-9: 256-512 patterns) the default samples 12 subsets per count."""
    problem, T, C, seen = setup
    q = 0.6
    want_t, want_p = _by_every_pattern(problem, T, C, seen, q)
    got = loss_outlook(problem, T, C, seen, q)
    assert got.subsets < 2 ** int(seen.sum()) / 3
    assert got.pose == pytest.approx(want_p, abs=0.03)
    assert got.trusted == pytest.approx(want_t, abs=0.05)
    assert got.trusted <= want_t + 0.05 and got == loss_outlook(problem, T, C, seen, q)   # seeded: repeatable


def test_every_ball_found_is_the_all_seen_prediction_and_fewer_found_trust_less(setup):
    problem, T, C, seen = setup
    allp = predict_error(problem, T, C, seen)
    one = loss_outlook(problem, T, C, seen, 1.0)
    assert one.trusted == pytest.approx(allp.trusted) and one.pose == 1.0 and one.subsets == 1
    t = [loss_outlook(problem, T, C, seen, q).trusted for q in (0.9, 0.6, 0.3)]
    assert t[0] > t[1] > t[2] >= 0.0, t
    assert loss_outlook(problem, T, C, seen, 0.05).pose < 0.01


def test_the_problem_carries_the_found_probability_and_refuses_nonsense(problem):
    from monotracker.planning.detector_defaults import DEFAULT_FOUND_PROBABILITY

    assert problem.found_probability == DEFAULT_FOUND_PROBABILITY
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="found probability"):
            replace(problem, found_probability=bad)


def test_the_cli_refuses_a_found_probability_out_of_range(tmp_path):
    r = subprocess.run([sys.executable, "-m", "monotracker", "plan-layout", str(tmp_path), "--target", "0,0,0",
                        "--found", "1.5"], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0
    assert "--found" in r.stderr and "Traceback" not in r.stderr
