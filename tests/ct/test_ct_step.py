"""The web UI's CT step at callback level (a fake viser GUI, the real session): a DICOM folder
with several series is listed and never loaded silently, the chosen series is loaded; the
fiducial kit fields reach ``Session.set_fiducial_kit``; rejected blobs are listed."""

from __future__ import annotations

import threading
from contextlib import nullcontext

import numpy as np
import pytest

from ct_test_helpers import gated_load

from monotracker.engine import Session, SessionConfig
from monotracker.sim.dicom_writer import stack_specs, write_series
from monotracker.ui import step_ct


def _field(p):
    """Air around a 1500 HU ball in 40 HU tissue (a CT the loader accepts)."""
    r = np.linalg.norm(p - np.array([16.0, 16.0, 8.0]), axis=-1)
    return np.where(r < 5.0, 1500.0, np.where(r < 10.0, 40.0, -1000.0))


class Handle:
    def __init__(self, label, value=None, visible=True, options=()):
        self.label, self.value, self.visible, self.options, self.content = label, value, visible, options, ""
        self.cb = None

    def on_click(self, fn):
        self.cb = fn
        return fn

    on_update = on_click


class FakeGui:
    def __init__(self):
        self.h = {}

    def _add(self, label, value=None, visible=True, options=()):
        h = Handle(label, value, visible, options)
        self.h[label] = h
        return h

    def add_folder(self, label):
        return nullcontext()

    def add_markdown(self, content=""):
        return self._add(f"md{len(self.h)}")

    def add_html(self, content="", visible=True):
        return self._add(f"html{len(self.h)}", visible=visible)

    def add_text(self, label, value, hint=None):
        return self._add(label, value)

    def add_button(self, label, color=None, visible=True):
        return self._add(label, visible=visible)

    def add_progress_bar(self, value, visible=True, animated=False):
        return self._add(f"progress{len(self.h)}", value, visible)

    def add_number(self, label, value, min=None, max=None, step=None, hint=None):
        return self._add(label, value)

    def add_button_group(self, label, options):
        return self._add(label, options=options)

    def add_vector3(self, label, value, step=None):
        return self._add(label, value)

    def add_dropdown(self, label, options, initial_value=None, hint=None, visible=True):
        return self._add(label, initial_value, visible, options)


class FakeView:
    def __init__(self, session):
        self.gui, self.session, self.lock, self.selected_fid = FakeGui(), session, threading.Lock(), 0
        self.said, self.watching = [], False

    def safe(self, what):
        return lambda fn: fn

    def say(self, ok, text):
        self.said.append((ok, text))

    def run(self, what, fn, *args):
        r = fn(*args)
        self.say(r.ok, f"{what}: {r.message}")
        return r

    def watch_job(self):
        self.watching = True


@pytest.fixture
def step(tmp_path, monkeypatch):
    monkeypatch.setattr(step_ct, "SlicePanel", lambda view, name: None)
    s = Session(SessionConfig(home=tmp_path / "home", clock="sim"))
    view = FakeView(s)
    yield step_ct.CtStep(view), view, s
    s.shutdown()


def test_several_series_are_listed_and_the_chosen_one_is_loaded(tmp_path, step):
    ui, view, s = step
    folder = tmp_path / "two"
    write_series(folder, stack_specs(np.arange(16) * 1.0), _field, series_uid="1.2.3.1", description="big")
    write_series(folder, stack_specs(np.arange(12) * 2.0, shear_y_per_mm=np.tan(np.radians(15.0))), _field,
                 series_uid="1.2.3.2", description="tilted")
    g = view.gui.h
    g["CT file or folder"].value = str(folder)
    g["Open CT"].cb(None)
    assert s.wait_for_job(1) is None  # nothing loaded: the operator must choose
    ok, text = view.said[-1]
    assert not ok and "2 series" in text
    assert g["Series"].visible and g["Open chosen series"].visible
    labels = list(g["Series"].options)
    assert len(labels) == 2 and "big, 16 slices" in labels[0] and "tilted, 12 slices" in labels[1]
    assert "tilt 15.0 deg" in labels[1] and "2.00 mm" in labels[1]
    html = ui.h_series_info.content
    assert "tilted" in html and "big" in html
    g["Series"].value = labels[1]
    g["Open chosen series"].cb(None)
    job = s.wait_for_job(300)
    assert job is not None and job.done and job.error is None, job
    assert view.watching and s.volume().array.shape[0] == 12
    assert any("gantry tilt 15.0 deg" in n for n in s.snapshot().ct.notes)


def test_a_single_series_folder_loads_at_once(tmp_path, step):
    ui, view, s = step
    folder = tmp_path / "one"
    write_series(folder, stack_specs(np.arange(16) * 1.0), _field, series_uid="1.2.3.9", description="only")
    view.gui.h["CT file or folder"].value = str(folder)
    view.gui.h["Open CT"].cb(None)
    job = s.wait_for_job(300)
    assert job is not None and job.done and job.error is None, job
    assert not view.gui.h["Series"].visible


def test_kit_fields_reach_the_session_and_bad_density_is_one_line(step):
    ui, view, s = step
    g = view.gui.h
    g["Ball radius (mm)"].value = 3.0
    g["Ball density (HU)"].value = "ceramic"
    g["Apply fiducial kit (detect again)"].cb(None)
    ok, text = view.said[-1]
    assert not ok and "density must be a number" in text and s.plan_copy().fiducial_kit is None
    g["Ball density (HU)"].value = "1600"
    g["Apply fiducial kit (detect again)"].cb(None)
    assert view.said[-1][0], view.said[-1]
    kit = s.plan_copy().fiducial_kit
    assert (kit.radius_mm, kit.density_hu) == (3.0, 1600.0)
    g["Ball radius (mm)"].value = 40.0
    g["Apply fiducial kit (detect again)"].cb(None)
    ok, text = view.said[-1]
    assert not ok and "implausible" in text


def test_rejected_blobs_are_listed():
    from types import SimpleNamespace

    from monotracker.engine.snapshot import CTRejectedBlob, CTSummary

    ct = CTSummary("x.nii.gz", (10, 10, 10), (1.0, 1.0, 1.0),
                   rejected=(CTRejectedBlob((1.0, 2.0, 3.0), 2.5, 120, "not round: 14.4 x 2.2 mm <clip>"),))
    html = step_ct.rejected_table(SimpleNamespace(ct=ct))
    assert "1.0, 2.0, 3.0" in html and "not round" in html and "&lt;clip&gt;" in html and "120" in html
    assert step_ct.rejected_table(SimpleNamespace(ct=None)) == ""


def test_cancel_button_stops_a_running_load(tmp_path, step, monkeypatch):
    ui, view, s = step
    gate, entered = gated_load(monkeypatch)
    folder = tmp_path / "one"
    write_series(folder, stack_specs(np.arange(16) * 1.0), _field, series_uid="1.2.3.9", description="only")
    view.gui.h["CT file or folder"].value = str(folder)
    view.gui.h["Open CT"].cb(None)
    assert entered.wait(60)
    assert s.snapshot().job is not None and not s.snapshot().job.done
    view.gui.h["Cancel CT job"].cb(None)
    assert view.said[-1][0], view.said[-1]
    job = s.snapshot().job
    assert job.done and "cancelled by the operator" in job.error
    gate.set()
    s.wait_for_job(300)
    assert s.snapshot().ct is None  # nothing of the cancelled load was kept


def test_kit_fields_show_the_plans_kit(tmp_path, monkeypatch):
    monkeypatch.setattr(step_ct, "SlicePanel", lambda view, name: None)
    s = Session(SessionConfig(home=tmp_path / "home", clock="sim"))
    try:
        assert s.set_fiducial_kit(2.5, 1700.0).ok
        view = FakeView(s)
        step_ct.CtStep(view)
        assert view.gui.h["Ball radius (mm)"].value == 2.5 and view.gui.h["Ball density (HU)"].value == "1700"
    finally:
        s.shutdown()


def test_ball_finish_choice_reaches_the_plan_and_shows_what_the_plan_says(step):
    """The "Ball finish" dropdown: every finish vision knows has one choice; a choice is kept in
    the plan (``Session.set_ball_finish``); a refused one is shown back as the plan's; a change
    made elsewhere (another tab) is shown at the next render."""
    from monotracker.vision.ball_gloss import FINISHES

    assert {v for v in step_ct.FINISH_CHOICES.values() if v is not None} == set(FINISHES)
    ui, view, s = step
    h = view.gui.h["Ball finish"]
    assert h.value == "as launched (read)" and h.value in h.options  # a new plan: the launch setting, named
    h.value = "glossy"
    h.cb(None)
    assert view.said[-1][0] and s.plan_copy().ball_finish == "glossy", view.said[-1]
    n = len(view.said)
    h.cb(None)                                                       # the same again: nothing to do
    assert len(view.said) == n and len(s.audit_entries(code="ball_finish_set")) == 1
    s._plan._robot_state = lambda: "armed"                           # the arm engaged: refused
    h.value = "matte"
    h.cb(None)
    assert not view.said[-1][0] and "disarm" in view.said[-1][1]
    assert h.value == "glossy" and s.plan_copy().ball_finish == "glossy"
    s._plan._robot_state = lambda: "disarmed"
    assert s.set_ball_finish("matte").ok                             # another tab
    ui.slices = type("NoSlices", (), {"render": lambda *a: None})()
    ui.render(s.snapshot())
    assert h.value == "matte"
