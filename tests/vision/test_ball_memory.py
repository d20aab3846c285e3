"""Balls of the last frames of a still head given back to a frame that misses them
(``vision/ball_memory.py``): what is given back, when motion stops it, and what the pose
tracker makes of it (against the synthetic scenes' exact truth)."""

import numpy as np
import pytest

from monotracker.registration.report import tre_mm
from monotracker.sim.scenes import _to_pixels, ellipse_centre_normalised, make_scene
from monotracker.vision.ball_memory import StillBallMemory
from monotracker.vision.camera_model import CameraModel
from monotracker.vision.detection import Detection, ImageFiducial
from monotracker.vision.frames import Frame
from monotracker.vision.point_detector import PointDetector
from monotracker.vision.pose_stream import NEWLY_LOST, OCCLUDED, SEEN, PoseTracker, TrackerConfig

BLANK = np.zeros((720, 1280, 3), np.uint8)
#: eight balls of 8 px radius spread over the image (px)
BALLS = np.array([[300, 200], [500, 220], [700, 210], [900, 230], [320, 450], [520, 470], [720, 460], [920, 480]],
                 float)


def _det(centres, refusal: str = "") -> Detection:
    return Detection([ImageFiducial(np.array(c, float), (8.0, 8.0), 0.0, 1.0, 201.0, "", {"edge_rms_px": 0.1})
                      for c in centres], [], 0.0, "test", refusal)


def _remembered(det: Detection) -> dict:
    """remembered ball centre (tuple) -> its age in frames"""
    return {tuple(np.round(f.centre_px, 6)): f.features["remembered_frames"] for f in det.fiducials
            if "remembered_frames" in f.features}


def test_a_still_heads_missing_ball_comes_back_where_it_was_found():
    mem = StillBallMemory(max_age_frames=7)
    mem.fill(_det(BALLS), 0, 0.0)
    out = mem.fill(_det(BALLS[1:]), 1, 1 / 30)                 # ball 0 missed in frame 1
    assert len(out.fiducials) == 8
    assert _remembered(out) == {tuple(BALLS[0]): 1}
    # this frame's own balls are the detector's, untouched and first
    assert np.array_equal(out.centres[:7], BALLS[1:])
    assert all("remembered_frames" not in f.features for f in out.fiducials[:7])
    # the ball keeps what the detector measured of it (its edge features)
    assert out.fiducials[7].features["edge_rms_px"] == 0.1
    # two frames later, still missed: from frame 0, age 3 (a remembered ball is not remembered again)
    mem.fill(_det(BALLS[1:]), 2, 2 / 30)
    out = mem.fill(_det(BALLS[1:]), 3, 3 / 30)
    assert _remembered(out) == {tuple(BALLS[0]): 3}
    # found again: nothing to give back
    assert _remembered(mem.fill(_det(BALLS), 4, 4 / 30)) == {}


def test_memory_ages_out_by_frames_and_by_time():
    mem = StillBallMemory(max_age_frames=3, max_age_s=1.0)
    mem.fill(_det(BALLS), 0, 0.0)
    for k in (1, 2, 3):
        assert _remembered(mem.fill(_det(BALLS[1:]), k, k / 30)) == {tuple(BALLS[0]): k}
    assert _remembered(mem.fill(_det(BALLS[1:]), 4, 4 / 30)) == {}
    mem = StillBallMemory(max_age_frames=7, max_age_s=0.1)
    mem.fill(_det(BALLS), 0, 0.0)
    assert _remembered(mem.fill(_det(BALLS[1:]), 1, 0.2)) == {}  # 0.2 s later: too old, whatever the index


@pytest.mark.parametrize("why", ["refused", "index back", "reset"])
def test_memory_is_cleared(why):
    mem = StillBallMemory()
    mem.fill(_det(BALLS), 5, 0.0)
    if why == "refused":
        out = mem.fill(_det([], refusal="rings, not balls"), 6, 1 / 30)
        assert out.fiducials == []
        k = 7
    elif why == "index back":
        k = 5                                                 # the same index again: a restarted source
    else:
        mem.reset()
        k = 6
    assert _remembered(mem.fill(_det(BALLS[1:]), k, k / 30)) == {}


def test_a_frame_that_could_not_stand_alone_gets_nothing():
    """With fewer than ``min_agreeing`` balls of its own (4: the tracker's min_fiducials) a frame
    gets no memory: an instrument hiding all but 3 balls leaves no pose standing on balls nobody
    sees, and 3 balls close together cannot show a turn of the head about them."""
    mem = StillBallMemory(min_agreeing=4)
    mem.fill(_det(BALLS), 0, 0.0)
    assert _remembered(mem.fill(_det(BALLS[:3]), 1, 1 / 30)) == {}
    assert len(_remembered(mem.fill(_det(BALLS[:4]), 2, 2 / 30))) == 4


@pytest.mark.parametrize("drift_px", [0.03, 0.06, 0.2, 1.0])
def test_a_drifting_head_gets_no_ball_further_off_than_the_shift_test_allows(drift_px):
    """The head drifts ``drift_px`` a frame (every ball alike) while ball 0 is missed after
    frame 0: a remembered ball may only come from a frame the balls have moved at most
    ``max_common_px`` since, so it lies at most that far from where the ball is now, at any
    drift; a fast drift gets nothing back at all."""
    mem = StillBallMemory(max_age_frames=7, max_common_px=0.15)
    step = np.array([drift_px, 0.0])
    mem.fill(_det(BALLS), 0, 0.0)
    given = 0
    for k in range(1, 8):
        now = BALLS + k * step
        out = mem.fill(_det(now[1:]), k, k / 30)
        for centre, age in _remembered(out).items():
            given += 1
            assert np.linalg.norm(np.array(centre) - now[0]) <= 0.15 + 1e-9, (k, age)
    assert given == int(min(7, np.floor(0.15 / drift_px + 1e-9)))


def test_one_ball_moved_more_than_the_limit_stops_the_memory():
    """A ball of both frames moved over ``max_shift_px`` (0.5): not still, nothing given back
    (the mean shift alone, 0.6 / 7 px, would pass)."""
    mem = StillBallMemory(max_shift_px=0.5, max_common_px=0.15)
    mem.fill(_det(BALLS), 0, 0.0)
    now = BALLS.copy()
    now[5] += [0.6, 0.0]
    assert _remembered(mem.fill(_det(now[1:]), 1, 1 / 30)) == {}



def test_notes_of_the_still_frames_are_read_newest_first_and_not_past_a_move():
    """What a frame writes down (:meth:`StillBallMemory.note`) is read by the next frames of the
    still head (newest first), within the memory's age; not past a frame the balls moved from,
    not by a frame with too few balls of its own, not after a reset, not with the memory off."""
    mem = StillBallMemory(max_age_frames=3)
    for k, seen in enumerate([[], [0.0], [0.1, 0.0]]):
        mem.fill(_det(BALLS), k, k / 30)
        assert mem.still_notes("share") == pytest.approx(seen)
        mem.note("share", 0.1 * k)
    mem.fill(_det(BALLS), 3, 3 / 30)
    assert mem.still_notes("share") == pytest.approx([0.2, 0.1, 0.0])
    assert mem.still_notes("other") == []
    mem.note("share", 0.3)
    mem.fill(_det(BALLS), 4, 4 / 30)                          # frame 0 is now older than 3 frames
    assert mem.still_notes("share") == pytest.approx([0.3, 0.2, 0.1])
    mem.note("share", 0.4)
    moved = BALLS + [1.0, 0.0]                                # the head moved: nothing from before
    mem.fill(_det(moved), 5, 5 / 30)
    assert mem.still_notes("share") == []
    mem.note("share", 0.5)
    mem.fill(_det(moved[:3]), 6, 6 / 30)                      # 3 balls of its own: cannot tell
    assert mem.still_notes("share") == []
    mem.fill(_det(moved), 7, 7 / 30)
    assert mem.still_notes("share") == pytest.approx([0.5])   # frame 6 wrote nothing
    mem.reset()
    mem.fill(_det(moved), 8, 8 / 30)
    assert mem.still_notes("share") == []
    off = StillBallMemory(max_age_frames=0)
    off.fill(_det(BALLS), 0, 0.0)
    off.note("share", 1.0)
    off.fill(_det(BALLS), 1, 1 / 30)
    assert off.still_notes("share") == []


# --- the pose tracker with a memory, on point-level scenes of known truth ---------------------

def _observe(s, rng, noise_px):
    T = s.T_cam_ct
    Xc = s.fiducials_ct @ T[:3, :3].T + T[:3, 3]
    px = _to_pixels(ellipse_centre_normalised(Xc, s.radius_mm), s.K, s.dist) + rng.normal(scale=noise_px,
                                                                                           size=(len(Xc), 2))
    minor = s.K[0, 0] * s.radius_mm / np.sqrt(Xc[:, 2] ** 2 - s.radius_mm**2)
    return px, minor


def _stream(remember_frames: int, seed: int = 3, frames: int = 12, noise_px: float = 0.05):
    """A still head whose detector misses 3 of its balls in each frame (a different 3 each
    frame, as shaded balls flicker at their limits); per frame (estimate, the balls found)."""
    rng = np.random.default_rng(seed)
    s = make_scene(rng, noise_px=0.0, ellipse_bias=True, distance_mm=(450.0, 500.0))
    target = s.targets_ct[8]
    det = PointDetector()
    cam = CameraModel(s.K, s.dist if s.dist is not None else np.zeros(5), (1280, 720))
    tr = PoseTracker(s.fiducials_ct, cam, detector=det, radius_mm=s.radius_mm, target_ct=target,
                     config=TrackerConfig(remember_frames=remember_frames))
    out = []
    for k in range(frames):
        px, minor = _observe(s, rng, noise_px)
        found = np.sort(rng.choice(len(px), len(px) - 3, replace=False))
        det.set(px[found], minor[found])
        out.append((tr.process(Frame(BLANK, k / 30.0, k)), set(found.tolist())))
    return s, target, out


def test_the_tracker_fits_remembered_balls_and_says_which_they_are():
    s, target, out = _stream(7)
    n = len(s.fiducials_ct)
    later = out[3:]
    assert all(e.n_matched > n - 3 for e, _ in later), [e.n_matched for e, _ in later]
    for e, found in out:
        assert e.n_detected == n - 3                              # this frame's own balls only
        assert set(e.remembered).isdisjoint(found)
        for j in e.remembered:                                    # not found in this frame: not "seen"
            assert e.status[j] in (NEWLY_LOST, OCCLUDED), (j, e.status[j])
        for j in found:
            assert e.status[j] == SEEN
        if e.ok:
            assert tre_mm(e.T_cam_ct, s.T_cam_ct, target[None])[0] <= 1.0


def test_remembered_balls_make_the_predicted_error_smaller_and_the_pose_no_worse():
    """Against the same stream without memory (same seed, same draws): the predicted error at the
    target is lower with the remembered balls, and the actual error of the poses no larger on
    the whole (the remembered centres are real measurements of a still head)."""
    _, _, without = _stream(0)
    s, target, with_memory = _stream(7)
    pred0 = np.nanmedian([e.predicted_tre_mm for e, _ in without[3:]])
    pred1 = np.nanmedian([e.predicted_tre_mm for e, _ in with_memory[3:]])
    assert pred1 < 0.8 * pred0, (pred0, pred1)
    err = [tre_mm(e.T_cam_ct, s.T_cam_ct, target[None])[0] for e, _ in with_memory if e.ok]
    assert len(err) >= len([e for e, _ in without if e.ok])
    assert max(err) <= 1.0, err


def test_a_tracker_reset_forgets_the_remembered_balls():
    """A new registration (``PoseTracker.reset``) starts with no memory: the next frame's missed
    balls are not given back (the stream before it may have been another head position)."""
    rng = np.random.default_rng(5)
    s = make_scene(rng, noise_px=0.0, ellipse_bias=True, distance_mm=(450.0, 500.0))
    det = PointDetector()
    cam = CameraModel(s.K, s.dist if s.dist is not None else np.zeros(5), (1280, 720))
    tr = PoseTracker(s.fiducials_ct, cam, detector=det, radius_mm=s.radius_mm, target_ct=s.targets_ct[8])
    px, minor = _observe(s, rng, 0.02)
    det.set(px, minor)
    tr.process(Frame(BLANK, 0.0, 0))
    det.set(px[2:], minor[2:])
    assert sorted(tr.process(Frame(BLANK, 1 / 30, 1)).remembered) == [0, 1]
    tr.reset()
    e = tr.process(Frame(BLANK, 2 / 30, 2))
    assert e.remembered == [] and e.n_matched <= len(px) - 2
