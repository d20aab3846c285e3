"""The surgical plan, in four layers that import only downwards:

* ``model.py`` -- :class:`Plan` (plain data: CT, fiducials, path, camera, hand-eye), its JSON, metrics;
* ``checks.py`` -- one validation per kind of plan state (commands, restore and arming use it);
* ``store.py`` -- ``plan.json``: the field-by-field restore, the strict load, and :class:`PlanStore`,
  which commits a changed plan (saved, then swapped in);
* ``editor.py`` -- :class:`PlanEditor`, the plan's commands, each one :meth:`PlanEditor.edit`
  transaction; and ``slicer.py``, the 3D Slicer markups export.
"""

from monotracker.engine.plan.model import (
    FORMAT,
    ROLES,
    STATUSES,
    VERSION,
    Plan,
    PlanFiducial,
    angle_to_skin_normal_deg,
    distance_segment_to_points_mm,
    path_length_mm,
)
from monotracker.engine.plan.store import load_plan, plan_from_dict

__all__ = ["FORMAT", "ROLES", "STATUSES", "VERSION", "Plan", "PlanFiducial", "angle_to_skin_normal_deg",
           "distance_segment_to_points_mm", "path_length_mm", "load_plan", "plan_from_dict"]
