"""A colour blob refused for its shape, scored again trimmed (``detection.trim_tail``,
``BlobRules.trim_tails``; opt-in, docs/vision.md "Ragged colour blobs scored again trimmed"): the
ball behind a tail is found, a ball cut by an occluder is not made whole by it, and a blob of two
balls is not passed off as one. Synthetic masks with known geometry, and one committed Mitsuba
frame judged against the scene's own truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from monotracker.sim.pbr.frameset import camera_frames, committed_root, list_scenes
from monotracker.vision import detection
from monotracker.vision.detect_classical import ClassicalDetector
from monotracker.vision.detection import BlobRules, score_blob, trim_tail

RULES = BlobRules(radius_mm=4.0, focal_px=1100.0)      # 13 px balls at ~340 mm lie in range
SS = 8                                                 # supersampling of the synthetic masks


def _contour(draw) -> np.ndarray:
    """The outer contour of a mask drawn by ``draw(mask, scale)`` at SS x and reduced (area)."""
    big = np.zeros((120 * SS, 160 * SS), np.uint8)
    draw(big, SS)
    small = cv2.resize(big, (160, 120), interpolation=cv2.INTER_AREA)
    cs, _ = cv2.findContours((small >= 128).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    return max(cs, key=cv2.contourArea)


def _ball(m, s, c=(70.3, 60.6), r=13.0):
    cv2.circle(m, (int(c[0] * s), int(c[1] * s)), int(r * s), 255, -1)


def _tail(m, s):
    """A contact shadow's tail: a thin ellipse leaving the ball's lower right side."""
    cv2.ellipse(m, (int(86 * s), int(70 * s)), (int(10 * s), int(3.0 * s)), 30, 0, 360, 255, -1)


def _score(cnt):
    return score_blob(cnt, cv2.contourArea(cnt), RULES)


def test_opt_in():
    """Not the default: see ``detection.TRIM_TAIL_SHARE`` for why."""
    assert BlobRules().trim_tails is False


def test_a_tail_is_cut_off_and_the_ball_left_scores():
    cnt = _contour(lambda m, s: (_ball(m, s), _tail(m, s)))
    score, feats, ell = _score(cnt)
    assert score < RULES.min_score                      # as the blob stage saw it before
    trimmed = trim_tail(cnt, ell[1][1])
    assert trimmed is not None
    t_score, _f, t_ell = _score(trimmed)
    assert t_score >= RULES.min_score
    assert np.hypot(t_ell[0][0] - 70.3, t_ell[0][1] - 60.6) < 0.6     # the ball's own centre (px)
    assert abs(t_ell[1][1] - 13.0) < 0.8                               # and size


def test_a_whole_ball_is_left_as_it_is():
    cnt = _contour(_ball)
    trimmed = trim_tail(cnt, _score(cnt)[2][1][1])
    if trimmed is not None:          # a pixel disc may lose a corner pixel to the opening
        assert abs(cv2.contourArea(trimmed) - cv2.contourArea(cnt)) <= 0.03 * cv2.contourArea(cnt)


def test_a_ball_cut_by_a_chord_stays_cut():
    """Trimming cuts thin parts only: a ball hidden below half its radius under its centre keeps
    its chord after the opening, still scores too low and is refused as before (a shallower cut
    passes the blob stage either way; the edge fit's cut test judges it further on)."""
    def cut(m, s):
        _ball(m, s)
        m[int((60.6 + 0.5 * 13.0) * s):, :] = 0
    cnt = _contour(cut)
    score, feats, ell = _score(cnt)
    assert score < RULES.min_score
    assert detection._trimmed_blob(cnt, cv2.contourArea(cnt), feats, ell, RULES) is None
    t_score, _tf, t_ell = _score(trim_tail(cnt, ell[1][1]))
    assert t_score < RULES.min_score and abs(t_ell[0][1] - ell[0][1]) < 0.3     # the chord is still there


def test_a_fragment_of_a_larger_blob_is_not_a_ball():
    """Two balls' worth of blob joined by a wide neck: the opening leaves it whole, still no
    ellipse of a ball's shape, and no second score is given."""
    def pair(m, s):
        _ball(m, s, (60.0, 60.0))
        _ball(m, s, (84.0, 60.0))
    cnt = _contour(pair)
    score, feats, ell = _score(cnt)
    assert score < RULES.min_score
    assert detection._trimmed_blob(cnt, cv2.contourArea(cnt), feats, ell, RULES) is None


@pytest.fixture(scope="module")
def cluttered_frame():
    """A committed Mitsuba tuning scene (every ball whole) under the clutter condition: contact
    shadows join two balls' colour blobs."""
    scenes = [s for s in list_scenes(committed_root() / "tuning") if s.hash.startswith("2224d86e")]
    assert len(scenes) == 1 and scenes[0].spec.split == "tuning"
    s = scenes[0]
    return s, camera_frames(s, "clutter", 1)[0]


def _found(scene, img, trim: bool) -> dict:
    """{truth index: (centre error px against the true ellipse centre, trimmed?)} of the balls
    the detector (with the camera's outlines, as the pose tracker runs it) accepts."""
    tr, cam = scene.truth, scene.camera_model()
    rules = BlobRules(radius_mm=tr.radius_mm, focal_px=float(cam.K[0, 0]), camera=cam, trim_tails=trim)
    out = {}
    for f in ClassicalDetector(rules).detect(img).fiducials:
        d = np.linalg.norm(tr.ellipse_centres_px - np.asarray(f.centre_px, float), axis=1)
        out[int(np.argmin(d))] = (float(d.min()), "trimmed_area_px" in f.features)
    return out


def test_shadowed_balls_of_a_rendered_frame_are_found(cluttered_frame):
    scene, img = cluttered_frame
    assert scene.truth.whole.all()
    before, now = _found(scene, img, False), _found(scene, img, True)
    trimmed = {j for j, (_e, t) in now.items() if t}
    assert len(trimmed) >= 2 and not trimmed & set(before)          # refused before, found now
    assert all(now[j][0] < 0.5 for j in trimmed)                     # px, against the truth
    assert set(before) <= set(now)
    assert all(abs(now[j][0] - before[j][0]) < 0.05 for j in before)  # the others as they were
