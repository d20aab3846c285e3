"""The camera path judged on physically rendered frames (issue 28).

Frames: Mitsuba 3 path-traced scenes (``monotracker.sim.pbr``: the sample head with textured skin,
the kit's green balls matte or glossy, OR lamps, drapes of several colours, gloved fingers, steel,
hair, green strays) through the calibrated lens, exact truth from the scene geometry. Each scene is
a still head streamed for ``--frames`` frames at 30 fps: the clean render through the
condition's camera chain, new sensor noise every frame (``sim.pbr.frameset.camera_frames``).

**Which frames** (printed in the header):
* default: the **tuning** set (``$MONOTRACKER_PBR/tuning``, default /work/pbr/tuning): anyone may
  look at it and tune on it;
* ``--held-out``: the **held-out** set (``$MONOTRACKER_PBR/held_out``): other seeds, other lamps
  (two, 5000 K + 4000 K, more ambient), other skin (olive-brown, shinier), other hair. Only ever
  scored: never tune a detector or a gate on it, never commit it; a threshold changed after
  looking at its numbers is said so in the commit;
* ``--quick``: the committed tuning crops (``tests/data/pbr``, with ``--renderer blender``
  ``tests/data/pbr_blender``; a few scenes per kind, no renderer needed) unless ``--root`` says
  otherwise.
* ``--root $MONOTRACKER_PBR/planned``: scenes whose camera stands where the layout planner
  approves it (``scripts/render_planned.py``: the same scenes' draws, cameras drawn until the
  planner predicts the pose trusted; 300-450 mm in practice), same split rules;
* ``--renderer blender``: the same scenes rendered by Blender's Cycles (a second renderer nobody
  here wrote; skin with sub-surface scattering, a pinhole lens; ``<root>/blender/<split>``,
  ``sim/pbr/blender_render.py``, ``sim.pbr.build.default_folder``; planner-placed Blender frames:
  ``--root $MONOTRACKER_PBR/planned --renderer blender``), same split rules. Frames of another
  renderer than ``--renderer`` (a ``--quick`` root, a folder of mixed frames) are refused, not
  scored under its name.
Render a set first: ``python -m monotracker.sim.pbr render --split tuning|held_out [--renderer
blender]`` (cached by scene hash; needs the ``render`` extra, or a Python with ``bpy``).

Conditions: ``clean`` (clean scenes, sharp lens, a good uncompressed sensor), ``OR`` (scenes with
gloved fingers, steel and hair; 1.5 px defocus, Bayer, raw noise, JPEG 85), ``degraded`` (the
clean scenes at 60 % light, 2.5 px defocus, noisier sensor, JPEG 70), ``clutter`` (OR + green
strays, dense and loose hair). Detectors: ``edge`` (today's default, with the camera's ball
outlines as the pose tracker sets them), ``no-band`` (``edge`` without the skin band reading,
``vision/skin_band.py``: contact-shadow evidence for the shading check where a small ball's edge
rays show none; the default since 2026-12-03, this is the detector before, the same-run baseline),
``chroma`` (the old soft-centroid baseline),
``learned`` (the ONNX segmenter), ``refined`` (``edge`` with the learned centre refiner,
``vision/centre_refiner.py``; opt-in; ``--refiner PATH`` scores another network), ``first``
(``edge`` without its second look at rejected blobs in the balls' own hue band,
``ClassicalDetector.narrow_second_pass``), ``narrow-lenient`` (``edge`` whose second look asks a
blob score of 0.35, not the first pass's 0.5: ``ClassicalDetector.narrow_min_score``, opt-in),
``shading`` (``edge`` with each shaded ball's centre moved towards its lit side and its colour
blob's centre, :mod:`monotracker.vision.shading_shift`; opt-in), ``outside-only`` (``edge``
whose contact-shadow test leaves out only shadowed rays outside the ball's outline, not those
inside it: ``BlobRules.shadow_in_px`` inf; the default before 2026-12-01), ``long-shadow``
(``edge`` whose shadow test reads the far background half the ball's radius beyond the near
one, at least 3 px: ``BlobRules.shadow_far_per_radius`` 0.5; opt-in, docs/vision.md "Long
contact shadows"), ``trim`` (``edge`` that scores a colour blob refused for its shape again
with its thin parts cut off: ``BlobRules.trim_tails``; opt-in, docs/vision.md "Ragged colour
blobs scored again trimmed"), ``smoothS`` (``edge`` with a third look, in frames blurred
over 1.6 px, at the blobs it refused, the colour mask thresholded on the frame smoothed by S x the
blur: ``ClassicalDetector.mask_smooth_per_blur``; ``smooth`` = 1.0, the value measured; opt-in, docs/vision.md
"Strongly blurred frames"; ``--blurred-side-floor`` sets the edge fit's ball-side floor there for
the whole run), ``idealS``
(not a detector: every whole ball at its true centre, edge RMS S px, e.g. ``ideal0.1``: the
ceiling the scenes and the gates allow, :class:`IdealDetector`). Each runs through the product's own chain: vision's
``PoseTracker`` (the detector with the camera's outlines, the registration, the trust gates).

Columns, per condition x detector x trust model (``before``: each frame alone, the trust model
before issue 28 and still the default; ``size``: the same with each ball's size excess covered
too, opt-in; ``calibrated``: still frames pooled, the centre bias
covered; ``p95``: the default with "trusted" read as "within 1 mm at 95 %"
(``max_not_right_probability`` 0.05), opt-in; ``no-check``: the default without the shading
check (:mod:`monotracker.vision.shading_check`), the default before 2026-12-01; ``no-memory``:
the default without the balls of the last frames of a still head (:mod:`monotracker.vision.ball_memory`,
``remember_frames`` 0), the default before 2026-12-01's second change; ``check-alone``: the
default with each frame's shading check on its own shadows only (``shading_check_still_frames``
False, the default before 2026-12-01's third change); ``prior-widened``: the default with the
first frames' noise prior widened as if measured from their few dof (``noise_prior_is_bound``
False, the default before 2026-12-01's fourth change); ``few6x2``: the default with a doubled cover
of each ball's bias up to 6 balls (``few_balls`` 6, ``few_balls_cover`` 2.0) on every frame (the
default applies it to frames whose balls read as glossy only); ``matte``: the default with every
frame read as matte (``glossy_highlight_ratio`` 0, the default before 2026-12-01's twenty-fifth
session, :mod:`monotracker.vision.ball_gloss`); ``no-disagreement``: the default without the
cover of a ball the others disagree with (``disagreement_quantile`` 0, the default before
2026-12-03's thirty-fifth session, :mod:`monotracker.registration.disagreement`); same frames,
same detections (the detections the first model's stream made: a model replayed on them reads
somewhat differently from the same model streamed live, its trust steering the detector's
search windows); ``before`` covers each ball's edge spread since the
per-frame model does, ``TrackerConfig.edge_bias_per_rms``; ``arm``: the ``before`` poses through
the session's own gate, what may move the arm: a pose agreeing with the last one the gate
trusted, or after a refusal spell 3 consecutive agreeing estimates, :func:`session_gate`;
``arm-no-check`` / ``arm-no-memory`` / ``arm-check-alone`` / ``arm-prior-widened`` /
``arm-few6x2`` / ``arm-matte`` / ``arm-no-disagreement``: those
models' poses through it):
* recall: whole balls (>= 98 % of the silhouette seen, ray-cast) found; precision: accepted
  detections that are a ball; partial: accepted balls that were partly hidden;
* centre err: mean / p95 px between the detected centre, carried to the sphere centre with the
  true depth (the registration's own ellipse -> sphere correction), and the true projected sphere
  centre; whole balls;
* trusted@1 / trusted@N: scenes whose pose at frame 1 / frame N is trusted and within 1 mm of the
  truth at the 80 mm deep target (80 mm below the fiducials' centroid along the patch normal);
* err med / p99 / max: error at that target of every trusted pose (mm);
* >2mm and 1-2mm: trusted poses that far off (wrong-but-valid), count and share of trusted;
* pred/act: RMS predicted TRE over RMS actual error, trusted poses (< 1: over-confident);
* pose % / <=1mm %: scenes whose frame-N centres give a pose at all (>= 4 balls matched), and
  one within 1 mm at the target, trusted or not (:func:`fitted_pose_error`): the ceiling of any
  trust model on these detections (the same for every trust model; trusted@N can only reach it).
``--planner``: a second table, per condition, the layout planner's prediction for each scene's
balls and camera (``planning.predict``: every ball seen, the worst one hidden, and with the
detector's measured losses, ``planning/ball_losses.py``; mean over scenes) against the share of
scenes trusted within 1 mm at frame N (first detector, default trust), overall and among the
scenes the planner approves.
Last line: one JSON object with every figure.

Usage: PYTHONPATH=app python benchmarks/camera_pbr.py [--quick] [--held-out] [--json] [--frames N]
       [--root DIR] [--scenes N] [--detectors edge,chroma,learned] [--planner]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from monotracker.errors import InputError
from monotracker.registration.report import layout_units, tre_mm
from monotracker.sim.pbr.build import RENDERERS, default_folder, renderer_name
from monotracker.sim.pbr.frameset import CONDITIONS, camera_frames, committed_root, list_scenes
from monotracker.sim.pbr.truth import sphere_centre_px
from monotracker.vision.frames import Frame
from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig
from monotracker.vision.recording import RecordingDetector

FPS = 30.0
#: the centre refiner's network for the ``refined`` detector (``--refiner``; None = the shipped one)
REFINER_MODEL = None


def make_detector(name: str, radius_mm: float, focal_px: float):
    from monotracker.vision.detect_classical import ClassicalDetector
    from monotracker.vision.detection import BlobRules

    rules = BlobRules(radius_mm=radius_mm, focal_px=focal_px)
    if name == "edge":
        return ClassicalDetector(rules)
    if name == "first":
        return ClassicalDetector(rules, narrow_second_pass=False)
    if name == "narrow-lenient":
        return ClassicalDetector(rules, narrow_min_score=0.35)
    if name == "shading":
        rules.shading_shift = True
        return ClassicalDetector(rules)
    if name == "no-band":
        rules.skin_band_ratio = 0.0
        return ClassicalDetector(rules)
    if name == "outside-only":
        rules.shadow_in_px = float("inf")
        return ClassicalDetector(rules)
    if name == "long-shadow":
        rules.shadow_far_per_radius = 0.5
        return ClassicalDetector(rules)
    if name == "trim":
        rules.trim_tails = True
        return ClassicalDetector(rules)
    if name.startswith("smooth"):
        # smoothS: the colour mask of a blurred frame smooths it by S x the measured blur
        # (ClassicalDetector.mask_smooth_per_blur; "smooth" = 1.0, as independent_optics.py's)
        return ClassicalDetector(rules, mask_smooth_per_blur=float(name[6:] or 1.0))
    if name == "chroma":
        return ClassicalDetector(rules, centre_method="chroma")
    if name == "refined":
        from monotracker.vision.centre_refiner import CentreRefiner

        return ClassicalDetector(rules, refiner=CentreRefiner(REFINER_MODEL))
    if name == "learned":
        from monotracker.vision.detect_learned import LearnedDetector

        return LearnedDetector(rules=rules)
    raise InputError(f"unknown detector {name!r} (edge, no-band, shading, outside-only, long-shadow, trim, smoothS, first, narrow-lenient, refined, chroma, learned, "
                     "idealS)")


class IdealDetector:
    """The trust model's ceiling on a scene (``--detectors idealS``): every whole ball found at its
    true ellipse centre plus 0.03 px of noise, reporting an edge RMS of S px (default 0.1), no
    partly hidden ball, no stray; the image is not looked at. What the scene's geometry (camera
    distance, how many balls are whole, their layout) and the gates allow a perfect detector whose
    centres are known to S px; compare with ``pose %`` / ``<=1mm %`` of the real detectors."""

    reads_image = False     # the truth's centres: the tracker averages no frames for it

    def __init__(self, truth, edge_rms_px: float = 0.1, seed: int = 0):
        self.truth, self.edge_rms_px = truth, float(edge_rms_px)
        self.rng = np.random.default_rng(seed)

    def detect(self, image, hint=None):
        from monotracker.vision.detection import Detection, ImageFiducial

        tr = self.truth
        fids = [ImageFiducial(np.asarray(p, float) + self.rng.normal(scale=0.03, size=2), (float(r), float(r)), 0.0,
                              1.0, float(np.pi * r * r), features={"edge_rms_px": self.edge_rms_px})
                for p, r in zip(tr.ellipse_centres_px[tr.whole], tr.radius_px[tr.whole])]
        return Detection(fids, [], 0.0, "ideal")


class Replay:
    """Gives back recorded detections in order (the same frames through another trust model);
    ``det`` is the detector that made them (the tracker's trust model looks it up)."""

    def __init__(self, log, det=None):
        self._it = iter(log)
        self.det = det

    def detect(self, image, hint=None):
        return next(self._it)


def trust_models() -> dict:
    """Trust models compared in one run: name -> TrackerConfig. ``before``: each frame alone,
    image noise from the residuals and each ball's edge spread (the default:
    ``centre_bias=None``); ``size``: the same with each ball's size excess covered too (opt-in,
    ``edge_size_per_excess`` 1.0); ``calibrated``: frames of a still head pooled, the detector's
    measured centre bias covered (``centre_bias="detector"``); ``p95``: the default with its
    promise read as "within 1 mm at 95 %" (``max_not_right_probability`` 0.05: the predicted
    error's distribution, not only its RMS, under 1 mm); ``no-check``: the default without the
    shading check (``shading_check_factor`` 0: the default before 2026-12-01); ``no-memory``: the
    default without the remembered balls of a still head (``remember_frames`` 0); ``check-alone``:
    the default with the shading check judging each frame on its own shadows only
    (``shading_check_still_frames`` False); ``prior-widened``: the default with the first frames'
    noise prior widened as if measured from their few dof (``noise_prior_is_bound`` False);
    ``few6x2``: the default with the few-ball cover at 6 balls and doubled (``few_balls`` 6,
    ``few_balls_cover`` 2.0) on every frame (on the tuning sets it removes nearly all trusted
    poses 1-2 mm off on Blender's planner-placed frames and costs about 4 in 10 of the scenes
    trusted within 1 mm at frame 8 on Mitsuba's, docs/vision.md "Blender's planner-placed tuning
    frames"; the default applies it only to frames whose balls read as glossy); ``matte``: the
    default with every frame read as matte (``glossy_highlight_ratio`` 0: the default before
    2026-12-01's twenty-fifth session, docs/vision.md "Glossy balls read from the frame");
    ``excess-reading``: the default with the shading check's second readings from each ball's
    outline size excess (``shading_check_reading`` "excess": opt-in, docs/vision.md "The shading
    check read from the outline's size"); ``averaged``: the default with the detector reading
    the mean of the still view's last 8 frames (``average_still_frames`` 8: opt-in; given only
    while the camera's noise is at least ``average_min_noise_dn``, 1.8 DN; its own detector run, not the default's detections replayed; docs/vision.md "A still view's frames
    averaged"); ``no-disagreement``: the default without the cover of a ball the others
    disagree with (``disagreement_quantile`` 0: the default before 2026-12-03's thirty-fifth
    session, docs/vision.md "A ball the others disagree with"); ``small-checked``: the default with
    the shading check applied wherever the balls' median fitted radius is under 10 px, shadows seen
    or not (``shading_check_small_radius_px`` 10: opt-in, docs/vision.md "Other lenses");
    ``push-floor``: the default with the shading check applied where no contact shadow is seen,
    each shaded ball's push taken as at least 0.3 px (``shading_check_unseen_push_px`` 0.3:
    opt-in, docs/vision.md "A push not seen"); ``band-floor``: the default with each ball that
    shows a band of shadow beside its unlit limb read at least 0.4 px towards its lit side where
    the shading check applies (``shading_check_band_floor_px`` 0.4: opt-in, docs/vision.md "A band
    of shadow beside the limb"); ``lens-blind``: the default without its short-lens floor (the
    band floor 0.4 px where the lens images the balls under 10 px from the planner's closest
    distance, ``short_lens_band_floor_px`` 0: the default before 2026-12-03's fortieth session,
    docs/vision.md "A lens outside the judged range"; through any other lens the same as
    ``before``)."""
    return {"before": TrackerConfig(centre_bias=None), "size": TrackerConfig(edge_size_per_excess=1.0),
            "calibrated": TrackerConfig(centre_bias="detector"), "p95": TrackerConfig(max_not_right_probability=0.05),
            "no-check": TrackerConfig(shading_check_factor=0.0), "no-memory": TrackerConfig(remember_frames=0),
            "check-alone": TrackerConfig(shading_check_still_frames=False),
            "prior-widened": TrackerConfig(noise_prior_is_bound=False),
            "few6x2": TrackerConfig(few_balls=6, few_balls_cover=2.0),
            "matte": TrackerConfig(glossy_highlight_ratio=0.0),
            "excess-reading": TrackerConfig(shading_check_reading="excess"),
            "averaged": TrackerConfig(average_still_frames=8),
            "no-disagreement": TrackerConfig(disagreement_quantile=0.0),
            "small-checked": TrackerConfig(shading_check_small_radius_px=10.0),
            "push-floor": TrackerConfig(shading_check_unseen_push_px=0.3),
            "band-floor": TrackerConfig(shading_check_band_floor_px=0.4),
            "lens-blind": TrackerConfig(short_lens_band_floor_px=0.0)}


def detection_stats(dets, truth, cam) -> dict:
    """Detection figures of a scene's frames against its truth (see the module docstring);
    ``cam`` the frames' CameraModel."""
    out = {"whole": 0, "found": 0, "accepted": 0, "true": 0, "partial": 0, "errs": []}
    ell = truth.ellipse_centres_px
    vf = truth.visible_fraction
    for d in dets:
        c = d.centres
        out["whole"] += int(truth.whole.sum())
        out["accepted"] += len(c)
        found = np.zeros(len(ell), bool)
        for p in c:
            dist = np.linalg.norm(ell - p, axis=1)
            j = int(np.argmin(dist))
            if dist[j] > max(2.0, 0.5 * truth.radius_px[j]) or vf[j] <= 0.0:
                continue
            out["true"] += 1
            if truth.whole[j] and not found[j]:
                found[j] = True
                s = sphere_centre_px(p[None], truth.fiducials_cam[j, 2:3], truth.radius_mm, cam.K, cam.dist)[0]
                out["errs"].append(float(np.linalg.norm(s - truth.projected_centres_px[j])))
            elif not truth.whole[j]:
                out["partial"] += 1
        out["found"] += int(found.sum())
    return out


def averages(cfg) -> bool:
    """The tracker of ``cfg`` gives its detector the mean of a still view's frames."""
    return cfg.average_still_frames > 1


def run_scene(scene, condition: str, det_name: str, n_frames: int, frames=None) -> dict:
    """One scene streamed through each trust model with one detector: per-model per-frame (ok,
    error mm, predicted TRE mm), and the detection figures."""
    cam = scene.camera_model()
    tr = scene.truth
    frames = frames if frames is not None else camera_frames(scene, condition, n_frames)
    if det_name.startswith("ideal"):
        rec = RecordingDetector(IdealDetector(tr, float(det_name[len("ideal"):] or 0.1)))
    else:
        rec = RecordingDetector(make_detector(det_name, tr.radius_mm, float(cam.K[0, 0])))
    res, own = {}, {}
    first = next(iter(trust_models().values()))
    for m, (name, cfg) in enumerate(trust_models().items()):
        if m == 0:
            det = rec
        elif averages(cfg) != averages(first) and not det_name.startswith("ideal"):
            # it reads other images than the first: a detector of its own, scored too
            det = own[name] = RecordingDetector(make_detector(det_name, tr.radius_mm, float(cam.K[0, 0])))
        else:
            det = Replay(list(rec.log), rec.det)
        trk = PoseTracker(tr.fiducials_ct, cam, detector=det, radius_mm=tr.radius_mm, target_ct=tr.target_ct,
                          config=cfg)
        rows, fitted = [], []
        gate, arm = session_gate(), []
        e = None
        for k, img in enumerate(frames):
            e = trk.process(Frame(img, k / FPS, k, None))
            err = float(tre_mm(e.T_cam_ct, tr.T_cam_ct, tr.target_ct)[0]) if e.ok else float("nan")
            rows.append((bool(e.ok), err, float(e.predicted_tre_mm), e.code))
            if m == 0 or name in own:
                fitted.append(fitted_pose_error(e, scene))
            if name in GATED:
                arm.append(_through_the_gate(gate, e, err))
        res[name] = rows
        if m == 0:
            res["_fitted"] = fitted
            res["_reason"] = e.reason if e is not None else ""     # the first trust model's, last frame
        elif name in own:
            res["_fitted_" + name] = fitted
        if name in GATED:
            res[GATED[name]] = arm
    res["_det"] = detection_stats(rec.log, tr, cam)
    for name, r in own.items():
        res["_det_" + name] = detection_stats(r.log, tr, cam)
    return res


#: the row of what may move the arm: the default trust model's poses through the session's gate
ARM = "arm"
#: trust model -> its row through the session's gate: the default's, the baselines of issue 28's
#: last changes measured in the same run (no-check, no-memory, check-alone, prior-widened, matte),
#: and ``few6x2``'s and ``excess-reading``'s (opt-in trust models: what they would let move the arm)
GATED = {"before": ARM, "no-check": "arm-no-check", "no-memory": "arm-no-memory", "check-alone": "arm-check-alone",
         "prior-widened": "arm-prior-widened", "few6x2": "arm-few6x2", "matte": "arm-matte",
         "excess-reading": "arm-excess-reading", "averaged": "arm-averaged",
         "no-disagreement": "arm-no-disagreement", "small-checked": "arm-small-checked",
         "push-floor": "arm-push-floor", "band-floor": "arm-band-floor", "lens-blind": "arm-lens-blind"}


def session_gate():
    """The session's own trust verdict over time (``engine.loop.gate.PoseGate`` with the default
    ``SessionConfig``): a pose the tracker trusts drives the arm only when it agrees with the last
    pose the gate trusted (within ``max_jump_mm`` / ``max_jump_deg``, that pose younger than 0.5
    s), or, with no such pose (first lock, after a refusal spell), once ``confirm_frames`` (3)
    consecutive estimates agree."""
    from monotracker.engine.config import SessionConfig
    from monotracker.engine.loop.gate import PoseGate

    return PoseGate.from_config(SessionConfig())


def _through_the_gate(gate, est, err: float) -> tuple:
    """(trusted by the gate, error mm at the target or NaN, predicted TRE mm, the gate's code)
    of the estimate ``est`` whose error at the target is ``err`` (mm, NaN unless the tracker
    trusted it: the gate never trusts more), fed to the gate as the tracking loop feeds it."""
    from monotracker.engine.rigs.base import estimate_to_sample

    v = gate.check_sample(estimate_to_sample(est, list(range(len(est.status)))))
    return (bool(v.trusted), err if v.trusted else float("nan"), float(est.predicted_tre_mm), v.code)


def fitted_pose_error(est, scene) -> float:
    """Error at the target (mm) of the pose fitted to a frame's matched centres, trusted or not
    (the registration's least squares from the centres the tracker matched,
    ``est.image_points_px``, started at the true pose); NaN with fewer than 4 matched. Over a
    set it is the ceiling of any trust model on these detections: a scene whose fitted pose is
    more than 1 mm off can only be refused or trusted wrongly."""
    from monotracker.registration.pnp import refine_pose
    from monotracker.registration.projection import undistort_to_normalised

    seen = np.isfinite(est.image_points_px[:, 0])
    if seen.sum() < 4:
        return float("nan")
    cam, tr = scene.camera_model(), scene.truth
    xn = undistort_to_normalised(est.image_points_px[seen], cam.K, cam.dist)
    fit = refine_pose(tr.T_cam_ct, tr.fiducials_ct[seen], xn, np.array([cam.K[0, 0], cam.K[1, 1]]), tr.radius_mm)
    return float(tre_mm(fit.T, tr.T_cam_ct, tr.target_ct)[0])


def ceiling(fitted: list, n_frames: int) -> dict:
    """Per condition x detector: scenes with a fitted pose at frame N, and with one within 1 mm
    at the target (trusted or not: what a perfect trust model could trust), percent."""
    last = np.array([f[n_frames - 1] for f in fitted])
    return {f"pose_at_{n_frames}_pct": 100.0 * float(np.mean(np.isfinite(last))) if len(last) else float("nan"),
            f"within_1mm_at_{n_frames}_pct": 100.0 * float(np.mean(last <= 1.0)) if len(last) else float("nan")}


def summarise(per_scene: list, n_frames: int) -> dict:
    """Figures of one condition x detector x trust model over its scenes."""
    ok1 = [r[0][0] and r[0][1] <= 1.0 for r in per_scene]
    okN = [r[n_frames - 1][0] and r[n_frames - 1][1] <= 1.0 for r in per_scene]
    trusted = [(e, p) for r in per_scene for ok, e, p, _ in r if ok]
    errs = np.array([e for e, _ in trusted])
    preds = np.array([p for _, p in trusted])
    out = {"scenes": len(per_scene), "trusted_at_1_pct": 100.0 * float(np.mean(ok1)) if ok1 else float("nan"),
           f"trusted_at_{n_frames}_pct": 100.0 * float(np.mean(okN)) if okN else float("nan"),
           "trusted_frames": int(len(errs)), "frames": int(sum(len(r) for r in per_scene))}
    if len(errs):
        out.update(err_median_mm=float(np.median(errs)), err_p99_mm=float(np.percentile(errs, 99)),
                   err_max_mm=float(errs.max()), over_2mm=int(np.sum(errs > 2.0)),
                   between_1_2mm=int(np.sum((errs > 1.0) & (errs <= 2.0))),
                   between_1_2mm_pct=100.0 * float(np.mean((errs > 1.0) & (errs <= 2.0))),
                   pred_over_act=float(np.sqrt(np.mean(preds**2)) / max(np.sqrt(np.mean(errs**2)), 1e-9)))
    else:
        out.update(err_median_mm=float("nan"), err_p99_mm=float("nan"), err_max_mm=float("nan"), over_2mm=0,
                   between_1_2mm=0, between_1_2mm_pct=float("nan"), pred_over_act=float("nan"))
    return out


def det_summary(stats: list) -> dict:
    whole = sum(s["whole"] for s in stats)
    acc = sum(s["accepted"] for s in stats)
    errs = np.array([e for s in stats for e in s["errs"]])
    return {"recall": sum(s["found"] for s in stats) / whole if whole else float("nan"),
            "precision": sum(s["true"] for s in stats) / acc if acc else float("nan"),
            "partial_accepted": int(sum(s["partial"] for s in stats)),
            "centre_err_mean_px": float(errs.mean()) if len(errs) else float("nan"),
            "centre_err_p95_px": float(np.percentile(errs, 95)) if len(errs) else float("nan")}


def fit_bias(scenes, conds, n_frames: int, say=print, detector: str = "edge") -> dict:
    """Measure the centre bias of the default detector on the (tuning) scenes: per scene and
    condition, each whole ball's mean error over ``n_frames`` frames (balls found in at least half
    of them) against the true ellipse centre; its common part c (the mean over the balls) and the
    per-ball rest u, and of that the part changing linearly across the layout (u = U G^T + w,
    ``registration.report.layout_units``; the gradient's four entries); the frame-to-frame noise
    from the scatter (its share removed from each).
    Returns the figures per condition and the centre bias they give: per coordinate,
    ``sigma = per_radius * r`` with ``per_radius`` the RMS over scenes of (bias / radius) / sqrt(2)
    (a calibrated variance, not a bound: the pooled residuals adapt the per-ball part per scene;
    the common part is only ever this prior)."""
    from monotracker.vision.detection import BlobRules

    rows = {}
    for cond in conds:
        cs = [s for s in scenes if s.spec.kind == CONDITIONS[cond]["kind"]]
        for s in cs:
            cam, tr = s.camera_model(), s.truth
            det = make_detector(detector, tr.radius_mm, float(cam.K[0, 0]))
            if isinstance(getattr(det, "rules", None), BlobRules):
                det.rules.camera = cam       # the camera's outlines, as the pose tracker sets them
            E = np.full((len(tr.fiducials_ct), n_frames, 2), np.nan)
            S = np.full((len(tr.fiducials_ct), n_frames), np.nan)         # each ball's edge RMS px
            for k, img in enumerate(camera_frames(s, cond, n_frames)):
                for f in det.detect(img).fiducials:
                    p = np.asarray(f.centre_px, float)
                    d = np.linalg.norm(tr.ellipse_centres_px - p, axis=1)
                    j = int(np.argmin(d))
                    if d[j] < max(2.0, 0.5 * tr.radius_px[j]) and tr.whole[j]:
                        E[j, k] = p - tr.ellipse_centres_px[j]
                        S[j, k] = float(f.features.get("edge_rms_px", np.nan))
            cnt = np.sum(np.isfinite(E[:, :, 0]), axis=1)
            use = cnt >= max(2, n_frames // 2)
            if use.sum() < 4:
                continue
            m = np.nanmean(E[use], axis=1)
            n = cnt[use].astype(float)
            noise2 = float(np.nansum((E[use] - m[:, None]) ** 2) / (2 * np.sum(n - 1)))
            r = tr.radius_px[use]
            c = m.mean(axis=0)
            k = int(use.sum())
            c_var = max(float(c @ c) / 2 - noise2 / (k * np.mean(n)), 0.0)
            u = m - c
            u_var = max(float(np.sum(u**2)) / (2 * (k - 1)) - noise2 / float(np.mean(n)), 0.0)
            # the part that changes linearly across the layout: u = U G^T + w (U: layout_units)
            U = layout_units(tr.ellipse_centres_px[use])
            G = np.linalg.pinv(U) @ u                                        # (2, 2)
            g_noise = noise2 / float(np.mean(n)) * float(np.trace(np.linalg.pinv(U.T @ U))) / 2
            g_var = max(float(np.sum(G**2)) / 4 - g_noise, 0.0)
            with np.errstate(all="ignore"):
                med_rms = float(np.nanmedian(S[use]))
            rows.setdefault(cond, []).append((float(np.mean(r)), noise2, c_var, u_var, g_var, med_rms))
    out = {"conditions": {}}
    allc, allu, allcpx, allupx, allg = [], [], [], [], []
    for cond, rs in rows.items():
        r = np.array([x[0] for x in rs])
        cr = np.array([x[2] for x in rs]) / r**2
        ur = np.array([x[3] for x in rs]) / r**2
        cpx = np.array([x[2] for x in rs])
        upx = np.array([x[3] for x in rs])
        gr = np.array([x[4] for x in rs]) / r**2
        allg += list(gr)
        allc += list(cr)
        allu += list(ur)
        allcpx += list(cpx)
        allupx += list(upx)
        out["conditions"][cond] = {"scenes": len(rs), "radius_px": float(np.mean(r)),
                                   "common_px": float(np.sqrt(np.mean(cpx))), "ball_px": float(np.sqrt(np.mean(upx))),
                                   "noise_px": float(np.sqrt(np.mean([x[1] for x in rs]))),
                                   "common_per_radius": float(np.sqrt(np.mean(cr))),
                                   "common_per_radius_p90": float(np.sqrt(np.percentile(cr, 90))),
                                   "ball_per_radius": float(np.sqrt(np.mean(ur))),
                                   "ball_per_radius_p90": float(np.sqrt(np.percentile(ur, 90))),
                                   "gradient_per_radius": float(np.sqrt(np.mean(gr))),
                                   "gradient_per_radius_p90": float(np.sqrt(np.percentile(gr, 90)))}
        rms = np.array([x[5] for x in rs])
        if np.all(np.isfinite(rms)) and np.all(rms > 0):
            # the per-frame model's factors: bias over the balls' median edge RMS (TrackerConfig.
            # edge_bias_per_rms / edge_common_per_rms; the gradient has no per-frame term)
            out["conditions"][cond].update(
                edge_rms_px=float(np.mean(rms)),
                ball_per_rms=float(np.sqrt(np.mean(upx / rms**2))),
                common_per_rms=float(np.sqrt(np.mean(cpx / rms**2))),
                gradient_per_rms=float(np.sqrt(np.mean(np.array([x[4] for x in rs]) / rms**2))))
        o = out["conditions"][cond]
        if "ball_per_rms" in o:
            say(f"{'':<9} per edge RMS ({o['edge_rms_px']:.3f} px): ball {o['ball_per_rms']:.2f}  "
                f"common {o['common_per_rms']:.2f}  gradient {o['gradient_per_rms']:.2f}")
        say(f"{cond:<9} {o['scenes']:>3} scenes  radius {o['radius_px']:5.1f} px  noise {o['noise_px']:.3f} px  "
            f"common {o['common_px']:.3f} px  ball {o['ball_px']:.3f} px  "
            f"common {o['common_per_radius']:.4f} r (p90 {o['common_per_radius_p90']:.4f})  "
            f"ball {o['ball_per_radius']:.4f} r (p90 {o['ball_per_radius_p90']:.4f})  "
            f"gradient {o['gradient_per_radius']:.4f} r (p90 {o['gradient_per_radius_p90']:.4f})")
    if allc:
        out["common_px"] = float(np.sqrt(np.mean(allcpx)))
        out["ball_px"] = float(np.sqrt(np.mean(allupx)))
        say(f"all: bias (ball_px={out['ball_px']:.3f}, common_px={out['common_px']:.3f}) per coordinate")
        out["common_per_radius"] = float(np.sqrt(np.mean(allc)))
        out["ball_per_radius"] = float(np.sqrt(np.mean(allu)))
        out["gradient_per_radius"] = float(np.sqrt(np.mean(allg)))
        say(f"all: bias (ball_per_radius={out['ball_per_radius']:.4f}, "
            f"common_per_radius={out['common_per_radius']:.4f}, "
            f"gradient_per_radius={out['gradient_per_radius']:.4f}) per coordinate")
    return out


_HEAD = {}


def planner_outlook(scene) -> dict:
    """The layout planner's prediction for the scene's balls seen from its camera
    (``planning.predict`` with the outlook of the detector's losses, ``planning/ball_losses.py``;
    the phantom's head mesh, the planner's default image noise and found probability, the scene's
    own target), as shares 0..1: ``all_seen`` and ``worst_hidden`` (its verdict: approved when
    >= ``MIN_TRUSTED``), ``with_losses`` and ``pose_with_losses``."""
    from monotracker.geometry import invert_transform
    from monotracker.planning import HeadSurface, predict
    from monotracker.planning.defaults import build_problem
    from monotracker.sim.pbr.surfaces import head_mesh
    from monotracker.sim.phantom import default_phantom

    if "head" not in _HEAD:
        ph = default_phantom()
        V, _n, _uv, F = head_mesh(ph, nu=200, nv=100)
        _HEAD.update(head=HeadSurface(V, F), ph=ph)
    ph, tr = _HEAD["ph"], scene.truth
    X = np.asarray(tr.fiducials_ct, float)
    problem = build_problem(_HEAD["head"], tr.target_ct, existing=X, radius_mm=tr.radius_mm, drape_offset_mm=None,
                            camera=scene.camera_model())
    n = (X - ph.centre_lps) / np.asarray(ph.skin_semi_axes_mm, float) ** 2   # the ellipsoid's exact normals
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    p = predict(problem, invert_transform(tr.T_cam_ct), X, n, losses=True)
    return {"all_seen": 0.0 if p.all_seen is None else p.all_seen.trusted,
            "worst_hidden": 0.0 if p.worst_hidden is None else p.worst_hidden.trusted,
            "with_losses": p.with_losses.trusted, "pose_with_losses": p.with_losses.pose}


def planner_table(rows: dict, n_frames: int, say) -> dict:
    """Per condition: the planner's predictions (mean over scenes, %) against the scenes trusted
    within 1 mm at frame ``n_frames`` (default detector and trust); ``rows[cond]`` a list of
    (outlook dict, trusted bool)."""
    from monotracker.planning.planner import MIN_TRUSTED

    say(f"\nthe layout planner's prediction against the outcome (default detector and trust; trusted within 1 mm at "
        f"frame {n_frames}; % of scenes; approved: predicted >= {100 * MIN_TRUSTED:.0f} % with the worst ball hidden)")
    say(f"{'condition':<9} {'scenes':>6} {'all seen':>8} {'worst hid':>9} {'w/ losses':>9} {'pose w/l':>8} "
        f"{'observed':>8}   {'approved':>8} {'w/ losses':>9} {'observed':>8}")
    out = {}
    for cond, rs in list(rows.items()) + [("all", [r for v in rows.values() for r in v])]:
        if not rs:
            continue
        P = {k: np.array([o[k] for o, _ in rs]) for k in rs[0][0]}
        ok = np.array([t for _, t in rs], bool)
        app = P["worst_hidden"] >= MIN_TRUSTED
        d = {"scenes": len(rs), **{f"{k}_pct": 100.0 * float(v.mean()) for k, v in P.items()},
             "observed_pct": 100.0 * float(ok.mean()), "approved": int(app.sum()),
             "approved_with_losses_pct": 100.0 * float(P["with_losses"][app].mean()) if app.any() else float("nan"),
             "approved_observed_pct": 100.0 * float(ok[app].mean()) if app.any() else float("nan")}
        out[cond] = d
        say(f"{cond:<9} {d['scenes']:>6} {d['all_seen_pct']:>8.0f} {d['worst_hidden_pct']:>9.0f} "
            f"{d['with_losses_pct']:>9.0f} {d['pose_with_losses_pct']:>8.0f} {d['observed_pct']:>8.0f}   "
            f"{d['approved']:>8} {d['approved_with_losses_pct']:>9.0f} {d['approved_observed_pct']:>8.0f}")
    return out


def per_scene(cs, runs, cond: str, det: str, n_frames: int) -> list:
    """One row per scene of ``run_scene``'s results ``runs`` (scenes ``cs``): its hash, whole
    balls, the fitted pose's error at frame N (mm, the ceiling), and per frame for the default
    trust model and through the session's gate: T (trusted) or the refusal code's first letter;
    with the codes counted, the trusted poses' worst error at the target (mm) and the default's
    reason at frame N where it refused (what bound it: the RMS, a tail gate, too few balls)."""
    rows = []
    for s, r in zip(cs, runs):
        row = {"condition": cond, "detector": det, "scene": s.hash, "whole": int(s.truth.whole.sum()),
               "fitted_mm_at_n": r["_fitted"][n_frames - 1], "reason_at_n": r.get("_reason", "")}
        for tm in ("before", ARM):
            frames = r[tm]
            row[tm] = "".join("T" if ok else (str(code) or "?")[0] for ok, _e, _p, code in frames)
            row[f"{tm}_codes"] = dict(Counter(str(code) for ok, _e, _p, code in frames if not ok))
            errs = [e for ok, e, _p, _c in frames if ok]
            row[f"{tm}_max_mm"] = max(errs) if errs else None
        rows.append(row)
    return rows


def _per_scene_line(row: dict) -> str:
    def one(tm):
        worst = row[f"{tm}_max_mm"]
        codes = ", ".join(f"{c} {n}" for c, n in sorted(row[f"{tm}_codes"].items()))
        return f"{tm} {row[tm]}" + (f" (max {worst:.2f} mm)" if worst is not None else "") + (f" [{codes}]" if codes else "")
    fitted = row["fitted_mm_at_n"]
    return (f"  {row['condition']:<9} {row['detector']:<9} {row['scene'][:8]} whole {row['whole']:>2} "
            f"fitted {'-' if not np.isfinite(fitted) else f'{fitted:.2f}':>4} mm  {one('before')}  {one(ARM)}"
            + (f"\n      frame {len(row['before'])}: {row['reason_at_n']}" if row.get("reason_at_n") else ""))


def _finite(obj):
    """NaN / inf -> None, so the JSON line is valid JSON."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="camera path on physically rendered frames (issue 28)")
    ap.add_argument("--quick", action="store_true", help="the committed tuning crops (tests/data/pbr)")
    ap.add_argument("--held-out", action="store_true", help="score the held-out set (never tune on it)")
    ap.add_argument("--json", action="store_true", help="print only the JSON line")
    ap.add_argument("--frames", type=int, default=8, help="frames streamed per still scene (default 8)")
    ap.add_argument("--root", type=Path, default=None, help="folder holding tuning/ and held_out/")
    ap.add_argument("--renderer", choices=RENDERERS, default="mitsuba",
                    help="whose frames: mitsuba (default) or blender (<root>/blender/<split>)")
    ap.add_argument("--scenes", type=int, default=0, help="at most this many scenes per kind (0 = all)")
    ap.add_argument("--detectors", default="edge,no-band,outside-only,chroma,learned")
    ap.add_argument("--conditions", default=",".join(CONDITIONS))
    ap.add_argument("--refiner", type=Path, default=None,
                    help="the centre refiner's ONNX network for the 'refined' detector (default: the shipped one)")
    ap.add_argument("--per-scene", action="store_true",
                    help="also each scene's frames, the default trust and through the session's gate: T trusted, "
                         "else the first letter of the refusal's code (t tre_limit, o occlusion, a acquiring, ...)")
    ap.add_argument("--planner", action="store_true",
                    help="also the layout planner's prediction per scene against the outcome (first detector)")
    ap.add_argument("--fit-bias", action="store_true",
                    help="measure the detectors' centre bias on the tuning set (px per coordinate)")
    ap.add_argument("--blurred-side-floor", type=float, default=None,
                    help="the edge fit's ball-side floor in strongly blurred frames for every detector of the run "
                         "(edge_fit.BLURRED_BALL_SIDE_FLOOR; opt-in 0.16, docs/vision.md 'Strongly blurred frames')")
    a = ap.parse_args(argv)
    global REFINER_MODEL
    REFINER_MODEL = a.refiner
    if a.blurred_side_floor is not None:
        from monotracker.vision import edge_fit

        edge_fit.BLURRED_BALL_SIDE_FLOOR = float(a.blurred_side_floor)
    if a.fit_bias and a.held_out:
        print("error: the centre bias is fitted on the tuning set only, never on the held-out set", file=sys.stderr)
        return 2
    split = "held_out" if a.held_out else "tuning"
    if a.quick and a.held_out:
        print("error: --quick reads the committed tuning crops; the held-out set is never committed", file=sys.stderr)
        return 2
    if a.quick:      # the committed crops: tests/data/pbr (Mitsuba) or tests/data/pbr_blender
        base = a.root or (committed_root() if a.renderer == "mitsuba" else committed_root().parent / "pbr_blender")
        folder = base / split
    else:
        folder = default_folder(split, a.renderer, a.root)
    try:
        scenes = list_scenes(folder) if folder.is_dir() else []
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not scenes:
        print(f"error: no rendered {split} set in {folder}: python -m monotracker.sim.pbr render --split {split} "
              f"--renderer {a.renderer} (needs pip install -e '.[render]', or a Python with bpy)", file=sys.stderr)
        return 2
    other = sorted({s.spec.renderer for s in scenes if renderer_name(s.spec.renderer) != a.renderer})
    if other:       # a --quick root names the split's folder itself, whatever the renderer
        print(f"error: --renderer {a.renderer}, but {folder} holds frames rendered by {', '.join(other)} "
              f"(--renderer {renderer_name(other[0])})", file=sys.stderr)
        return 2
    dets = [d.strip() for d in a.detectors.split(",") if d.strip()]
    conds = [c.strip() for c in a.conditions.split(",") if c.strip()]
    bad = [c for c in conds if c not in CONDITIONS]
    if bad:
        print(f"error: unknown condition(s) {bad} (have {list(CONDITIONS)})", file=sys.stderr)
        return 2
    for dn in dets:     # a bad name is one line now, not a traceback in the middle of a run
        try:
            if dn.startswith("ideal"):
                if not float(dn[len("ideal"):] or 0.1) >= 0:
                    raise ValueError
            else:
                make_detector(dn, 4.0, 1100.0)
        except ValueError:
            print(f"error: {dn!r}: idealS takes an edge RMS in px, e.g. ideal0.1", file=sys.stderr)
            return 2
        except InputError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    say = (lambda *x, **k: None) if a.json else print
    if a.fit_bias:
        fits = {}
        for dn in dets:
            say(f"centre bias of the {dn} detector, {folder} ({len(scenes)} scenes), {a.frames} frames per scene")
            fits[dn] = fit_bias(scenes, conds, a.frames, say, dn)
        print(json.dumps(_finite(fits)))
        return 0
    label = ("HELD-OUT set: only ever scored, never tuned on" if a.held_out else
             "TUNING set: may be looked at and tuned on")
    renderers = sorted({s.spec.renderer for s in scenes})
    say(f"camera path on physically rendered frames ({', '.join(renderers)}) - {label}")
    say(f"frames: {folder} ({len(scenes)} scenes), a still head streamed {a.frames} frames at {FPS:g} fps; "
        f"target 80 mm deep; trust models: {', '.join(trust_models())}, and through the session's gate: "
        f"{', '.join(f'{v} ({k})' for k, v in GATED.items())}")
    dw = max([9] + [len(d) for d in dets])
    tw = max([12] + [len(t) for t in [*trust_models(), *GATED.values()]])
    hdr = (f"{'condition':<9} {'detector':<{dw}} {'trust':<{tw}} {'scenes':>6} {'recall':>6} {'prec':>5} {'partial':>7} "
           f"{'err px':>6} {'p95 px':>6} {'tr@1 %':>6} {'tr@' + str(a.frames) + ' %':>6} {'med mm':>6} "
           f"{'p99 mm':>6} {'max mm':>6} {'>2mm':>4} {'1-2mm':>9} {'pred/act':>8} {'pose %':>6} {'<=1mm %':>7}")
    say(hdr)
    result = {"set": split, "folder": str(folder), "renderers": renderers, "frames": a.frames, "conditions": {}}
    t0 = time.perf_counter()
    planner_rows = {}
    for cond in conds:
        kind = CONDITIONS[cond]["kind"]
        cs = [s for s in scenes if s.spec.kind == kind]
        if a.scenes:
            cs = cs[: a.scenes]
        if not cs:
            continue
        streams = {s.hash: camera_frames(s, cond, a.frames) for s in cs}
        result["conditions"][cond] = {}
        for dn in dets:
            runs = [run_scene(s, cond, dn, a.frames, streams[s.hash]) for s in cs]
            ds = det_summary([r["_det"] for r in runs])
            ds.update(ceiling([r["_fitted"] for r in runs], a.frames))
            if a.planner and dn == dets[0]:
                first = next(iter(trust_models()))
                planner_rows[cond] = [(planner_outlook(s), bool(r[first][a.frames - 1][0] and r[first][a.frames - 1][1] <= 1.0))
                                      for s, r in zip(cs, runs)]
            result["conditions"][cond][dn] = {"detection": ds}
            own = {}        # trust models with a detector of their own: their detection figures
            for tm in trust_models():
                if "_det_" + tm in runs[0]:
                    own[tm] = own[GATED.get(tm, tm)] = det_summary([r["_det_" + tm] for r in runs])
                    own[tm].update(ceiling([r["_fitted_" + tm] for r in runs], a.frames))
                    result["conditions"][cond][dn]["detection_" + tm] = own[tm]
            for tm in [*trust_models(), *GATED.values()]:
                sm = summarise([r[tm] for r in runs], a.frames)
                result["conditions"][cond][dn][tm] = sm
                ds = own.get(tm, result["conditions"][cond][dn]["detection"])
                say(f"{cond:<9} {dn:<{dw}} {tm:<{tw}} {sm['scenes']:>6} {ds['recall']:>6.2f} {ds['precision']:>5.2f} "
                    f"{ds['partial_accepted']:>7} {ds['centre_err_mean_px']:>6.3f} {ds['centre_err_p95_px']:>6.2f} "
                    f"{sm['trusted_at_1_pct']:>6.0f} {sm[f'trusted_at_{a.frames}_pct']:>6.0f} "
                    f"{sm['err_median_mm']:>6.2f} {sm['err_p99_mm']:>6.2f} {sm['err_max_mm']:>6.2f} "
                    f"{sm['over_2mm']:>4} {sm['between_1_2mm']:>3} ({sm['between_1_2mm_pct']:>3.0f}%) "
                    f"{sm['pred_over_act']:>8.2f} {ds[f'pose_at_{a.frames}_pct']:>6.0f} "
                    f"{ds[f'within_1mm_at_{a.frames}_pct']:>7.0f}")
            if a.per_scene:
                rows = per_scene(cs, runs, cond, dn, a.frames)
                result.setdefault("per_scene", []).extend(rows)
                for row in rows:
                    say(_per_scene_line(row))
    if a.planner:
        result["planner"] = planner_table(planner_rows, a.frames, say)
    result["seconds"] = round(time.perf_counter() - t0, 1)
    say(f"({result['seconds']:.0f} s)")
    print(json.dumps(_finite(result)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
