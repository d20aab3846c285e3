"""Balls found in the last frames of a still head, given back to a frame that misses them
(issue 28: a pose from more balls, sooner).

Why: on physically rendered frames a whole ball's acceptance flickers from frame to frame of a
still head: its edge fit, cut test and blob score sit near their limits and each frame's sensor
noise tips them one way or the other. On the Mitsuba tuning scenes (8 frames of a still head,
the default chain) a frame holds 60 / 31 / 35 / 28 of the whole balls that the 8 frames hold 75
/ 39 / 58 / 34 of (clean / OR / degraded / clutter, 10 scenes each); scenes whose frames hold
4 or more balls on average 8 / 3 / 5 / 2, with 4 or more over the 8 frames together 10 / 6 / 8 /
5. A ball's place does not change while the head is still, so a frame may use where the last
frames found it. docs/vision.md "Balls of the last frames of a still head" has the trust
figures (tuning and held-out).

What a remembered ball is: a ball the detector accepted in one of the last
:attr:`StillBallMemory.max_age_frames` frames (and at most :attr:`~StillBallMemory.max_age_s`
ago), with no ball of this frame on it. It is given back as that frame found it (centre,
outline, edge features), marked ``features["remembered_frames"]`` = its age in frames.

How motion is handled (the choices, written down): memory is taken from a past frame only when
the balls found in both frames have not moved between them: at least
:attr:`~StillBallMemory.min_agreeing` balls of this frame lie on balls of that frame (within
half a ball's minor semi-axis), none of them moved more than :attr:`~StillBallMemory.max_shift_px`
and their mean shift is at most :attr:`~StillBallMemory.max_common_px` (px). Each remembered
ball is tested against the frame it comes from, so drift cannot accumulate from frame to
frame: a head drifting slower than ``max_common_px`` over the age of a remembered ball leaves
it at most that far (plus the noise of the shift test) from where it is now. The first past
frame (newest first) that fails the test ends the search: older frames are further off. A
past frame sharing fewer than ``min_agreeing`` balls with this one cannot be tested and gives
nothing (the search goes on to the older frames). On
the rendered still frames the shift between consecutive frames is per ball p50 / p99 0.06 /
0.34 px (clean) to 0.19 / 0.56 px (degraded), the mean over a frame's balls p90 0.07-0.18 px,
p99 0.11-0.28 px (so a still head's frame now and then takes no memory: that costs only balls).
Frames skipped (a pipeline that drops frames) only age the memory; a detector's refusal of the
frame, a frame index that does not increase or a reset (the camera moved, a new registration)
clears it.

Units: image px (distorted image, as the detector's centres); frames by their index; s.
"""

from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np

from .detection import Detection, ImageFiducial


class StillBallMemory:
    """The balls of the last frames of a still head (see the module docstring).

    Args:
        max_age_frames: a ball is remembered for at most this many frames (0: never).
        max_age_s: ... and for at most this long (s), whatever the frame rate.
        max_shift_px: no ball found in both frames may have moved more than this (px).
        max_common_px: the mean shift of the balls found in both frames at most this (px).
        min_agreeing: at least this many balls of this frame found in the past frame too. The
            pose tracker passes its ``min_fiducials`` (4): memory only adds balls to a frame
            that could give a pose on its own. With 3 (tried), an instrument hiding all but 3
            balls would leave the pose standing on balls nobody sees for the memory's age, and
            3 agreeing balls close together cannot show a turn of the head about them, which
            moves the far, remembered balls most.
    """

    def __init__(self, max_age_frames: int = 7, max_age_s: float = 0.3, max_shift_px: float = 0.5,
                 max_common_px: float = 0.15, min_agreeing: int = 4):
        self.max_age_frames = max(0, int(max_age_frames))
        self.max_age_s = float(max_age_s)
        self.max_shift_px = float(max_shift_px)
        self.max_common_px = float(max_common_px)
        self.min_agreeing = max(1, int(min_agreeing))
        #: (frame index, t_capture s, the balls the detector accepted in that frame, their centres
        #: (k, 2) px, half their minor semi-axes (k,) px, its notes), oldest first
        self._frames: deque = deque(maxlen=max(1, self.max_age_frames))
        self._last_index: int | None = None
        #: the notes of the past frames this frame was found still against (newest first)
        self._still_notes: list = []

    def note(self, key: str, value) -> None:
        """Write down something the tracker measured in the frame last given to :meth:`fill`
        (e.g. the share of its balls with a contact shadow beside them), for the next frames of
        the still head to read with :meth:`still_notes`."""
        if self._frames:
            self._frames[-1][5][key] = value

    def still_notes(self, key: str) -> list:
        """The values of ``key`` that :meth:`note` wrote in past frames of which the frame last
        given to :meth:`fill` was found still (the balls they share not moved: the test that
        gives balls back, within the memory's age), newest first; empty with the memory off, after
        a reset, or for a frame with fewer than ``min_agreeing`` balls of its own."""
        return [n[key] for n in self._still_notes if key in n]

    def reset(self) -> None:
        """Forget every frame (a camera fault, the camera moved, a new registration)."""
        self._frames.clear()
        self._last_index = None
        self._still_notes = []

    def fill(self, det: Detection, frame_index: int, t_capture: float) -> Detection:
        """``det`` with the remembered balls it lacks appended (their ``features`` carry
        ``remembered_frames``), and this frame's own balls remembered. A detection the
        detector refused, or a frame index not after the last one, clears the memory first;
        with ``max_age_frames`` 0 ``det`` comes back as it is."""
        self._still_notes = []
        if self.max_age_frames <= 0:
            return det
        if det.refusal or (self._last_index is not None and frame_index <= self._last_index):
            self.reset()
        self._last_index = int(frame_index)
        own = [f for f in det.fiducials if "remembered_frames" not in f.features]
        centres = np.array([f.centre_px for f in own], float).reshape(-1, 2)
        near = 0.5 * np.array([min(f.axes_px) for f in own], float)
        added = self._remembered(centres, int(frame_index), float(t_capture))
        self._frames.append((int(frame_index), float(t_capture), own, centres, near, {}))
        if not added:
            return det
        return dataclasses.replace(det, fiducials=list(det.fiducials) + added)

    def _remembered(self, cur: np.ndarray, index: int, t: float) -> list:
        """The remembered balls for a frame whose own balls lie at ``cur`` ((n, 2) px)."""
        if not self._frames or len(cur) < self.min_agreeing:
            return []
        have = cur
        added = []
        for past_index, past_t, past, pc, near, notes in reversed(self._frames):
            age = index - past_index
            if age > self.max_age_frames or t - past_t > self.max_age_s:
                break
            still = self._still_since(cur, pc, near)
            if still is None:
                continue            # too few balls in common to tell: nothing from that frame
            if not still:
                break
            self._still_notes.append(notes)
            new = np.linalg.norm(pc[:, None] - have[None], axis=2).min(axis=1) >= near
            for k in np.flatnonzero(new):
                f = past[k]
                added.append(ImageFiducial(np.array(f.centre_px, float), f.axes_px, f.angle_deg, f.score,
                                           f.area_px, "", {**f.features, "remembered_frames": age}))
            have = np.concatenate([have, pc[new]])
        return added

    def _still_since(self, cur: np.ndarray, pc: np.ndarray, near: np.ndarray) -> bool | None:
        """Whether the balls of this frame (centres ``cur`` (n, 2) px) that lie on balls of a
        past frame (centres ``pc`` (m, 2) px, within ``near`` (m,) px of them) moved at most
        ``max_shift_px`` each and ``max_common_px`` on average since that frame; None when
        fewer than ``min_agreeing`` of them do (cannot tell)."""
        if not len(pc):
            return None
        d = np.linalg.norm(cur[:, None] - pc[None], axis=2)
        j = d.argmin(axis=1)
        rows = np.arange(len(cur))
        same = d[rows, j] < near[j]
        if same.sum() < self.min_agreeing:
            return None
        shift = cur[same] - pc[j[same]]
        return bool(np.linalg.norm(shift, axis=1).max() <= self.max_shift_px
                    and np.linalg.norm(shift.mean(axis=0)) <= self.max_common_px)
