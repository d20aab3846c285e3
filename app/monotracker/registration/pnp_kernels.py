"""The pose refinement of :mod:`.pnp`, compiled (numba): residuals, analytic Jacobian and the
Levenberg-Marquardt loop in one machine-code function.

:func:`.pnp.refine_pose` is called ~5-15 times per frame (the registration's fit, the
moved-fiducial screening's leave-one-out refits, the still-head pool): in NumPy each call spent
~1-2 ms in the overhead of small array operations on 9 points, ~9 ms of the frame's 33 ms. The
NumPy functions of :mod:`.pnp` stay the reference (``refine_pose_reference``,
``residuals_and_jacobian_reference``); ``tests/registration/test_pnp_kernels.py`` checks that both
give the same pose, residuals, normal matrix and Jacobian. Same model and parametrisation (see
:mod:`.pnp`): left perturbation (w rad, dt mm, camera frame), residuals in equivalent pinhole px,
the exact sphere-bias model when ``radius_mm`` > 0. The 6x6 damped normal equations are solved by
Gaussian elimination with partial pivoting (LAPACK's ``gesv`` does the same; an exactly zero
pivot is the singular case where NumPy raises ``LinAlgError``: the damping grows, as there).
"""

from __future__ import annotations

import math

import numpy as np

from .compiled import compiled


@compiled
def residuals_and_jacobian(R, t, X, obs, fx, fy, radius, sw, r, J):
    """Fill r (2k,) px and J (2k, 6) px per (rad, mm) for the pose (R (3, 3), t (3,) mm), model
    points X (k, 3) mm, normalised observations obs (k, 2); ``radius`` mm (0: plain pinhole, as None in :mod:`.pnp`);
    ``sw`` (2k,) row weights (sqrt of the point weights, repeated) or an empty array."""
    k = X.shape[0]
    R2 = radius * radius
    weighted = sw.shape[0] > 0
    for i in range(k):
        q0 = R[0, 0] * X[i, 0] + R[0, 1] * X[i, 1] + R[0, 2] * X[i, 2]
        q1 = R[1, 0] * X[i, 0] + R[1, 1] * X[i, 1] + R[1, 2] * X[i, 2]
        q2 = R[2, 0] * X[i, 0] + R[2, 1] * X[i, 1] + R[2, 2] * X[i, 2]
        a = q0 + t[0]
        b = q1 + t[1]
        c = q2 + t[2]
        if radius != 0.0:
            den = c * c - R2
            s = c / den
            ds = -(c * c + R2) / (den * den)
        else:
            s = 1.0 / c
            ds = -1.0 / (c * c)
        u, v = 2 * i, 2 * i + 1
        r[u] = (a * s - obs[i, 0]) * fx
        r[v] = (b * s - obs[i, 1]) * fy
        # d proj / d Xc = [[s, 0, a ds], [0, s, b ds]] (times fx, fy); d Xc / d w = -[q]x
        ads, bds = a * ds, b * ds
        J[u, 0] = fx * (ads * q1)
        J[u, 1] = fx * (s * q2 - ads * q0)
        J[u, 2] = fx * (-s * q1)
        J[u, 3] = fx * s
        J[u, 4] = 0.0
        J[u, 5] = fx * ads
        J[v, 0] = fy * (-s * q2 + bds * q1)
        J[v, 1] = fy * (-bds * q0)
        J[v, 2] = fy * (s * q0)
        J[v, 3] = 0.0
        J[v, 4] = fy * s
        J[v, 5] = fy * bds
        if weighted:
            for row in (u, v):
                r[row] *= sw[row]
                for col in range(6):
                    J[row, col] *= sw[row]


@compiled
def _so3_exp(w, out):
    """Rodrigues: the rotation matrix of the rotation vector w (3,) rad into out (3, 3)."""
    th = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    if th < 1e-8:
        A, B = 1.0, 0.5
    else:
        A = math.sin(th) / th
        B = (1.0 - math.cos(th)) / (th * th)
    Kx = np.zeros((3, 3))
    Kx[0, 1], Kx[0, 2] = -w[2], w[1]
    Kx[1, 0], Kx[1, 2] = w[2], -w[0]
    Kx[2, 0], Kx[2, 1] = -w[1], w[0]
    for i in range(3):
        for j in range(3):
            kk = 0.0
            for m in range(3):
                kk += Kx[i, m] * Kx[m, j]
            out[i, j] = (1.0 if i == j else 0.0) + A * Kx[i, j] + B * kk


@compiled
def _solve(A, g, x):
    """x = A^-1 g for a small square A (Gaussian elimination, partial pivoting); False when a
    pivot is exactly zero (singular)."""
    n = A.shape[0]
    M = A.copy()
    y = g.copy()
    for col in range(n):
        p = col
        best = abs(M[col, col])
        for row in range(col + 1, n):
            if abs(M[row, col]) > best:
                best = abs(M[row, col])
                p = row
        if best == 0.0:
            return False
        if p != col:
            for j in range(n):
                M[col, j], M[p, j] = M[p, j], M[col, j]
            y[col], y[p] = y[p], y[col]
        for row in range(col + 1, n):
            f = M[row, col] / M[col, col]
            if f != 0.0:
                for j in range(col, n):
                    M[row, j] -= f * M[col, j]
                y[row] -= f * y[col]
    for row in range(n - 1, -1, -1):
        acc = y[row]
        for j in range(row + 1, n):
            acc -= M[row, j] * x[j]
        x[row] = acc / M[row, row]
    return True


@compiled
def _normal(J, r, JtJ, g):
    n, m = J.shape
    for a in range(m):
        acc = 0.0
        for i in range(n):
            acc += J[i, a] * r[i]
        g[a] = acc
        for b in range(a, m):
            acc = 0.0
            for i in range(n):
                acc += J[i, a] * J[i, b]
            JtJ[a, b] = acc
            JtJ[b, a] = acc


@compiled
def refine(R0, t0, X, obs, fx, fy, radius, sw, max_iter, tol):
    """The LM loop of :func:`.pnp.refine_pose_reference`, step for step. Returns (R, t,
    iterations, converged, JtJ of the weighted Jacobian at the optimum)."""
    k = X.shape[0]
    R = R0.copy()
    t = t0.copy()
    lam = 1e-3
    r = np.empty(2 * k)
    J = np.empty((2 * k, 6))
    rn = np.empty(2 * k)
    Jn = np.empty((2 * k, 6))
    residuals_and_jacobian(R, t, X, obs, fx, fy, radius, sw, r, J)
    cost = 0.0
    for i in range(2 * k):
        cost += r[i] * r[i]
    JtJ = np.empty((6, 6))
    g = np.empty(6)
    A = np.empty((6, 6))
    dx = np.zeros(6)
    Rd = np.empty((3, 3))
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - the count is returned after the loop
        _normal(J, r, JtJ, g)
        improved = False
        rel = 0.0
        dx[:] = 0.0
        for _ in range(8):
            for a in range(6):
                for b in range(6):
                    A[a, b] = JtJ[a, b]
                A[a, a] += lam * (JtJ[a, a] + 1e-12)
            if not _solve(A, -g, dx):
                lam *= 10.0
                continue
            _so3_exp(dx[:3], Rd)
            Rn = np.empty((3, 3))
            for a in range(3):
                for b in range(3):
                    Rn[a, b] = Rd[a, 0] * R[0, b] + Rd[a, 1] * R[1, b] + Rd[a, 2] * R[2, b]
            tn = t + dx[3:]
            residuals_and_jacobian(Rn, tn, X, obs, fx, fy, radius, sw, rn, Jn)
            cn = 0.0
            for i in range(2 * k):
                cn += rn[i] * rn[i]
            if np.isfinite(cn) and cn <= cost:
                rel = (cost - cn) / max(cost, 1e-30)
                R, t, cost = Rn, tn, cn
                r, rn = rn, r
                J, Jn = Jn, J
                lam = max(lam * 0.3, 1e-9)
                improved = True
                break
            lam *= 10.0
        nd = 0.0
        for a in range(6):
            nd += dx[a] * dx[a]
        if not improved or rel < tol or math.sqrt(nd) < 1e-12:
            converged = True
            break
    _normal(J, r, JtJ, g)
    return R, t, it, converged, JtJ


def warm_up() -> None:
    """Compile (or load from the cache) the kernels on a tiny input, off the time-critical path."""
    X = np.array([[0.0, 0, 0], [30, 0, 0], [0, 30, 0], [0, 0, 30]])
    obs = (X[:, :2] / (X[:, 2:] + 500.0))
    r, J = np.empty(8), np.empty((8, 6))
    R, t = np.eye(3), np.array([0.0, 0.0, 500.0])
    residuals_and_jacobian(R, t, X, obs, 1000.0, 1000.0, 4.0, np.empty(0), r, J)
    refine(R, t, X, obs, 1000.0, 1000.0, 4.0, np.empty(0), 5, 1e-9)
