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
    """(trusted, pose) by brute force; ``q`` one share or (n,) shares, one per ball."""
    idx = np.flatnonzero(seen)
    qs = np.broadcast_to(np.asarray(q, float), (len(C),))[idx]
    trusted = pose = 0.0
    for found in itertools.product((False, True), repeat=len(idx)):
        found = np.array(found)
        w = float(np.prod(np.where(found, qs, 1.0 - qs)))
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


@pytest.mark.parametrize("n_seen", [6, None])
def test_balls_short_of_skin_are_found_less_and_the_outlook_is_still_the_every_pattern_average(setup, n_seen):
    """Balls marked short of skin are found with ``short_ratio`` times the share of the others:
    the outlook is the brute-force average with per-ball shares, exact over every subset with 6
    seen balls and within sampling error with all of them (8-9: the conditional draws)."""
    problem, T, C, seen = setup
    seen = seen.copy()
    if n_seen is not None:
        seen[np.flatnonzero(seen)[n_seen:]] = False
    short = np.zeros(len(C), bool)
    short[np.flatnonzero(seen)[[0, 2, 3]]] = True
    q, ratio = 0.7, 0.4
    want_t, want_p = _by_every_pattern(problem, T, C, seen, np.where(short, q * ratio, q))
    kw = dict(per_count=64, min_weight=0.0) if n_seen is not None else {}
    got = loss_outlook(problem, T, C, seen, q, short_of_skin=short, short_ratio=ratio, **kw)
    # sampled (12 draws per count): over 20 seeds the trusted share's spread is 0.013 and the
    # pose's 0.03 (a pose is all or nothing per subset), both centred on the exact figures (0.165 /
    # 0.707 against 0.166 / 0.706): three spreads
    tol_t, tol_p = (1e-9, 1e-9) if n_seen is not None else (0.04, 0.09)
    assert got.trusted == pytest.approx(want_t, abs=tol_t) and got.pose == pytest.approx(want_p, abs=tol_p)
    assert got.found_probability == q and got.found_short == pytest.approx(q * ratio) and got.short_of_skin == 3
    assert got.expected_found == pytest.approx(q * (seen.sum() - 3) + q * ratio * 3)
    alike = loss_outlook(problem, T, C, seen, q, **kw)
    assert alike.found_short is None and alike.short_of_skin == 0
    assert got.trusted < alike.trusted and got.pose < alike.pose      # fewer found, fewer trusted
    if n_seen is None:
        assert got == loss_outlook(problem, T, C, seen, q, short_of_skin=short, short_ratio=ratio)   # seeded
        # centred on the exact figures: the mean over 8 seeds (its spread ~0.005 / ~0.011)
        many = [loss_outlook(problem, T, C, seen, q, short_of_skin=short, short_ratio=ratio, seed=k) for k in range(8)]
        assert np.mean([o.trusted for o in many]) == pytest.approx(want_t, abs=0.012)
        assert np.mean([o.pose for o in many]) == pytest.approx(want_p, abs=0.03)


def test_the_prediction_counts_the_balls_its_visibility_puts_short_of_skin(setup):
    from monotracker.planning.detector_defaults import SHORT_OF_SKIN_FOUND_RATIO

    problem, T, C, _ = setup
    N = skin_normals_under(problem.head, C, problem.radius_mm)
    p = predict(problem, T, C, N, losses=True)
    short = p.visibility.short_of_skin
    assert p.with_losses.short_of_skin == int(short.sum())
    assert p.with_losses.found_short == pytest.approx(problem.found_probability * SHORT_OF_SKIN_FOUND_RATIO)
    want = loss_outlook(problem, T, C, p.visibility.seen, short_of_skin=short, noise_px=p.noise_px)
    assert p.with_losses.trusted == pytest.approx(want.trusted)
    d = p.to_dict()["with_detector_losses"]
    assert d["balls_short_of_skin"] == int(short.sum())


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
