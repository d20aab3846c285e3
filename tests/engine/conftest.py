import json

import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.sim.or_layout import default_layout
from monotracker.sim.phantom import default_phantom

from .doubles import FollowerRobotRig, TruthCameraRig


def plan_sample(session: Session) -> None:
    """Confirm the phantom's fiducials (as operator-added points) and set the sample path."""
    ph = default_phantom()
    for c in ph.fiducial_centres_lps:
        assert session.add_fiducial(c, ph.fiducial_radius_mm).ok
    assert session.confirm_fiducials().ok
    assert session.use_sample_plan().ok


def saved_plan(home) -> dict:
    """A complete plan (phantom fiducials, sample path, the twin's hand-eye) saved by a session
    in ``home``; its plan.json as written."""
    s = Session(SessionConfig(home=home, clock="sim"))
    try:
        plan_sample(s)
        assert s.set_hand_eye(default_layout().T_base_cam).ok
    finally:
        s.shutdown()
    return json.loads((home / "plan.json").read_text())


def restart(home, d=None, **kw) -> Session:
    """A new session on ``home`` (simulated clock, a still truth camera, a follower arm), after
    writing ``d`` as its plan.json when given: what a restart after a crash sees."""
    if d is not None:
        (home / "plan.json").write_text(json.dumps(d))
    cam, rob = TruthCameraRig("still"), FollowerRobotRig()
    return Session(SessionConfig(home=home, clock="sim", **kw), camera_factory=lambda *a: cam,
                   robot_factory=lambda *a: rob)


def alerts_of(s: Session, code: str) -> list:
    """The session's alerts of one code."""
    return [a for a in s.snapshot().alerts if a.code == code]


@pytest.fixture
def home(tmp_path):
    return tmp_path / "home"


@pytest.fixture
def make_session(home):
    made = []

    def make(**kw):
        factories = {k: kw.pop(k) for k in ("camera_factory", "robot_factory") if k in kw}
        cfg = SessionConfig(home=home, **kw)
        s = Session(cfg, **factories)
        made.append(s)
        return s

    yield make
    for s in made:
        s.shutdown()
