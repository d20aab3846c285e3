import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.sim.phantom import default_phantom


def plan_sample(session: Session) -> None:
    """Confirm the phantom's fiducials (as operator-added points) and set the sample path
    (no CT load: fast)."""
    ph = default_phantom()
    for c in ph.fiducial_centres_lps:
        assert session.add_fiducial(c, ph.fiducial_radius_mm).ok
    assert session.confirm_fiducials().ok
    assert session.use_sample_plan().ok


@pytest.fixture(scope="module")
def planned_home(tmp_path_factory):
    """A session folder holding a locked plan on the phantom's fiducials and the sample path."""
    home = tmp_path_factory.mktemp("planned")
    s = Session(SessionConfig(home=home, clock="sim"))
    plan_sample(s)
    s.shutdown()
    return home


@pytest.fixture
def fresh_home(planned_home, tmp_path):
    import shutil

    home = tmp_path / "home"
    home.mkdir()
    shutil.copy(planned_home / "plan.json", home / "plan.json")
    return home
