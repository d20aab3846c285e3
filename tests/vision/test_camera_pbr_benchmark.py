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
def result():
    spec = importlib.util.spec_from_file_location("camera_pbr_bench", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = mod.main(["--quick", "--json", "--frames", "3", "--detectors", "edge,ideal0.1", "--conditions", "clean,OR"])
    assert rc == 0
    return json.loads(out.getvalue().strip().splitlines()[-1])


def test_the_ceiling_bounds_what_is_trusted(result):
    """A scene trusted within 1 mm at frame N has a pose within 1 mm there (the fitted pose is the
    trusted one), and one within 1 mm has a pose at all: trusted@N <= <=1mm % <= pose %."""
    for cond, dets in result["conditions"].items():
        for name, d in dets.items():
            det = d["detection"]
            assert det["within_1mm_at_3_pct"] <= det["pose_at_3_pct"], (cond, name)
            for model, m in d.items():
                if model != "detection":
                    assert m["trusted_at_3_pct"] <= det["within_1mm_at_3_pct"] + 1e-9, (cond, name, model)


def test_the_ideal_detector_finds_every_whole_ball_at_its_centre(result):
    for cond, dets in result["conditions"].items():
        ideal = dets["ideal0.1"]["detection"]
        assert ideal["recall"] == 1.0 and ideal["partial_accepted"] == 0, cond
        assert ideal["centre_err_mean_px"] < 0.1, cond
    clean = result["conditions"]["clean"]
    assert clean["ideal0.1"]["detection"]["within_1mm_at_3_pct"] == 100.0
    assert clean["ideal0.1"]["before"]["trusted_at_3_pct"] >= clean["edge"]["before"]["trusted_at_3_pct"]
