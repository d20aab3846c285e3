"""The learned centre refiner (issue 28 item 2): its crop geometry, and what it does to the
centres of physically rendered balls (the committed Mitsuba tuning crops, truth from the scene's
geometry; the network never saw them: it was trained on the ``train`` split) and of our own
simulator's sharp balls (truth from the simulator)."""

from __future__ import annotations

import numpy as np
import pytest

from monotracker.errors import InputError
from monotracker.sim.pbr.frameset import CONDITIONS, camera_frames, committed_root, list_scenes
from monotracker.vision import centre_refiner as cr
from monotracker.vision.centre_refiner import CentreRefiner
from monotracker.vision.detect_classical import ClassicalDetector
from monotracker.vision.detection import BlobRules


def test_offsets_go_to_the_crop_and_back_in_every_orientation():
    d = np.array([0.13, -0.07])
    for ang, mir in cr.ORIENTATIONS:
        back = cr.crop_offset_to_image(cr.image_offset_to_crop(d, ang, mir), ang, mir)
        assert np.allclose(back, d, atol=1e-12), (ang, mir)


@pytest.mark.parametrize("ang,mir", [(0.0, False), (np.pi / 2, False), (0.0, True), (np.pi, True)])
def test_the_crop_grid_is_laid_as_documented(ang, mir):
    """A bright dot half a span right of the centre lands where the crop's axes say: its offset
    from the crop's centre, in radii, read back through ``crop_offset_to_image``, is the dot's
    offset in the image."""
    img = np.zeros((200, 200, 3), np.uint8)
    c, r = np.array([100.0, 100.0]), 10.0
    dot = c + np.array([0.5 * cr.SPAN * r, 0.0])
    img[int(dot[1]) - 1:int(dot[1]) + 2, int(dot[0]) - 1:int(dot[0]) + 2] = 255
    p = cr.sample_crop(img, c, r, ang, mir)[0]
    iy, ix = np.unravel_index(np.argmax(p), p.shape)
    u = ((ix + 0.5) / cr.CROP * 2 - 1) * cr.SPAN          # crop axes, radii
    v = ((iy + 0.5) / cr.CROP * 2 - 1) * cr.SPAN
    found = c + r * cr.crop_offset_to_image((u, v), ang, mir)
    assert np.linalg.norm(found - dot) < 0.6 * cr.SPAN * r * 2 / cr.CROP + 1.0, (found, dot)


def test_a_missing_network_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="centre refiner model not found"):
        CentreRefiner(tmp_path / "none.onnx")
    with pytest.raises(ValueError, match="orientations"):
        CentreRefiner(orientations=0)


def _errors(frames_and_truths):
    """Centre error (px) of each accepted ball of a whole-ball truth: (edge fit's, refined);
    ``frames_and_truths`` yields (detector, image, ellipse centres px, whole, radii px)."""
    edge, refined = [], []
    for det, img, ell, whole, radius in frames_and_truths:
        for f in det.detect(img).fiducials:
            d = np.linalg.norm(ell - f.centre_px, axis=1)
            j = int(np.argmin(d))
            if d[j] > max(2.0, 0.5 * radius[j]) or not whole[j]:
                continue
            refined.append(float(d[j]))
            edge.append(float(np.linalg.norm(ell[j] - f.features["edge_centre_px"])))
    return np.array(edge), np.array(refined)


def _first_frames(scenes, cond, kind, refiner):
    for s in (x for x in scenes if x.spec.kind == kind):
        cam, tr = s.camera_model(), s.truth
        det = ClassicalDetector(BlobRules(radius_mm=tr.radius_mm, focal_px=float(cam.K[0, 0]), camera=cam),
                                refiner=refiner)
        yield det, camera_frames(s, cond, 1)[0], tr.ellipse_centres_px, tr.whole, tr.radius_px


def test_rendered_balls_centres_are_brought_nearer_their_truth():
    """Every committed tuning crop, the first frame of each condition, the edge detector with the
    camera's outlines: over all conditions the refined centres are on average at most 0.8 x as
    far from the true ellipse centres as the edge fit's, and at most 0.75 x in the clean, degraded
    and clutter frames (measured 2026-11-30: 0.71 x overall; 0.67, 0.61, 0.44 x). Not in the OR
    crops: there the refiner moves the five balls of one scene (350b8d) 0.2-0.4 px the wrong way
    (0.20 -> 0.32 px over the condition's 10 balls), although on the 10 OR scenes of the full tuning
    set it halves the error and on the held-out set too (docs/vision.md): a known weakness."""
    scenes = list_scenes(committed_root() / "tuning")
    refiner = CentreRefiner()
    pooled_edge, pooled_refined = [], []
    for cond, c in CONDITIONS.items():
        edge, refined = _errors(_first_frames(scenes, cond, c["kind"], refiner))
        assert len(edge) >= 8, cond
        pooled_edge += list(edge)
        pooled_refined += list(refined)
        if cond != "OR":
            assert refined.mean() <= 0.75 * edge.mean(), (cond, edge.mean(), refined.mean())
    assert np.mean(pooled_refined) <= 0.8 * np.mean(pooled_edge), (np.mean(pooled_edge), np.mean(pooled_refined))


def test_our_sharp_balls_stay_where_the_edge_fit_puts_them():
    """Our simulator's clean frames (sharp, no shading to correct): the refined centres stay within
    0.1 px of the truth on average and never move a ball by more than 0.35 px."""
    from monotracker.sim.camera_sim import SimulatedCamera

    cam = SimulatedCamera(seed=11)
    rules = BlobRules(radius_mm=cam.phantom.fiducial_radius_mm, focal_px=float(cam.K[0, 0]), camera=cam.camera)
    det = ClassicalDetector(rules, refiner=CentreRefiner())
    errs, moves = [], []
    for t in (0.0, 0.7, 1.4):
        img, tr = cam.render(t)
        for f in det.detect(img).fiducials:
            d = np.linalg.norm(tr.ellipse_centres_px - f.centre_px, axis=1)
            errs.append(float(d.min()))
            moves.append(float(np.linalg.norm(f.centre_px - f.features["edge_centre_px"])))
    assert len(errs) >= 20
    assert np.mean(errs) < 0.1 and max(moves) < 0.35, (np.mean(errs), max(moves))


def test_the_trust_model_covers_refined_centres_with_their_own_factors():
    """The per-frame trust model takes a refined ball's error as ``refined_bias_per_rms`` x its edge
    RMS (not ``edge_bias_per_rms``) and the shift common to the balls as ``refined_common_per_rms``
    x their median edge RMS: halving both halves the predicted TRE (the noise floor aside); the
    edge factors then change nothing."""
    from monotracker.vision.frames import Frame
    from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig

    def predicted(scene, **factors):
        cam, tr = scene.camera_model(), scene.truth
        img = camera_frames(scene, "clean", 1)[0]
        det = ClassicalDetector(BlobRules(radius_mm=tr.radius_mm, focal_px=float(cam.K[0, 0]), camera=cam),
                                refiner=CentreRefiner())
        trk = PoseTracker(tr.fiducials_ct, cam, detector=det, radius_mm=tr.radius_mm, target_ct=tr.target_ct,
                          config=TrackerConfig(noise_prior_px=0.01, **factors))
        e = trk.process(Frame(img, 0.0, 0, None))
        return e.predicted_tre_mm if e.n_matched >= 4 else float("nan")

    scene = next(s for s in list_scenes(committed_root() / "tuning") if s.spec.kind == "clean"
                 and np.isfinite(predicted(s)))
    base = predicted(scene, refined_bias_per_rms=1.0, refined_common_per_rms=1.0)
    half = predicted(scene, refined_bias_per_rms=0.5, refined_common_per_rms=0.5)
    edge_changed = predicted(scene, refined_bias_per_rms=1.0, refined_common_per_rms=1.0, edge_bias_per_rms=0.1,
                             edge_common_per_rms=0.1)
    assert half == pytest.approx(0.5 * base, rel=0.05), (base, half)
    assert edge_changed == pytest.approx(base, rel=1e-9)


def test_the_calibrated_trust_model_knows_a_refined_detector():
    """The calibrated model looks up the refined detector's own measured bias (smaller than the
    edge detector's), also through a wrapper such as the camera rigs' ``KeepDetections``."""
    from monotracker.engine.rigs.validation import KeepDetections
    from monotracker.vision.centre_bias import CENTRE_BIAS, centre_bias_of

    rules = BlobRules(radius_mm=4.0, focal_px=1100.0)
    refined = ClassicalDetector(rules, refiner=CentreRefiner())
    assert centre_bias_of(refined) is CENTRE_BIAS["refined"]
    assert centre_bias_of(ClassicalDetector(rules)) is CENTRE_BIAS["edge"]
    wrapped = KeepDetections(np.diag([1100.0, 1100.0, 1.0]), 4.0)
    wrapped.inner = refined
    assert centre_bias_of(wrapped) is CENTRE_BIAS["refined"]
    assert CENTRE_BIAS["refined"].common_per_radius < CENTRE_BIAS["edge"].common_per_radius
