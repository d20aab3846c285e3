"""Helpers shared by the CT tests (a module with a unique name, so that a full-suite run never
imports another folder's ``conftest`` in its place)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from monotracker.sim.ct_phantom import DenseBlob, ScanParams, generate_ct, patch_scan_params
from monotracker.sim.phantom import default_phantom


def patch_params(phantom=None, margin_mm: float = 7.0, **kw) -> ScanParams:
    """A scan of only the fiducial patch (fast): 0.5 x 0.5 x 1.0 mm, oblique, noisy."""
    return patch_scan_params(phantom, margin_mm, **kw)


def touching_ball_scan():
    """The fiducial patch with a tenth ball touching ball 0 (centres 8 mm apart, along the scalp's
    tangent): ``(ct, truth)``, truth = the nine fiducial centres then the extra ball's (LPS mm)."""
    ph = default_phantom()
    c = ph.fiducial_centres_lps
    n = (c[0] - ph.centre_lps) / np.linalg.norm(c[0] - ph.centre_lps)
    t = np.cross(n, [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t)
    extra = c[0] + 8.0 * t
    ct = generate_ct(ph, patch_params(ph, margin_mm=12.0, distractors=(DenseBlob(extra, np.full(3, 4.0), 3000.0, name="touching ball"),)))
    return ct, np.vstack([ct.fiducial_centres_lps, extra])


def write_dicom_series(image: sitk.Image, folder: Path, series_uid: str | None = None, description: str = "phantom") -> list[Path]:
    """Write a 3D int16 HU image as a CT DICOM series (one file per slice) with the tags that
    SimpleITK/GDCM need to read origin, spacing and direction back."""
    folder.mkdir(parents=True, exist_ok=True)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    d = image.GetDirection()
    uid_root = "1.2.826.0.1.3680043.2.1125"
    series_uid = series_uid or f"{uid_root}.1.{int(time.time() * 1e3) % 10**9}.{np.random.randint(10**6)}"
    study_uid = f"{uid_root}.2.1"
    common = [
        ("0008|0060", "CT"),
        ("0008|0008", "ORIGINAL\\PRIMARY\\AXIAL"),
        ("0020|000d", study_uid),
        ("0020|000e", series_uid),
        ("0020|0052", f"{uid_root}.3.1"),  # FrameOfReferenceUID: one scan (scanners always write it)
        ("0020|0037", "\\".join(f"{x:.10f}" for x in (d[0], d[3], d[6], d[1], d[4], d[7]))),
        ("0008|103e", description),
        ("0028|1052", "0"),
        ("0028|1053", "1"),
        ("0018|0050", f"{image.GetSpacing()[2]:.6f}"),
        ("0010|0010", "PHANTOM^HEAD"),
    ]
    paths = []
    for k in range(image.GetDepth()):
        sl = image[:, :, k]
        for tag, val in common:
            sl.SetMetaData(tag, val)
        pos = image.TransformIndexToPhysicalPoint((0, 0, k))
        sl.SetMetaData("0020|0032", "\\".join(f"{x:.6f}" for x in pos))
        sl.SetMetaData("0020|0013", str(k + 1))
        sl.SetMetaData("0008|0018", f"{series_uid}.{k + 1}")
        p = folder / f"{description}_{k:04d}.dcm"
        writer.SetFileName(str(p))
        writer.Execute(sl)
        paths.append(p)
    return paths


def gated_load(monkeypatch, name: str = "load_volume"):
    """``monotracker.ct.<name>`` (``load_volume``; ``detect_fiducials`` for a kit's detection)
    waits on ``gate`` (released by the test) before doing its work; ``entered`` is set once a
    call is inside. Returns ``(gate, entered)`` (threading.Event)."""
    import monotracker.ct as ct_pkg

    gate, entered = threading.Event(), threading.Event()
    real = getattr(ct_pkg, name)

    def slow(*args, **kw):
        entered.set()
        gate.wait(120)
        return real(*args, **kw)

    monkeypatch.setattr(ct_pkg, name, slow)
    return gate, entered
