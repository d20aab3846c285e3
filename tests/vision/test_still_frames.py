"""The mean of a still view's frames (``vision/still_frames.py``): what joins it, how much
noise it removes, and which motions and changes start it again. Frames are drawn here (shaded
discs, supersampled, on a textured background, then shot and read noise per frame, optionally
JPEG): the truth of each motion is known exactly."""

import cv2
import numpy as np
import pytest

from monotracker.vision.detection import Detection, ImageFiducial
from monotracker.vision.frames import Frame
from monotracker.vision.still_frames import StillFrames

H, W = 360, 640
#: nine balls (centre x, y, radius px)
BALLS = np.array([[120, 90, 11], [320, 80, 11], [520, 100, 11], [110, 190, 11], [330, 180, 11], [530, 200, 11],
                  [130, 290, 11], [310, 280, 11], [510, 290, 11]], float)
_RNG = np.random.default_rng(7)
_TEXTURE = cv2.GaussianBlur(_RNG.normal(0, 1, (H, W)).astype(np.float32), (0, 0), 1.2)


def _scene(balls: np.ndarray, occluder=None, patch=None) -> np.ndarray:
    """Noise-free linear radiance (H, W, 3) in [0, 1]: skin-toned background with texture and a
    gradient, green balls darker at their limb (coverage supersampled 8 x 8 per pixel)."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    img = np.empty((H, W, 3), np.float32)
    base = 0.35 + 0.25 * xx / W + 0.04 * _TEXTURE
    img[..., 0], img[..., 1], img[..., 2] = 0.55 * base, 0.7 * base, base
    ss = (np.arange(8) + 0.5) / 8 - 0.5
    for cx, cy, r in balls:
        x0, x1, y0, y1 = int(cx - r - 2), int(cx + r + 3), int(cy - r - 2), int(cy + r + 3)
        py, px = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        sx = px[..., None, None] + ss[None, None, None, :] - cx
        sy = py[..., None, None] + ss[None, None, :, None] - cy
        rr = np.sqrt(sx * sx + sy * sy) / r
        inside = rr < 1
        shade = np.where(inside, np.sqrt(np.clip(1 - rr * rr, 0, 1)) * 0.6 + 0.4, 0.0)
        cov = inside.mean(axis=(2, 3))
        lum = (shade.sum(axis=(2, 3)) / np.maximum(inside.sum(axis=(2, 3)), 1)).astype(np.float32)
        ball = np.stack([0.08 * lum, 0.55 * lum, 0.12 * lum], axis=-1)
        img[y0:y1, x0:x1] = img[y0:y1, x0:x1] * (1 - cov[..., None]) + ball * cov[..., None]
    if occluder is not None:             # a grey bar (x0, y0, x1, y1)
        x0, y0, x1, y1 = occluder
        img[y0:y1, x0:x1] = 0.6
    if patch is not None:
        x0, y0, x1, y1 = patch
        img[y0:y1, x0:x1] *= 0.5
    return img


def _camera(lin: np.ndarray, seed: int, full_well: float = 2000.0, read_e: float = 8.0, jpeg: int = 0) -> np.ndarray:
    """The camera's 8-bit BGR frame of ``lin``: shot and read noise (electrons), gamma 1/2.2, JPEG."""
    rng = np.random.default_rng(seed)
    e = lin * full_well
    e = e + np.sqrt(e + read_e ** 2) * rng.standard_normal(e.shape).astype(np.float32)
    out = np.clip(255.0 * np.clip(e / full_well, 0, 1) ** (1 / 2.2) + 0.5, 0, 255).astype(np.uint8)
    if jpeg:
        out = cv2.imdecode(cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, jpeg])[1], cv2.IMREAD_COLOR)
    return out


def _truth_bgr(lin: np.ndarray) -> np.ndarray:
    return 255.0 * np.clip(lin, 0, 1) ** (1 / 2.2)


def test_a_still_views_frames_join_the_mean_and_its_noise_falls_as_one_over_sqrt_n():
    lin = _scene(BALLS)
    truth = _truth_bgr(lin)
    sf = StillFrames(max_frames=8)
    single = []
    for k in range(8):
        frame = _camera(lin, k)
        out = sf.add(frame, BALLS)
        assert sf.n == k + 1 and sf.last_reason == ("first frame" if k == 0 else "")
        single.append(float(np.std(frame.astype(np.float32) - truth)))
    ratio = float(np.std(out.astype(np.float32) - truth)) / float(np.mean(single))
    assert 0.3 < ratio < 0.45, ratio          # 1 / sqrt(8) = 0.35 (8-bit rounding adds a little)
    # beyond max_frames it keeps counting, weighting the newest 1 / max_frames
    sf.add(_camera(lin, 99), BALLS)
    assert sf.n == 9


@pytest.mark.parametrize("jpeg", [0, 80])
def test_a_still_view_with_shot_noise_is_never_started_again(jpeg):
    lin = _scene(BALLS)
    sf = StillFrames(max_frames=8)
    for k in range(30):
        sf.add(_camera(lin, 100 + k, jpeg=jpeg), BALLS)
    assert sf.n == 30, sf.last_reason


@pytest.mark.parametrize("shift", [0.05, 0.1, 0.5])
def test_the_balls_moving_together_start_the_mean_again(shift):
    sf = StillFrames(max_frames=8)
    lin = _scene(BALLS)
    for k in range(4):
        sf.add(_camera(lin, k), BALLS)
    moved = BALLS + np.array([shift, -0.5 * shift, 0.0])
    frame = _camera(_scene(moved), 10)
    out = sf.add(frame, BALLS)
    assert sf.n == 1 and sf.last_reason, sf.last_reason
    if shift <= 0.1:           # too small for any pixel to change much: the shift test's
        assert "moved" in sf.last_reason, sf.last_reason
    assert np.array_equal(out, frame)              # the detector reads the new frame itself


def test_a_small_turn_of_the_head_starts_the_mean_again():
    """0.03 deg about the image centre: each ball moves 0.05-0.16 px, each in its own direction."""
    sf = StillFrames(max_frames=8)
    for k in range(4):
        sf.add(_camera(_scene(BALLS), k), BALLS)
    a = np.deg2rad(0.03)
    c = np.array([W / 2, H / 2])
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    turned = BALLS.copy()
    turned[:, :2] = (BALLS[:, :2] - c) @ R.T + c
    assert 0.04 < np.abs(turned[:, :2] - BALLS[:, :2]).max() < 0.2
    sf.add(_camera(_scene(turned), 10), BALLS)
    assert sf.n == 1 and "moved" in sf.last_reason, sf.last_reason


def test_one_ball_moving_alone_starts_the_mean_again():
    sf = StillFrames(max_frames=8)
    for k in range(4):
        sf.add(_camera(_scene(BALLS), k), BALLS)
    moved = BALLS.copy()
    moved[4, 0] += 0.25
    sf.add(_camera(_scene(moved), 10), BALLS)
    assert sf.n == 1 and "a ball moved" in sf.last_reason and "(330, 180)" in sf.last_reason, sf.last_reason


def test_an_occluder_over_a_ball_starts_the_mean_again():
    sf = StillFrames(max_frames=8)
    for k in range(4):
        sf.add(_camera(_scene(BALLS), k), BALLS)
    # a bar over the right third of ball 4 (330, 180): 7 x 30 px
    sf.add(_camera(_scene(BALLS, occluder=(335, 165, 342, 195)), 10), BALLS)
    assert sf.n == 1 and sf.last_reason, sf.last_reason


def test_a_change_away_from_the_balls_starts_the_mean_again():
    """A hand's shadow where no ball was found: it could hide a ball no detection knew of."""
    sf = StillFrames(max_frames=8)
    for k in range(4):
        sf.add(_camera(_scene(BALLS), k), BALLS)
    sf.add(_camera(_scene(BALLS, patch=(400, 220, 460, 250)), 10), BALLS)
    assert sf.n == 1 and "tile changed" in sf.last_reason, sf.last_reason


def test_a_new_frame_size_starts_the_mean_again_and_a_bad_length_is_refused():
    sf = StillFrames(max_frames=4)
    sf.add(_camera(_scene(BALLS), 0), BALLS)
    small = np.zeros((100, 200, 3), np.uint8)
    assert sf.add(small, np.zeros((0, 3))) is small and sf.last_reason == "frame size changed"
    with pytest.raises(ValueError, match="max_frames"):
        StillFrames(max_frames=0)


class _Recorder:
    """A detector that records the images it is given and finds the drawn balls."""

    def __init__(self):
        self.images = []

    def detect(self, image, hint=None):
        self.images.append(image)
        return Detection([ImageFiducial(b[:2].copy(), (b[2], b[2]), 0.0, 1.0, np.pi * b[2] ** 2, "", {})
                          for b in BALLS], [], 0.0, "rec")


def test_the_tracker_gives_its_detector_the_mean_only_when_asked():
    from monotracker.vision.camera_model import CameraModel
    from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig

    cam = CameraModel(np.array([[600.0, 0, W / 2], [0, 600.0, H / 2], [0, 0, 1]]), np.zeros(5), (W, H))
    fids = np.array([[x, y, 0.0] for x, y, _ in BALLS[:5]]) * 0.1
    frames = [_camera(_scene(BALLS), k) for k in range(4)]
    for avg, averaged in ((0, False), (8, True)):
        rec = _Recorder()
        trk = PoseTracker(fids, cam, detector=rec, config=TrackerConfig(average_still_frames=avg, average_min_noise_dn=0.0))
        for k, f in enumerate(frames):
            trk.process(Frame(f, k / 30, k, None))
        assert (trk.still_frames is not None) == averaged
        assert rec.images[0] is frames[0]
        if averaged:
            assert trk.still_frames.n == 4
            est = trk.process(Frame(frames[0], 4 / 30, 4, None))
            assert est.averaged_frames == 5 and est.stages_s["average"] > 0
            trk.camera_fault(5, 5 / 30, "stalled", "camera stalled")     # a fault: the view may differ after it
            assert trk.still_frames.n == 0
            est = trk.process(Frame(frames[1], 6 / 30, 6, None))
            assert est.averaged_frames == 1
            ref = StillFrames(8)
            for f in frames:
                want = ref.add(f, BALLS)
            assert np.array_equal(rec.images[3], want)
        else:
            assert all(a is b for a, b in zip(rec.images, frames))
    with pytest.raises(ValueError, match="average_still_frames"):
        TrackerConfig(average_still_frames=-1)


def _window_mask(balls: np.ndarray, margin: float = 4.0) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    mask = np.zeros((H, W), bool)
    for cx, cy, r in balls:
        mask |= (np.abs(xx - cx) <= r + margin) & (np.abs(yy - cy) <= r + margin)
    return mask


@pytest.mark.parametrize("full_well, noisy", [(20000.0, False), (300.0, True)])
def test_the_mean_is_given_only_while_the_camera_is_noisy(full_well, noisy):
    """``min_noise_dn``: a quiet camera's frames are read alone (the mean is still kept and
    tested), a noisy one's mean is given; the noise it measures in the balls' windows is the
    frames' own (two frames' grey difference / sqrt 2 there)."""
    lin = _scene(BALLS)
    frames = [_camera(lin, k, full_well=full_well) for k in range(6)]
    sf = StillFrames(max_frames=8, min_noise_dn=1.8)
    for f in frames:
        out = sf.add(f, BALLS)
    assert sf.n == 6 and sf.giving is noisy and (out is frames[-1]) is (not noisy)
    g0, g1 = (cv2.cvtColor(f, cv2.COLOR_BGR2GRAY).astype(np.float32) for f in frames[:2])
    own = float(np.std((g1 - g0)[_window_mask(BALLS)])) / np.sqrt(2)
    assert bool(own >= 1.8) is noisy                  # the two cameras lie either side of the limit
    assert 0.7 < sf.noise_dn / own < 1.4, (sf.noise_dn, own)
    sf.add(np.roll(frames[0], 2, axis=1), BALLS)      # moved: read alone, whatever the noise
    assert sf.n == 1 and not sf.giving
    with pytest.raises(ValueError, match="min_noise_dn"):
        StillFrames(min_noise_dn=-1.0)


@pytest.mark.parametrize("trajectory", ["still", "breathing"])
def test_a_breathing_head_starts_the_mean_again_and_its_poses_stay_right(trajectory):
    """Our simulator's photo-like camera at 30 fps: over a still head the mean grows; over a
    breathing one (a few mm a cycle) it starts again, and the poses trusted with the mean are
    as right as those without it (error at the planned target against the simulator's truth)."""
    from monotracker.geometry import apply_transform
    from monotracker.sim.camera_sim import SimulatedCamera
    from monotracker.sim.trajectories import make_trajectory
    from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig

    cam = SimulatedCamera(seed=3, optics="photo", trajectory=make_trajectory(trajectory))
    ph = cam.phantom
    frames = [cam.render(k / 30.0) for k in range(40)]
    worst, counts, longest = {}, {}, 0
    for avg in (0, 8):
        trk = PoseTracker(cam.fiducials_ct, cam.camera, radius_mm=ph.fiducial_radius_mm,
                          target_ct=ph.sample_target_lps, config=TrackerConfig(average_still_frames=avg))
        errs, starts = [], 0
        for k, (img, tr) in enumerate(frames):
            e = trk.process(Frame(img, k / 30.0, k, tr))
            if avg:
                starts += trk.still_frames.n == 1
                longest = max(longest, trk.still_frames.n)
            if e.ok:
                tgt = ph.sample_target_lps
                errs.append(float(np.linalg.norm(apply_transform(e.T_cam_ct, tgt) - apply_transform(tr.T_cam_ct, tgt))))
        assert len(errs) >= 30, (avg, len(errs))
        worst[avg], counts[avg] = max(errs), starts
    assert worst[8] < 1.0 and worst[8] <= worst[0] + 0.15, worst
    if trajectory == "still":
        assert counts[8] == 1 and longest == 40            # one start: the first frame
    else:
        assert counts[8] >= 10, counts                      # the breathing head keeps starting it again


def test_a_detector_that_reads_no_image_gets_no_mean():
    """Given points (the engine's simulated-points rig, replays) cost no frame averaging."""
    from monotracker.vision.camera_model import CameraModel
    from monotracker.vision.point_detector import PointDetector
    from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig
    from monotracker.vision.recording import RecordingDetector

    cam = CameraModel(np.array([[600.0, 0, W / 2], [0, 600.0, H / 2], [0, 0, 1]]), np.zeros(5), (W, H))
    fids = np.array([[x, y, 0.0] for x, y, _ in BALLS[:5]]) * 0.1
    for det in (PointDetector(), RecordingDetector(PointDetector())):
        trk = PoseTracker(fids, cam, detector=det, config=TrackerConfig(average_still_frames=8))
        assert trk.still_frames is None
    assert PoseTracker(fids, cam, detector=_Recorder(), config=TrackerConfig(average_still_frames=8)).still_frames


def test_the_windows_tested_are_the_found_balls_and_the_refused_ones_of_a_balls_size():
    from monotracker.vision.still_frames import ball_windows

    acc = [ImageFiducial(np.array([100.0, 100.0]), (11.0, 10.0), 0.0, 1.0, 350.0),
           ImageFiducial(np.array([200.0, 100.0]), (10.5, 10.0), 0.0, 1.0, 330.0)]
    rej = [ImageFiducial(np.array([300.0, 100.0]), (12.0, 9.0), 0.0, 0.3, 340.0, "score 0.30"),    # a ball's size
           ImageFiducial(np.array([400.0, 100.0]), (4.0, 3.0), 0.0, 0.3, 40.0, "score 0.30"),     # a fragment
           ImageFiducial(np.array([500.0, 100.0]), (60.0, 40.0), 0.0, 0.0, 7000.0, "too large")]  # a drape
    w = ball_windows(Detection(acc, rej, 0.0, "t"), None)
    assert w.tolist() == [[100.0, 100.0, 10.0], [200.0, 100.0, 10.0], [300.0, 100.0, 9.0]]
    assert ball_windows(Detection([], [], 0.0, "t"), None).shape == (0, 3)


#: search windows round balls 1, 4 and 7 (x0, y0, x1, y1 px), as a tracked detector reads them
BOXES = [(290, 50, 350, 110), (300, 150, 360, 210), (280, 250, 340, 310)]


def test_in_the_detectors_windows_the_mean_is_kept_there_only():
    lin = _scene(BALLS)
    truth = _truth_bgr(lin)
    sf = StillFrames(max_frames=8)
    sf.add(_camera(lin, 0), BALLS)                      # a whole-frame read starts it
    for k in range(1, 8):
        frame = _camera(lin, k)
        out = sf.add(frame, BALLS[[1, 4, 7]], region=BOXES)
        assert sf.n == k + 1 and sf.last_reason == "", sf.last_reason
    inside = np.zeros((H, W), bool)
    for x0, y0, x1, y1 in BOXES:
        inside[y0:y1, x0:x1] = True
    assert np.array_equal(out[~inside], frame[~inside])          # the frame itself outside
    err_in = float(np.std(out[inside].astype(np.float32) - truth[inside]))
    err_frame = float(np.std(frame[inside].astype(np.float32) - truth[inside]))
    assert err_in < 0.45 * err_frame, (err_in, err_frame)          # the mean of 8 inside


def test_a_change_outside_the_windows_is_judged_at_the_next_whole_frame_read():
    sf = StillFrames(max_frames=8)
    sf.add(_camera(_scene(BALLS), 0), BALLS)
    changed = _scene(BALLS, patch=(400, 220, 460, 250))              # outside every box
    for k in range(1, 4):
        sf.add(_camera(changed, k), BALLS[[1, 4, 7]], region=BOXES)
    assert sf.n == 4                                                  # the detector did not read it
    sf.add(_camera(changed, 9), BALLS)                                # a whole-frame read
    assert sf.n == 1 and "tile changed" in sf.last_reason, sf.last_reason


def test_a_change_inside_a_window_away_from_the_balls_starts_the_mean_again():
    sf = StillFrames(max_frames=8)
    sf.add(_camera(_scene(BALLS), 0), BALLS)
    sf.add(_camera(_scene(BALLS), 1), BALLS[[1, 4, 7]], region=BOXES)
    sf.add(_camera(_scene(BALLS, patch=(292, 52, 305, 75)), 2), BALLS[[1, 4, 7]], region=BOXES)
    assert sf.n == 1 and sf.last_reason, sf.last_reason


def test_the_tracker_keeps_the_mean_where_its_detector_reads():
    """A detector that says what it reads (``reads(hint, shape)``, as the classical detector's
    search windows while tracked) gets the mean there and the frame elsewhere."""
    from monotracker.vision.camera_model import CameraModel
    from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig

    class Windowed(_Recorder):
        def reads(self, hint, shape):
            return BOXES

    cam = CameraModel(np.array([[600.0, 0, W / 2], [0, 600.0, H / 2], [0, 0, 1]]), np.zeros(5), (W, H))
    fids = np.array([[x, y, 0.0] for x, y, _ in BALLS[:5]]) * 0.1
    frames = [_camera(_scene(BALLS), k) for k in range(4)]
    rec = Windowed()
    trk = PoseTracker(fids, cam, detector=rec, config=TrackerConfig(average_still_frames=8))
    for k, f in enumerate(frames):
        trk.process(Frame(f, k / 30, k, None))
    inside = np.zeros((H, W), bool)
    for x0, y0, x1, y1 in BOXES:
        inside[y0:y1, x0:x1] = True
    assert trk.still_frames.n == 4
    assert np.array_equal(rec.images[-1][~inside], frames[-1][~inside])
    assert not np.array_equal(rec.images[-1][inside], frames[-1][inside])
