"""The detector's hint: the balls' image ellipses predicted from the last trusted pose
(``DetectionHint``), and the pose tracker handing it to its detector."""

import numpy as np

from monotracker.sim.camera_sim import SimulatedCamera
from monotracker.sim.phantom import default_phantom
from monotracker.sim.trajectories import make_trajectory
from monotracker.vision.camera_model import CameraModel
from monotracker.vision.detect_classical import ClassicalDetector
from monotracker.vision.detection import DetectionHint
from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig

from independent_render import FRAME_K, FRAME_SIZE, sphere_image_ellipse

PH = default_phantom()


def test_hint_is_the_exact_image_ellipse_of_each_sphere():
    """Against the cone's conic (independent_render, no code shared): centre, axes and the
    major axis' direction of spheres across the field, 300-800 mm away, up to 45 deg off axis."""
    rng = np.random.default_rng(4)
    cam = CameraModel(FRAME_K, np.zeros(5), FRAME_SIZE)
    z = rng.uniform(300, 800, 40)
    X = np.column_stack([rng.uniform(-0.45, 0.45, 40) * z, rng.uniform(-0.28, 0.28, 40) * z, z])
    T = np.eye(4)
    T[:3, 3] = [5.0, -3.0, 20.0]          # CT -> camera: a shift, so the pose is applied
    hint = DetectionHint.from_pose(cam, T, X - T[:3, 3], 4.0, frame_index=7, age_frames=2)
    assert len(hint) == 40 and hint.frame_index == 7 and hint.age_frames == 2
    assert list(hint.fiducial_indices) == list(range(40))
    for i, Xi in enumerate(X):
        c, a, b, th = sphere_image_ellipse(Xi, 4.0)
        assert np.linalg.norm(hint.centres_px[i] - c) < 0.01
        assert abs(hint.axes_px[i, 0] - a) < 0.01 and abs(hint.axes_px[i, 1] - b) < 0.01
        if a - b > 0.05:    # the direction of a near-circle's major axis is not defined
            d = (hint.angles_deg[i] - np.degrees(th) + 90.0) % 180.0 - 90.0
            assert abs(d) < 1.0


def test_hint_leaves_out_spheres_behind_the_camera():
    cam = CameraModel(FRAME_K, np.zeros(5), FRAME_SIZE)
    X = np.array([[0.0, 0.0, 500.0], [10.0, 0.0, -400.0], [0.0, 20.0, 600.0]])
    hint = DetectionHint.from_pose(cam, np.eye(4), X, 4.0)
    assert list(hint.fiducial_indices) == [0, 2]


class _Recorder:
    """A classical detector that keeps the hints it was given."""

    def __init__(self):
        self.inner = ClassicalDetector()
        self.rules = self.inner.rules
        self.hints = []

    def detect(self, image, hint=None):
        self.hints.append(hint)
        return self.inner.detect(image, hint)


def test_tracker_hands_the_detector_the_predicted_balls():
    """Frame 0: full search; then the balls predicted from the last trusted pose, within a pixel
    of the simulator's exact ellipse centres of the new frame (a breathing head); the whole frame
    searched every ``full_search_every`` frames (``search_all``); after a camera fault a cold
    full search (no hint)."""
    cam = SimulatedCamera(trajectory=make_trajectory("breathing"), seed=2, max_frames=12)
    rec = _Recorder()
    trk = PoseTracker(PH.fiducial_centres_lps, cam.camera, detector=rec, radius_mm=PH.fiducial_radius_mm,
                      config=TrackerConfig(full_search_every=5))
    ests = []
    for f in cam:
        ests.append(trk.process(f))
        if len(ests) == 8:
            trk.camera_fault(f.index + 1, f.t_capture + 0.03, "frozen", "camera frozen")
    assert all(e.ok for e in ests), [e.reason for e in ests]
    hints = rec.hints
    assert hints[0] is None
    assert [i for i, h in enumerate(hints) if h is None] == [0, 8]              # cold: first, after the fault
    assert [i for i, h in enumerate(hints) if h is not None and h.search_all] == [5]
    for i, h in enumerate(hints):
        if h is None:
            continue
        assert h.frame_index == i - 1 and h.age_frames == 1
        assert list(h.fiducial_indices) == list(range(9))
        truth = ests[i].truth.ellipse_centres_px
        assert np.max(np.linalg.norm(h.centres_px - truth, axis=1)) < 1.0
        assert np.allclose(h.axes_px[:, 1], ests[i].truth.radius_px, rtol=0.1)


def test_tracker_calls_a_detector_without_a_hint_parameter():
    """A detector whose ``detect`` takes only the image still works (called without the hint)."""
    calls = []

    class Old:
        def __init__(self):
            self.inner = ClassicalDetector()

        def detect(self, image):
            calls.append(1)
            return self.inner.detect(image)

    cam = SimulatedCamera(seed=1, max_frames=3)
    trk = PoseTracker(PH.fiducial_centres_lps, cam.camera, detector=Old(), radius_mm=PH.fiducial_radius_mm)
    assert all(trk.process(f).ok for f in cam) and len(calls) == 3


def _truth_hint(cam, tr, age=1):
    return DetectionHint.from_pose(cam.camera, tr.T_cam_ct, cam.fiducials_ct, cam.phantom.fiducial_radius_mm,
                                   frame_index=0, age_frames=age)


def test_window_search_finds_the_balls_of_a_full_search_and_no_stray_outside():
    """With the balls' ellipses predicted, only windows around them are searched: the same balls
    at the same centres as a full-frame search, and a round ball-sized green stray far from
    them (which the full search accepts as a ball) is not reported."""
    from monotracker.sim.camera_sim import SceneEvents, Stray

    cam = SimulatedCamera(seed=0, events=SceneEvents(strays=[Stray(0, 5, (900.0, 380.0), 9.0, "round", 5)]))
    img, tr = cam.render(0.5)
    from monotracker.vision.detection import BlobRules

    det = ClassicalDetector(BlobRules(camera=cam.camera))
    full = det.detect(img)
    stray = np.array([900.0, 380.0])
    assert np.linalg.norm(full.centres - stray, axis=1).min() < 3     # the full search takes it
    win = det.detect(img, _truth_hint(cam, tr))
    assert len(win.fiducials) == 9
    assert np.linalg.norm(win.centres - stray, axis=1).min() > 100
    d = np.linalg.norm(win.centres[:, None] - tr.ellipse_centres_px[None], axis=2)
    assert sorted(d.argmin(1)) == list(range(9)) and d.min(1).max() < 0.3
    near = np.linalg.norm(full.centres[:, None] - win.centres[None], axis=2).min(0)
    assert near.max() < 0.02, near


def test_window_search_refuses_a_blob_larger_than_its_window():
    """A ball-coloured patch reaching into a ball's window from outside it (a drape of the balls'
    hue) is refused as extending beyond the window, not cut down to a ball-sized blob."""
    cam = SimulatedCamera(seed=0)
    img, tr = cam.render(0.5)
    det = ClassicalDetector()
    det.detect(img)                                   # a full search first (measures the blur)
    hint = _truth_hint(cam, tr)
    k = 4
    c = tr.ellipse_centres_px[k]
    a = hint.axes_px[k, 0]
    img = img.copy()
    # a green strip from 2 radii right of ball k (inside its window) to far beyond the window
    x0 = int(c[0] + 2 * a)
    img[int(c[1] - a):int(c[1] + a), x0:x0 + 300] = (40, 160, 40)
    d = det.detect(img, hint)
    assert np.linalg.norm(d.centres - [x0 + 10, c[1]], axis=1).min() > 20
    assert any(r.reason.startswith("extends beyond its search window") for r in d.rejected)
    assert np.linalg.norm(d.centres - c, axis=1).min() < 0.5        # the ball itself is still found


def test_window_search_finds_nothing_where_the_prediction_is_wrong():
    """A hint that is 60 px off (a stale pose): the balls are not reported at the predicted
    places (no guessing), so the pose fails and the tracker returns to a full search."""
    cam = SimulatedCamera(seed=0)
    img, tr = cam.render(0.5)
    hint = _truth_hint(cam, tr)
    off = DetectionHint(hint.centres_px + [60.0, 0.0], hint.axes_px, hint.angles_deg, hint.fiducial_indices)
    d = ClassicalDetector().detect(img, off)
    for p in d.centres:
        assert np.linalg.norm(tr.ellipse_centres_px - p, axis=1).min() < 0.5   # only true balls, if any
    assert len(d.fiducials) < 9


def test_window_search_fits_each_ball_in_one_pass_when_the_prediction_holds(monkeypatch):
    """Tracking (a hint), each ball's edge rays start from its own centre of the previous search
    (detection.START_AT_LAST_PX) and no ball of a head that did not move needs the re-centred
    second pass; the centres stay those of the truth. Started from their blobs' contours several
    balls are fitted twice."""
    from monotracker.vision import detection, edge_fit
    from monotracker.vision.detection import BlobRules

    cam = SimulatedCamera(seed=0, optics="photo", distance_mm=1100.0 * 4.0 / 18.0)    # 18 px balls
    img, tr = cam.render(0.5)
    det = ClassicalDetector(BlobRules(camera=cam.camera))
    det.detect(img)                  # a full search first (measures the blur, the balls' centres)
    passes = []
    inner = edge_fit._edge_points
    monkeypatch.setattr(edge_fit, "_edge_points", lambda image, balls, *a, **k: passes.append(len(balls))
                        or inner(image, balls, *a, **k))
    hint = _truth_hint(cam, tr)
    d = det.detect(img, hint)
    assert passes[0] == 9 and sum(passes[1:]) <= 1, passes
    dist = np.linalg.norm(d.centres[:, None] - tr.ellipse_centres_px[None], axis=2)
    assert len(d.fiducials) == 9 and dist.min(1).max() < 0.3
    passes.clear()
    monkeypatch.setattr(detection, "START_AT_LAST_PX", 0.0)
    det.detect(img, hint)
    assert sum(passes[1:]) >= 2, passes               # the contour's centre is often > 0.6 px off


def test_window_search_finds_balls_that_moved_from_their_prediction():
    """Balls 3 px from where the hint predicts them and from where the last search found them
    (the head moved more than expected): their rays start from their own blobs, and every ball is
    found at its true centre."""
    from monotracker.vision.detection import BlobRules

    cam = SimulatedCamera(seed=0, optics="photo")
    img, tr = cam.render(0.5)
    det = ClassicalDetector(BlobRules(camera=cam.camera))
    det.detect(np.roll(img, (-2, 3), axis=(0, 1)))     # the last search saw them 3.6 px away
    hint = _truth_hint(cam, tr)
    moved = DetectionHint(hint.centres_px + [2.4, -1.8], hint.axes_px, hint.angles_deg, hint.fiducial_indices)
    d = det.detect(img, moved)
    dist = np.linalg.norm(d.centres[:, None] - tr.ellipse_centres_px[None], axis=2)
    assert len(d.fiducials) == 9 and sorted(dist.argmin(1)) == list(range(9)) and dist.min(1).max() < 0.3
