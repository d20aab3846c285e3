"""DICOM as PACS exports and scanners really hand it over: files without the 128-byte preamble,
CD/USB exports under a DICOMDIR, localizers and screen captures filed under the CT series,
malformed rescale values, several series of one scan or of different scans in one folder.
Each is loaded right (checked at known LPS points against the plain series) or refused in one line.
"""

from __future__ import annotations

import numpy as np
import pydicom
import pytest
from pydicom.uid import SecondaryCaptureImageStorage, generate_uid

from monotracker.ct import list_series, load_volume
from monotracker.errors import InputError
from monotracker.sim.dicom_writer import known_point_errors, stack_specs, write_series

ROWS = COLS = 32
PS = (1.0, 1.0)
SPECS = stack_specs(np.arange(12) * 2.0, origin=(0.0, 0.0, -4.0))
POINTS = np.random.default_rng(3).uniform([6, 6, -2], [25, 25, 16], size=(30, 3))


def _field(p):
    return -1000 + 60 * p[:, 0] + 20 * p[:, 2]


def _one_line(exc) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and "Traceback" not in msg and len(msg) < 500
    return msg


def _errors(tmp_path, post):
    """Known-point errors (mm) of a series written by pydicom, then reshaped by ``post(folder)
    -> path to load``."""
    count = [0]

    def write(field):
        folder = tmp_path / f"s{count[0]}"
        count[0] += 1
        write_series(folder, SPECS, field, ROWS, COLS, PS)
        return post(folder)

    return known_point_errors(write, load_volume, SPECS, POINTS, ROWS, COLS, PS)


def _strip_preamble(folder):
    """Rewrite every file the ACR-NEMA way: no preamble, no "DICM", no file meta, implicit VR LE,
    no extension (as older scanners and some PACS exports write them)."""
    for p in sorted(folder.glob("*.dcm")):
        ds = pydicom.dcmread(p)
        del ds.file_meta
        ds.preamble = None
        out = p.with_suffix("")
        ds.save_as(out, implicit_vr=True, little_endian=True, enforce_file_format=False)
        p.unlink()
        assert out.read_bytes()[128:132] != b"DICM"
    return folder


def test_files_without_preamble_load_exactly(tmp_path):
    err = _errors(tmp_path, _strip_preamble)
    assert np.abs(err).max() < 0.05


def _dicomdir_export(folder):
    """A CD/USB export: the series moved into DICOM/<ids>/ by pydicom's FileSet, a DICOMDIR at
    the root, file names without extension."""
    from pydicom.fileset import FileSet

    root = folder.parent / (folder.name + "_cd")
    fs = FileSet()
    for p in sorted(folder.glob("*.dcm")):
        ds = pydicom.dcmread(p)
        ds.StudyDate, ds.StudyTime, ds.StudyID, ds.SeriesNumber = "20261124", "101500", "1", 2
        fs.add(ds)
    fs.write(root)
    assert (root / "DICOMDIR").is_file() and not list(root.glob("*.dcm"))
    return root


def test_dicomdir_export_loads_from_its_folder_or_the_dicomdir_file(tmp_path):
    err = _errors(tmp_path, _dicomdir_export)
    assert np.abs(err).max() < 0.05
    err = _errors(tmp_path, lambda f: _dicomdir_export(f) / "DICOMDIR")
    assert np.abs(err).max() < 0.05


def _add_localizer(folder, series_uid):
    """A sagittal scout filed under the CT series (ImageType ...\\LOCALIZER), as scanners do."""
    ds = pydicom.dcmread(next(iter(sorted(folder.glob("*.dcm")))))
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.SeriesInstanceUID = series_uid
    ds.ImageType = ["ORIGINAL", "PRIMARY", "LOCALIZER"]
    ds.ImageOrientationPatient = [0, 1, 0, 0, 0, -1]
    ds.ImagePositionPatient = [16, 0, 30]
    ds.InstanceNumber = 999
    ds.save_as(folder / "zz_scout.dcm", enforce_file_format=True)


def _add_screen_capture(folder, series_uid):
    """A dose screen (secondary capture, no position) filed under the CT series."""
    ds = pydicom.dcmread(next(iter(sorted(folder.glob("*.dcm")))))
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = SecondaryCaptureImageStorage
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.SeriesInstanceUID = series_uid
    for tag in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing"):
        delattr(ds, tag)
    ds.save_as(folder / "zz_dose.dcm", enforce_file_format=True)


def test_localizer_and_screen_capture_in_the_series_are_left_out_with_a_note(tmp_path):
    def post(folder):
        uid = pydicom.dcmread(next(iter(sorted(folder.glob("*.dcm"))))).SeriesInstanceUID
        _add_localizer(folder, uid)
        _add_screen_capture(folder, uid)
        return folder

    err = _errors(tmp_path, post)
    assert np.abs(err).max() < 0.05
    vol = load_volume(tmp_path / "s0")
    assert vol.array.shape[0] == len(SPECS)
    assert any("localizer" in n and "zz_scout.dcm" in n for n in vol.notes)
    assert any("secondary capture" in n and "zz_dose.dcm" in n for n in vol.notes)
    info = list_series(tmp_path / "s0")[0]
    assert info.ok and info.slices == len(SPECS)


def test_without_the_filter_the_scout_would_have_broken_the_series(tmp_path):
    """The independent check that the localizer case is a real one: the same folder, the scout
    relabelled as an ordinary image, is refused (mixed orientations), never loaded wrong."""
    folder = tmp_path / "s"
    write_series(folder, SPECS, _field, ROWS, COLS, PS)
    uid = pydicom.dcmread(next(iter(sorted(folder.glob("*.dcm"))))).SeriesInstanceUID
    _add_localizer(folder, uid)
    ds = pydicom.dcmread(folder / "zz_scout.dcm")
    ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
    ds.save_as(folder / "zz_scout.dcm", enforce_file_format=True)
    with pytest.raises(InputError) as exc:
        load_volume(folder)
    assert "orientation" in _one_line(exc).lower()


@pytest.mark.parametrize("slope, expect", [(b"0.0 ", "RescaleSlope is 0"), (b"abc ", "RescaleSlope is malformed")])
def test_malformed_rescale_is_refused_in_one_line(tmp_path, slope, expect):
    folder = tmp_path / "s"
    paths = write_series(folder, SPECS, _field, ROWS, COLS, PS)
    tag = b"\x28\x00\x53\x10DS\x04\x00"        # (0028,1053) RescaleSlope, explicit VR LE, "1.0 "
    raw = paths[5].read_bytes()
    assert raw.count(tag + b"1.0 ") == 1
    paths[5].write_bytes(raw.replace(tag + b"1.0 ", tag + slope))
    with pytest.raises(InputError) as exc:
        load_volume(folder)
    assert expect in _one_line(exc)


def _series_pair(tmp_path, same_scan: bool):
    folder = tmp_path / "two"
    write_series(folder, SPECS, _field, ROWS, COLS, PS, series_uid="1.2.3.1", description="head")
    small = stack_specs(np.arange(20) * 0.5, origin=(0.0, 0.0, 0.0))     # more files, less of the patient
    write_series(folder, small, _field, ROWS, COLS, PS, series_uid="1.2.3.2", description="thin recon")
    if not same_scan:
        for p in folder.glob("thin*.dcm"):
            ds = pydicom.dcmread(p)
            ds.StudyInstanceUID = "1.2.3.99"
            ds.FrameOfReferenceUID = "1.2.3.98"
            ds.save_as(p, enforce_file_format=True)
    return folder


def test_several_series_of_one_scan_pick_the_one_covering_most_of_the_patient(tmp_path):
    folder = _series_pair(tmp_path, same_scan=True)
    vol = load_volume(folder)
    assert vol.array.shape[0] == len(SPECS)          # 12 slices over 22 mm, not 20 over 9.5 mm
    assert any("picked 1.2.3.1" in n and "1.2.3.2" in n for n in vol.notes)


def _retag(folder, pattern, **tags):
    for p in folder.glob(pattern):
        ds = pydicom.dcmread(p)
        for k, v in tags.items():
            if v is None:
                delattr(ds, k)
            else:
                setattr(ds, k, v)
        ds.save_as(p, enforce_file_format=True)


def test_of_two_reconstructions_over_one_range_the_finer_slices_are_picked(tmp_path):
    """A 5 mm and a 0.625 mm reconstruction of the same range (and a 0.5 mm derived series, e.g.
    a MIP or reformat, labelled DERIVED): the fine original one is the CT to detect fiducials in,
    whatever the thick one's slab adds to its nominal extent."""
    folder = tmp_path / "recons"
    write_series(folder, stack_specs(np.arange(4) * 5.0), _field, ROWS, COLS, PS, series_uid="1.2.3.1", description="thick")
    write_series(folder, stack_specs(np.arange(25) * 0.625), _field, ROWS, COLS, PS, series_uid="1.2.3.2", description="fine")
    write_series(folder, stack_specs(np.arange(31) * 0.5), _field, ROWS, COLS, PS, series_uid="1.2.3.3", description="mip")
    _retag(folder, "mip*.dcm", ImageType=["DERIVED", "SECONDARY", "MIP"])
    vol = load_volume(folder)
    assert vol.array.shape[0] == 25 and np.allclose(sorted(vol.spacing_mm), (0.625, 1.0, 1.0))
    assert any("picked 1.2.3.2" in n for n in vol.notes)


def test_a_screen_capture_labelled_ot_does_not_make_the_ct_series_not_ct(tmp_path):
    """Exports label dose screens Modality OT; left out with a note, never a reason to refuse the CT."""
    folder = tmp_path / "s"
    write_series(folder, SPECS, _field, ROWS, COLS, PS)
    uid = pydicom.dcmread(next(iter(sorted(folder.glob("*.dcm"))))).SeriesInstanceUID
    _add_screen_capture(folder, uid)
    _retag(folder, "zz_dose.dcm", Modality="OT")
    vol = load_volume(folder)
    assert vol.array.shape[0] == len(SPECS) and any("secondary capture" in n for n in vol.notes)
    info = list_series(folder)[0]
    assert info.ok and info.slices == len(SPECS)


def test_series_without_a_frame_of_reference_are_not_taken_for_one_scan(tmp_path):
    """Nothing says two series without FrameOfReferenceUID share coordinates: refused until chosen."""
    folder = _series_pair(tmp_path, same_scan=True)
    _retag(folder, "*.dcm", FrameOfReferenceUID=None)
    with pytest.raises(InputError) as exc:
        load_volume(folder)
    assert "different scans" in _one_line(exc)


def test_series_of_different_scans_are_refused_until_one_is_chosen(tmp_path):
    folder = _series_pair(tmp_path, same_scan=False)
    with pytest.raises(InputError) as exc:
        load_volume(folder)
    msg = _one_line(exc)
    assert "different scans" in msg and "1.2.3.1" in msg and "1.2.3.2" in msg and "--series" in msg
    assert load_volume(folder, series="1.2.3.2").array.shape[0] == 20
