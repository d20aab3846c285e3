"""Three slice images (axial, coronal, sagittal; LPS-aligned, radiological convention) in one
tab's step panel, redrawn only when what they show changes (at the Plan step with the layout
planner's suggested balls, S1..Sn)."""

from __future__ import annotations

import numpy as np

from monotracker.ui.slices import PLANES, render_slice, suggested_balls, volume_bounds_lps


class SlicePanel:
    """``key``: which step's slices (a step's scene key). ``render(snap, point)`` draws the planes
    through ``point`` (LPS mm; None: the volume's centre)."""

    def __init__(self, view, key: str):
        self.view, self.key = view, key
        self.handles = {p: view.gui.add_image(np.zeros((8, 8, 3), np.uint8), label=p, format="jpeg") for p in PLANES}

    def render(self, snap, point) -> None:
        vol = self.view.session.volume()
        if vol is None:
            return
        if point is None:
            lo, hi = volume_bounds_lps(vol)
            point = (lo + hi) / 2
        plan = snap.plan
        sug, sug_r = suggested_balls(snap, self.key)
        key = (id(vol), tuple(np.round(np.asarray(point, float), 2)), tuple((f.id, f.status) for f in snap.fiducials),
               None if plan.entry_lps_mm is None else tuple(plan.entry_lps_mm),
               None if plan.target_lps_mm is None else tuple(plan.target_lps_mm),
               None if sug is None else (sug.round(2).tobytes(), sug_r))
        keys = self.view.scene_keys
        if keys.get(("slices", self.key)) == key:
            return
        keys[("slices", self.key)] = key
        for plane in PLANES:
            img, _ = render_slice(vol, plane, point, snap.fiducials, plan.entry_lps_mm, plan.target_lps_mm,
                                  suggested=sug, suggested_radius_mm=sug_r)
            self.handles[plane].image = img
