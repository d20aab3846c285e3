"""Two acquisitions interleaved under one series and one AcquisitionNumber (two stacks offset by
half a spacing) are refused with one line, not read as one volume at half the spacing; series
that only look alike (a helical run with rising times, two acquisitions one above the other,
two motion-free interleaved stacks: true positions, a right volume) still load. Series are
written with pydicom, every slice with its true position and time."""

from __future__ import annotations

import numpy as np
import pytest

from monotracker.ct import list_series, load_volume
from monotracker.errors import InputError
from monotracker.sim.dicom_writer import SliceSpec, axial_iop, write_series

N = 12
SP = 1.6667


def _field(p):
    """A 1500 HU ball in 40 HU tissue in air, with a gradient (real content along the stack)."""
    r = np.linalg.norm(p - np.array([16.0, 16.0, 10.0]), axis=-1)
    return np.where(r < 6.0, 1500.0, np.where(r < 13.0, 40.0 + 3.0 * p[:, 2], -1000.0))


def _interleaved(times: bool, duplicate_instances: bool, shift_mm: float = 0.0) -> list[SliceSpec]:
    a = [SliceSpec(np.array([0.0, 0.0, k * SP]), axial_iop(), instance=k + 1, acquisition=1,
                   time_s=36000.0 + 0.5 * k if times else None) for k in range(N)]
    b = [SliceSpec(np.array([0.0, 0.0, (k + 0.5) * SP]), axial_iop(), instance=(k + 1) if duplicate_instances else N + k + 1,
                   acquisition=1, time_s=36300.0 + 0.5 * k if times else None, shift_mm=(0.0, shift_mm, 0.0)) for k in range(N)]
    return a + b


@pytest.mark.parametrize("times,dup,shift,word", [
    (True, False, 0.0, "slice times alternate"),
    (False, True, 0.0, "instance numbers run twice"),
    (False, False, 3.0, "neighbouring slices differ"),
])
def test_interleaved_acquisitions_are_refused(tmp_path, times, dup, shift, word):
    folder = tmp_path / "inter"
    write_series(folder, _interleaved(times, dup, shift), _field)
    with pytest.raises(InputError) as exc:
        load_volume(folder)
    msg = str(exc.value)
    assert word in msg and "interleaved" in msg and "\n" not in msg, msg
    if times or dup:  # the header evidence is seen when listing, too
        (info,) = list_series(folder)
        assert not info.ok and any(word in n for n in info.notes), info.notes


def test_look_alikes_still_load(tmp_path):
    # a helical series: times rising slice by slice
    helical = [SliceSpec(np.array([0.0, 0.0, k * 0.8]), axial_iop(), time_s=36000.0 + 0.3 * k) for k in range(2 * N)]
    write_series(tmp_path / "helical", helical, _field)
    assert load_volume(tmp_path / "helical").array.shape[0] == 2 * N
    # two acquisitions one above the other (a long scan in two parts), 5 minutes apart
    parts = [SliceSpec(np.array([0.0, 0.0, k * 0.8]), axial_iop(), time_s=(36000.0 if k < N else 36300.0) + 0.3 * k)
             for k in range(2 * N)]
    write_series(tmp_path / "parts", parts, _field)
    assert load_volume(tmp_path / "parts").array.shape[0] == 2 * N
    # interleaved stacks with continuing numbers and no motion: the true positions, a right volume
    write_series(tmp_path / "still", _interleaved(False, False, 0.0), _field)
    vol = load_volume(tmp_path / "still")
    assert vol.array.shape[0] == 2 * N and abs(vol.spacing_mm[2] - SP / 2) < 1e-3
