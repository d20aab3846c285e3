import pytest

from monotracker.sim.camera_sim import SimulatedCamera


@pytest.fixture(scope="session")
def sim_still():
    """One still simulated camera shared by tests (construction costs ~1 s)."""
    return SimulatedCamera(seed=0)
