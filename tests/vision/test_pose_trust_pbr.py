"""Trust on physically rendered frames (issue 28 item 3): the committed Mitsuba tuning crops
(tests/data/pbr, no renderer needed) streamed through the product's PoseTracker as a still head,
each pose judged against the scene's own geometry (``truth.T_cam_ct``, the 80 mm deep target)."""

from __future__ import annotations

import numpy as np
import pytest

from monotracker.registration.report import tre_mm
from monotracker.sim.pbr.frameset import CONDITIONS, camera_frames, committed_root, list_scenes
from monotracker.vision.frames import Frame
from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig

N_FRAMES = 8


@pytest.fixture(scope="module")
def scenes():
    return list_scenes(committed_root() / "tuning")


def _stream(scene, condition, config):
    """(trusted?, error at the target mm, predicted TRE mm) per frame."""
    tr = scene.truth
    trk = PoseTracker(tr.fiducials_ct, scene.camera_model(), radius_mm=tr.radius_mm, target_ct=tr.target_ct,
                      config=config)
    out = []
    for k, img in enumerate(camera_frames(scene, condition, N_FRAMES)):
        e = trk.process(Frame(img, k / 30.0, k, None))
        out.append((bool(e.ok), float(tre_mm(e.T_cam_ct, tr.T_cam_ct, tr.target_ct)[0]) if e.ok else np.nan,
                    float(e.predicted_tre_mm)))
    return out


def _trusted_errors(scenes, config):
    errs = []
    for cond, c in CONDITIONS.items():
        for s in (x for x in scenes if x.spec.kind == c["kind"]):
            errs += [e for ok, e, _ in _stream(s, cond, config) if ok]
    return np.array(errs)


def test_no_trusted_pose_is_wrong_on_rendered_frames(scenes):
    """Every condition, every committed scene, 8 frames each: no trusted pose is more than 1 mm
    off at the target, with the product's per-frame trust model (which still trusts poses
    here) or with the calibrated one. (The calibrated model used to trust some of these; since
    it covers the bias that changes across the layout, measured on Mitsuba's and Blender's
    tuning frames, it trusts none of the committed crops: its reach is in the notes.)"""
    per_frame = _trusted_errors(scenes, TrackerConfig())
    assert len(per_frame) >= 1, "the product's trust model must still trust a pose on rendered frames"
    assert np.all(per_frame <= 1.0), np.sort(per_frame)[-5:]
    calibrated = _trusted_errors(scenes, TrackerConfig(centre_bias="detector"))
    assert np.all(calibrated <= 1.0), np.sort(calibrated)[-5:]




@pytest.fixture(scope="module")
def blender_scenes():
    return list_scenes(committed_root().parent / "pbr_blender" / "tuning")


def test_blender_frames_balls_are_where_the_scene_says_and_no_trusted_pose_over_2mm(blender_scenes):
    """The committed crops of the second renderer (Blender's Cycles: skin with sub-surface
    scattering, a pinhole lens; tests/data/pbr_blender, tuning split, 2 scenes per kind): the
    default detector's accepted balls lie where the scene geometry projects them (within 1.5 px:
    the Blender export, its camera and the truth agree), and neither trust model trusts a pose
    more than 2 mm off at the target in any condition (issue 28's hard limit)."""
    from monotracker.vision.detect_classical import ClassicalDetector
    from monotracker.vision.detection import BlobRules

    assert {s.spec.renderer for s in blender_scenes} == {"blender-cycles-1"}
    assert {s.spec.split for s in blender_scenes} == {"tuning"}, "held-out frames are never committed"
    assert {s.spec.kind for s in blender_scenes} == {"clean", "OR", "clutter"}
    near = 0
    for s in blender_scenes:
        cam, tr = s.camera_model(), s.truth
        det = ClassicalDetector(BlobRules(radius_mm=tr.radius_mm, focal_px=float(cam.K[0, 0]), camera=cam))
        for p in det.detect(s.image).centres:
            d = np.linalg.norm(tr.ellipse_centres_px - p, axis=1)
            near += int(d.min() < 1.5)
    assert near >= 10, near
    for config in (TrackerConfig(), TrackerConfig(centre_bias="detector")):
        errs = _trusted_errors(blender_scenes, config)
        assert np.all(errs <= 2.0), np.sort(errs)[-5:]


def test_blender_frames_no_trusted_pose_over_1mm(blender_scenes):
    """Known until 2026-12-01 (an xfail since 2026-11-30): on the Blender OR crop b0c7930b the
    default trusted frames 1.02-1.07 mm off at a predicted 0.52-0.67 mm, 5 whole balls 0.2-0.44
    px off at an edge RMS of 0.09-0.13 px. Its balls are glossy and sit beside contact shadows:
    read so from the frame (:mod:`monotracker.vision.ball_gloss`), their few-ball cover is the
    wider one and the default trusts none of them, but still trusts poses on these crops. Read
    as matte (``glossy_highlight_ratio`` 0, the default before) the same frames are trusted over
    1 mm again: what the reading buys, on frames nobody here rendered."""
    default = _trusted_errors(blender_scenes, TrackerConfig())
    assert len(default) >= 3 and np.all(default <= 1.0), np.sort(default)
    calibrated = _trusted_errors(blender_scenes, TrackerConfig(centre_bias="detector"))
    assert np.all(calibrated <= 1.0), np.sort(calibrated)[-5:]
    matte = _trusted_errors(blender_scenes, TrackerConfig(glossy_highlight_ratio=0.0))
    assert np.any(matte > 1.0), np.sort(matte)[-5:]


@pytest.mark.parametrize("renderer", ["mitsuba", "blender"])
def test_the_size_excess_covers_centre_errors_the_edge_spread_misses(renderer):
    """Against the rendered truth (the committed tuning crops of either renderer, 2 frames per
    scene, accepted whole balls): each ball's centre error per coordinate over its cover. The
    edge RMS alone leaves a long tail (p90 1.6 on Mitsuba's crops, 2.7 on Blender's); the cover
    the opt-in size cover gives (``TrackerConfig.edge_size_per_excess`` 1.0), max(edge RMS, |size
    excess|) with the excess measured against the TRUE sphere outline, shortens it on both
    (Blender's by more than a quarter)."""
    from monotracker.vision.detect_classical import ClassicalDetector
    from monotracker.vision.detection import BlobRules
    from monotracker.vision.sphere_outline import sphere_ellipses

    root = committed_root() / "tuning" if renderer == "mitsuba" else committed_root().parent / "pbr_blender" / "tuning"
    err, rms, excess = [], [], []
    for cond, c in CONDITIONS.items():
        for s in (x for x in list_scenes(root) if x.spec.kind == c["kind"]):
            cam, tr = s.camera_model(), s.truth
            det = ClassicalDetector(BlobRules(radius_mm=tr.radius_mm, focal_px=float(cam.K[0, 0]), camera=cam))
            outline = sphere_ellipses(cam, tr.fiducials_ct @ tr.T_cam_ct[:3, :3].T + tr.T_cam_ct[:3, 3],
                                      tr.radius_mm)[1][:, 1]
            for img in camera_frames(s, cond, 2):
                for f in det.detect(img).fiducials:
                    d = np.linalg.norm(tr.ellipse_centres_px - f.centre_px, axis=1)
                    j = int(np.argmin(d))
                    if d[j] <= 2.0 and tr.whole[j]:
                        err.append(d[j] / np.sqrt(2.0))
                        rms.append(f.features["edge_rms_px"])
                        excess.append(abs(f.features["edge_minor_px"] - outline[j]))
    err, rms, excess = map(np.array, (err, rms, excess))
    assert len(err) >= 50, len(err)
    before = np.percentile(err / rms, 90)
    now = np.percentile(err / np.maximum(rms, 1.0 * excess), 90)
    assert now < before, (now, before)
    if renderer == "blender":
        assert now < 0.75 * before, (now, before)
