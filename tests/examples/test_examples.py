"""Every script in examples/ runs on a fresh install and passes its own ground-truth check.

Each example exits non-zero when its result disagrees with the simulator's truth (a wrong pose,
a missed fiducial, an arm that does not hold), so a zero exit code is a real assertion; the
printed lines are checked for the key facts too. The time limit is generous: it only catches a
hang (the machine may be loaded), never measures speed.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = sorted((ROOT / "examples").glob("[0-9][0-9]_*.py"))

#: a line each example must print (beyond its own exit-code check)
EXPECT = {
    "01_register_synthetic_scene.py": "right",
    "02_detect_ct_fiducials.py": "error vs ground truth",
    "03_detect_image_fiducials.py": "vs the true ellipse centres",
    "04_pose_stream_sim_camera.py": "fiducial 6 lost",
    "05_apff_tracker_sim_ur10.py": "stale target: state holding",
    "06_headless_session.py": "3D Slicer markups",
    "07_record_and_replay.py": "poses reproduced within 0.001 mm",
    "08_openigtlink_client.py": "pose=VALID",
}

#: examples that run the engine or a pose stream on the real clock, or the demo on a simulated
#: clock that counts measured CPU time (a loaded machine changes what they see: example 06's tip
#: was 40 mm off in a loaded suite, issue 35): the serial lane's (tests/conftest.py). The others
#: (a manual clock, pure computation) run 2-wide with the rest of the suite.
SERIAL = {"04_pose_stream_sim_camera.py", "06_headless_session.py", "07_record_and_replay.py",
          "08_openigtlink_client.py"}


def _example(p: Path):
    return pytest.param(p, id=p.stem, marks=[pytest.mark.serial] if p.name in SERIAL else [])


def test_every_example_is_listed_in_the_index_and_here():
    index = (ROOT / "examples" / "README.md").read_text()
    assert EXAMPLES, "no examples found"
    for p in EXAMPLES:
        assert p.name in index, f"{p.name} missing from examples/README.md"
        assert p.name in EXPECT, f"{p.name} has no expectation in this test"
    assert SERIAL <= set(EXPECT), SERIAL - set(EXPECT)


@pytest.mark.parametrize("script", [_example(p) for p in EXAMPLES])
def test_example_runs_and_checks_itself(script, tmp_path):
    # TMPDIR: what an example leaves in a temporary folder lands in pytest's own, not in /tmp
    # (before the examples removed theirs, each run of the suite left ~270 MB there)
    env = dict(os.environ, PYTHONPATH=str(ROOT / "app"), MONOTRACKER_HOME=str(tmp_path), TMPDIR=str(tmp_path))
    proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=420)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"{script.name} failed (exit {proc.returncode}):\n{out[-3000:]}"
    assert "Traceback" not in out, out[-3000:]
    assert EXPECT[script.name] in proc.stdout, proc.stdout[-3000:]
