"""Each CT fiducial's state over the frames of a pose stream (:class:`FiducialStates`): the status
words of :mod:`.pose_estimate` and the one-line alerts a change of state raises.

``seen`` (found in this frame), ``newly_lost`` (found in the previous frame, not now: the alert
is raised in this same frame), ``occluded`` (not found now nor in the previous frame),
``unknown`` (no frame has found it yet), ``moved`` (excluded: it moved relative to the others).
A ball the tracker took from the last frames of a still head (:mod:`.ball_memory`) counts as
seen for ``occluded`` but not as found now. No geometry here: :mod:`.pose_tracker` says which
fiducials each frame found.
"""

from __future__ import annotations

import numpy as np

from .pose_estimate import MOVED, NEWLY_LOST, OCCLUDED, SEEN, UNKNOWN


class FiducialStates:
    """What the stream knows of ``n`` fiducials from the frames so far."""

    def __init__(self, n: int):
        self.n = int(n)
        self.prev_found = np.zeros(self.n, bool)    # found in the last frame
        self.ever_seen = np.zeros(self.n, bool)     # found (or remembered) in any frame so far
        self.last_aside: list = []                  # fiducials set aside in the last frame (alerted once)

    def _status(self, found_now: np.ndarray, excluded) -> list[str]:
        return [MOVED if j in excluded else SEEN if found_now[j] else NEWLY_LOST if self.prev_found[j]
                else OCCLUDED if self.ever_seen[j] else UNKNOWN for j in range(self.n)]

    def after_frame(self, seen: np.ndarray, remembered: np.ndarray, excluded, aside: list,
                    frame_index: int) -> tuple[list[str], list[str]]:
        """The statuses of a frame that was judged (``seen``: (n,) bool, matched or found near
        the last pose's projection; ``remembered``: (n,) bool, of those taken from the last
        frames; ``excluded``: fiducial indices excluded as moved; ``aside``: [(detection index,
        fiducial, px)] set aside for this frame) and the alerts its changes raise: a new set of
        balls set aside (once while it stays the same), balls newly lost. Remembers this frame."""
        found_now = seen & ~remembered      # found in this frame (a remembered ball is not)
        status = self._status(found_now, excluded)
        alerts = []
        ids = [j for _, j, _ in aside]
        if aside and ids != self.last_aside:
            alerts.append("; ".join(f"fiducial {j} set aside in frame {frame_index}: found {px:.1f} px from where "
                                    "the others put it (partly hidden or off?)" for _, j, px in aside))
        self.last_aside = ids
        lost = [j for j, s in enumerate(status) if s == NEWLY_LOST]
        if lost:
            alerts.append(f"fiducial{'s' if len(lost) > 1 else ''} {', '.join(map(str, lost))} lost "
                          f"(occluded?) in frame {frame_index}")
        self.prev_found = found_now
        self.ever_seen |= seen
        return status, alerts

    def after_invalid(self, excluded) -> list[str]:
        """The statuses of a frame that saw nothing (a camera fault, an unusable frame: every ball
        found in the last frame is newly lost); the next frame starts from nothing found."""
        status = self._status(np.zeros(self.n, bool), excluded)
        self.prev_found = np.zeros(self.n, bool)
        return status
