"""Cached quantiles of the chi-square and F distributions (scipy.stats' ``ppf`` costs ~0.1-1 ms
a call in its argument checks, and the trust gates ask the same few (probability, dof)
questions every frame: ~15 % of a frame's CPU before caching). A new (probability, dof) -- each
frame while the pooled noise estimate's dof grow, the first ~30 frames of a stream -- goes to
the special function that ``ppf`` itself evaluates (``gammaincinv``, ``fdtri``: the same
numbers, ~4 us instead of ~130 us a call)."""

from __future__ import annotations

from functools import lru_cache

from scipy import special
from scipy.stats import chi2
from scipy.stats import f as f_dist


@lru_cache(maxsize=4096)
def _chi2_ppf(q: float, dof: int) -> float:
    if 0.0 < q < 1.0 and dof > 0:
        return float(2.0 * special.gammaincinv(dof / 2.0, q))     # scipy.stats.chi2._ppf
    return float(chi2.ppf(q, dof))


@lru_cache(maxsize=4096)
def _f_ppf(q: float, d1: int, d2: int) -> float:
    if 0.0 < q < 1.0 and d1 > 0 and d2 > 0:
        return float(special.fdtri(d1, d2, q))                      # scipy.stats.f._ppf
    return float(f_dist.ppf(q, d1, d2))


def chi2_ppf(q: float, dof) -> float:
    """``scipy.stats.chi2.ppf(q, dof)``, cached (integer dof as the registrations have)."""
    d = float(dof)
    return _chi2_ppf(float(q), int(d)) if d == int(d) else float(chi2.ppf(q, d))


def f_ppf(q: float, d1, d2) -> float:
    """``scipy.stats.f.ppf(q, d1, d2)``, cached for integer dof."""
    a, b = float(d1), float(d2)
    if a == int(a) and b == int(b):
        return _f_ppf(float(q), int(a), int(b))
    return float(f_dist.ppf(q, a, b))
