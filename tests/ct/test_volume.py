"""CT loading: format round-trips to the same physical points, real DICOM files written by
others (pydicom's test data), and a clear one-line InputError for every bad input."""

from __future__ import annotations

import copy

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from ct_test_helpers import write_dicom_series
from pydicom.data import get_testdata_file
from pydicom.uid import generate_uid

from monotracker.ct import detect_fiducials, load_volume
from monotracker.ct.volume import Volume
from monotracker.errors import InputError
from monotracker.paths import sample_ct_path
from monotracker.sim.ct_phantom import ScanParams, generate_ct
from monotracker.sim.phantom import default_phantom


@pytest.fixture(scope="module")
def small_ct():
    """A coarse (1.0 x 1.2 x 2.0 mm), oblique whole-head CT: quick to write in every format."""
    return generate_ct(default_phantom(), ScanParams(spacing_mm=(1.0, 1.2, 2.0), noise_hu=10.0))


@pytest.fixture(scope="module")
def written(small_ct, tmp_path_factory):
    """The same scan as DICOM series, NIfTI, NRRD and MHA."""
    d = tmp_path_factory.mktemp("formats")
    img = small_ct.to_sitk()
    paths = {"dicom": d / "dicom"}
    write_dicom_series(img, paths["dicom"])
    for ext in ("nii.gz", "nrrd", "mha"):
        paths[ext] = d / f"head.{ext}"
        sitk.WriteImage(img, str(paths[ext]), useCompression=True)
    return paths


def test_all_formats_load_to_the_same_physical_points(small_ct, written):
    ijk = np.array([[0, 0, 0], [10, 20, 30], [100, 50, 40], [np.float64(small_ct.array.shape[2] - 1), 3.5, 7.25]])
    truth_lps = small_ct.origin_mm + (ijk * small_ct.spacing_mm) @ small_ct.direction.T
    for fmt, path in written.items():
        vol = load_volume(path)
        # float32 headers (NIfTI) keep positions to ~1e-5 mm
        assert np.allclose(vol.index_to_lps(ijk), truth_lps, atol=1e-3), fmt
        assert np.allclose(vol.lps_to_index(truth_lps), ijk, atol=1e-4), fmt
        assert np.array_equal(vol.array, small_ct.array), fmt
        assert vol.array.shape == small_ct.array.shape
        assert not np.allclose(vol.direction, np.eye(3))


def test_all_formats_give_the_same_fiducials(written):
    centres = {fmt: detect_fiducials(load_volume(p)).centres for fmt, p in written.items()}
    truth = default_phantom().fiducial_centres_lps
    for fmt, c in centres.items():
        assert len(c) == 9, fmt
        assert np.allclose(c, centres["mha"], atol=1e-3), fmt
        # 2 mm slices, 1.2 mm pixels: still well under a voxel
        assert np.abs(c[:, None, :] - truth[None]).sum(-1).min(axis=1).max() < 0.3


def test_index_lps_round_trip_on_the_sample():
    vol = load_volume(sample_ct_path())
    rng = np.random.default_rng(3)
    ijk = rng.uniform(0, 100, size=(50, 3))
    assert np.allclose(vol.lps_to_index(vol.index_to_lps(ijk)), ijk, atol=1e-9)
    # agrees with SimpleITK's own mapping
    for p in ijk[:5]:
        assert np.allclose(vol.image.TransformContinuousIndexToPhysicalPoint(p.tolist()), vol.index_to_lps(p[None])[0], atol=1e-6)
    # and zyx order is the reversed index
    assert np.allclose(vol.zyx_to_lps(ijk[:, ::-1]), vol.index_to_lps(ijk))


# ------------------------------------------------------------------ several series
def test_lps_to_index_inverts_a_sheared_grid():
    """A direction matrix that is not orthonormal (sheared grid, e.g. an affine registration's
    output kept by ITK): lps_to_index inverts index_to_lps (the transpose would not), checked
    against ITK's own TransformPhysicalPointToContinuousIndex."""
    D = np.array([[1.0, 0.3, 0.0], [0.0, 0.95, 0.2], [0.1, 0.0, 1.0]])
    img = sitk.Image([8, 9, 10], sitk.sitkInt16)
    img.SetSpacing((0.5, 0.7, 1.25))
    img.SetOrigin((-20.0, 13.0, 4.0))
    img.SetDirection(tuple(D.ravel()))
    vol = Volume.from_image(img)
    ijk = np.array([[0.0, 0.0, 0.0], [3.5, 2.25, 7.0], [7.0, 8.0, 9.0]])
    lps = vol.index_to_lps(ijk)
    itk = np.array([img.TransformContinuousIndexToPhysicalPoint(tuple(p)) for p in ijk])
    assert np.allclose(lps, itk, atol=1e-9)
    assert np.allclose(vol.lps_to_index(lps), ijk, atol=1e-9)
    assert np.allclose(vol.lps_to_index(lps[1]), ijk[1], atol=1e-9)  # one point, (3,)


def test_folder_with_several_series_picks_the_one_covering_the_patient_and_says_so(small_ct, tmp_path):
    img = small_ct.to_sitk()
    write_dicom_series(img, tmp_path, series_uid="1.2.826.0.1.3680043.2.1125.9.1")
    write_dicom_series(img[:, :, 10:20], tmp_path, series_uid="1.2.826.0.1.3680043.2.1125.9.2", description="scout")
    vol = load_volume(tmp_path)
    assert vol.array.shape[0] == img.GetDepth()
    assert any("picked 1.2.826.0.1.3680043.2.1125.9.1" in n and "1.2.826.0.1.3680043.2.1125.9.2" in n for n in vol.notes)
    vol2 = load_volume(tmp_path, series="1.2.826.0.1.3680043.2.1125.9.2")
    assert vol2.array.shape[0] == 10
    # the smaller series starts at slice 10 of the same geometry
    assert np.allclose(vol2.index_to_lps([[0, 0, 0]]), vol.index_to_lps([[0, 0, 10]]), atol=1e-3)
    with pytest.raises(InputError, match="not in"):
        load_volume(tmp_path, series="1.2.3.4")


# ------------------------------------------------------------------ real DICOM by others
def _ct_small_series(folder, n=4):
    """pydicom's CT_small.dcm (a real scanner slice) copied into an n-slice series, 5 mm apart."""
    src = pydicom.dcmread(get_testdata_file("CT_small.dcm"))
    series = generate_uid()
    for k in range(n):
        ds = copy.deepcopy(src)
        ds.SeriesInstanceUID = series
        ds.SOPInstanceUID = generate_uid()
        ds.InstanceNumber = k + 1
        ipp = [float(x) for x in src.ImagePositionPatient]
        ipp[2] += 5.0 * k
        ds.ImagePositionPatient = ipp
        ds.SliceLocation = ipp[2]
        ds.save_as(folder / f"ct_{k}.dcm")
    return src


def test_real_ct_dicom_series_matches_pydicom(tmp_path):
    src = _ct_small_series(tmp_path)
    vol = load_volume(tmp_path)
    hu = src.pixel_array * float(src.RescaleSlope) + float(src.RescaleIntercept)
    assert vol.array.shape == (4, src.Rows, src.Columns)
    for k in range(4):
        assert np.array_equal(vol.array[k], hu)
    assert np.allclose(vol.spacing_mm, [float(src.PixelSpacing[1]), float(src.PixelSpacing[0]), 5.0])
    assert np.allclose(vol.origin_mm, [float(x) for x in src.ImagePositionPatient], atol=1e-4)
    iop = np.array([float(x) for x in src.ImageOrientationPatient])
    assert np.allclose(vol.direction[:, 0], iop[:3]) and np.allclose(vol.direction[:, 1], iop[3:])
    # pixel (row 7, col 11) of slice 2 is at IPP + col * spacing_c * row_dir + ... (DICOM PS3.3 C.7.6.2.1.1)
    p = vol.index_to_lps([[11, 7, 2]])[0]
    expect = np.array([float(x) for x in src.ImagePositionPatient]) + 11 * float(src.PixelSpacing[1]) * iop[:3] + 7 * float(src.PixelSpacing[0]) * iop[3:] + [0, 0, 10.0]
    assert np.allclose(p, expect, atol=1e-4)


def test_real_single_ct_slice_is_refused_as_2d():
    with pytest.raises(InputError, match="2D"):
        load_volume(get_testdata_file("CT_small.dcm"))


def test_real_mr_series_is_refused_as_not_ct(tmp_path):
    src = pydicom.dcmread(get_testdata_file("MR_small.dcm"))
    series = generate_uid()
    for k in range(3):
        ds = copy.deepcopy(src)
        ds.SeriesInstanceUID, ds.SOPInstanceUID, ds.InstanceNumber = series, generate_uid(), k + 1
        ipp = [float(x) for x in src.ImagePositionPatient]
        ipp[2] += 2.0 * k
        ds.ImagePositionPatient = ipp
        ds.save_as(tmp_path / f"mr_{k}.dcm")
    with pytest.raises(InputError, match="Hounsfield"):
        load_volume(tmp_path)


def test_real_truncated_dicom_is_refused(tmp_path):
    with pytest.raises(InputError):
        load_volume(get_testdata_file("MR_truncated.dcm"))


# ------------------------------------------------------------------ bad input
def _one_line(exc_info) -> str:
    msg = str(exc_info.value)
    assert "\n" not in msg and len(msg) < 400 and "Traceback" not in msg
    return msg


def test_missing_path(tmp_path):
    with pytest.raises(InputError, match="no such file") as e:
        load_volume(tmp_path / "nope.nii.gz")
    _one_line(e)


def test_empty_folder(tmp_path):
    with pytest.raises(InputError, match="empty") as e:
        load_volume(tmp_path)
    _one_line(e)


def test_folder_without_dicom(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(InputError, match="no DICOM series") as e:
        load_volume(tmp_path)
    _one_line(e)


def test_empty_and_unknown_files(tmp_path):
    (tmp_path / "zero.nii.gz").write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        load_volume(tmp_path / "zero.nii.gz")
    (tmp_path / "x.txt").write_text("not an image")
    with pytest.raises(InputError, match="cannot read") as e:
        load_volume(tmp_path / "x.txt")
    _one_line(e)


@pytest.mark.parametrize("fmt", ["nii.gz", "mha", "nrrd", "nii"])
def test_truncated_file(written, small_ct, tmp_path, fmt):
    src = tmp_path / f"full.{fmt}"
    sitk.WriteImage(small_ct.to_sitk(), str(src), useCompression=(fmt != "nii"))
    data = src.read_bytes()
    bad = tmp_path / f"cut.{fmt}"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError) as e:
        load_volume(bad)
    _one_line(e)


def test_2d_image(tmp_path):
    img = sitk.GetImageFromArray(np.full((64, 64), -1000, np.int16))
    sitk.WriteImage(img, str(tmp_path / "slice.mha"))
    with pytest.raises(InputError, match="2D") as e:
        load_volume(tmp_path / "slice.mha")
    _one_line(e)


def _write(tmp_path, arr, spacing=(0.5, 0.5, 1.0), name="v.mha"):
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing(spacing)
    sitk.WriteImage(img, str(tmp_path / name))
    return tmp_path / name


def test_8bit_picture_is_not_ct(tmp_path):
    arr = np.random.default_rng(0).integers(0, 256, size=(8, 32, 32)).astype(np.uint8)
    with pytest.raises(InputError, match="0..255") as e:
        load_volume(_write(tmp_path, arr))
    _one_line(e)


def test_unscaled_12bit_is_not_ct(small_ct, tmp_path):
    # raw detector values 0..4095 without the -1024 intercept
    arr = (small_ct.array.astype(np.int32) + 1024).astype(np.uint16)
    with pytest.raises(InputError, match="Hounsfield") as e:
        load_volume(_write(tmp_path, arr, spacing=tuple(small_ct.spacing_mm)))
    _one_line(e)


@pytest.mark.parametrize("spacing", [(0.01, 0.5, 1.0), (0.5, 0.5, 25.0)])
def test_absurd_spacing(small_ct, tmp_path, spacing):
    with pytest.raises(InputError, match="spacing") as e:
        load_volume(_write(tmp_path, small_ct.array[:20], spacing=spacing))
    _one_line(e)


def test_colour_volume_is_refused(tmp_path):
    img = sitk.Compose([sitk.GetImageFromArray(np.full((4, 8, 8), -1000, np.int16))] * 3)
    sitk.WriteImage(img, str(tmp_path / "rgb.mha"))
    with pytest.raises(InputError, match="values per voxel"):
        load_volume(tmp_path / "rgb.mha")


def test_volume_from_image_keeps_geometry(small_ct):
    vol = Volume.from_image(small_ct.to_sitk())
    assert np.allclose(vol.spacing_mm, small_ct.spacing_mm)
    assert np.allclose(vol.origin_mm, small_ct.origin_mm)
    assert np.allclose(vol.direction, small_ct.direction)
