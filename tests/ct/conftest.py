"""Shared fixtures for the CT tests: small synthetic scans generated once per session."""

from __future__ import annotations

import pytest
from ct_test_helpers import patch_params

from monotracker.sim.ct_phantom import generate_ct
from monotracker.sim.phantom import default_phantom


@pytest.fixture(scope="session")
def patch_ct():
    """Fiducial patch at 0.5 x 0.5 x 1.0 mm with the default oblique direction and noise."""
    return generate_ct(default_phantom(), patch_params())


@pytest.fixture(scope="session")
def patch_volume(patch_ct):
    from monotracker.ct.volume import Volume

    return Volume.from_image(patch_ct.to_sitk(), source="patch")
