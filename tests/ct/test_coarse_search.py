"""The coarse-grid split of large volumes (``blob_search``: a whole head is not relabelled on
the full grid at every threshold) gives the same answers as the full-grid ladder: the metal,
touching-ball and pathological-metal scans are searched here with a coarse grid forced on
(blocks of 2 and 4 voxels, tiny full-grid boxes), against the generator's analytic truth."""

from __future__ import annotations

import numpy as np
import pytest
from ct_test_helpers import patch_params, touching_ball_scan
from scipy.spatial.distance import cdist
from test_fiducials import match

from monotracker.ct import FiducialKit, blob_search, detect_fiducials, load_volume
from monotracker.ct.volume import Volume
from monotracker.paths import sample_ct_path
from monotracker.sim.ct_phantom import DenseBlob, generate_ct, metal_distractors
from monotracker.sim.phantom import default_phantom


@pytest.fixture
def coarse(monkeypatch):
    """Force the coarse grid with blocks of about ``b`` voxels (``blob_search._blocks``: near
    cubic in mm); records the blocks of each coarse pass."""
    calls = []
    real = blob_search.block_max

    def force(b: int, fine_box: int = 30_000):
        monkeypatch.setattr(blob_search, "block_size", lambda shape: b)
        monkeypatch.setattr(blob_search, "FINE_BOX_MAX", fine_box)
        monkeypatch.setattr(blob_search, "block_max", lambda arr, bb: calls.append(bb) or real(arr, bb))
        return calls

    return force


def test_block_max_is_the_maximum_over_blocks():
    rng = np.random.default_rng(3)
    a = rng.integers(-1000, 3000, (9, 10, 11)).astype(np.int16)
    m = blob_search.block_max(a, 4)
    assert m.shape == (3, 3, 3)
    for k in range(3):
        for j in range(3):
            for i in range(3):
                assert m[k, j, i] == a[4 * k:4 * k + 4, 4 * j:4 * j + 4, 4 * i:4 * i + 4].max()


@pytest.mark.parametrize("b", [2, 4])
def test_metal_scan_same_answers_on_the_coarse_grid(coarse, b):
    ph = default_phantom()
    ct = generate_ct(ph, patch_params(ph, spacing_mm=(0.8, 0.8, 1.25), fiducial_hu=1500.0,
                                      distractors=metal_distractors(ph, streak_hu=300.0)))
    calls = coarse(b)
    det = detect_fiducials(Volume.from_image(ct.to_sitk()))
    assert calls and max(calls[0]) >= b  # the coarse grid was used
    err, missed, false = match(det.centres, ct.fiducial_centres_lps)
    assert det.ok and (missed, false) == (0, 0), det.reason
    assert err.max() < 0.1
    metal = np.array([m.centre_lps for m in ct.params.distractors])
    rej = np.array([r.centre_lps for r in det.rejected])
    assert cdist(metal, rej).min(axis=1).max() < 3.0  # every metal object still listed


@pytest.mark.parametrize("b", [2, 4])
def test_touching_balls_separate_on_the_coarse_grid(coarse, b):
    ct, truth = touching_ball_scan()
    coarse(b)
    det = detect_fiducials(Volume.from_image(ct.to_sitk()), kit=FiducialKit(radius_mm=4.0))
    err, missed, false = match(det.centres, truth)
    assert (missed, false) == (0, 0), det.reason
    assert err.max() < 0.15


def test_pathological_metal_bounded_on_the_coarse_grid(coarse):
    ph = default_phantom()
    big = DenseBlob(ph.fiducial_centres_lps.mean(axis=0) - 25.0 * ph.view_direction_lps, np.array([45.0, 40.0, 22.0]),
                    3071.0, name="metal block", streak_hu=1500.0)
    ct = generate_ct(ph, patch_params(ph, spacing_mm=(1.0, 1.0, 1.5), distractors=(big,)))
    coarse(4)
    det = detect_fiducials(Volume.from_image(ct.to_sitk()))
    assert len(det.rejected) < 60
    # the block itself is listed as too large, near where it is
    assert any("too large" in r.reason and np.linalg.norm(r.centre_lps - big.centre_lps) < 15.0 for r in det.rejected), \
        [r.reason for r in det.rejected]


def test_whole_head_sample_uses_the_coarse_grid_and_finds_every_ball(monkeypatch):
    """The bundled whole-head sample is larger than one full-grid box: searched coarse first,
    all balls within 0.1 mm of the truth, the skin clip still listed."""
    calls = []
    real = blob_search.block_max
    monkeypatch.setattr(blob_search, "block_max", lambda arr, b: calls.append(b) or real(arr, b))
    vol = load_volume(sample_ct_path())
    assert vol.array.size > blob_search.FINE_BOX_MAX
    det = detect_fiducials(vol)
    assert calls and max(calls[0]) >= 2
    err, missed, false = match(det.centres, default_phantom().fiducial_centres_lps)
    assert (missed, false) == (0, 0) and err.max() < 0.1
    clip = np.mean(default_phantom().clip_segment_lps, axis=0)
    assert any(np.linalg.norm(r.centre_lps - clip) < 2.0 for r in det.rejected)


@pytest.mark.parametrize("dtype", [np.int16, np.float32])
def test_label_stats_equal_scipy_per_component(dtype):
    """The blob search's one-pass statistics (ct/label_kernels.py) against SciPy's sizes,
    boxes and first densest voxel per component, on a view of a larger array (as a crop)."""
    from scipy import ndimage

    from monotracker.ct.label_kernels import label_stats

    rng = np.random.default_rng(5)
    big = rng.integers(-1000, 3000, (14, 15, 16)).astype(dtype)
    big[3, 4, 5] = big[3, 4, 6] = 2999  # a tie: the first in C order wins
    sub = big[1:13, 2:14, 3:15]
    labels, n = ndimage.label(sub > 2800, structure=np.ones((3, 3, 3), bool))
    assert n > 5
    counts, lo, hi, peak, pos = label_stats(labels, sub, n)
    assert np.array_equal(counts[1:], np.bincount(labels.ravel(), minlength=n + 1)[1:])
    for lab, sl in enumerate(ndimage.find_objects(labels), start=1):
        assert tuple(lo[lab]) == tuple(s.start for s in sl) and tuple(hi[lab]) == tuple(s.stop for s in sl)
        vals = np.where(labels[sl] == lab, sub[sl], -np.inf)
        at = np.unravel_index(int(np.argmax(vals)), vals.shape)
        assert peak[lab] == vals[at]
        assert tuple(pos[lab]) == tuple(s.start + a for s, a in zip(sl, at))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_threshold_label_equals_scipy_label(seed):
    """The blob search's compiled labelling (26-connected union-find) against
    ``ndimage.label``: the same components, numbered the same, with and without a restriction,
    on a view of a larger array; and statistics equal to SciPy's."""
    from scipy import ndimage

    from monotracker.ct.label_kernels import threshold_label

    rng = np.random.default_rng(seed)
    # smoothed noise: blobs of every shape (U-shapes that merge late in the raster scan too)
    big = ndimage.gaussian_filter(rng.normal(0, 1, (30, 34, 38)), 1.5)
    big = (1000 * big / big.std()).astype(np.int16)
    sub = big[2:28, 3:31, 1:37]
    restrict = rng.random(sub.shape) < 0.8
    for T, r in [(600.0, None), (300.0, None), (600.0, restrict), (-5000.0, None)]:
        mask = sub > T if r is None else (sub > T) & r
        ref, n_ref = ndimage.label(mask, structure=np.ones((3, 3, 3), bool))
        labels, n, counts, lo, hi, peak, pos = threshold_label(sub, T, r)
        assert n == n_ref and n > (0 if T < -1000 else 3)
        assert np.array_equal(labels, ref)
        assert np.array_equal(counts[1:], np.bincount(ref.ravel(), minlength=n + 1)[1:])
        for lab, sl in enumerate(ndimage.find_objects(ref), start=1):
            assert tuple(lo[lab]) == tuple(s.start for s in sl) and tuple(hi[lab]) == tuple(s.stop for s in sl)
            assert peak[lab] == sub[tuple(pos[lab])] == sub[sl][ref[sl] == lab].max()


@pytest.mark.parametrize("seed", [3, 4, 5, 6])
def test_threshold_label_runs_equal_scipy_label(seed):
    """The labelling joins runs of voxels along i (ct/label_kernels.py): masks made of runs
    (long, short, one voxel; touching a run of a neighbouring row only corner to corner, one
    voxel past its end; runs at the ends of rows, which must not join the next row) give the
    components, numbering and statistics of ``ndimage.label`` (26-connected) and SciPy's."""
    from scipy import ndimage

    from monotracker.ct.label_kernels import threshold_label

    rng = np.random.default_rng(seed)
    shape = (9, 11, 13)
    mask = np.zeros(shape, bool)
    for k in range(6):  # random runs in slices 0-5, slice 6 empty, hand-made cases in 7-8
        for j in range(shape[1]):
            i = int(rng.integers(0, 4))
            while i < shape[2] and rng.random() < 0.6:
                n = int(rng.choice([1, 1, 2, 3, 6, 13]))
                mask[k, j, i:i + n] = True
                i += n + int(rng.integers(2, 7))
    mask[7, 0, -1] = mask[7, 1, 0] = True  # the end of one row and the start of the next: apart
    mask[7, 4, 2:5] = True
    mask[8, 5, 5:8] = True  # corner to corner, one voxel past the end: joined
    mask[7, 8, 2:5] = True
    mask[8, 9, 6:9] = True  # two voxels past the end: apart
    vals = rng.integers(-500, 3000, shape).astype(np.int16)
    vals[mask] = rng.integers(1000, 1010, int(mask.sum()))  # ties: the first in C order wins
    vals[~mask] = 0
    big = np.zeros((11, 14, 16), np.int16)
    big[1:10, 2:13, 3:16] = vals
    sub = big[1:10, 2:13, 3:16]
    restrict = rng.random(shape) < 0.85
    for r in (None, restrict):
        m = mask if r is None else mask & r
        ref, n_ref = ndimage.label(m, structure=np.ones((3, 3, 3), bool))
        labels, n, counts, lo, hi, peak, pos = threshold_label(sub, 500.0, r)
        assert n == n_ref > 3
        assert np.array_equal(labels, ref)
        assert np.array_equal(counts[1:], np.bincount(ref.ravel(), minlength=n + 1)[1:])
        for lab, sl in enumerate(ndimage.find_objects(ref), start=1):
            assert tuple(lo[lab]) == tuple(s.start for s in sl) and tuple(hi[lab]) == tuple(s.stop for s in sl)
            v = np.where(ref[sl] == lab, sub[sl], -1)
            at = np.unravel_index(int(np.argmax(v)), v.shape)
            assert peak[lab] == v[at] and tuple(pos[lab]) == tuple(s.start + a for s, a in zip(sl, at))
    lab0 = threshold_label(sub, 500.0)[0]
    assert lab0[7, 0, -1] != lab0[7, 1, 0] and lab0[7, 4, 2] == lab0[8, 5, 7] and lab0[7, 8, 4] != lab0[8, 9, 6]


@pytest.mark.parametrize("seed", [0, 1])
def test_threshold_runs_equal_labels(seed):
    """The blob search labels without a label array (label_kernels.threshold_runs): the same
    components and statistics as threshold_label; each component's voxels (from its runs) are
    ``np.argwhere(labels == lab)``; a search one level up restricted to a component's runs in
    its own box equals one restricted to its mask (float32 values too: compared in double)."""
    from scipy import ndimage

    from monotracker.ct.label_kernels import threshold_label, threshold_runs

    rng = np.random.default_rng(seed)
    big = ndimage.gaussian_filter(rng.normal(0, 1, (30, 34, 38)), 1.5)
    for dtype in (np.int16, np.float32):
        big_t = (1000 * big / big.std()).astype(dtype)
        sub = big_t[2:28, 3:31, 1:37]
        for T, r in [(300.0, None), (200.0, rng.random(sub.shape) < 0.8)]:
            labels, n, counts, lo, hi, peak, pos = threshold_label(sub, T, r)
            n2, counts2, lo2, hi2, peak2, pos2, comps = threshold_runs(sub, T, r)
            assert n2 == n > 3
            for a, b in zip((counts, lo, hi, peak, pos), (counts2, lo2, hi2, peak2, pos2)):
                assert np.array_equal(a[1:], b[1:])
            for lab in range(1, n + 1):
                assert np.array_equal(comps.voxels(lab), np.argwhere(labels == lab))
                sl = tuple(slice(int(lo[lab, a]), int(hi[lab, a])) for a in range(3))
                box = sub[sl]
                T2 = T + 0.5 * (float(peak[lab]) - T)
                ref = threshold_label(box, T2, labels[sl] == lab)
                got = threshold_runs(box, T2, comps.runs_in(lab, lo[lab], hi[lab]))
                assert got[0] == ref[1]
                for a, b in zip(ref[2:], got[1:6]):
                    assert np.array_equal(a[1:], b[1:])
                for sub_lab in range(1, ref[1] + 1):
                    assert np.array_equal(got[6].voxels(sub_lab), np.argwhere(ref[0] == sub_lab))


@pytest.mark.parametrize("dtype", [np.int16, np.uint16, np.int32])
def test_compiled_block_max_equals_numpy(dtype):
    """Integer volumes take the compiled block maxima (label_kernels.block_max_int): equal to
    a reshape-and-reduce for blocks that do not divide the shape, on a view as on a copy."""
    from monotracker.ct.label_kernels import block_max_int

    rng = np.random.default_rng(7)
    big = rng.integers(0, 3000, (23, 30, 41)).astype(dtype)
    for a in (big, big[1:, 2:, 3:]):
        for bb in [(3, 5, 5), (1, 2, 7), (4, 4, 4)]:
            pad = [(-s) % b for s, b in zip(a.shape, bb)]
            p = np.pad(a, [(0, x) for x in pad], constant_values=np.iinfo(dtype).min)
            s = p.shape
            ref = p.reshape(s[0] // bb[0], bb[0], s[1] // bb[1], bb[1], s[2] // bb[2], bb[2]).max(axis=(1, 3, 5))
            assert np.array_equal(block_max_int(a, bb), ref)
            assert np.array_equal(blob_search.block_max(a, bb), ref)


@pytest.mark.parametrize("dtype", [np.int16, np.uint16, np.int32, np.float32])
def test_sample_histogram_equals_numpy(dtype):
    """The grey levels' histogram of a strided sample (ct/levels.py, compiled for integer
    scans): NumPy's bincount of the clipped values and the sample's minimum, values beyond
    -1024..4095 HU included."""
    from monotracker.ct.levels import sample_histogram, soft_tissue_levels

    rng = np.random.default_rng(11)
    lo = 0 if dtype == np.uint16 else -3000
    big = rng.integers(lo, 6000, (20, 22, 24)).astype(dtype)
    big[3, 4, 5] = lo  # the minimum, inside the sample
    sample = big[1::2, ::2, 1::2]
    hist, smin = sample_histogram(sample)
    ref = np.bincount(np.clip(sample.astype(np.int32), -1024, 4095).ravel() + 1024, minlength=5120)
    assert hist.dtype == float and np.array_equal(hist, ref) and hist.sum() == sample.size
    assert smin == float(sample.min()) == float(lo)
    assert soft_tissue_levels(sample) == soft_tissue_levels(sample, hist)
