"""``benchmarks/camera_pbr.py`` on the committed crops: its ceiling columns agree with what they
claim to bound, and its ideal detector is what it says (no renderer needed)."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "camera_pbr.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("camera_pbr_bench", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def result(bench):
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = bench.main(["--quick", "--json", "--frames", "3", "--detectors", "edge,ideal0.1", "--conditions", "clean,OR",
                       "--planner", "--per-scene"])
    assert rc == 0
    return json.loads(out.getvalue().strip().splitlines()[-1])


def test_the_ceiling_bounds_what_is_trusted(result):
    """A scene trusted within 1 mm at frame N has a pose within 1 mm there (the fitted pose is the
    trusted one), and one within 1 mm has a pose at all: trusted@N <= <=1mm % <= pose %."""
    for cond, dets in result["conditions"].items():
        for name, d in dets.items():
            for key in [k for k in d if k.startswith("detection")]:
                det = d[key]
                assert det["within_1mm_at_3_pct"] <= det["pose_at_3_pct"], (cond, name, key)
            for model, m in d.items():
                if not model.startswith("detection"):
                    # a trust model with a detector of its own (the still view's mean) has its
                    # own detection figures and ceiling
                    own = d.get("detection_" + model) or d.get("detection_" + model.removeprefix("arm-"))
                    det = own or d["detection"]
                    assert m["trusted_at_3_pct"] <= det["within_1mm_at_3_pct"] + 1e-9, (cond, name, model)


def test_the_ideal_detector_finds_every_whole_ball_at_its_centre(result):
    for cond, dets in result["conditions"].items():
        ideal = dets["ideal0.1"]["detection"]
        assert ideal["recall"] == 1.0 and ideal["partial_accepted"] == 0, cond
        assert ideal["centre_err_mean_px"] < 0.1, cond
    clean = result["conditions"]["clean"]
    assert clean["ideal0.1"]["detection"]["within_1mm_at_3_pct"] == 100.0
    assert clean["ideal0.1"]["before"]["trusted_at_3_pct"] >= clean["edge"]["before"]["trusted_at_3_pct"]


def test_the_planner_table_scores_the_first_detectors_outcome(result):
    """Its observed share is the first detector's trusted@N with the default trust, per condition;
    fewer balls found cannot be trusted more often than all of them, nor than the chance of a pose."""
    plan = result["planner"]
    for cond, dets in result["conditions"].items():
        p = plan[cond]
        assert p["observed_pct"] == pytest.approx(dets["edge"]["before"]["trusted_at_3_pct"]), cond
        assert p["with_losses_pct"] <= p["all_seen_pct"] + 1e-9 and p["with_losses_pct"] <= p["pose_with_losses_pct"]
    assert plan["all"]["scenes"] == sum(plan[c]["scenes"] for c in result["conditions"])


def test_the_arm_row_is_the_default_through_the_sessions_gate(bench, result):
    """``arm``: the default model's poses through the session's gate (engine.loop.gate). From a
    cold start the gate trusts nothing before 3 consecutive agreeing estimates (confirm_frames):
    in 3-frame streams only frame 3 of a scene, and never a frame the default refused. With the
    ideal detector on the clean crops (the same pose every frame) a scene the default trusts in
    all 3 frames is the gate's at frame 3 (3 of the 4 scenes, 9 of 12 frames, when written)."""
    for cond, dets in result["conditions"].items():
        for name, d in dets.items():
            for model, row in bench.GATED.items():      # the default's row and every other model's alike
                gated, ungated = d[row], d[model]
                assert gated["trusted_at_1_pct"] == 0.0, (cond, name, row)
                assert gated["trusted_frames"] <= min(ungated["trusted_frames"], ungated["scenes"]), (cond, name, row)
    clean = result["conditions"]["clean"]["ideal0.1"]
    fully = round(clean["before"]["trusted_at_3_pct"] * clean["before"]["scenes"] / 100)
    assert fully > 0 and clean["before"]["trusted_frames"] == 3 * fully
    assert clean["arm"]["trusted_at_3_pct"] == clean["before"]["trusted_at_3_pct"]
    assert clean["arm"]["trusted_frames"] == fully


def test_the_per_scene_rows_add_up_to_the_table(bench, result):
    """``--per-scene``: one row per scene, condition and detector whose frames (T trusted, else the
    refusal code's first letter) add up to the table's trusted frames and trusted-at-N share, for
    the default and through the gate; the gate never trusts a frame the default refused, and its
    codes count exactly the frames it refused."""
    rows = result["per_scene"]
    for cond, dets in result["conditions"].items():
        for name, d in dets.items():
            mine = [r for r in rows if r["condition"] == cond and r["detector"] == name]
            assert len(mine) == d["before"]["scenes"] > 0, (cond, name)
            for tm in ("before", bench.ARM):
                assert sum(r[tm].count("T") for r in mine) == d[tm]["trusted_frames"], (cond, name, tm)
                at_n = 100.0 * sum(r[tm][-1] == "T" for r in mine) / len(mine)
                assert d[tm]["trusted_at_3_pct"] <= at_n + 1e-9, (cond, name, tm)   # the table's also within 1 mm
                for r in mine:
                    assert len(r[tm]) == 3 and sum(r[f"{tm}_codes"].values()) == 3 - r[tm].count("T")
            for r in mine:
                assert all(b == "T" or a != "T" for a, b in zip(r[bench.ARM], r["before"])), r


@pytest.mark.parametrize("name", ["nope", "idealx"])
def test_a_bad_detector_name_is_one_line_not_a_traceback(bench, name, capsys):
    assert bench.main(["--quick", "--detectors", f"edge,{name}"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and name in err and "\n" not in err


@pytest.mark.parametrize("renderer, folder", [("blender", "pbr"), ("mitsuba", "pbr_blender")])
def test_frames_of_another_renderer_are_refused_not_scored(bench, renderer, folder, capsys):
    """A ``--quick`` root names the split's folder itself: asked for Blender's frames where
    Mitsuba's lie (or the reverse) the benchmark says so in one line instead of scoring the other
    renderer's frames under this one's name (with any root it did, 2026-12-01)."""
    root = Path(__file__).resolve().parents[1] / "data" / folder
    assert bench.main(["--quick", "--root", str(root), "--renderer", renderer, "--detectors", "edge"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --renderer " + renderer) and "rendered by" in err and "\n" not in err


def test_one_folder_rule_for_every_renderer(tmp_path):
    """``default_folder`` is the one rule (rendering and scoring alike): ``<root>/<split>`` for
    Mitsuba, ``<root>/blender/<split>`` for Blender, with or without a given root."""
    from monotracker.sim.pbr.build import default_folder

    assert default_folder("held_out", "mitsuba", tmp_path) == tmp_path / "held_out"
    assert default_folder("held_out", "blender", tmp_path) == tmp_path / "blender" / "held_out"
    assert default_folder("tuning", "blender").parts[-2:] == ("blender", "tuning")


def test_the_wider_few_ball_cover_is_measured_beside_the_default(bench, result):
    """``few6x2`` (the candidate: each ball's bias cover doubled up to 6 balls) is scored on the
    same detections as the default: a wider cover refuses what the default refuses (it trusts no
    more frames); its gated row, ``arm-few6x2``, is checked with the others above."""
    assert bench.GATED["few6x2"] == "arm-few6x2"
    for cond, dets in result["conditions"].items():
        for name, d in dets.items():
            cand, before = d["few6x2"], d["before"]
            assert cand["scenes"] == before["scenes"], (cond, name)
            assert cand["trusted_frames"] <= before["trusted_frames"], (cond, name)


def test_the_default_before_the_gloss_reading_is_measured_beside_it(bench, result):
    """``matte`` (every frame read as matte: the default before the frame's gloss reading,
    :mod:`monotracker.vision.ball_gloss`) is scored on the same detections as the default, which
    only widens the cover of frames read as glossy: the default trusts no more frames than it,
    and no fewer than ``few6x2`` (that cover on every frame)."""
    assert bench.GATED["matte"] == "arm-matte"
    for cond, dets in result["conditions"].items():
        for name, d in dets.items():
            matte, default, wide = d["matte"], d["before"], d["few6x2"]
            assert matte["scenes"] == default["scenes"], (cond, name)
            assert wide["trusted_frames"] <= default["trusted_frames"] <= matte["trusted_frames"], (cond, name)


def test_the_still_views_mean_is_scored_with_its_own_detections(bench, result):
    """``averaged`` (the detector reads the mean of the still view's frames,
    ``TrackerConfig.average_still_frames``, opt-in) runs a detector of its own: the edge
    detector's row has its own detection figures and ceiling; the ideal detector, which reads no
    image, replays the default's detections."""
    assert bench.GATED["averaged"] == "arm-averaged"
    assert not bench.averages(next(iter(bench.trust_models().values())))
    for cond, dets in result["conditions"].items():
        edge, ideal = dets["edge"], dets["ideal0.1"]
        assert "detection_averaged" in edge and "detection_averaged" not in ideal, cond
        assert set(edge["detection_averaged"]) == set(edge["detection"]), cond
        assert 0.0 <= edge["detection_averaged"]["recall"] <= 1.0, cond
        assert ideal["averaged"]["trusted_frames"] == ideal["before"]["trusted_frames"], cond
