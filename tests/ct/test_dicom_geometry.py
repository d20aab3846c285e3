"""DICOM geometry from every slice's own position: series written with pydicom the way scanners
write them (true per-pixel LPS positions known), checked at known points within 0.1 mm after
loading, or refused with a one-line InputError naming the problem."""

from __future__ import annotations

import itertools

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk

from monotracker.ct import list_series, load_volume
from monotracker.ct.volume import Volume
from monotracker.errors import InputError
from monotracker.sim.dicom_writer import (
    known_point_errors,
    stack_specs,
    tilted_iop,
    write_enhanced,
    write_series,
)

ROWS = COLS = 32
PS = (1.0, 1.0)
_count = itertools.count()


def _errors(tmp_path, specs, points, loader=load_volume):
    def write(field):
        folder = tmp_path / f"s{len(list(tmp_path.glob('s*')))}"
        write_series(folder, specs, field, ROWS, COLS, PS)
        return folder

    return known_point_errors(write, loader, specs, points, ROWS, COLS, PS)


def _inner_points(z_lo, z_hi, y_shift=0.0, n=40, seed=0):
    """Points well inside every slice's footprint (x, y in 6..25 mm + shift), z inside the stack."""
    rng = np.random.default_rng(seed)
    p = rng.uniform([6, 6, z_lo], [25, 25, z_hi], size=(n, 3))
    p[:, 1] += y_shift * (p[:, 2] - 0.0)
    return p


def _plain_sitk(folder):
    r = sitk.ImageSeriesReader()
    r.SetFileNames(r.GetGDCMSeriesFileNames(str(folder)))
    return Volume.from_image(r.Execute())


def test_regular_series_is_exact_and_matches_simpletk(tmp_path):
    specs = stack_specs(np.arange(20) * 1.5, origin=(0.0, 0.0, -10.0))
    pts = _inner_points(-8, 16)
    ours = _errors(tmp_path, specs, pts)
    assert np.abs(ours).max() < 0.05
    vol = load_volume(tmp_path / "s0")
    assert not any("resampled" in n for n in vol.notes)
    assert np.allclose(vol.spacing_mm, [1.0, 1.0, 1.5])
    ref = _plain_sitk(tmp_path / "s0")
    assert np.array_equal(vol.array, ref.array)
    assert np.allclose(vol.origin_mm, ref.origin_mm, atol=1e-4)


@pytest.mark.parametrize("encoding", ["sheared", "tilted_iop"])
def test_gantry_tilt_is_resampled_right_in_both_encodings(tmp_path, encoding):
    tilt = 15.0
    z = np.arange(16) * 2.0
    if encoding == "sheared":
        specs = stack_specs(z, shear_y_per_mm=np.tan(np.radians(tilt)))
        pts = _inner_points(1, 29, y_shift=np.tan(np.radians(tilt)))
    else:
        specs = stack_specs(z, iop=tilted_iop(tilt))
        # tilted planes: pixel (c, r) at (c, r cos t, z + r sin t); keep points inside all
        rng = np.random.default_rng(1)
        r = rng.uniform(6, 25, 40)
        p = np.column_stack([rng.uniform(6, 25, 40), r * np.cos(np.radians(tilt)), rng.uniform(2, 28, 40) + r * np.sin(np.radians(tilt))])
        pts = p
    err = _errors(tmp_path, specs, pts)
    assert np.linalg.norm(err, axis=1).max() < 0.1, np.linalg.norm(err, axis=1).max()
    vol = load_volume(tmp_path / "s0")
    assert any("gantry tilt 15.0 deg" in n for n in vol.notes), vol.notes
    # the plain series reader is what the fix is for: it is off by millimetres here
    plain = known_point_errors(lambda f: _write_to(tmp_path, specs, f), _plain_sitk, specs, pts, ROWS, COLS, PS)
    assert np.linalg.norm(plain, axis=1).max() > 2.0


def _write_to(tmp_path, specs, field):
    folder = tmp_path / f"p{next(_count)}"
    write_series(folder, specs, field, ROWS, COLS, PS)
    return folder


def test_uneven_spacing_is_resampled_with_a_note(tmp_path):
    z = np.r_[np.arange(10) * 1.25, 11.25 + np.arange(1, 9) * 2.5]
    specs = stack_specs(z)
    err = _errors(tmp_path, specs, _inner_points(0.5, 30))
    assert np.linalg.norm(err, axis=1).max() < 0.1
    vol = load_volume(tmp_path / "s0")
    assert any("uneven slice spacing" in n for n in vol.notes), vol.notes
    assert vol.spacing_mm[2] == pytest.approx(1.25)


@pytest.mark.parametrize("missing", [1, 2])
def test_a_few_missing_slices_are_interpolated_with_a_note(tmp_path, missing):
    z = np.arange(24) * 1.0
    z = np.r_[z[:10], z[10 + missing:]]
    err = _errors(tmp_path, stack_specs(z), _inner_points(0.5, 22))
    assert np.linalg.norm(err, axis=1).max() < 0.1
    vol = load_volume(tmp_path / "s0")
    assert any(f"{missing} missing slice" in n for n in vol.notes), vol.notes
    assert vol.array.shape[0] == 24


@pytest.mark.parametrize("missing", [3, 5])
def test_many_missing_slices_are_refused(tmp_path, missing):
    z = np.arange(24) * 1.0
    z = np.r_[z[:10], z[10 + missing:]]
    write_series(tmp_path / "s", stack_specs(z), lambda p: -1000 + 40 * p[:, 2], ROWS, COLS, PS)
    with pytest.raises(InputError, match=f"about {missing} slices missing between 9.0 and {10 + missing}.0 mm"):
        load_volume(tmp_path / "s")


def test_reversed_instance_numbers_and_file_order_do_not_matter(tmp_path):
    specs = stack_specs(np.arange(12) * 2.0)
    for k, s in enumerate(specs):
        s.instance = len(specs) - k
    err = _errors(tmp_path, specs, _inner_points(1, 21))
    assert np.linalg.norm(err, axis=1).max() < 0.05


def test_enhanced_multiframe_ct_loads_with_its_per_frame_geometry(tmp_path):
    specs = stack_specs(np.arange(14) * 1.5, shear_y_per_mm=np.tan(np.radians(10.0)))
    pts = _inner_points(1, 18, y_shift=np.tan(np.radians(10.0)))

    def write(field):
        return write_enhanced(tmp_path / f"mf{next(_count)}.dcm", specs, field, ROWS, COLS, PS)

    err = known_point_errors(write, load_volume, specs, pts, ROWS, COLS, PS)
    assert np.linalg.norm(err, axis=1).max() < 0.1


def _field(p):
    return -1000 + 60 * p[:, 0] + 20 * p[:, 2]


def test_mixed_orientations_are_refused(tmp_path):
    specs = stack_specs(np.arange(10) * 2.0)
    specs[4].iop = tilted_iop(20.0)
    write_series(tmp_path / "s", specs, _field, ROWS, COLS, PS)
    with pytest.raises(InputError, match="mixes slice orientations"):
        load_volume(tmp_path / "s")


def test_duplicate_position_with_other_content_is_refused_same_content_ignored(tmp_path):
    specs = stack_specs(np.r_[np.arange(10) * 2.0, 8.0])
    write_series(tmp_path / "same", specs, _field, ROWS, COLS, PS)
    vol = load_volume(tmp_path / "same")
    assert vol.array.shape[0] == 10 and any("duplicate slice" in n for n in vol.notes)
    paths = write_series(tmp_path / "diff", specs, _field, ROWS, COLS, PS)
    ds = pydicom.dcmread(paths[-1])
    ds.PixelData = (ds.pixel_array + 50).astype("<i2").tobytes()
    ds.save_as(paths[-1])
    with pytest.raises(InputError, match="two slices at the same position"):
        load_volume(tmp_path / "diff")


def test_interleaved_acquisitions_under_one_uid_are_refused(tmp_path):
    z = np.arange(20) * 0.83
    specs = stack_specs(z)
    for k, s in enumerate(specs):
        s.acquisition = 1 + k % 2
    write_series(tmp_path / "s", specs, _field, ROWS, COLS, PS)
    with pytest.raises(InputError, match="2 acquisitions"):
        load_volume(tmp_path / "s")


def test_sequential_acquisitions_in_blocks_are_one_volume(tmp_path):
    specs = stack_specs(np.arange(16) * 1.0)
    for k, s in enumerate(specs):
        s.acquisition = 1 + k // 4  # step-and-shoot: one acquisition per table position
    write_series(tmp_path / "s", specs, _field, ROWS, COLS, PS)
    assert load_volume(tmp_path / "s").array.shape[0] == 16


@pytest.mark.parametrize("damage", ["truncated", "garbage"])
def test_a_corrupt_slice_is_refused_never_dropped(tmp_path, damage):
    paths = write_series(tmp_path / "s", stack_specs(np.arange(12) * 1.0), _field, ROWS, COLS, PS)
    raw = paths[5].read_bytes()
    paths[5].write_bytes(raw[: len(raw) - 700] if damage == "truncated" else raw[:128] + b"DICM" + b"\x07" * 50)
    with pytest.raises(InputError, match=paths[5].name):
        load_volume(tmp_path / "s")


def test_unreadable_folder_gives_a_clear_line(tmp_path, monkeypatch):
    import os
    from pathlib import Path

    write_series(tmp_path / "s", stack_specs(np.arange(6) * 1.0), _field, ROWS, COLS, PS)
    os.chmod(tmp_path / "s", 0)
    try:
        if os.access(tmp_path / "s", os.R_OK):  # root ignores modes: make the OS refusal happen anyway
            def refuse(self):
                raise PermissionError(13, "Permission denied", str(self))

            monkeypatch.setattr(Path, "iterdir", refuse)
        with pytest.raises(InputError, match="permission denied"):
            load_volume(tmp_path / "s")
    finally:
        os.chmod(tmp_path / "s", 0o755)


def test_list_series_and_pick_one(tmp_path):
    folder = tmp_path / "two"
    write_series(folder, stack_specs(np.arange(12) * 2.0), _field, ROWS, COLS, PS, series_uid="1.2.3.1", description="head")
    write_series(folder, stack_specs(np.arange(8) * 1.0, shear_y_per_mm=np.tan(np.radians(12.0))), _field, ROWS, COLS, PS,
                 series_uid="1.2.3.2", description="tilted")
    infos = list_series(folder)
    assert [i.uid for i in infos] == ["1.2.3.1", "1.2.3.2"]
    assert infos[0].slices == 12 and infos[0].description == "head" and infos[0].spacing_mm[2] == pytest.approx(2.0)
    assert infos[1].tilt_deg == pytest.approx(12.0, abs=0.01) and infos[1].ok
    assert load_volume(folder, series="1.2.3.2").array.shape[0] == 8
    with pytest.raises(InputError, match="1.2.3.9 is not in"):
        load_volume(folder, series="1.2.3.9")


def test_nan_anywhere_in_a_float_volume_is_refused(tmp_path):
    a = np.full((40, 30, 30), -1000.0, np.float32)
    a[10:20, 10:20, 10:20] = 1500.0
    a[39, 29, 29] = np.nan  # one voxel, on a slice a sample would skip
    for ext in ("nii.gz", "nrrd", "mha"):
        p = tmp_path / f"v.{ext}"
        sitk.WriteImage(sitk.GetImageFromArray(a), str(p))
        with pytest.raises(InputError, match="1 NaN or infinite voxels"):
            load_volume(p)
    a[39, 29, 29] = np.inf
    sitk.WriteImage(sitk.GetImageFromArray(a), str(tmp_path / "inf.nii"))
    with pytest.raises(InputError, match="NaN or infinite"):
        load_volume(tmp_path / "inf.nii")


def test_cli_lists_series_and_shows_the_resampling_note(tmp_path, capsys):
    from monotracker.cli import main

    folder = tmp_path / "cli"
    write_series(folder, stack_specs(np.arange(12) * 2.0, shear_y_per_mm=np.tan(np.radians(15.0))), _field, ROWS, COLS, PS,
                 series_uid="1.2.3.7", description="tilted head")
    assert main(["detect-ct", str(folder), "--list-series"]) == 0
    out = capsys.readouterr().out
    assert "1.2.3.7" in out and "tilted head" in out and "12 slices" in out and "tilt 15.0 deg" in out
    main(["detect-ct", str(folder), "--series", "1.2.3.7"])
    out = capsys.readouterr().out
    assert "note: gantry tilt 15.0 deg" in out
    z = np.r_[np.arange(5), np.arange(11, 20)] * 1.0
    write_series(tmp_path / "gap", stack_specs(z), _field, ROWS, COLS, PS)
    assert main(["detect-ct", str(tmp_path / "gap")]) != 0
    captured = capsys.readouterr()
    err_lines = [ln for ln in (captured.err + captured.out).splitlines() if ln.strip()]
    assert len(err_lines) == 1 and "slices missing" in err_lines[0], err_lines


def test_session_loads_the_chosen_series_and_shows_the_note(tmp_path):
    from monotracker.engine import Session, SessionConfig

    folder = tmp_path / "two"
    write_series(folder, stack_specs(np.arange(16) * 1.0), _field, ROWS, COLS, PS, series_uid="1.2.3.1", description="big")
    write_series(folder, stack_specs(np.arange(12) * 2.0, shear_y_per_mm=np.tan(np.radians(15.0))), _field, ROWS, COLS, PS,
                 series_uid="1.2.3.2", description="tilted")
    s = Session(SessionConfig(home=tmp_path / "home", clock="sim"))
    try:
        assert s.load_ct(str(folder), series="1.2.3.2").ok
        job = s.wait_for_job(300)
        assert job is not None and job.done
        snap = s.snapshot()
        assert snap.ct is not None, job
        assert any("gantry tilt 15.0 deg" in n for n in snap.ct.notes), snap.ct.notes
        assert s.volume().array.shape[0] == 12
    finally:
        s.shutdown()
