"""The 3D context view beside the live camera overlay: what moves in it is sent at most once per
``LIVE_SCENE_PERIOD_S`` on a live step (each change makes the browser redraw the whole 3D view,
which starved the live image without a GPU), on every tick elsewhere, and at once when the step
changes or the head appears. Time is a fake clock; the scene a recording double."""

from __future__ import annotations

import threading
from types import SimpleNamespace
from unittest.mock import MagicMock

import numpy as np

from monotracker.ui import scene as scene_mod
from monotracker.ui.scene import LIVE_SCENE_PERIOD_S, SceneView


def _snap(T_cam_ct):
    return SimpleNamespace(
        head_mesh=None, fiducials=(), plan=SimpleNamespace(entry_lps_mm=None, target_lps_mm=None),
        scene=SimpleNamespace(T_cam_ct=T_cam_ct, T_base_ct=None, T_base_cam=None, q=None, T_base_tip=None),
        camera=SimpleNamespace(K=None, image_size=None))


def _pose(x_mm):
    T = np.eye(4)
    T[:3, 3] = (x_mm, 0.0, 400.0)
    return T


def test_live_step_sends_the_head_pose_at_most_once_per_period(monkeypatch):
    view = MagicMock()
    view.scene_keys = {}
    view.nav_panel.return_value = None
    view.nav_scene.scene_lock = threading.Lock()
    view.scene.add_frame.side_effect = lambda name, **kw: SimpleNamespace(name=name, visible=kw.get("visible", True))
    sv = SceneView(view)
    now = [1000.0]
    monkeypatch.setattr(scene_mod.time, "monotonic", lambda: now[0])
    sent = []  # (step, t, x mm) of every pose the ct group got
    step_now = ["plan"]
    monkeypatch.setattr(SceneView, "_set_pose", lambda self, h, T: sent.append((step_now[0], now[0], T[0, 3]))
                        if h is self._ct_frame else None)
    dt = 0.125  # the render thread's tick (s)

    def tick(step, snap):
        step_now[0] = step
        sv.render(snap, step)
        now[0] += dt

    for _ in range(4):  # off the live steps: every tick
        tick("plan", _snap(None))
    assert len(sent) == 4
    sent.clear()
    # Register, no pose yet: the head is hidden, nothing to send
    tick("register", _snap(None))
    assert sent == [] and sv._ct_frame.visible is False
    # the first pose shows the head at once
    t_first = now[0]
    tick("register", _snap(_pose(0.0)))
    assert [(t, x) for _, t, x in sent] == [(t_first, 0.0)]
    # a moving head, 8 Hz poses for 3 s: at most one pose per period, and the newest each time
    for k in range(1, 25):
        tick("register", _snap(_pose(float(k))))
    times = [t for _, t, _ in sent]
    assert all(b - a >= LIVE_SCENE_PERIOD_S - 1e-9 for a, b in zip(times, times[1:])), times
    assert len(sent) == 1 + int(24 * dt / LIVE_SCENE_PERIOD_S)  # 3 s of poses: 3 more
    # each one sent is the newest pose of its tick (x mm = tick index since the first pose)
    assert all(x == round((t - t_first) / dt) for _, t, x in sent)
    # leaving the live step: the next step's first tick sends at once, and every tick after it
    sent.clear()
    t_plan = now[0]
    tick("plan", _snap(None))
    tick("plan", _snap(None))
    assert [t for _, t, _ in sent] == [t_plan, t_plan + dt]
