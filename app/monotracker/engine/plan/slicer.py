"""3D Slicer markups export (``.mrk.json``, coordinate system LPS, mm)."""

from __future__ import annotations

from pathlib import Path

from monotracker.engine.persistence import atomic_write_json
from monotracker.errors import InputError

_SCHEMA = "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/Schema/markups-schema-v1.0.3.json#"


def _markup(kind: str, name: str, points: list[tuple[str, list[float], bool]]) -> dict:
    return {
        "@schema": _SCHEMA,
        "markups": [{
            "type": kind,
            "coordinateSystem": "LPS",
            "coordinateUnits": "mm",
            "name": name,
            "controlPoints": [
                {"id": str(i + 1), "label": label, "position": [float(v) for v in pos],
                 "selected": True, "locked": True, "visibility": True,
                 "positionStatus": "defined", "description": "confirmed" if ok else ""}
                for i, (label, pos, ok) in enumerate(points)
            ],
        }],
    }


def write_markups(plan, folder: Path) -> list[Path]:
    """Write ``fiducials.mrk.json`` (usable fiducials) and, if planned, ``path.mrk.json`` (a line
    entry -> target). Returns the written files. Raises InputError if the folder is unusable."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create {folder}: {exc}") from exc
    out = []
    fids = [(f"F{f.id}", f.centre_lps_mm.tolist(), True) for f in plan.usable_fiducials()]
    p = folder / "fiducials.mrk.json"
    atomic_write_json(p, _markup("Fiducial", "MonoTracker fiducials", fids))
    out.append(p)
    if plan.path_complete:
        p = folder / "path.mrk.json"
        atomic_write_json(p, _markup("Line", "MonoTracker path", [("entry", plan.entry_lps_mm.tolist(), True),
                                                                 ("target", plan.target_lps_mm.tolist(), True)]))
        out.append(p)
    return out
