"""The sphere fits of :mod:`.sphere_fit`, compiled (numba): a bounded, robust Levenberg-Marquardt.

:mod:`.sphere_fit` documents the two models (a blurred ball; a blurred ball resting on / sunk
into a blurred plane) and keeps SciPy's ``least_squares`` as the reference
(``solver="scipy"``). This module minimises the same robust cost,
``0.5 f**2 sum rho((r_i / f)**2)`` (``rho`` soft-L1 or Cauchy as in SciPy, ``r_i`` the model
minus the voxel value, HU), with the same model, Jacobian and bounds, so both stop at the same
minimum (``tests/ct/test_fit_kernels.py``: centres within 1e-3 mm on random balls and on the
phantom's). Why: a whole head's fits are ~14 problems of ~5 000 voxels x 7-11 parameters,
7-19 evaluations each, and SciPy's trust-region solver spends most of its time in an SVD of the
(n x p) Jacobian and in array overhead; here one pass over the voxels per evaluation
accumulates the cost, the gradient and the (p x p) Gauss-Newton matrix, without storing the
Jacobian (~10x less time per fit).

The step: the Gauss-Newton matrix of the robust cost (``J^T diag(rho' + 2 z rho'') J``, the
second-order correction SciPy uses, clipped to stay positive) with Marquardt damping on its
diagonal (Nielsen's update of the damping), gradient ``J^T (rho' r)``; a parameter at a bound
whose step points outwards is held (projected). Stops as SciPy does: relative cost reduction
below ``ftol`` with a trustworthy model, step below ``xtol`` relative to the parameters, or the
scaled gradient below ``gtol``; ``max_nfev`` evaluations without that: not converged
(``success`` False, as SciPy's status 0).
:mod:`.sphere_fit` adds two tests that SciPy does not have (``robust_lm``'s ``dtol`` and
``step_tol``): the predicted decrease of the undamped step below ``ftol`` once the model has
been seen to predict well, and, after a rejected step, an undamped step of the centre and radius
below 1e-4 mm; on the whole-head phantoms they halve the voxel evaluations of the fits and move
no centre or radius by more than 1.2e-5 mm (``tests/ct/test_fit_kernels.py``).

Parameter vectors: sphere ``[cx, cy, cz, r, s, H, b]``; surface ``[cx, cy, cz, r, s, H, b_out,
b_in, theta, phi, h]`` (mm, mm, mm, HU, HU, HU, rad, rad, mm). ``M`` (3x3, mm^2) the voxel box's
covariance in LPS (zeros: none).
"""

from __future__ import annotations

import math

import numpy as np

from monotracker.registration.compiled import compiled

_SQRT2 = math.sqrt(2.0)
_INV_SQRT_PI = 1.0 / math.sqrt(math.pi)
LOSS_SOFT_L1 = 0
LOSS_CAUCHY = 1
MODEL_SPHERE = 0
MODEL_SURFACE = 1


@compiled
def _evaluate(model, p, pts, vals, M, use_M, f_scale, loss, A, g):
    """One pass over the voxels at ``p``: returns (cost, inlier sum of squares, inliers) and
    fills ``A`` (p x p, the robust Gauss-Newton matrix) and ``g`` (gradient)."""
    npar = p.shape[0]
    for a in range(npar):
        g[a] = 0.0
        for b in range(npar):
            A[a, b] = 0.0
    J = np.empty(npar)
    cx, cy, cz, r, s0, H = p[0], p[1], p[2], p[3], p[4], p[5]
    # the plane (surface model)
    nx = ny = nz = 0.0
    dthx = dthy = dthz = dphx = dphy = dphz = 0.0
    sP = 1.0
    bo = bi = h = 0.0
    if model == MODEL_SURFACE:
        bo, bi, th, ph, h = p[6], p[7], p[8], p[9], p[10]
        st, ct, sp_, cp = math.sin(th), math.cos(th), math.sin(ph), math.cos(ph)
        nx, ny, nz = st * cp, st * sp_, ct
        dthx, dthy, dthz = ct * cp, ct * sp_, -st
        dphx, dphy, dphz = -st * sp_, st * cp, 0.0
        q = (nx * (M[0, 0] * nx + M[0, 1] * ny + M[0, 2] * nz) + ny * (M[1, 0] * nx + M[1, 1] * ny + M[1, 2] * nz)
             + nz * (M[2, 0] * nx + M[2, 1] * ny + M[2, 2] * nz))
        sP = math.sqrt(s0 * s0 + q)
    else:
        bo = p[6]
    k2 = 1.0 / (_SQRT2 * sP)
    cost = 0.0
    ss_in = 0.0
    n_in = 0
    f2 = f_scale * f_scale
    for i in range(pts.shape[0]):
        rx, ry, rz = pts[i, 0] - cx, pts[i, 1] - cy, pts[i, 2] - cz
        dist = math.sqrt(rx * rx + ry * ry + rz * rz)
        dd = dist if dist > 1e-9 else 1e-9
        ex, ey, ez = rx / dd, ry / dd, rz / dd
        if use_M:
            q = (ex * (M[0, 0] * ex + M[0, 1] * ey + M[0, 2] * ez) + ey * (M[1, 0] * ex + M[1, 1] * ey + M[1, 2] * ez)
                 + ez * (M[2, 0] * ex + M[2, 1] * ey + M[2, 2] * ez))
            sF = math.sqrt(s0 * s0 + q)
        else:
            sF = s0
        kF = 1.0 / (_SQRT2 * sF)
        u = (dist - r) * kF
        fill = 0.5 * math.erfc(u)
        if model == MODEL_SURFACE:
            z = (h - (rx * nx + ry * ny + rz * nz)) * k2
            pf = 0.5 * math.erfc(z)
            bg = bo + (bi - bo) * pf
            res = bg * (1.0 - fill) + H * fill - vals[i]
            gF = -_INV_SQRT_PI * math.exp(-u * u) * (H - bg)
            gP = -_INV_SQRT_PI * math.exp(-z * z) * (1.0 - fill) * (bi - bo)
            J[0] = -gF * kF * ex + gP * k2 * nx
            J[1] = -gF * kF * ey + gP * k2 * ny
            J[2] = -gF * kF * ez + gP * k2 * nz
            J[3] = -gF * kF
            J[4] = -gF * u * s0 / (sF * sF) - gP * z * s0 / (sP * sP)
            J[5] = fill
            J[6] = (1.0 - fill) * (1.0 - pf)
            J[7] = (1.0 - fill) * pf
            J[8] = -gP * k2 * (rx * dthx + ry * dthy + rz * dthz)
            J[9] = -gP * k2 * (rx * dphx + ry * dphy + rz * dphz)
            J[10] = gP * k2
        else:
            res = bo + (H - bo) * fill - vals[i]
            k = (H - bo) * (-_INV_SQRT_PI * math.exp(-u * u))
            J[0] = -k * kF * ex
            J[1] = -k * kF * ey
            J[2] = -k * kF * ez
            J[3] = -k * kF
            J[4] = -k * u * s0 / (sF * sF)
            J[5] = fill
            J[6] = 1.0 - fill
        zz = res * res / f2
        if loss == LOSS_CAUCHY:
            rho = math.log1p(zz)
            d1 = 1.0 / (1.0 + zz)
            d2 = -d1 * d1
        else:
            t = math.sqrt(1.0 + zz)
            rho = 2.0 * (t - 1.0)
            d1 = 1.0 / t
            d2 = -0.5 * d1 / (1.0 + zz)
        cost += rho
        if abs(res) < 3.0 * f_scale:
            ss_in += res * res
            n_in += 1
        w = d1 + 2.0 * zz * d2
        if w < 1e-10:
            w = 1e-10
        wr = d1 * res
        for a in range(npar):
            ja = J[a]
            g[a] += wr * ja
            wja = w * ja
            for b in range(a, npar):
                A[a, b] += wja * J[b]
    for a in range(npar):
        for b in range(a + 1, npar):
            A[b, a] = A[a, b]
    return 0.5 * f2 * cost, ss_in, n_in


@compiled
def _damped_system(A, g, x, lo, hi, lam, B, rhs):
    """``B = A + lam diag(A)`` and ``rhs = -g``, with every parameter held at a bound whose
    step would point outwards taken out (its row and column of ``B`` the identity, its
    ``rhs`` 0): the step ``B^-1 rhs`` keeps it where it is."""
    npar = x.shape[0]
    for a in range(npar):
        held = (x[a] <= lo[a] and g[a] > 0.0) or (x[a] >= hi[a] and g[a] < 0.0)
        for b in range(npar):
            B[a, b] = A[a, b]
        rhs[a] = -g[a]
        if held:
            for b in range(npar):
                B[a, b] = 0.0
                B[b, a] = 0.0
            B[a, a] = 1.0
            rhs[a] = 0.0
    for a in range(npar):
        B[a, a] += lam * max(A[a, a], 1e-12)


@compiled
def robust_lm(model, x0, lo, hi, pts, vals, M, use_M, f_scale, loss, max_nfev, ftol, xtol, gtol, dtol=0.0,
              trust_start=False, step_tol=0.0):
    """Bounded robust Levenberg-Marquardt (module docstring) from ``x0`` (clipped 1e-6 inside
    the bounds). Returns (x, inlier RMS (|r| < 3 f_scale; inf without inliers), success, nfev).

    Two more stopping tests (0: off), both on the undamped Gauss-Newton step ``-A^-1 g`` from
    the current point (so not shrunk by the damping, unlike the step just tried):
    ``dtol``: its predicted decrease (half the Newton decrement ``g^T A^-1 g``) is at most
    ``dtol * F`` while the model is trusted: the last accepted step's actual decrease was at
    least a quarter of the predicted (as the ``ftol`` test asks), or ``trust_start`` (a start
    that is a converged fit of the same model on a subsample). ``step_tol`` (mm): after a
    rejected step, the centre's and radius' parts of that step (parameters 0-3) are all at most
    ``step_tol``: the model's predicted gain did not materialise and what it would still move
    is below what matters (without this the fit spends 5-7 further rejected steps, each a pass
    over the voxels, until the damped step falls below ``xtol``)."""
    npar = x0.shape[0]
    x = x0.copy()
    for a in range(npar):
        x[a] = min(max(x[a], lo[a] + 1e-6), hi[a] - 1e-6)
    A = np.empty((npar, npar))
    g = np.empty(npar)
    A_t = np.empty((npar, npar))
    g_t = np.empty(npar)
    F, ss, n_in = _evaluate(model, x, pts, vals, M, use_M, f_scale, loss, A, g)
    nfev = 1
    lam = 1e-3
    nu = 2.0
    success = False
    trusted = trust_start
    rejected = False
    x_t = np.empty(npar)
    B = np.empty((npar, npar))
    rhs = np.empty(npar)
    while nfev < max_nfev:
        # gradient test (scaled as SciPy's x_scale="jac": by the Jacobian's column norms)
        gmax = 0.0
        for a in range(npar):
            d = math.sqrt(max(A[a, a], 1e-30))
            held = (x[a] <= lo[a] and g[a] > 0.0) or (x[a] >= hi[a] and g[a] < 0.0)
            if not held:
                gmax = max(gmax, abs(g[a]) / d)
        if gmax < gtol * max(math.sqrt(2.0 * F), 1e-300) or F == 0.0:
            success = True
            break
        if (dtol > 0.0 and trusted) or (step_tol > 0.0 and rejected):
            # the undamped Gauss-Newton step from here (bounds held as below): what the model
            # says is left to gain (the Newton decrement) and how far the centre and radius
            # would still move (mm)
            _damped_system(A, g, x, lo, hi, 1e-12, B, rhs)
            dn = np.linalg.solve(B, rhs)
            dec = 0.0
            for a in range(npar):
                dec += rhs[a] * dn[a]
            geo = max(abs(dn[0]), abs(dn[1]), abs(dn[2]), abs(dn[3]))
            if (trusted and 0.5 * dec <= dtol * F) or (rejected and geo <= step_tol):
                success = True
                break
        _damped_system(A, g, x, lo, hi, lam, B, rhs)
        dx = np.linalg.solve(B, rhs)
        step2 = 0.0
        x2 = 0.0
        for a in range(npar):
            x_t[a] = min(max(x[a] + dx[a], lo[a]), hi[a])
            dx[a] = x_t[a] - x[a]
            step2 += dx[a] * dx[a]
            x2 += x[a] * x[a]
        # predicted reduction of the quadratic model for the (clipped) step
        pred = 0.0
        for a in range(npar):
            s_ = 0.0
            for b in range(npar):
                s_ += A[a, b] * dx[b]
            pred -= g[a] * dx[a] + 0.5 * dx[a] * s_
        F_t, ss_t, n_t = _evaluate(model, x_t, pts, vals, M, use_M, f_scale, loss, A_t, g_t)
        nfev += 1
        small_step = math.sqrt(step2) < xtol * (xtol + math.sqrt(x2))
        if F_t < F:
            ratio = (F - F_t) / pred if pred > 0.0 else 0.0
            dF = F - F_t
            F_old = F
            for a in range(npar):
                x[a] = x_t[a]
                g[a] = g_t[a]
                for b in range(npar):
                    A[a, b] = A_t[a, b]
            F, ss, n_in = F_t, ss_t, n_t
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3) if ratio > 0.0 else 1.0
            nu = 2.0
            trusted = ratio > 0.25
            rejected = False
            if (dF < ftol * F_old and ratio > 0.25) or small_step:
                success = True
                break
        else:
            if small_step:
                success = True
                break
            trusted = False
            rejected = True
            lam *= nu
            nu *= 2.0
            if lam > 1e16:
                break
    rms = math.sqrt(ss / n_in) if n_in > 0 else math.inf
    return x, rms, success, nfev


@compiled
def fit_window(sub, lo, A, origin, centre, r0, M, sib_c, sib_r, pad, use_pad):
    """The voxels of a blob's fit window, in one pass over its index box (``sub``: the box's
    values, k, j, i, starting at index ``lo``): LPS position ``A (i, j, k) + origin`` (mm;
    ``A`` the direction times the spacing), kept when nearer to ``centre`` than ``r0 + 1.5 +
    2.5 sqrt(0.25 + e^T M e)`` (``e`` the unit vector from the centre, ``M`` the voxel box's
    covariance, mm^2) and, for every neighbouring blob ``(sib_c[m], sib_r[m])``, nearer to this
    blob's surface than to that one's. Returns ``(pts (n, 3) mm, vals (n,) HU, dist (n,) mm
    from the centre)`` of the kept voxels, in C order of the box, and ``pad_pts`` (q, 3): every
    voxel of the box whose value is ``pad`` (when ``use_pad``), kept or not."""
    nk, nj, ni = sub.shape
    n_box = nk * nj * ni
    pts = np.empty((n_box, 3))
    vals = np.empty(n_box)
    dist = np.empty(n_box)
    pad_pts = np.empty((n_box if use_pad else 0, 3))
    m = 0
    q = 0
    cx, cy, cz = centre[0], centre[1], centre[2]
    for kk in range(nk):
        k = float(lo[0] + kk)
        for jj in range(nj):
            j = float(lo[1] + jj)
            for ii in range(ni):
                i = float(lo[2] + ii)
                px = i * A[0, 0] + j * A[0, 1] + k * A[0, 2] + origin[0]
                py = i * A[1, 0] + j * A[1, 1] + k * A[1, 2] + origin[1]
                pz = i * A[2, 0] + j * A[2, 1] + k * A[2, 2] + origin[2]
                v = float(sub[kk, jj, ii])
                if use_pad and v == pad:
                    pad_pts[q, 0], pad_pts[q, 1], pad_pts[q, 2] = px, py, pz
                    q += 1
                rx, ry, rz = px - cx, py - cy, pz - cz
                d = math.sqrt(rx * rx + ry * ry + rz * rz)
                dd = d if d > 1e-9 else 1e-9
                ex, ey, ez = rx / dd, ry / dd, rz / dd
                quad = (ex * (M[0, 0] * ex + M[0, 1] * ey + M[0, 2] * ez) + ey * (M[1, 0] * ex + M[1, 1] * ey + M[1, 2] * ez)
                        + ez * (M[2, 0] * ex + M[2, 1] * ey + M[2, 2] * ez))
                if not d < r0 + 1.5 + 2.5 * math.sqrt(0.25 + quad):
                    continue
                keep = True
                for s in range(sib_r.shape[0]):
                    sx, sy, sz = px - sib_c[s, 0], py - sib_c[s, 1], pz - sib_c[s, 2]
                    if not math.sqrt(sx * sx + sy * sy + sz * sz) - sib_r[s] > d - r0:
                        keep = False
                        break
                if not keep:
                    continue
                pts[m, 0], pts[m, 1], pts[m, 2] = px, py, pz
                vals[m] = v
                dist[m] = d
                m += 1
    return pts[:m].copy(), vals[:m].copy(), dist[:m].copy(), pad_pts[:q].copy()
