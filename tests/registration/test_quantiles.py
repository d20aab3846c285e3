"""The cached quantiles (registration.quantiles) are scipy.stats' ppf, new arguments included."""

import pytest
from scipy.stats import chi2, f

from monotracker.registration import quantiles


@pytest.mark.parametrize("q", [1e-6, 0.001, 0.05, 0.5, 0.95, 0.99, 0.999, 1 - 1e-9])
def test_quantiles_equal_scipy_stats(q):
    for d in (1, 2, 3, 7, 30, 200, 5000):
        assert quantiles.chi2_ppf(q, d) == pytest.approx(chi2.ppf(q, d), rel=1e-12)
        assert quantiles.chi2_ppf(q, d + 0.5) == pytest.approx(chi2.ppf(q, d + 0.5), rel=1e-12)
        for d2 in (1, 4, 17, 300):
            assert quantiles.f_ppf(q, d, d2) == pytest.approx(f.ppf(q, d, d2), rel=1e-12)


def test_quantiles_at_the_ends_as_scipy_stats():
    assert quantiles.chi2_ppf(0.0, 3) == chi2.ppf(0.0, 3) and quantiles.chi2_ppf(1.0, 3) == chi2.ppf(1.0, 3)
    assert quantiles.f_ppf(1.0, 2, 5) == f.ppf(1.0, 2, 5) and quantiles.f_ppf(0.0, 2, 5) == f.ppf(0.0, 2, 5)
