"""CT inputs that used to load silently wrong or fail with words that send the operator after
the wrong problem (issue 36): a NIfTI without orientation, values that are not HU (scl_slope
1e30), spacing written in cm (NIfTI and DICOM), a sheared sform, a volume larger than the
memory left, an unreadable file as an ordinary user. Each gives one line saying what is wrong
and what to do (or, for the orientation, a WARNING note kept with the CT, shown by the CLI and
the app)."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from monotracker.ct import load_volume
from monotracker.errors import InputError
from monotracker.sim.ct_phantom import ScanParams, generate_ct
from monotracker.sim.dicom_writer import stack_specs, write_series
from monotracker.sim.phantom import default_phantom

APP = str(Path(__file__).resolve().parents[2] / "app")


@pytest.fixture(scope="module")
def head():
    """A coarse whole head (axis-aligned grid), 1.0 x 1.2 x 2.0 mm."""
    return generate_ct(default_phantom(), ScanParams(spacing_mm=(1.0, 1.2, 2.0), noise_hu=10.0, direction=np.eye(3)))


def _nifti(tmp_path, ct, name, patches=()) -> Path:
    """``ct`` as an uncompressed NIfTI-1 whose header fields are then overwritten:
    ``patches`` = (byte offset, struct format, value(s)), little endian as ITK writes it."""
    p = tmp_path / name
    sitk.WriteImage(ct.to_sitk(), str(p))
    raw = bytearray(p.read_bytes())
    assert struct.unpack_from("<i", raw, 0)[0] == 348
    for off, fmt, val in patches:
        struct.pack_into("<" + fmt, raw, off, *(val if isinstance(val, tuple) else (val,)))
    p.write_bytes(bytes(raw))
    return p


QFORM, SFORM, SLOPE, INTER, PIXDIM_I, SROW_X, SROW_Y, SROW_Z = 252, 254, 112, 116, 80, 280, 296, 312


def _one_line(exc_info) -> str:
    msg = str(exc_info.value)
    assert "\n" not in msg and "Traceback" not in msg
    return msg


def test_nifti_without_orientation_loads_with_a_warning_the_cli_shows(tmp_path, head, capsys):
    p = _nifti(tmp_path, head, "noorient.nii", [(QFORM, "h", 0), (SFORM, "h", 0)])
    vol = load_volume(p)
    warn = [n for n in vol.notes if n.startswith("WARNING")]
    assert len(warn) == 1 and "no orientation" in warn[0] and "mirrored" in warn[0], vol.notes
    # the same file with its orientation: no warning (the warning is about the header, not the data)
    assert not any(n.startswith("WARNING") for n in load_volume(_nifti(tmp_path, head, "ok.nii")).notes)
    from monotracker.cli import main

    main(["detect-ct", str(p)])
    assert "note: WARNING: noorient.nii has no orientation" in capsys.readouterr().out


def test_nifti_without_orientation_warning_is_kept_with_the_ct_in_the_app(tmp_path, head):
    from monotracker.engine import Session, SessionConfig

    p = _nifti(tmp_path, head, "noorient.nii", [(QFORM, "h", 0), (SFORM, "h", 0)])
    s = Session(SessionConfig(home=tmp_path / "home", clock="sim"))
    try:
        assert s.load_ct(str(p)).ok
        job = s.wait_for_job(300)
        assert job is not None and job.done and job.error is None, job
        notes = s.snapshot().ct.notes
        assert any(n.startswith("WARNING") and "no orientation" in n for n in notes), notes
    finally:
        s.shutdown()


def test_values_scaled_out_of_hounsfield_range_name_the_slope(tmp_path, head):
    p = _nifti(tmp_path, head, "slope.nii", [(SLOPE, "f", 1e30), (INTER, "f", 0.0)])
    with pytest.raises(InputError) as e:
        load_volume(p)
    msg = _one_line(e)
    assert "not Hounsfield units" in msg and "scl_slope 1e+30" in msg, msg


def test_nifti_spacing_in_cm_is_named(tmp_path, head):
    p = _nifti(tmp_path, head, "cm.nii", [(PIXDIM_I, "3f", (0.1, 0.12, 0.2)), (SROW_X, "4f", (-0.1, 0, 0, 0)),
                                          (SROW_Y, "4f", (0, -0.12, 0, 0)), (SROW_Z, "4f", (0, 0, 0.2, 0))])
    with pytest.raises(InputError) as e:
        load_volume(p)
    msg = _one_line(e)
    assert "written in cm" in msg and "1 x 1.2 x 2 mm" in msg, msg


def test_dicom_spacing_in_cm_is_named(tmp_path):
    # PixelSpacing and slice positions written in cm (0.05 and 0.1 for 0.5 mm pixels and 1 mm slices)
    def field(p):
        r = np.linalg.norm(p[:, :2] - 6.4, axis=1)
        return np.where(r < 4.0, 40.0, -1000.0) + np.where((r > 4.0) & (r < 4.7), 1400.0, 0.0)

    write_series(tmp_path / "cm", stack_specs(np.arange(24) * 0.1), field, 256, 256, (0.05, 0.05))
    with pytest.raises(InputError) as e:
        load_volume(tmp_path / "cm")
    msg = _one_line(e)
    assert "written in cm" in msg and "0.5 x 0.5 x 1 mm" in msg, msg


def test_sheared_sform_is_named_not_called_corrupt(tmp_path, head):
    sheared = [(SROW_X, "4f", (-1.0, 0.3, 0.0, 0.0)), (SROW_Y, "4f", (0.0, -1.2, 0.0, 0.0)), (SROW_Z, "4f", (0.0, 0.0, 2.0, 0.0))]
    p = _nifti(tmp_path, head, "shear.nii", [(QFORM, "h", 0), (SFORM, "h", 1)] + sheared)
    with pytest.raises(InputError) as e:
        load_volume(p)
    msg = _one_line(e)
    assert "sheared" in msg and "resample it onto a regular grid" in msg and "corrupt" not in msg, msg
    # with the scanner's qform beside it, the qform is used, and a note says the sform was passed over
    vol = load_volume(_nifti(tmp_path, head, "shear_q.nii", [(QFORM, "h", 1), (SFORM, "h", 1)] + sheared))
    assert any("sheared" in n and "qform" in n for n in vol.notes), vol.notes


def _sparse_nifti(path: Path, dims=(2048, 2048, 1024)) -> Path:
    """A NIfTI-1 header for ``dims`` int16 voxels and a sparse data block (no disk used)."""
    hdr = bytearray(352)
    struct.pack_into("<i", hdr, 0, 348)
    struct.pack_into("<8h", hdr, 40, 3, *dims, 1, 1, 1, 1)
    struct.pack_into("<hh", hdr, 70, 4, 16)  # int16
    struct.pack_into("<8f", hdr, 76, 1.0, 0.5, 0.5, 0.5, 0, 0, 0, 0)
    struct.pack_into("<f", hdr, 108, 352.0)
    struct.pack_into("<ff", hdr, 112, 1.0, 0.0)
    hdr[123] = 2  # mm
    struct.pack_into("<hh", hdr, 252, 1, 0)
    hdr[344:348] = b"n+1\0"
    with open(path, "wb") as fh:
        fh.write(hdr)
        fh.truncate(352 + int(np.prod(dims)) * 2)
    return path


def test_volume_larger_than_the_memory_left_is_refused_before_reading(tmp_path):
    p = _sparse_nifti(tmp_path / "huge.nii")  # 8 GiB of voxels
    code = (
        "import resource, sys\n"
        "from monotracker.ct import load_volume\n"
        "from monotracker.errors import InputError\n"
        "vm = [int(x.split()[1]) * 1024 for x in open('/proc/self/status') if x.startswith('VmSize:')][0]\n"
        "lim = vm + (3 << 30)\n"
        "resource.setrlimit(resource.RLIMIT_AS, (lim, lim))\n"
        "try:\n"
        "    load_volume(sys.argv[1])\n"
        "    print('LOADED')\n"
        "except InputError as exc:\n"
        "    print('REFUSED', exc)\n"
    )
    env = dict(os.environ, PYTHONPATH=APP, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", code, str(p)], capture_output=True, text=True, env=env, timeout=600)
    line = out.stdout.strip()
    assert line.startswith("REFUSED"), (out.stdout, out.stderr[-2000:])
    assert "too large for this machine's memory" in line and "2048 x 2048 x 1024" in line and "8.0 GiB" in line, line
    assert "address-space limit" in line or "free memory" in line or "memory limit" in line, line


def _world_usable(path: Path) -> bool:
    """Whether every folder on the way to ``path`` may be entered, and the file read, by anyone."""
    path = Path(path).resolve()
    return all(os.stat(p).st_mode & 0o001 for p in path.parents) and bool(os.stat(path).st_mode & 0o005)


def _python_for_others() -> tuple[str, str]:
    """(interpreter, extra PYTHONPATH) that another user can run with this one's packages: this
    interpreter when it is reachable, else the system's of the same version with this
    environment's site-packages (a pyenv Python under /root is not reachable by others)."""
    import site
    import sysconfig

    if _world_usable(Path(sys.executable)):
        return sys.executable, ""
    alt = Path(f"/usr/bin/python{sys.version_info[0]}.{sys.version_info[1]}")
    pkgs = sysconfig.get_paths()["purelib"]
    if alt.exists() and _world_usable(alt) and _world_usable(Path(pkgs)):
        return str(alt), os.pathsep.join([pkgs, *site.getsitepackages()])
    pytest.skip("no Python interpreter another user can run (needed to see a permission refusal as root)")


def _run_as_other_user(code: str, *args: str) -> subprocess.CompletedProcess:
    """Run ``code`` as an ordinary user: this one when it is not root, else ``nobody`` (root
    reads every file, so the refusal can only be seen as someone else)."""
    env = dict(os.environ, PYTHONPATH=APP, OMP_NUM_THREADS="1")
    exe, kw = sys.executable, {}
    if os.geteuid() == 0:
        exe, extra = _python_for_others()
        if extra:
            env["PYTHONPATH"] = os.pathsep.join([APP, extra])
        kw = dict(user=65534, group=65534, extra_groups=[], cwd="/")
        env["HOME"] = "/tmp"
    return subprocess.run([exe, "-c", code, *args], capture_output=True, text=True, env=env, timeout=300, **kw)


_LOAD = (
    "import sys\n"
    "from monotracker.ct import load_volume\n"
    "from monotracker.errors import InputError\n"
    "try:\n"
    "    load_volume(sys.argv[1])\n"
    "    print('LOADED')\n"
    "except InputError as exc:\n"
    "    print('REFUSED', exc)\n"
)


@pytest.mark.parametrize("ext", ["nii.gz", "nrrd"])
def test_unreadable_file_as_an_ordinary_user_says_permission_denied(head, ext):
    with tempfile.TemporaryDirectory(prefix="ct-perm-") as d:
        os.chmod(d, 0o755)  # the folder open, the file closed
        p = Path(d) / f"head.{ext}"
        sitk.WriteImage(head.to_sitk()[:, :, :20], str(p), useCompression=True)
        os.chmod(p, 0o600 if os.geteuid() == 0 else 0o000)
        out = _run_as_other_user(_LOAD, str(p))
        line = out.stdout.strip()
        assert line.startswith("REFUSED"), (out.stdout, out.stderr[-2000:])
        assert "permission denied" in line and "mode 0" in line and "read access" in line, line
        assert "corrupt" not in line and "not a recognised" not in line, line


def test_file_in_a_closed_folder_is_not_called_missing(head):
    with tempfile.TemporaryDirectory(prefix="ct-perm-") as d:
        inner = Path(d) / "closed"
        inner.mkdir()
        p = inner / "head.nrrd"
        sitk.WriteImage(head.to_sitk()[:, :, :20], str(p))
        os.chmod(d, 0o755)
        os.chmod(inner, 0o700 if os.geteuid() == 0 else 0o000)
        try:
            out = _run_as_other_user(_LOAD, str(p))
        finally:
            os.chmod(inner, 0o755)
        line = out.stdout.strip()
        assert line.startswith("REFUSED"), (out.stdout, out.stderr[-2000:])
        assert "permission denied" in line and "no such file" not in line, line
