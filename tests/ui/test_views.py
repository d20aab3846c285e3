"""Pure view helpers: slices, overlay projection, frame codes, CLI guards."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from monotracker.errors import InputError


def test_slices_show_fiducials_where_the_phantom_has_them():
    from monotracker.ct import load_volume
    from monotracker.paths import sample_ct_path
    from monotracker.sim.phantom import default_phantom
    from monotracker.ui.slices import PLANES, render_slice, sample_slice, slice_geometry

    vol = load_volume(sample_ct_path())
    c = default_phantom().fiducial_centres_lps[0]
    for plane in PLANES:
        g = slice_geometry(vol, plane, c)
        hu = sample_slice(vol, g)
        col, row = np.round(g.to_pixel(c)[0]).astype(int)
        assert hu[row, col] > 2000, plane  # the ceramic ball (3000 HU) at its true centre
        assert np.allclose(g.to_lps(*g.to_pixel(c)[0]), c, atol=1e-9)
        img, _ = render_slice(vol, plane, c)
        assert img.dtype == np.uint8 and img.ndim == 3


def test_project_points_matches_pinhole_and_hides_points_behind():
    from monotracker.ui.overlay import project_points

    K = np.array([[1000.0, 0, 640], [0, 1000.0, 360], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [10.0, -5.0, 400.0]
    p = np.array([[0.0, 0.0, 0.0], [20.0, 10.0, 50.0], [0.0, 0.0, -500.0]])
    uv = project_points(p, T, K)
    q = p + T[:3, 3]
    expect = q[:2, :2] / q[:2, 2:3] * 1000.0 + [640, 360]
    assert np.allclose(uv[:2], expect, atol=1e-6)
    assert np.all(np.isnan(uv[2]))


@pytest.mark.parametrize("index", [0, 1, 77, 123456, 2**20 - 1])
def test_frame_code_survives_jpeg(index):
    from monotracker.ui.overlay import frame_code_strip, read_frame_code

    img = np.full((720, 1280, 3), 128, np.uint8)
    strip = frame_code_strip(index)
    img[-strip.shape[0]:, :strip.shape[1]] = strip
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 60])
    back = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    assert read_frame_code(back[-strip.shape[0]:, :strip.shape[1]]) == index


def test_serve_refuses_network_host_without_flag_and_bad_pin():
    from monotracker.ui.commands import check_host, resolve_pin

    check_host("127.0.0.1", False)
    check_host("0.0.0.0", True)
    with pytest.raises(InputError, match="allow-remote"):
        check_host("0.0.0.0", False)
    with pytest.raises(InputError, match="4 digits"):
        resolve_pin("12")
    assert resolve_pin("2468") == ("2468", False)
    pin, generated = resolve_pin(None) if __import__("os").environ.get("MONOTRACKER_PIN") is None else ("000000", True)
    assert generated and len(pin) == 6 and pin.isdigit()


def test_serve_cli_bad_input_is_one_line(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    r = subprocess.run([sys.executable, "-m", "monotracker", "serve", "--host", "0.0.0.0"], cwd=root,
                       env={"PYTHONPATH": str(root / "app"), "MONOTRACKER_HOME": str(tmp_path), "PATH": "/usr/bin:/bin"},
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().startswith("error:") and "Traceback" not in r.stderr


def test_overlay_draws_for_both_estimate_kinds_and_flags_hidden_fiducials():
    """The overlay is drawn from vision's PoseEstimate (arrays) and the engine's PoseSample
    (dicts); a hidden fiducial gets a red ring at its reprojected place, the banner says why."""
    from types import SimpleNamespace as NS

    from monotracker.ui.overlay import RED, draw_overlay, project_points

    K = np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0, 0, 400.0]
    centres = np.array([[0.0, 0, 0], [40, 0, 0], [0, 40, 0], [-40, -20, 0]])
    fids = tuple(NS(id=i, centre_lps_mm=c, radius_mm=4.0, status="confirmed") for i, c in enumerate(centres))
    status = {0: "seen", 1: "seen", 2: "seen", 3: "occluded"}
    pose = NS(trusted=False, reason="only 3 fiducials", T_cam_ct=T, fiducial_status=status,
              residuals_px={0: 0.1, 1: 0.2, 2: 0.3}, fre_mm=0.1, predicted_tre_mm=0.5)
    snap = NS(pose=pose, camera=NS(K=K, dist=None), fiducials=fids,
              plan=NS(entry_lps_mm=None, target_lps_mm=None))
    uv = project_points(centres, T, K)
    img = np.zeros((720, 1280, 3), np.uint8)
    est_arrays = NS(T_cam_ct=T, status=list(status.values()), image_points_px=uv,
                    residuals_px=np.array([0.1, 0.2, 0.3, np.nan]))
    est_dicts = NS(T_cam_ct=T, fiducial_status=status, residuals_px=pose.residuals_px)
    for est in (est_arrays, est_dicts, None):
        out = draw_overlay(img, est, snap)
        u, v = np.round(uv[3]).astype(int)
        ring = out[v - 16:v + 17, u - 16:u + 17].reshape(-1, 3)
        assert np.any(np.all(ring == RED, axis=1))  # red ring around the hidden fiducial
        assert out[5:35, :].reshape(-1, 3)[:, 2].mean() > 100  # red-ish banner: pose not valid
