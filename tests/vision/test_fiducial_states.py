"""Each fiducial's status over the frames (vision/fiducial_states.py), against hand-written
sequences."""

import numpy as np

from monotracker.vision.fiducial_states import FiducialStates


def _b(*idx, n=4):
    out = np.zeros(n, bool)
    out[list(idx)] = True
    return out


def test_statuses_and_alerts_over_a_hand_written_sequence():
    st = FiducialStates(4)
    none = _b()
    # frame 0: 0 and 1 found; 2 and 3 never seen
    status, alerts = st.after_frame(_b(0, 1), none, {}, [], 0)
    assert status == ["seen", "seen", "unknown", "unknown"] and alerts == []
    # frame 1: 1 lost (alerted in this frame), 2 found, 3 excluded as moved
    status, alerts = st.after_frame(_b(0, 2), none, {3: 1.4}, [], 1)
    assert status == ["seen", "newly_lost", "seen", "moved"]
    assert alerts == ["fiducial 1 lost (occluded?) in frame 1"]
    # frame 2: 1 still missing (occluded now, no second alert); 0 taken from the last frames
    # (remembered: seen for the record, not found now -> newly lost)
    status, alerts = st.after_frame(_b(0, 2), _b(0), {3: 1.4}, [], 2)
    assert status == ["newly_lost", "occluded", "seen", "moved"]
    assert alerts == ["fiducial 0 lost (occluded?) in frame 2"]
    # frame 3: 2 set aside (found, left out of the pose): alerted once while the set stays
    status, alerts = st.after_frame(_b(0, 2), none, {3: 1.4}, [(5, 2, 1.84)], 3)
    assert status[0] == "seen" and status[2] == "seen"
    assert alerts == ["fiducial 2 set aside in frame 3: found 1.8 px from where the others put it (partly hidden or off?)"]
    _, alerts = st.after_frame(_b(0, 2), none, {3: 1.4}, [(5, 2, 1.9)], 4)
    assert alerts == []
    # a frame that saw nothing: what the last frame found is newly lost, then occluded
    assert st.after_invalid({3: 1.4}) == ["newly_lost", "occluded", "newly_lost", "moved"]
    assert st.after_invalid({3: 1.4}) == ["occluded", "occluded", "occluded", "moved"]
