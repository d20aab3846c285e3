"""Find the sphere fiducials in a CT automatically (LPS millimetres).

What it shows: :func:`monotracker.ct.load_volume` (DICOM folder, NIfTI, NRRD, MHA: refuses bad
input with one line) and :func:`monotracker.ct.detect_fiducials` on the bundled sample CT, a
synthetic head with nine 4 mm alumina balls and a steel skin clip as a distractor. Each found
centre is compared with the sample's ground truth (``sample_data/phantom_truth.json``); the
dense blobs the detector rejected are listed with the reason. Exits non-zero if a ball is
missed or a centre is more than 0.2 mm off.

Run: ``python examples/02_detect_ct_fiducials.py [CT_PATH]`` (default: the bundled sample)
"""

from __future__ import annotations

import json
import sys

import numpy as np

from monotracker.ct import detect_fiducials, load_volume
from monotracker.errors import InputError
from monotracker.paths import sample_ct_path, sample_data_dir


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    path = argv[0] if argv else sample_ct_path()
    try:
        vol = load_volume(path)
    except InputError as exc:            # corrupt file, wrong units, unsupported geometry ...
        print(f"cannot use this CT: {exc}")
        return 2
    print(vol.describe())
    det = detect_fiducials(vol)
    print(f"{len(det.fiducials)} fiducials" + ("" if det.ok else f" ({det.reason})"))
    for i, f in enumerate(det.fiducials):
        x, y, z = f.centre_lps
        print(f"  {i}: ({x:8.2f}, {y:8.2f}, {z:8.2f}) mm LPS, radius {f.radius_mm:.2f} mm, score {f.score:.2f}")
    for r in det.rejected:
        print(f"  rejected: {r}")
    if argv:                              # no ground truth for the user's own CT
        return 0 if det.ok else 1
    truth = np.array(json.loads((sample_data_dir() / "phantom_truth.json").read_text())["fiducial_centres_lps_mm"])
    found = det.centres
    err = np.array([np.linalg.norm(found - t, axis=1).min() if len(found) else np.inf for t in truth])
    print(f"error vs ground truth: mean {err.mean():.3f} mm, max {err.max():.3f} mm over {len(truth)} balls")
    return 0 if (len(found) == len(truth) and err.max() < 0.2) else 1


if __name__ == "__main__":
    sys.exit(main())
