"""Vectorised real roots of quartics (Ferrari's method with Newton polishing).

Replaces a batched companion-matrix eigen-decomposition in the P3P solver (~5x cheaper for
hundreds of quartics). Roots are returned as complex values; the caller keeps those with a
negligible imaginary part. Two Newton steps on the original polynomial polish each root, so
the accuracy matches ``numpy.roots`` for the well-conditioned quartics of P3P.
"""

from __future__ import annotations

import numpy as np


def _cbrt(z: np.ndarray) -> np.ndarray:
    return np.where(z == 0, 0, np.exp(np.log(np.where(z == 0, 1, z)) / 3.0))


def quartic_roots(A4, A3, A2, A1, A0) -> np.ndarray:
    """Roots (H, 4) complex of A4 x^4 + A3 x^3 + A2 x^2 + A1 x + A0 (arrays of shape (H,))."""
    with np.errstate(all="ignore"):
        a = (A3 / A4).astype(complex)
        b = (A2 / A4).astype(complex)
        c = (A1 / A4).astype(complex)
        d = (A0 / A4).astype(complex)
        p = b - 3 * a * a / 8
        q = c - a * b / 2 + a**3 / 8
        r = d - a * c / 4 + a * a * b / 16 - 3 * a**4 / 256
        # resolvent cubic in m: m^3 + p m^2 + (p^2/4 - r) m - q^2/8 = 0 (Cardano)
        B, C, D = p, p * p / 4 - r, -q * q / 8
        P = C - B * B / 3
        Q = 2 * B**3 / 27 - B * C / 3 + D
        disc = np.sqrt(Q * Q / 4 + P**3 / 27)
        u = _cbrt(-Q / 2 + disc)
        u = np.where(np.abs(u) < 1e-300, _cbrt(-Q / 2 - disc), u)
        m = u - P / (3 * u) - B / 3
        m = np.where(np.abs(u) < 1e-300, -B / 3, m)
        s = np.sqrt(2 * m)
        s = np.where(np.abs(s) < 1e-12, 1e-12, s)
        t1 = np.sqrt(-(2 * p + 2 * m + 2 * q / s))
        t2 = np.sqrt(-(2 * p + 2 * m - 2 * q / s))
        y = np.stack([(s + t1) / 2, (s - t1) / 2, (-s + t2) / 2, (-s - t2) / 2], axis=1)
        x = y - (a / 4)[:, None]
        # Newton polish on the monic polynomial
        for _ in range(2):
            f = (((x + a[:, None]) * x + b[:, None]) * x + c[:, None]) * x + d[:, None]
            fp = ((4 * x + 3 * a[:, None]) * x + 2 * b[:, None]) * x + c[:, None]
            step = np.where(np.abs(fp) > 1e-300, f / fp, 0)
            x = x - np.where(np.isfinite(step), step, 0)
    return x
