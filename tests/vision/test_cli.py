"""vision CLI: simulate-camera, detect-image (against the written truth), clear errors."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

APP = str(Path(__file__).resolve().parents[2] / "app")


def _run(args, tmp_path):
    env = dict(os.environ, PYTHONPATH=APP, MONOTRACKER_HOME=str(tmp_path))
    return subprocess.run([sys.executable, "-m", "monotracker", *args], capture_output=True, text=True,
                          cwd=tmp_path, env=env)


def test_simulate_then_detect(tmp_path):
    r = _run(["simulate-camera", "--out", "sim", "--frames", "2", "--trajectory", "breathing"], tmp_path)
    assert r.returncode == 0, r.stderr
    truth = json.loads((tmp_path / "sim" / "truth.json").read_text())
    assert len(truth) == 2 and (tmp_path / "sim" / "camera.yml").is_file()
    r = _run(["detect-image", "sim/frame_00001.png", "--camera", "sim/camera.yml", "--json",
              "--annotate", "ann.png"], tmp_path)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    c = np.array([f["centre_px"] for f in out["fiducials"]])
    t = np.array(truth[1]["ellipse_centres_px"])
    assert len(c) == 9
    assert np.linalg.norm(c[:, None] - t[None], axis=2).min(1).max() < 0.3
    assert (tmp_path / "ann.png").is_file()


def test_detect_image_errors(tmp_path):
    r = _run(["detect-image", "missing.png"], tmp_path)
    assert r.returncode == 2 and "not found" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    (tmp_path / "bad.png").write_bytes(b"garbage")
    r = _run(["detect-image", "bad.png"], tmp_path)
    assert r.returncode == 2 and "cannot read image" in r.stderr
    (tmp_path / "cam.json").write_text("{}")
    import cv2
    cv2.imwrite(str(tmp_path / "ok.png"), np.zeros((20, 20, 3), np.uint8))
    r = _run(["detect-image", "ok.png", "--camera", "cam.json"], tmp_path)
    assert r.returncode == 2 and "lacks camera_matrix" in r.stderr
