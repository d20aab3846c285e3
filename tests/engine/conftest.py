import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.sim.phantom import default_phantom


def plan_sample(session: Session) -> None:
    """Confirm the phantom's fiducials (as operator-added points) and set the sample path."""
    ph = default_phantom()
    for c in ph.fiducial_centres_lps:
        assert session.add_fiducial(c, ph.fiducial_radius_mm).ok
    assert session.confirm_fiducials().ok
    assert session.use_sample_plan().ok


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
