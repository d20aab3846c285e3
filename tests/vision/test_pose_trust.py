"""The pose stream's trust decisions on point-level scenes with known truth.

A detector double hands the tracker the exact ellipse centres of a synthetic scene (OpenCV's
projection, ``sim.scenes``) plus Gaussian noise, with the balls' true image size; the true pose
is known, so every trusted pose can be checked at deep targets.
"""

import numpy as np
import pytest

from monotracker.registration.noise import CentreBias
from monotracker.registration.report import tre_mm
from monotracker.sim.scenes import _to_pixels, ellipse_centre_normalised, make_scene
from monotracker.vision.camera_model import CameraModel
from monotracker.vision.frames import Frame
from monotracker.vision.point_detector import PointDetector
from monotracker.vision.pose_stream import MOVED, SEEN, PoseTracker, TrackerConfig

BLANK = np.zeros((720, 1280, 3), np.uint8)


def _observe(s, X_scene, rng, noise_px):
    """Image points and ball sizes of the scene's balls at ``X_scene`` (CT mm; may differ from the CT)."""
    T = s.T_cam_ct
    Xc = X_scene @ T[:3, :3].T + T[:3, 3]
    px = _to_pixels(ellipse_centre_normalised(Xc, s.radius_mm), s.K, s.dist)
    px = px + rng.normal(scale=noise_px, size=px.shape)
    minor = s.K[0, 0] * s.radius_mm / np.sqrt(Xc[:, 2] ** 2 - s.radius_mm**2)
    return px, minor


def _tracker(s, target, **cfg):
    det = PointDetector()
    tr = PoseTracker(s.fiducials_ct, CameraModel(s.K, s.dist if s.dist is not None else np.zeros(5), (1280, 720)),
                     detector=det, radius_mm=s.radius_mm, target_ct=target, config=TrackerConfig(**cfg))
    return tr, det


def _run(s, tr, det, rng, noise_px, frames, X_scene=None, strays=None):
    X_scene = s.fiducials_ct if X_scene is None else X_scene
    out = []
    for k in range(frames):
        px, minor = _observe(s, X_scene, rng, noise_px)
        if strays is not None and len(strays):
            px = np.concatenate([px, strays])
            minor = np.concatenate([minor, np.full(len(strays), np.median(minor))])
        perm = rng.permutation(len(px))
        det.set(px[perm], minor[perm])
        out.append(tr.process(Frame(BLANK, k / 30.0, k)))
    return out


def test_tre_gate_refuses_noisy_far_poses_and_trusts_clean_ones():
    rng = np.random.default_rng(4)
    s = make_scene(rng, noise_px=0.0, ellipse_bias=True, distance_mm=(650.0, 700.0))
    target = s.targets_ct[8]                                  # 80 mm deep
    tr, det = _tracker(s, target)
    clean = _run(s, tr, det, rng, 0.05, 15)
    assert all(e.ok for e in clean), [e.reason for e in clean]
    # no floor: the pooled noise estimate sees 0.05 px, and the prediction follows it
    assert clean[-1].sigma_source == "pooled" and 0.035 < clean[-1].sigma_px < 0.07
    assert clean[-1].predicted_tre_mm < 0.5
    noisy = _run(s, tr, det, rng, 0.8, 5)      # under the 1.5 px RMS gate, far over 1 mm at the target
    assert not any(e.ok for e in noisy)
    assert all(e.code == "tre_limit" and "over the 1 mm limit" in e.reason for e in noisy)
    assert noisy[0].alerts and "no valid pose" in noisy[0].alerts[-1]
    # the limits are settings
    tr2, det2 = _tracker(s, target, max_predicted_tre_mm=50.0, max_wrong_probability=1.0)
    assert all(e.ok for e in _run(s, tr2, det2, rng, 0.8, 12)[-3:])


def test_the_tail_gate_refuses_a_pose_that_may_well_be_2_mm_off():
    """An RMS under the limit is not enough: the chance of > 2 mm at the target must be tiny."""
    rng = np.random.default_rng(4)
    s = make_scene(rng, noise_px=0.0, ellipse_bias=True, distance_mm=(650.0, 700.0))
    target = s.targets_ct[8]
    tr, det = _tracker(s, target, max_predicted_tre_mm=5.0)          # RMS limit out of the way
    ests = _run(s, tr, det, rng, 0.5, 15)
    assert not any(e.ok for e in ests[-5:])
    assert all(e.code == "tre_limit" and "may exceed 2 mm" in e.reason for e in ests[-5:])
    assert all(e.predicted_tre_mm < 5.0 for e in ests[-5:])


def _share_over_1mm(noise_px, **cfg):
    """(trusted, trusted > 1 mm off at the 80 mm target) over 8 scenes x 20 frames at 400-450 mm."""
    trusted = over = 0
    for seed in range(8):
        rng = np.random.default_rng(100 + seed)
        s = make_scene(rng, noise_px=0.0, ellipse_bias=True, distance_mm=(400.0, 450.0))
        target = s.targets_ct[8]
        tr, det = _tracker(s, target, **cfg)
        for e in _run(s, tr, det, rng, noise_px, 20):
            if e.ok:
                trusted += 1
                over += bool(tre_mm(e.T_cam_ct, s.T_cam_ct, target[None])[0] > 1.0)
            elif cfg:
                assert e.code != "tre_limit" or "over the 1 mm limit" in e.reason or "may exceed" in e.reason
    return trusted, over


def test_the_one_mm_promise_needs_the_error_distribution_not_its_rms():
    """The RMS gate alone (the default) trusts poses whose error exceeds 1 mm far more often than
    1 in 20 (Gaussian centres, no shading at all: the gate's own statistics); with
    ``max_not_right_probability`` 0.05 the trusted poses keep "within 1 mm at 95 %" (true poses
    known), and where the noise allows it the stream still trusts nearly every frame."""
    ok, over = _share_over_1mm(0.3)
    assert ok >= 60 and over / ok > 0.05, (ok, over)
    ok95, over95 = _share_over_1mm(0.3, max_not_right_probability=0.05)
    assert ok95 < ok / 4 and over95 <= max(1, 0.05 * ok95), (ok95, over95)
    ok95, over95 = _share_over_1mm(0.2, max_not_right_probability=0.05)
    assert ok95 >= 130 and over95 <= 0.05 * ok95, (ok95, over95)


@pytest.mark.parametrize("noise_px", [0.1, 0.3, 0.6, 1.0])
def test_no_wrong_but_valid_pose(noise_px):
    wrong_but_valid = 0
    for seed in range(6):
        rng = np.random.default_rng(50 + seed)
        s = make_scene(rng, noise_px=0.0, ellipse_bias=True, n_stray=seed % 3)
        target = s.targets_ct[6]
        tr, det = _tracker(s, target)
        strays = s.image_points[s.stray_indices]
        for e in _run(s, tr, det, rng, noise_px, 8, strays=strays):
            if e.ok:
                err = tre_mm(e.T_cam_ct, s.T_cam_ct, target[None])[0]
                wrong_but_valid += err > 2.0
                # strays ignored: only real fiducials are matched
                assert e.n_matched == len(s.fiducials_ct)
    assert wrong_but_valid == 0


def test_moved_ball_alert_names_it_and_it_stays_excluded():
    rng = np.random.default_rng(11)
    s = make_scene(rng, noise_px=0.0, ellipse_bias=True)
    j = 4
    X = s.fiducials_ct.copy()
    T = s.T_cam_ct
    # 3 mm across the line of sight (camera x axis, expressed in CT)
    X[j] = X[j] + 3.0 * T[:3, :3].T @ np.array([1.0, 0.0, 0.0])
    tr, det = _tracker(s, s.targets_ct[6])
    ests = _run(s, tr, det, rng, 0.2, 6, X_scene=X)
    first = ests[0]
    assert first.moved and first.moved[0][0] == j and 2.0 < first.moved[0][1] < 4.0
    assert any(f"fiducial {j} moved about" in a for a in first.alerts)
    for e in ests:
        assert e.ok, e.reason
        assert e.status[j] == MOVED and e.excluded == [j]
        assert sum(st == SEEN for st in e.status) == len(X) - 1
        assert tre_mm(e.T_cam_ct, T, s.targets_ct).max() < 2.0
    assert not any(e.moved for e in ests[1:])                   # alerted once, excluded for good
    assert not any("moved" in a for e in ests[1:] for a in e.alerts)
    # even once the ball is back where the CT has it, it does not come back silently
    back = _run(s, tr, det, rng, 0.2, 2)
    assert all(e.status[j] == MOVED for e in back)
    tr.reset()                                                  # the operator re-checked the fiducials
    again = _run(s, tr, det, rng, 0.2, 2)
    assert all(e.ok and e.status[j] == SEEN for e in again)


def test_engine_gate_keeps_the_estimators_code_and_gates_on_predicted_tre():
    from monotracker.engine.loop.gate import PoseGate

    g = PoseGate(confirm_frames=1, max_predicted_tre_mm=1.0)
    T = np.eye(4)
    T[2, 3] = 500.0
    v = g.check(False, "camera stream ended", None, 0, None, 0.0, code="camera_ended")
    assert not v.trusted and v.code == "camera_ended"
    assert g.check(False, "no pose", None, 2, None, 0.0).code == "occlusion"      # no code given: as before
    v = g.check(True, "", T, 9, 0.3, 0.1, predicted_tre_mm=1.4)
    assert not v.trusted and v.code == "tre_limit" and "1.40 mm" in v.reason
    assert g.check(True, "", T, 9, 0.3, 0.2, predicted_tre_mm=0.4).trusted
    assert g.check(True, "", T, 9, 0.3, 0.3, predicted_tre_mm=None).trusted      # no target: no TRE gate


def test_the_calibrated_model_never_trusts_a_pose_without_a_predicted_error():
    """The calibrated (pooled) trust model restarts its pool when a fiducial is found moved. The
    frame that found it used to be given out trusted with no predicted TRE at all: in this 0.6 px
    stream (a false 'moved' of 1.11 mm on fiducial 5 at frame 2) that pose was 1.19 mm off at the
    target. Now that frame starts the new pool and is gated like any other; and with a really
    moved ball (3 mm) every frame is still trusted, each with its predicted error."""
    rng = np.random.default_rng(52)
    s = make_scene(rng, noise_px=0.0, ellipse_bias=True, n_stray=2)
    target = s.targets_ct[6]
    tr, det = _tracker(s, target, centre_bias="detector")
    ests = _run(s, tr, det, rng, 0.6, 8, strays=s.image_points[s.stray_indices])
    assert any(e.moved for e in ests), "the stream no longer has its false 'moved': pick another seed"
    for e in ests:
        if e.ok:
            assert np.isfinite(e.predicted_tre_mm) and e.predicted_tre_mm <= 1.0, e
            assert tre_mm(e.T_cam_ct, s.T_cam_ct, target[None])[0] <= 1.0
    rng = np.random.default_rng(11)
    s = make_scene(rng, noise_px=0.0, ellipse_bias=True)
    X = s.fiducials_ct.copy()
    X[4] = X[4] + 3.0 * s.T_cam_ct[:3, :3].T @ np.array([1.0, 0.0, 0.0])
    # the point double has no shading: a small bias of its own (the table's entry for an
    # unknown detector covers shaded balls 8-9 px wide and trusts nothing at 0.2 px)
    tr, det = _tracker(s, s.targets_ct[6], centre_bias=CentreBias(ball_px=0.05, common_px=0.05, gradient_px=0.02))
    ests = _run(s, tr, det, rng, 0.2, 6, X_scene=X)
    assert ests[0].moved and ests[0].moved[0][0] == 4
    assert all(e.ok and np.isfinite(e.predicted_tre_mm) for e in ests), [e.reason for e in ests]


def _one_ball_off(bias_px, frames=15, seeds=6, balls=None, from_frame=0, off=(2,), **cfg):
    """A still head at 400-450 mm, every ball's centre with 0.15 px of noise (its edge spread,
    reported as such) except the balls ``off`` (ball 2), each ``bias_px`` off in a fixed direction
    of its own (partly hidden, an instrument's reflection) from frame ``from_frame`` on; ``balls``: only the first so many
    found. (trusted, trusted > 1 mm off at the 80 mm target, refusals' reasons, the estimates)."""
    trusted = over = 0
    reasons, ests = [], []
    for seed in range(seeds):
        rng = np.random.default_rng(300 + seed)
        s = make_scene(rng, noise_px=0.0, ellipse_bias=True, distance_mm=(400.0, 450.0))
        target = s.targets_ct[8]
        tr, det = _tracker(s, target, **cfg)
        dirs = {j: rng.uniform(0.0, 2.0 * np.pi) for j in off}
        for k in range(frames):
            px, minor = _observe(s, s.fiducials_ct, rng, 0.15)
            for j, a in dirs.items():
                px[j] += bias_px * np.array([np.cos(a), np.sin(a)]) * (k >= from_frame)
            det.set(px[:balls], minor[:balls], edge_rms_px=0.15)
            e = tr.process(Frame(BLANK, k / 30.0, k))
            ests.append(e)
            if e.ok:
                trusted += 1
                over += bool(tre_mm(e.T_cam_ct, s.T_cam_ct, target[None])[0] > 1.0)
            else:
                reasons.append(e.reason)
    return trusted, over, reasons, ests


def test_a_ball_two_pixels_off_is_set_aside_and_the_others_trusted():
    """One ball 2 px off among balls right to 0.15 px: its edge spread says 0.15 px and it is
    under the moved-fiducial test's 1 mm, so without the leave-one-out test the stream trusts
    poses over 1 mm off at the target. With it (the default) the others put that ball ~2 px from
    where it was found: it is set aside for the frame, the pose from the others is trusted and
    right, the ball stays "seen", and the alert names it once, not every frame."""
    ok0, over0, *_ = _one_ball_off(2.0, disagreement_quantile=0.0)
    assert ok0 >= 60 and over0 >= 5, (ok0, over0)
    ok1, over1, _reasons, ests = _one_ball_off(2.0)
    assert over1 == 0 and ok1 >= 0.9 * ok0, (ok1, over1, ok0)
    assert all([j for j, _ in e.set_aside] == [2] and 1.5 < e.set_aside[0][1] < 2.6 for e in ests), ests[0].set_aside
    assert all(e.status[2] == SEEN and np.isnan(e.residuals_px[2]) for e in ests if e.ok)
    alerts = [a for e in ests for a in e.alerts if "set aside" in a]
    assert len(alerts) == 6 and all(a.startswith("fiducial 2 set aside") for a in alerts), alerts   # once a stream
    # where the balls are all right to their spread it changes nothing
    assert _one_ball_off(0.0)[:2] == _one_ball_off(0.0, disagreement_quantile=0.0)[:2]


def test_a_ball_going_off_mid_stream_among_six_is_set_aside():
    """Six balls found, one goes 2 px off at frame 10 (an instrument arrives): the noise pooled
    from the first frames is low, so without the leave-one-out test the stream trusts many poses
    over 1 mm off; with it that ball is set aside from frame 10 on (5 remain: fewer poses are
    trusted, with the few-ball cover) and none trusted is over 1 mm off."""
    ok0, over0, *_ = _one_ball_off(2.0, frames=25, balls=6, from_frame=10, disagreement_quantile=0.0)
    assert over0 >= 20, (ok0, over0)
    ok1, over1, _reasons, ests = _one_ball_off(2.0, frames=25, balls=6, from_frame=10)
    assert over1 == 0 and ok1 >= 30, (ok1, over1)
    after = [e for k, e in enumerate(ests) if k % 25 >= 10 and e.n_detected]
    # (in one scene the ball's offset lies mostly along what the other five leave loose: there it
    # is not set aside, and those frames are refused by their predicted error)
    assert sum(bool(e.set_aside) for e in after) >= 0.7 * len(after)
    assert not any(e.set_aside for k, e in enumerate(ests) if k % 25 < 10)


def test_two_balls_off_set_one_aside_and_the_other_is_still_judged():
    """Two balls 2.5 px off from frame 5 on: setting the worst aside leaves the other one in the
    fit, so the fit without it is tested again (before that was done, 2 of 3 trusted poses here
    were over 1 mm off): no trusted pose over 1 mm off."""
    ok, over, _reasons, ests = _one_ball_off(2.5, frames=20, seeds=8, from_frame=5, off=(2, 5))
    assert over == 0, (ok, over)
    assert sum(bool(e.set_aside) for e in ests) >= 10
