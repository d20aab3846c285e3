"""Classical detector vs the simulator's truth."""

import numpy as np

from monotracker.sim.camera_sim import Occluder, SceneEvents, SimulatedCamera, Stray, _finger
from monotracker.sim.trajectories import make_trajectory
from monotracker.vision.detect_classical import ClassicalDetector


def _match(centres, truth, tol=2.0):
    d = np.linalg.norm(centres[:, None] - truth[None], axis=2)
    return d.argmin(1), d.min(1)


def test_all_balls_found_to_subpixel(sim_still):
    det = ClassicalDetector()
    for t in (0.0, 1.0):
        img, tr = sim_still.render(t)
        d = det.detect(img)
        assert len(d.fiducials) == 9
        j, err = _match(d.centres, tr.ellipse_centres_px)
        assert sorted(j) == list(range(9))
        assert err.max() < 0.3, err
        for f in d.fiducials:
            assert 0.5 <= f.score <= 1.0
            assert 6 < f.axes_px[1] <= f.axes_px[0] < 11


def test_clip_is_not_a_fiducial(sim_still):
    img, tr = sim_still.render(0.0)
    d = ClassicalDetector().detect(img)
    a, b = sim_still.phantom.clip_segment_lps
    from monotracker.geometry import apply_transform
    clip_px = sim_still.camera.project(apply_transform(tr.T_cam_ct, 0.5 * (a + b)[None]))[0]
    assert np.linalg.norm(d.centres - clip_px, axis=1).min() > 10


def test_partially_occluded_ball_is_rejected(sim_still):
    px = sim_still.rest_projection()
    k = 3
    # a finger whose tip stops at the ball's centre: about half of it hidden
    oc = Occluder(0.0, 10.0, _finger(60, 900, 0.0), px[k] + [300, 0], px[k] + [0.0, 0], sweep_s=0.0)
    cam = SimulatedCamera(events=SceneEvents(occluders=[oc]), seed=0)
    img, tr = cam.render(1.0)
    assert 0.2 < tr.visible_fraction[k] < 0.8
    d = ClassicalDetector().detect(img)
    near = np.linalg.norm(d.centres - tr.ellipse_centres_px[k], axis=1) if len(d.centres) else np.array([99.0])
    assert near.min() > 3, "a half-hidden ball (biased centre) must not be accepted"
    assert len(d.fiducials) == int(tr.visible.sum())
    # it is reported among the rejected candidates, with a reason
    rej = [r for r in d.rejected if np.linalg.norm(r.centre_px - tr.ellipse_centres_px[k]) < 8]
    assert rej and rej[0].reason.startswith("score")


def test_irregular_strays_rejected_round_ones_may_pass():
    strays = [Stray(0, 5, (200.0, 150.0), 12.0, "irregular", 1), Stray(0, 5, (1000.0, 500.0), 12.0, "streak", 2)]
    cam = SimulatedCamera(events=SceneEvents(strays=strays), seed=0)
    img, tr = cam.render(1.0)
    d = ClassicalDetector().detect(img)
    assert len(d.fiducials) == 9
    j, err = _match(d.centres, tr.ellipse_centres_px)
    assert err.max() < 0.3


def test_detection_under_motion_blur_dim_light_and_noise():
    from monotracker.sim.camera_sim import SceneEvents
    cam = SimulatedCamera(trajectory=make_trajectory("drift"), noise_sigma=4.0,
                          events=SceneEvents(lighting=[(0, 0.6), (100, 0.6)]), seed=2)
    img, tr = cam.render(7.0)
    d = ClassicalDetector().detect(img)
    j, err = _match(d.centres, tr.ellipse_centres_px)
    assert len(d.fiducials) == 9 and err.max() < 0.5


def test_no_fiducials_in_a_blank_image():
    d = ClassicalDetector().detect(np.full((720, 1280, 3), 90, np.uint8))
    assert d.fiducials == [] and d.centres.shape == (0, 2)


def test_centres_hold_under_photo_like_optics():
    """Lens blur, gloss, Bayer + raw noise, drapes behind outline balls (OR-layout view): edge
    centres within 0.08 px mean of the exact ellipse centres; today's chroma centroid is pulled
    several times further (that is the point of the edge fit)."""
    from monotracker.sim.optics import Optics
    from monotracker.sim.or_layout import default_layout

    cam = SimulatedCamera(seed=1, optics=Optics(jpeg_quality=0, hair_density=0.0), T_cam_world=default_layout().T_cam_ct0)
    errs = {"edge": [], "chroma": []}
    for t in (0.0, 0.7, 1.9):
        img, tr = cam.render(t)
        for method in errs:
            d = ClassicalDetector(centre_method=method).detect(img)
            j, err = _match(d.centres, tr.ellipse_centres_px, tol=3.0)
            if method == "edge":
                assert err.max() < 0.3, err
                assert len(d.fiducials) >= int(tr.visible.sum()) - 1
            errs[method] += list(err)
    assert np.mean(errs["edge"]) < 0.08, np.mean(errs["edge"])
    assert np.mean(errs["chroma"]) > 2 * np.mean(errs["edge"])


def test_centres_hold_under_jpeg_with_realistic_blur(monkeypatch):
    """The photo-like preset (defocus 1.5 px, Bayer + raw noise, hair, gloss, drapes) with JPEG
    85 (4:2:0): edge centres within 0.08 px mean of the exact ellipse centres, on two scenes (one
    with a green-blue drape all round the head, inside the default green band). JPEG keeps luma
    sharp but subsamples and block-quantises colour; without the colour smoothing along the rays
    (edge_fit.CHROMA_SIGMA_PX = 0) the same frames give 0.083 px vs 0.073 px with it (the edge
    fit before the near background, edge_fit.NEAR_BACKGROUND: ~0.12 px vs ~0.08 px)."""
    from monotracker.sim.optics import PRESETS
    from monotracker.sim.or_layout import default_layout
    from monotracker.vision import edge_fit

    frames = []
    for seed in (1, 4):
        cam = SimulatedCamera(seed=seed, optics=PRESETS["photo"], T_cam_world=default_layout().T_cam_ct0)
        frames += [cam.render(t) for t in (0.0, 0.7, 1.9)]

    def errors(narrow=False, **kw):
        errs, second, found, vis = [], [], 0, 0
        for img, tr in frames:
            d = ClassicalDetector(narrow_second_pass=narrow, **kw).detect(img)
            j, err = _match(d.centres, tr.ellipse_centres_px, tol=3.0)
            assert err.max() < 0.35, err
            errs += list(err)
            found += len(err)
            vis += int(tr.visible.sum())
            extra = np.array([f.centre_px for f in d.fiducials if "narrowed_band" in f.features]).reshape(-1, 2)
            if len(extra):
                second += list(_match(extra, tr.ellipse_centres_px, tol=3.0)[1])
        return np.array(errs), found / vis, np.array(second)

    # the edge fit itself: the first pass alone
    errs, recall, _ = errors()
    assert np.mean(errs) < 0.08, np.mean(errs)
    assert recall > 0.6, recall          # balls on the outline against drape are refused, not biased
    # the narrowed second look adds balls lying on the drape, 0.17-0.25 px off (the mean over
    # all balls is then ~0.082 px; with the opt-in lower blob score of the second look,
    # narrow_min_score 0.35, every visible ball of these frames, those 0.09-0.27 px off, ~0.094)
    errs_n, recall_n, second = errors(narrow=True)
    assert recall_n >= recall and len(second) >= 3 and second.max() < 0.3, (recall_n, recall, second)
    assert np.mean(errs_n) < 0.09, np.mean(errs_n)
    errs_o, recall_o, second_o = errors(narrow=True, narrow_min_score=0.35)
    assert recall_o > recall_n and len(second_o) > len(second) and second_o.max() < 0.3, (recall_o, second_o)
    monkeypatch.setattr(edge_fit, "CHROMA_SIGMA_PX", 0.0)
    errs_off, _, _ = errors()
    assert np.mean(errs_off) > 1.05 * np.mean(errs), (np.mean(errs_off), np.mean(errs))


def test_balls_inside_a_ball_coloured_drape_are_found():
    """A green-blue drape (hue ~87, inside the default green band) all round the head makes one
    mask blob with the head as a hole; the balls on the head are blobs inside that hole. They
    must still be analysed (the detector once took only outermost contours and found none)."""
    import cv2

    from monotracker.sim.optics import PRESETS
    from monotracker.sim.or_layout import default_layout

    cam = SimulatedCamera(seed=4, optics=PRESETS["photo"], T_cam_world=default_layout().T_cam_ct0)
    img, tr = cam.render(0.0)
    det = ClassicalDetector()
    n, _, stats, _ = cv2.connectedComponentsWithStats(det.mask(img))
    assert stats[1:, 4].max() > 0.3 * img.shape[0] * img.shape[1]      # the drape is in the mask
    d = det.detect(img)
    assert len(d.fiducials) >= 3                                        # (none before)
    j, err = _match(d.centres, tr.ellipse_centres_px, tol=3.0)
    assert err.max() < 0.3


def test_windows_masked_in_one_mosaic_equal_each_window_masked_alone():
    """The window search's colour masks, made in one go from the windows stacked into a mosaic
    (ClassicalDetector._window_masks), equal mask() of each window on its own (its own opening,
    OpenCV's border), on a photo-like frame with windows on and beside the balls, at the image's
    corners and overlapping each other, and for a red band that wraps through hue 0."""
    cam = SimulatedCamera(seed=4, optics="photo")
    img, tr = cam.render(0.3)
    h, w = img.shape[:2]
    rng = np.random.default_rng(1)
    boxes = [(int(c[0]) - 30, int(c[1]) - 25, int(c[0]) + 27, int(c[1]) + 33) for c in tr.ellipse_centres_px]
    boxes += [(0, 0, 41, 17), (w - 50, h - 60, w, h), (0, h - 3, 5, h)]
    boxes += [tuple(int(v) for v in (x, y, x + rng.integers(3, 90), y + rng.integers(3, 90)))
              for x, y in zip(rng.integers(0, w - 90, 6), rng.integers(0, h - 90, 6))]
    boxes = [(max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)) for x0, y0, x1, y1 in boxes]
    det = ClassicalDetector()
    n_set = 0
    for hue in ((35, 90), (170, 10)):
        det.hue_lo, det.hue_hi = hue
        for (x0, y0, x1, y1), got in zip(boxes, det._window_masks(img, boxes)):
            ref = det.mask(img[y0:y1, x0:x1])
            assert got.shape == ref.shape and np.array_equal(got, ref), (x0, y0, x1, y1)
            n_set += int(got.any())
    assert n_set >= 9


def _ring_contour(r: float, dent, n: int = 400) -> np.ndarray:
    """An OpenCV contour (int px, as findContours gives) of a circle of radius ``r`` px at (100,
    100) whose radius at angle t is ``r + dent(t)``."""
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    rho = r + dent(t)
    pts = np.stack([100.0 + rho * np.cos(t), 100.0 + rho * np.sin(t)], axis=1)
    return np.round(pts).astype(np.int32).reshape(-1, 1, 2)


def test_the_boundary_tolerance_grows_with_the_ball():
    """The boundary factor's tolerance is 0.6 px up to an 8 px radius and 7.5 % of the radius above
    (shading dents a ball's colour mask by a share of its size): a 13 px ball whose mask is dented
    by 0.2 r over its lit side (0.52 px RMS off an ellipse) is kept, where the fixed 0.6 px refused
    it (the formula before, written out here); a 6 px ball dented the same way scores as before; a
    13 px ball cut by a chord a quarter of its diameter in still scores far below the 0.5 floor."""
    import math

    import cv2

    from monotracker.vision.detection import BlobRules, score_blob

    rules = BlobRules(radius_mm=4.0, focal_px=1100.0)

    def score(contour):
        s, f, _ = score_blob(contour, float(cv2.contourArea(contour)), rules)
        return s, s / f["f_fit"] * math.exp(-(f["fit_rms_px"] / 0.6) ** 2), f

    def dent(r):
        return lambda t: -0.2 * r * np.clip(np.cos(t), 0.0, None) ** 8

    near, near_before, f = score(_ring_contour(13.0, dent(13.0)))
    assert near >= 0.5 > near_before, (near, near_before, f["fit_rms_px"])
    far, far_before, _ = score(_ring_contour(6.0, dent(6.0)))
    assert far == far_before >= 0.5
    t = np.linspace(0.0, 2.0 * np.pi, 400, endpoint=False)
    x = np.minimum(13.0 * np.cos(t), 13.0 * 0.5)                   # a chord a quarter diameter in
    cut = np.round(np.stack([100 + x, 100 + 13.0 * np.sin(t)], axis=1)).astype(np.int32).reshape(-1, 1, 2)
    assert score(cut)[0] < 0.2, score(cut)[2]
