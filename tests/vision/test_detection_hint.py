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

from .independent_render import FRAME_K, FRAME_SIZE, sphere_image_ellipse

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
    of the simulator's exact ellipse centres of the new frame (a breathing head); a full-frame
    search every ``full_search_every`` frames; after a camera fault a full search again."""
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
    full = [i for i, h in enumerate(hints) if h is None]
    assert full == [0, 5, 8], full
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
