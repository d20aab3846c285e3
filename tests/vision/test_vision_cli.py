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
    # the same frame with the learned centre refiner (opt-in, issue 28): the same 9 balls, still
    # within 0.35 px of the truth on our sharp render
    r = _run(["detect-image", "sim/frame_00001.png", "--camera", "sim/camera.yml", "--json", "--detector", "refined"],
             tmp_path)
    assert r.returncode == 0, r.stderr
    assert "not for clinical use" in r.stderr
    c = np.array([f["centre_px"] for f in json.loads(r.stdout)["fiducials"]])
    assert len(c) == 9
    assert np.linalg.norm(c[:, None] - t[None], axis=2).min(1).max() < 0.35


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


def test_detect_image_refuses_grayscale_and_absurd_calibrations(tmp_path):
    """A grayscale picture and a calibration with fx = 1e9 / image_width = inf each give one line
    saying what is wrong (before: "0 fiducials" for the grey picture, an OverflowError traceback
    for the infinite width)."""
    import cv2

    from monotracker.sim.camera_sim import SimulatedCamera

    img, _ = SimulatedCamera(seed=1).render(0.0)
    cv2.imwrite(str(tmp_path / "grey.png"), cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    r = _run(["detect-image", "grey.png"], tmp_path)
    assert r.returncode == 2 and "grayscale" in r.stderr and "colour camera" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    cv2.imwrite(str(tmp_path / "colour.png"), img)
    good = {"camera_matrix": [[1100, 0, 641.3], [0, 1100, 358.2], [0, 0, 1]],
            "distortion_coefficients": [-0.12, 0.09, 0.0004, -0.0003, 0.0], "image_width": 1280, "image_height": 720}
    for change, needle in (({"image_width": float("inf")}, "image_width is inf"),
                           ({"camera_matrix": [[1e9, 0, 640], [0, 1e9, 360], [0, 0, 1]]}, "field of view")):
        (tmp_path / "cam.json").write_text(json.dumps({**good, **change}))
        r = _run(["detect-image", "colour.png", "--camera", "cam.json"], tmp_path)
        assert r.returncode == 2 and needle in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


def test_choosing_the_learned_detector_says_it_is_not_for_clinical_use(tmp_path):
    """issue 28 item 4: the learned detector was trained on the simple render only and gave trusted
    poses over 2 mm off on physically rendered frames: where it is chosen, one line says it is not for
    clinical use; the classical default says nothing of the kind."""
    import cv2

    from monotracker.sim.camera_sim import SimulatedCamera

    img, _ = SimulatedCamera(seed=1).render(0.0)
    cv2.imwrite(str(tmp_path / "f.png"), img)
    r = _run(["detect-image", "f.png", "--detector", "learned"], tmp_path)
    assert r.returncode == 0, r.stderr
    warn = [ln for ln in r.stderr.splitlines() if "not for clinical use" in ln]
    assert len(warn) == 1 and warn[0].startswith("WARNING:") and "classical" in warn[0]
    r = _run(["detect-image", "f.png"], tmp_path)
    assert r.returncode == 0 and "clinical" not in r.stderr
