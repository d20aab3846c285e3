"""The edge fit's shadow-side rays inside the outline (``edge_fit.SHADOW_IN_PX``, a detector's
``BlobRules.shadow_in_px``; issue 28 item 2) on the committed physically rendered crops (Mitsuba and Blender tuning splits,
tests/data/pbr*, no renderer needed): on a ball's unlit side the limb merges with its contact
shadow and that arc's edge lies inside the true outline, which makes whole balls fail the cut
test. Judged against each scene's own truth (true ellipse centres, visible fraction per ball),
the detector with the camera's outlines as the pose tracker sets them, first frame of each
condition. The default since 2026-12-01 (nineteenth session): before the tracker's shading check
it let trusted poses 1-2 mm off through on the held-out sets (docs/vision.md); these tests keep the
rule doing what it says against the rule before it (outside rays only)."""

from __future__ import annotations

import numpy as np
import pytest

from monotracker.sim.pbr.frameset import CONDITIONS, camera_frames, committed_root, list_scenes
from monotracker.vision import edge_fit
from monotracker.vision.detect_classical import ClassicalDetector
from monotracker.vision.detection import BlobRules

SETS = ("pbr", "pbr_blender", "pbr_planned")


def _found(scene, image, shadow_in_px=None, shadow_far_per_radius=None) -> dict:
    """{ball index: centre error px} of the balls the detector accepts (matched to the truth);
    ``shadow_in_px``, ``shadow_far_per_radius`` the detector's ``BlobRules`` settings (None: the
    defaults)."""
    tr, cam = scene.truth, scene.camera_model()
    rules = BlobRules(radius_mm=tr.radius_mm, focal_px=float(cam.K[0, 0]), shadow_in_px=shadow_in_px,
                      shadow_far_per_radius=shadow_far_per_radius)
    rules.camera = cam
    out = {}
    for f in ClassicalDetector(rules).detect(image).fiducials:
        d = np.linalg.norm(tr.ellipse_centres_px - np.asarray(f.centre_px, float), axis=1)
        j = int(np.argmin(d))
        if d[j] < max(2.0, 0.5 * tr.radius_px[j]):
            out[j] = float(d[j])
    return out


@pytest.fixture(scope="module")
def both():
    """Per scene x condition: (truth, found with the rule (the default), found with only outside
    rays (``BlobRules.shadow_in_px`` inf, the detector's own setting: no module state changed))."""
    rows = []
    for name in SETS:
        for scene in list_scenes(committed_root().parent / name / "tuning"):
            for cond, c in CONDITIONS.items():
                if scene.spec.kind != c["kind"]:
                    continue
                img = camera_frames(scene, cond, 1)[0]
                rows.append((scene.truth, _found(scene, img), _found(scene, img, float("inf"))))
    return rows


def test_the_default_leaves_shadowed_rays_inside_the_outline_out():
    assert edge_fit.SHADOW_IN_PX == 0.6


def test_more_whole_balls_are_found_and_their_centres_are_good(both):
    """Net gain in whole balls found (6 gained, 2 lost when written), each ball found only with
    the rule within 0.75 px of its true ellipse centre (0.17-0.54 px when written)."""
    gained = lost = 0
    for truth, rule, outside in both:
        for j in set(rule) - set(outside):
            if truth.whole[j]:
                gained += 1
                assert rule[j] < 0.75, (j, rule[j])
        lost += sum(1 for j in set(outside) - set(rule) if truth.whole[j])
    assert gained - lost >= 3, (gained, lost)


def test_no_more_partly_hidden_balls_are_accepted(both):
    """A ball really cut (visible fraction under the whole-ball mark) accepted with the rule was
    accepted without it too: the rule leaves only shadowed arcs out, not occluders' chords."""
    for truth, rule, outside in both:
        extra = [j for j in set(rule) - set(outside) if not truth.whole[j]]
        assert not extra, [(j, float(truth.visible_fraction[j])) for j in extra]
