"""The edges of the scan (issue 32): a resampled DICOM series keeps every acquired voxel (balls
at the corners and edges of tilted, sheared and unevenly spaced series come out within 0.1 mm,
the grid holds every slice's corner pixels, in the smaller of the orientations, and the note
says the largest correction), and a ball cut by the field of view, the first or last slice or
missing slices is refused with "cut by the edge of the scan", never given a biased centre.

Truth is geometric and independent of the loader: the balls are written at known LPS positions
by ``sim.dicom_writer`` (every pixel at its true place) or by ``sim.ct_phantom``."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.distance import cdist

from monotracker.ct import FiducialKit, detect_fiducials, load_volume
from monotracker.ct.volume import Volume
from monotracker.geometry import rotation_about_axis
from monotracker.sim.ct_phantom import ball_grid_array, generate_ct, patch_scan_params
from monotracker.sim.dicom_writer import (
    SliceSpec,
    acquisition_solid,
    ball_field,
    pixel_points,
    points_inset,
    specs_along,
    write_series,
)
from monotracker.sim.phantom import default_phantom

R = 3.0  # ball radius, mm
BALL_HU, TISSUE_HU = 2500.0, 20.0
ROWS, COLS, PS = 64, 56, (0.8, 0.7)


def _ball_field(centres, air_centre):
    """HU at LPS points: soft tissue with a pocket of air and blurred balls (edge sigma 0.5 mm)."""
    return ball_field(centres, R, air_centre, BALL_HU, TISSUE_HU, edge_sigma_mm=0.5)


def _series(iop_rot: np.ndarray, steps: np.ndarray) -> list[SliceSpec]:
    return specs_along(iop_rot, steps)


def _acquisition_edges(specs):
    return acquisition_solid(specs, ROWS, COLS, PS)


def _inset_points(specs, inset_mm, where="corners"):
    return points_inset(specs, inset_mm, ROWS, COLS, PS, where)


t15 = np.radians(15.0)
X = np.array([1.0, 0.0, 0.0])


def _uneven(n1=12, n2=14, g1=1.0, g2=1.25):
    return np.r_[np.full(n1, g1), np.full(n2, g2)]


SERIES = {
    # gantry tilt in the IOP encoding: tilted slices, positions along the table (S)
    "tilted IOP, uneven spacing": lambda: _series(rotation_about_axis(X, t15), _uneven()[:, None] * [0, 0, 1.0]),
    # gantry tilt in the position encoding: axial slices, positions sheared along P
    "sheared positions, uneven spacing": lambda: _series(np.eye(3), _uneven()[:, None] * [0, np.tan(t15), 1.0]),
    "tilted IOP 25 deg about P": lambda: _series(rotation_about_axis(np.array([0, 1.0, 0]), np.radians(25.0)),
                                                 np.full((30, 3), [0, 0, 1.1])),
    # (the gap away from the balls: one across it is refused, see test_a_ball_across_missing_slices_is_refused)
    "sheared both ways, 1 missing slice": lambda: _series(np.eye(3), np.r_[np.full(10, 1.0), [2.0], np.full(29, 1.0)][:, None]
                                                          * [np.tan(np.radians(8.0)), np.tan(t15), 1.0]),
}


def _all_corner_pixels(specs):
    return np.concatenate([pixel_points(s, ROWS, COLS, PS)[[0, 0, -1, -1], [0, -1, 0, -1]] for s in specs])


@pytest.mark.parametrize("name", list(SERIES))
def test_balls_at_the_corners_and_edges_of_a_resampled_series_are_within_0_1_mm(tmp_path, name):
    specs = SERIES[name]()
    balls = np.vstack([_inset_points(specs, R + 0.9), _inset_points(specs, R + 0.9, "edges")])
    o, E = _acquisition_edges(specs)
    write_series(tmp_path / "s", specs, _ball_field(balls, o + E @ [0.5, 0.5, 0.5]), ROWS, COLS, PS)
    vol = load_volume(tmp_path / "s")
    det = detect_fiducials(vol, kit=FiducialKit(radius_mm=R))
    D = cdist(balls, det.centres) if len(det.centres) else np.full((len(balls), 1), np.inf)
    assert D.min(axis=1).max() < 0.1, (D.min(axis=1).round(3), [r.reason for r in det.rejected])
    assert len(det.centres) == len(balls)
    # the grid holds every acquired voxel centre (the corner pixels of every slice bound them)
    idx = vol.lps_to_index(_all_corner_pixels(specs))
    assert idx.min() > -1e-2 and np.all(idx.max(axis=0) < np.array(vol.size_ijk) - 1 + 1e-2), (idx.min(axis=0), idx.max(axis=0))
    # the note names the largest correction: where a plain stack (first position, slices along
    # the normal at their mean gap) puts the slices' corner pixels against where they were
    row, col = specs[0].iop[:3], specs[0].iop[3:]
    nrm = np.cross(row, col)
    d = np.array([s.ipp @ nrm for s in specs])
    order = np.argsort(d)
    step = (d[order[-1]] - d[order[0]]) / (len(specs) - 1)
    plain = specs[order[0]].ipp + np.outer(np.arange(len(specs)) * step, nrm)
    truth = max(np.linalg.norm(specs[i].ipp - plain[k]) for k, i in enumerate(order))
    note = next((n for n in vol.notes if "largest geometric correction" in n), "")
    m = re.search(r"largest geometric correction ([0-9.]+) mm", note)
    assert m and abs(float(m.group(1)) - truth) < 0.01, (vol.notes, truth)


def test_resampled_grid_takes_the_smaller_orientation(tmp_path):
    # a long tilted stack of narrow slices: the box along the table axis is far smaller than
    # the one along the slice normal (which must hold the whole drift of the slices)
    specs = _series(rotation_about_axis(X, np.radians(20.0)), np.full((119, 3), [0, 0, 1.0]))
    balls = _inset_points(specs, R + 0.9)
    o, E = _acquisition_edges(specs)
    write_series(tmp_path / "s", specs, _ball_field(balls, o + E @ [0.5, 0.5, 0.5]), ROWS, COLS, PS)
    vol = load_volume(tmp_path / "s")
    corners = _all_corner_pixels(specs)
    row, col = specs[0].iop[:3], specs[0].iop[3:]
    F = np.column_stack([row, col, np.cross(row, col)])
    q = corners @ F
    slice_box = np.prod((q.max(axis=0) - q.min(axis=0)) / np.array([PS[1], PS[0], 1.0 * np.cos(np.radians(20.0))]) + 1)
    assert np.prod(vol.size_ijk) < 0.75 * slice_box, (vol.size_ijk, slice_box)
    assert any("table axis" in n for n in vol.notes), vol.notes
    det = detect_fiducials(vol, kit=FiducialKit(radius_mm=R))
    assert cdist(balls, det.centres).min(axis=1).max() < 0.1


# ------------------------------------------------------------------ balls cut by the scan's edge
def _cut(det, centre, tol=2.0):
    """The rejection of the ball at ``centre`` (LPS mm), or None."""
    near = [r for r in det.rejected if np.linalg.norm(r.centre_lps - centre) < R + tol]
    return near[0] if near else None


def _grid_volume(centres, shape=(40, 60, 60), sp=(0.5, 0.5, 1.0), noise=15.0):
    """A plain grid (identity direction, origin 0) of tissue with air on one side, bone slab,
    and balls at ``centres``; shape (k, j, i), spacing (i, j, k) mm."""
    img = sitk.GetImageFromArray(ball_grid_array(centres, R, shape, sp, BALL_HU, TISSUE_HU, noise))
    img.SetSpacing(tuple(float(x) for x in sp))
    return Volume.from_image(img)


@pytest.mark.parametrize("where", ["first slice", "last slice", "field of view"])
def test_a_ball_cut_by_the_grid_is_refused(where):
    inside = np.array([14.0, 13.0, 20.0])
    cut = {"first slice": [14.0, 13.0, 1.5], "last slice": [14.0, 13.0, 38.0], "field of view": [28.5, 13.0, 20.0]}[where]
    vol = _grid_volume([inside, np.array(cut)])
    det = detect_fiducials(vol, kit=FiducialKit(radius_mm=R))
    assert len(det.centres) == 1 and np.linalg.norm(det.centres[0] - inside) < 0.1, (det.reason, det.centres)
    rej = _cut(det, np.array(cut))
    assert rej is not None and "cut by the edge of the scan" in rej.reason, [r.reason for r in det.rejected]


def test_balls_cut_by_the_reconstruction_circle_are_refused_the_rest_found():
    ph = default_phantom()
    p0 = patch_scan_params(ph, margin_mm=8.0, fov_circle=True)
    # the grid moved 20 mm along its j axis: the reconstruction circle now cuts two balls
    params = replace(p0, grid_centre_lps=np.asarray(p0.grid_centre_lps) + np.asarray(p0.direction) @ [0.0, 20.0, 0.0])
    ct = generate_ct(ph, params)
    vol = Volume.from_image(ct.to_sitk())
    truth = ct.fiducial_centres_lps
    R4 = ph.fiducial_radius_mm
    # from the geometry alone (generator: voxels farther than max(ni wi, nj wj) / 2 from the
    # grid's in-plane centre are padded with -1024): how far each ball is inside the circle
    # and inside the grid's box
    size = np.array(ct.array.shape[::-1])
    sp = ct.spacing_mm
    rel = (truth - ct.origin_mm) @ ct.direction  # grid-frame mm
    rc = max(size[0] * sp[0], size[1] * sp[1]) / 2.0
    circle = rc - np.hypot(rel[:, 0] - (size[0] - 1) / 2.0 * sp[0], rel[:, 1] - (size[1] - 1) / 2.0 * sp[1]) - R4
    box = np.min(np.column_stack([rel, (size - 1) * sp - rel]), axis=1) - R4
    cut = (circle < -1.0) & (box > 1.0)
    clear = (circle > 1.5) & (box > 1.5)
    assert cut.sum() >= 2 and clear.sum() >= 4, (circle.round(1), box.round(1))
    det = detect_fiducials(vol, kit=FiducialKit(radius_mm=R4))
    D = cdist(truth, det.centres) if len(det.centres) else np.full((len(truth), 1), np.inf)
    assert D[clear].min(axis=1).max() < 0.1, D.min(axis=1).round(3)
    assert np.all(D[~clear].min(axis=1) > 1.0), "a ball the scan cuts was given a centre"
    for c in truth[cut]:
        rej = _cut(det, c, tol=4.0)
        assert rej is not None and "cut by the edge of the scan" in rej.reason, [r.reason for r in det.rejected]


def test_a_ball_outside_the_slanted_face_of_a_tilted_series_is_refused(tmp_path):
    specs = _series(rotation_about_axis(X, np.radians(20.0)), np.full((39, 3), [0, 0, 1.0]))
    o, E = _acquisition_edges(specs)
    inside = _inset_points(specs, R + 1.0)[[0, 3]]
    # a ball centred on the slanted face (the column edge of the slices, swept along the table):
    # half of it lies outside every slice, where the resampled grid holds no data
    face = o + E @ np.array([0.5, 1.0, 0.5])
    write_series(tmp_path / "s", specs, _ball_field(np.vstack([inside, face]), o + E @ [0.5, 0.5, 0.5]), ROWS, COLS, PS)
    vol = load_volume(tmp_path / "s")
    det = detect_fiducials(vol, kit=FiducialKit(radius_mm=R))
    assert cdist(inside, det.centres).min(axis=1).max() < 0.1
    assert cdist([face], det.centres).min() > 1.0 if len(det.centres) else True
    rej = _cut(det, face, tol=3.0)
    assert rej is not None and "cut by the edge of the scan" in rej.reason, [r.reason for r in det.rejected]


def test_a_ball_across_missing_slices_is_refused(tmp_path):
    steps = np.r_[np.full(14, 1.0), [3.0], np.full(14, 1.0)][:, None] * [0, 0, 1.0]  # 2 slices missing
    specs = _series(np.eye(3), steps)
    o, E = _acquisition_edges(specs)
    z_gap = 14.0 + 1.5  # the middle of the gap, mm
    across = np.array([o[0] + 20.0, o[1] + 20.0, z_gap])
    clear = np.array([o[0] + 20.0, o[1] + 32.0, 5.0])
    write_series(tmp_path / "s", specs, _ball_field([across, clear], o + E @ [0.8, 0.8, 0.5]), ROWS, COLS, PS)
    vol = load_volume(tmp_path / "s")
    assert any("2 missing slice" in n for n in vol.notes), vol.notes
    det = detect_fiducials(vol, kit=FiducialKit(radius_mm=R))
    assert len(det.centres) == 1 and np.linalg.norm(det.centres[0] - clear) < 0.1, (det.reason, det.centres)
    rej = _cut(det, across)
    assert rej is not None and "cut by the edge of the scan" in rej.reason and "missing" in rej.reason, \
        [r.reason for r in det.rejected]


@pytest.mark.parametrize("shear", [0.0, 0.3])
def test_the_edge_check_reads_every_voxel_within_reach_of_the_ball(shear):
    """The edge check before a blob's fit (issue 32 item 3: refuse cheaply before building the
    fit window) looks at the voxels of a small box around the ball only: that box must hold
    every voxel of the window within reach of the ball, on an oblique and on a sheared grid
    (truth: brute force over the whole window)."""
    from monotracker.ct.fiducials import _ball_box, _box_points

    rng = np.random.default_rng(5)
    D = rotation_about_axis(np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]), 0.7)
    D = D @ np.array([[1.0, 0.0, 0.0], [0.0, 1.0, shear], [0.0, 0.0, 1.0]])
    img = sitk.GetImageFromArray(rng.integers(-1000, 2000, (30, 40, 50)).astype(np.int16))
    img.SetSpacing((0.6, 0.7, 1.3))
    img.SetDirection(tuple(D.ravel()))
    img.SetOrigin((10.0, -20.0, 5.0))
    vol = Volume.from_image(img)
    lo, hi = np.array([2, 3, 4]), np.array([28, 37, 45])
    all_pts, all_vals = _box_points(vol, lo, hi)
    for _ in range(20):
        c = vol.zyx_to_lps(rng.uniform(lo, hi - 1)[None])[0]
        reach = float(rng.uniform(0.5, 6.0))
        truth = np.linalg.norm(all_pts - c, axis=1) <= reach
        blo, bhi = _ball_box(vol, c, reach, lo, hi)
        assert np.all(blo >= lo) and np.all(bhi <= hi)
        pts, vals = _box_points(vol, blo, bhi)
        near = np.linalg.norm(pts - c, axis=1) <= reach
        assert near.sum() == truth.sum()
        assert sorted(vals[near].tolist()) == sorted(all_vals[truth].tolist())
