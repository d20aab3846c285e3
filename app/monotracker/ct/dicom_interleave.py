"""Two acquisitions interleaved under one DICOM series and one AcquisitionNumber.

Two stacks offset by part of a slice spacing (e.g. a repeat scan after motion, exported into
the first one's series) have true positions, but read as one volume at half the spacing they
mix two patient positions slice by slice: a geometry that looks fine and is not. Checked on the
slices of one series sorted along the slice normal (:mod:`monotracker.ct.dicom_series`).
"""

from __future__ import annotations

import numpy as np

from monotracker.errors import InputError


def _alternates(member: np.ndarray) -> bool:
    """Two groups (0/1 along the stack, each of >= 2 slices) that take turns: the group changes
    at more than half of the steps (one block after the other changes once)."""
    if len(member) < 4 or min(int(member.sum()), int((1 - member).sum())) < 2:
        return False
    return int(np.sum(member[1:] != member[:-1])) > 0.5 * (len(member) - 1)


def check_interleaved(slices: list, what: str) -> None:
    """Refuse two acquisitions interleaved under one series and one AcquisitionNumber (two
    stacks offset by part of a spacing read as one volume at half the spacing). ``slices``
    sorted along the normal. Evidence, any one enough: the slice times fall in two clusters
    that alternate along the stack; the instance numbers run twice, the two runs alternating;
    with the pixels at hand, each slice is less like its neighbours than like the slices two
    away (the two stacks differ: motion between them)."""
    n = len(slices)
    hint = "export each acquisition as its own series"
    times = [s.time_s for s in slices]
    if n >= 4 and all(t is not None for t in times):
        t = np.array(times, float)
        u = np.sort(t)
        jumps = np.diff(u)
        k = int(np.argmax(jumps)) if len(jumps) else 0
        within = np.r_[jumps[:k], jumps[k + 1:]]
        if len(jumps) and jumps[k] > max(2.0, 10.0 * (float(np.median(within)) if len(within) else 0.0)):
            member = (t > u[k]).astype(int)
            if _alternates(member):
                raise InputError(f"{what}: two acquisitions interleaved in one series (slice times alternate between "
                                 f"{_hms(u[0])} and {_hms(u[k + 1])} along the stack); they are not one volume: {hint}")
    inst = [s.instance for s in slices]
    if n >= 4 and all(i > 0 for i in inst) and len(set(inst)) < n:
        seen: dict = {}
        member = np.zeros(n, int)
        for j, i in sorted(enumerate(inst), key=lambda ji: (ji[1], str(slices[ji[0]].path))):
            member[j] = seen.get(i, 0)
            seen[i] = seen.get(i, 0) + 1
        if member.max() == 1 and _alternates(member):
            raise InputError(f"{what}: two acquisitions interleaved in one series (instance numbers run twice, the runs "
                             f"alternating along the stack); they are not one volume: {hint}")
    if n >= 8 and all(s.pixels is not None for s in slices):
        px = [np.asarray(s.pixels[::4, ::4], float) for s in slices]
        lag1 = np.array([np.mean(np.abs(px[i + 1] - px[i])) for i in range(n - 1)])
        lag2 = np.array([np.mean(np.abs(px[i + 2] - px[i])) for i in range(n - 2)])
        # every neighbour pair unlike, while slices two apart agree: two stacks taking turns
        if float(np.median(lag1)) > 2.0 * float(np.median(lag2)) + 1.0 and float(np.mean(lag1[:-1] > lag2)) > 0.8:
            raise InputError(f"{what}: neighbouring slices differ far more than slices two apart (median "
                             f"{np.median(lag1):.0f} vs {np.median(lag2):.0f} HU): two acquisitions interleaved in one "
                             f"series?; they are not one volume: {hint}")


def _hms(t: float) -> str:
    h, m = int(t // 3600), int(t % 3600 // 60)
    return f"{h:02d}:{m:02d}:{t % 60:04.1f}"
