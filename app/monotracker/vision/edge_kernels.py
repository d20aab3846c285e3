"""The edge fit's inner loops, compiled (numba): per-ray unmixing and edge, known-shape outline fits.

:mod:`.edge_fit` documents what is computed and why; this module computes the same per ray and
per ball in compiled loops, because the NumPy form spends its time in the overhead of hundreds
of small array operations per frame (~1.2 ms per ball of 20 px radius per pass, ~1 ms of Python
per ball's fits; the pose pipeline's budget is 10 ms per frame for everything). The NumPy
functions of :mod:`.edge_fit` stay the reference: ``tests/vision/test_edge_kernels.py`` checks
that both give the same edges, usable rays, fits and refusals on rendered frames and random
balls (arithmetic in float64 here, partly float32 there: edges agree to ~1e-4 px).

Why numba (a dependency): these loops are a few hundred lines of arithmetic on arrays of tens of
thousands of samples; numba compiles them from Python source with no build step and caches the
machine code next to the module (``cache=True``; the first use after an install compiles for
~10-20 s, :func:`warm_up` does it ahead of the first frame).

Layouts: ray profiles ``prof`` (N, k, 3) float32, the rays of ball b are rows
``starts[b] : starts[b] + counts[b]``; ``step`` (N,) px per sample. Edge points of m balls padded
to (m, R, 2) with ``valid`` (m, R) (a ball of n rays fills its first n rows).
"""

from __future__ import annotations

import math

import numpy as np

from monotracker.registration.compiled import compiled


#: numba's njit(cache=True), cached where this folder is not writable (registration/compiled.py)
_compiled = compiled


@_compiled
def _kth_smallest(x, k):
    """The value ``np.sort(x)[k]`` (0 <= k < len(x); NaNs sort last), by selection (quickselect on a
    copy of the finite values, O(n) on average; ``x`` is not changed). Written out rather than
    ``np.partition`` / ``np.sort``: numba's implementations of those took ~6 and ~3 s of each
    process's first compile (the kernels' cold start after an install), the same values."""
    n = len(x)
    a = np.empty(n)
    m = 0
    if k < 0:
        return np.nan
    for i in range(n):
        if not math.isnan(x[i]):
            a[m] = x[i]
            m += 1
    if k >= m:
        return np.nan
    lo, hi = 0, m - 1
    while lo < hi:
        pivot = a[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


@_compiled
def _ball_directions(P, starts, counts, edge_k):
    """(N, 3): per ray its ball's colour direction, the component-wise median (upper middle for an
    even count, as ``np.sort(v)[len(v) // 2]``) of the unit colour vectors of the inner
    ``edge_k`` samples of all its rays, normalised."""
    N = P.shape[0]
    out = np.zeros((N, 3))
    for b in range(len(starts)):
        s, c = starts[b], counts[b]
        m = c * edge_k
        v = np.empty((3, m))
        q = 0
        for n in range(s, s + c):
            for j in range(edge_k):
                nn = math.sqrt(P[n, j, 0] ** 2 + P[n, j, 1] ** 2 + P[n, j, 2] ** 2) + 1e-9
                for ch in range(3):
                    v[ch, q] = P[n, j, ch] / nn
                q += 1
        bd = np.empty(3)
        for ch in range(3):
            # the (m // 2)-th smallest by selection, O(m): the value np.sort(v[ch])[m // 2] gives
            # (these sorts were a third of ray_edges' time)
            bd[ch] = _kth_smallest(v[ch], m // 2)
        nb = math.sqrt(bd[0] ** 2 + bd[1] ** 2 + bd[2] ** 2) + 1e-12
        for n in range(s, s + c):
            for ch in range(3):
                out[n, ch] = bd[ch] / nb
    return out


@_compiled
def _dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@_compiled
def _gamma_row(Pn, bd, G1, slope, t, gamma_n):
    """One ray: the background share per sample (clipped to [0, 1]) of ``p = alpha b + gamma
    (G1 + t slope)``; returns True when every sample's 2 x 2 system is regular."""
    k = Pn.shape[0]
    g1b, sb = _dot3(G1, bd), _dot3(slope, bd)
    g11, g1s, ss = _dot3(G1, G1), _dot3(G1, slope), _dot3(slope, slope)
    good_all = True
    for j in range(k):
        tj = t[j]
        bg = g1b + tj * sb
        gg = g11 + 2 * tj * g1s + tj * tj * ss
        pb = Pn[j, 0] * bd[0] + Pn[j, 1] * bd[1] + Pn[j, 2] * bd[2]
        pg = (Pn[j, 0] * G1[0] + Pn[j, 1] * G1[1] + Pn[j, 2] * G1[2]
              + tj * (Pn[j, 0] * slope[0] + Pn[j, 1] * slope[1] + Pn[j, 2] * slope[2]))
        det = gg - bg * bg
        good = det > 1e-12
        good_all = good_all and good
        g = (pg - bg * pb) / (det if good else 1.0)
        gamma_n[j] = min(max(g, 0.0), 1.0)
    return good_all


@_compiled
def _last_below(row, level):
    """Index of the last sample below ``level``; k - 1 when none is (``np.argmax`` of all False)."""
    k = row.shape[0]
    for j in range(k - 1, -1, -1):
        if row[j] < level:
            return j, True
    return k - 1, False


@_compiled
def _crossing(row, level):
    """Fractional sample index where the row last rises through ``level`` (edge_fit._crossing)."""
    k = row.shape[0]
    j, _ = _last_below(row, level)
    j = min(max(j, 0), k - 2)
    g0, g1 = row[j], row[j + 1]
    return j + min(max((level - g0) / max(g1 - g0, 1e-6), 0.0), 1.0)


@_compiled
def _median(x):
    """np.median's value (NaN last, as np.sort orders it)."""
    n = len(x)
    return 0.5 * (_kth_smallest(x, (n - 1) // 2) + _kth_smallest(x, n // 2))


@_compiled
def ray_edges(prof, prof_e, starts, counts, step, blur_px, max_resid, ball_side_floor, ball_side_cap, near_background,
              integration_share, crossing_agree_px, near_bg_margin_px, near_bg_window_px, psf_radius_per_blur):
    """Per ray of ``prof`` (N, k, 3) (and ``prof_e``: the same rays with colour smoothed along
    them, or ``prof`` itself): (edge position from the ray's start, px (N,); usable (N,) bool;
    25-75 % rise width px (N,), NaN where not usable), as :func:`.edge_fit._edge_points`
    computes them for blur ``blur_px`` px, the unmixing residual limit ``max_resid`` and the
    ball-side test's floor and cap (``edge_fit.ball_side_floor``, ``BALL_SIDE_CAP``)."""
    N, k, _ = prof.shape
    edge_k = max(k // 10, 3)
    half = k // 8
    t = np.empty(k)
    for j in range(k):
        t[j] = j - (k - 1.5 * half - 0.5)
    zero3 = np.zeros(3)
    bdir = _ball_directions(prof, starts, counts, edge_k)
    smoothed = prof_e is not prof
    bdir_e = _ball_directions(prof_e, starts, counts, edge_k) if smoothed else bdir
    gamma = np.empty((N, k))
    gamma_e = np.empty((N, k))
    edge = np.zeros(N)
    usable = np.zeros(N, np.bool_)
    widths = np.full(N, np.nan)
    g_noise = np.empty(N)
    G1 = np.empty(3)
    G2 = np.empty(3)
    slope = np.empty(3)
    Ge1 = np.empty(3)
    Ge2 = np.empty(3)
    slope_e = np.empty(3)
    Gn = np.empty(3)
    j_lo = np.zeros(N, np.int64)
    j_hi = np.zeros(N, np.int64)
    ball_side = np.zeros(N)
    for n in range(N):
        for ch in range(3):
            a = 0.0
            for j in range(k - 2 * half, k - half):
                a += prof[n, j, ch]
            G1[ch] = a / half
            a = 0.0
            for j in range(k - half, k):
                a += prof[n, j, ch]
            G2[ch] = a / half
            slope[ch] = (G2[ch] - G1[ch]) / half
        good_all = _gamma_row(prof[n], bdir[n], G1, slope, t, gamma[n])
        gm0, gm1, gm2 = 0.5 * (G1[0] + G2[0]), 0.5 * (G1[1] + G2[1]), 0.5 * (G1[2] + G2[2])
        gnorm = math.sqrt(gm0 * gm0 + gm1 * gm1 + gm2 * gm2)
        ok = (gm0 * bdir[n, 0] + gm1 * bdir[n, 1] + gm2 * bdir[n, 2] < 0.995 * gnorm) and gnorm > 1e-4 and good_all
        dev = 0.0
        mean = 0.0
        for j in range(k - 2 * half, k):
            dev = max(dev, abs(gamma[n, j] - 1.0))
            mean += gamma[n, j]
        ok = ok and dev < 0.2
        mean /= 2 * half
        var = 0.0
        for j in range(k - 2 * half, k):
            var += (gamma[n, j] - mean) ** 2
        g_noise[n] = math.sqrt(var / (2 * half))
        st = step[n]
        jh, any_below = _last_below(gamma[n], 0.5)
        half_w = int(math.ceil((1.5 + blur_px) / st))
        jl = max(jh - half_w, 0)
        half_i = int(math.ceil(max(integration_share * blur_px, 1.0) / st))
        if smoothed:
            for ch in range(3):
                a = 0.0
                for j in range(k - 2 * half, k - half):
                    a += prof_e[n, j, ch]
                Ge1[ch] = a / half
                a = 0.0
                for j in range(k - half, k):
                    a += prof_e[n, j, ch]
                Ge2[ch] = a / half
                slope_e[ch] = (Ge2[ch] - Ge1[ch]) / half
            _gamma_row(prof_e[n], bdir_e[n], Ge1, slope_e, t, gamma_e[n])
        else:
            gamma_e[n] = gamma[n]
        jhe, any_e = _last_below(gamma_e[n], 0.5)
        ok = ok and any_e and abs(jhe - jh) * st <= crossing_agree_px
        if near_background:
            js = min(jhe + int(math.ceil((blur_px * psf_radius_per_blur + near_bg_margin_px) / st)),
                     k - max(k // 8, 3))
            je = js + max(int(math.ceil(near_bg_window_px / st)), 3)
            je = min(je, k)
            for ch in range(3):
                a = 0.0
                for j in range(js, je):
                    a += prof_e[n, j, ch]
                Gn[ch] = a / (je - js)
            _gamma_row(prof_e[n], bdir_e[n], Gn, zero3, t, gamma_e[n])
            jhe, any_e = _last_below(gamma_e[n], 0.5)
            ok = ok and any_e
        ok = ok and any_below
        j_lo[n] = jl
        j_hi[n] = min(jh + half_w + 1, k)
        # the ball side of the window must be ball
        a = 0.0
        for j in range(jl, min(jl + edge_k, k)):
            a += 1.0 - gamma[n, j]
        ball_side[n] = a / edge_k
        # edge: integral of (1 - gamma_e) over the integration window
        jli = max(jhe - half_i, 0)
        jhi = min(jhe + half_i + 1, k)
        a = 0.0
        for j in range(jli, jhi):
            a += 1.0 - gamma_e[n, j]
        edge[n] = (jli - 0.5 + a) * st
        usable[n] = ok
    # per ball: the noise of gamma on the clean background, and the checks that need it
    for b in range(len(starts)):
        s, c = starts[b], counts[b]
        nb = _median(g_noise[s:s + c])
        lim = 1.0 - min(max(ball_side_floor + 2.0 * nb, ball_side_floor), ball_side_cap)
        for n in range(s, s + c):
            if usable[n] and not ball_side[n] > lim:
                usable[n] = False
    # a third colour in the edge window: the unmixing's relative residual (line background)
    for n in range(N):
        if not usable[n]:
            continue
        for ch in range(3):
            a = 0.0
            for j in range(k - 2 * half, k - half):
                a += prof[n, j, ch]
            G1[ch] = a / half
            a = 0.0
            for j in range(k - half, k):
                a += prof[n, j, ch]
            slope[ch] = (a / half - G1[ch]) / half
        bd = bdir[n]
        g1b, sb = _dot3(G1, bd), _dot3(slope, bd)
        g11, g1s, ss = _dot3(G1, G1), _dot3(G1, slope), _dot3(slope, slope)
        worst = 0.0
        for j in range(j_lo[n], j_hi[n]):
            tj = t[j]
            bg = g1b + tj * sb
            gg = g11 + 2 * tj * g1s + tj * tj * ss
            p0, p1, p2 = prof[n, j, 0], prof[n, j, 1], prof[n, j, 2]
            pb = p0 * bd[0] + p1 * bd[1] + p2 * bd[2]
            pg = p0 * G1[0] + p1 * G1[1] + p2 * G1[2] + tj * (p0 * slope[0] + p1 * slope[1] + p2 * slope[2])
            det = gg - bg * bg
            pp = p0 * p0 + p1 * p1 + p2 * p2
            proj = (gg * pb * pb - 2.0 * bg * pb * pg + pg * pg) / (det if det > 1e-12 else 1.0)
            r = math.sqrt(max(pp - proj, 0.0) / max(pp, 1e-12))
            worst = max(worst, r)
        if not worst < max_resid:
            usable[n] = False
            continue
        widths[n] = (_crossing(gamma[n], 0.75) - _crossing(gamma[n], 0.25)) * step[n]
    return edge, usable, widths


# --- known-shape outline fits (edge_fit._fit_outline, _robust_ellipse, _hidden_arc) ----------


@_compiled
def _solve3(A, b):
    """x of A x = b (3 x 3, Gaussian elimination with partial pivoting); ok False if singular."""
    M = np.empty((3, 4))
    for i in range(3):
        for j in range(3):
            M[i, j] = A[i, j]
        M[i, 3] = b[i]
    for c in range(3):
        p = c
        for r in range(c + 1, 3):
            if abs(M[r, c]) > abs(M[p, c]):
                p = r
        if M[p, c] == 0.0:
            return np.zeros(3), False
        if p != c:
            for j in range(4):
                M[c, j], M[p, j] = M[p, j], M[c, j]
        for r in range(c + 1, 3):
            f = M[r, c] / M[c, c]
            for j in range(c, 4):
                M[r, j] -= f * M[c, j]
    x = np.zeros(3)
    for i in range(2, -1, -1):
        a = M[i, 3]
        for j in range(i + 1, 3):
            a -= M[i, j] * x[j]
        x[i] = a / M[i, i]
    ok = np.isfinite(x[0]) and np.isfinite(x[1]) and np.isfinite(x[2])
    return x, ok


@_compiled
def fit_outline(px, py, keep, ratio, major_deg):
    """The ellipse of shape (``ratio`` minor / major, major axis ``major_deg``) through the
    ``keep`` points (px, py): (cx, cy, d1, d2, ok), as :func:`.edge_fit._fit_outline`."""
    n = len(px)
    ca, sa = math.cos(math.radians(major_deg)), math.sin(math.radians(major_deg))
    cnt = 0
    mx = 0.0
    my = 0.0
    for i in range(n):
        if keep[i]:
            mx += px[i]
            my += py[i]
            cnt += 1
    if cnt < 3:
        return 0.0, 0.0, 1.0, 1.0, False
    mx /= cnt
    my /= cnt
    u = np.empty(n)
    v = np.empty(n)
    for i in range(n):
        dx, dy = px[i] - mx, py[i] - my
        u[i] = (dx * ca + dy * sa) * ratio
        v[i] = -dx * sa + dy * ca
    A = np.zeros((3, 3))
    bb = np.zeros(3)
    for i in range(n):
        if keep[i]:
            a0, a1 = u[i], v[i]
            w = a0 * a0 + a1 * a1
            A[0, 0] += a0 * a0
            A[0, 1] += a0 * a1
            A[0, 2] += a0
            A[1, 1] += a1 * a1
            A[1, 2] += a1
            A[2, 2] += 1.0
            bb[0] += a0 * w
            bb[1] += a1 * w
            bb[2] += w
    A[1, 0], A[2, 0], A[2, 1] = A[0, 1], A[0, 2], A[1, 2]
    sol, ok = _solve3(A, bb)
    if not ok:
        return 0.0, 0.0, 1.0, 1.0, False
    cu, cv = 0.5 * sol[0], 0.5 * sol[1]
    r = math.sqrt(max(sol[2] + cu * cu + cv * cv, 1e-12))
    for _ in range(2):
        JJ = np.zeros((3, 3))
        Jr = np.zeros(3)
        for i in range(n):
            if keep[i]:
                du, dv = u[i] - cu, v[i] - cv
                rho = max(math.hypot(du, dv), 1e-9)
                j0, j1 = -du / rho, -dv / rho
                res = rho - r
                JJ[0, 0] += j0 * j0
                JJ[0, 1] += j0 * j1
                JJ[0, 2] -= j0
                JJ[1, 1] += j1 * j1
                JJ[1, 2] -= j1
                JJ[2, 2] += 1.0
                Jr[0] -= j0 * res
                Jr[1] -= j1 * res
                Jr[2] += res
        JJ[1, 0], JJ[2, 0], JJ[2, 1] = JJ[0, 1], JJ[0, 2], JJ[1, 2]
        stp, ok = _solve3(JJ, Jr)
        if not ok:
            return 0.0, 0.0, 1.0, 1.0, False
        cu += stp[0]
        cv += stp[1]
        r += stp[2]
    cu /= ratio
    return mx + cu * ca - cv * sa, my + cu * sa + cv * ca, 2.0 * r / ratio, 2.0 * r, True


@_compiled
def ellipse_residuals(px, py, cx, cy, d1, d2, angle_deg, out):
    """Signed distances (px, > 0 outside) of the points from the ellipse, into ``out``, as
    :func:`.edge_fit._ellipse_residuals`."""
    th = math.radians(angle_deg)
    c, s = math.cos(th), math.sin(th)
    au, av = d1 / 2, d2 / 2
    for i in range(len(px)):
        qx, qy = px[i] - cx, py[i] - cy
        u = qx * c + qy * s
        v = -qx * s + qy * c
        rho = math.sqrt((u / au) ** 2 + (v / av) ** 2)
        grad = math.sqrt((u / au ** 2) ** 2 + (v / av ** 2) ** 2) / max(rho, 1e-9)
        out[i] = (rho - 1.0) / max(grad, 1e-9)


@_compiled
def _masked_median(x, mask):
    cnt = 0
    for i in range(len(x)):
        if mask[i]:
            cnt += 1
    y = np.empty(cnt)
    q = 0
    for i in range(len(x)):
        if mask[i]:
            y[q] = x[i]
            q += 1
    return _median(y)


@_compiled
def robust_outline(px, py, usable, ratio, major_deg, min_share):
    """As :func:`.edge_fit._robust_ellipse` with a known shape: (ok, cx, cy, d1, d2, keep, rms)."""
    n = len(px)
    need = max(min_share * n, 6.0)
    keep = usable.copy()
    res = np.empty(n)
    cx = cy = d1 = d2 = 0.0
    converged = False
    for _ in range(3):
        if keep.sum() < need:
            return False, 0.0, 0.0, 1.0, 1.0, keep, 0.0
        cx, cy, d1, d2, ok = fit_outline(px, py, keep, ratio, major_deg)
        if not ok:
            return False, 0.0, 0.0, 1.0, 1.0, keep, 0.0
        ellipse_residuals(px, py, cx, cy, d1, d2, major_deg, res)
        med = _masked_median(res, keep)
        dev = np.abs(res - med)
        scale = max(1.4826 * _masked_median(dev, keep), 0.08)
        keep_next = usable & (dev < 3.0 * scale)
        same = True
        for i in range(n):
            if keep_next[i] != keep[i]:
                same = False
                break
        if same:
            converged = True
            break
        keep = keep_next
    if not converged:
        if keep.sum() < need:
            return False, 0.0, 0.0, 1.0, 1.0, keep, 0.0
        cx, cy, d1, d2, ok = fit_outline(px, py, keep, ratio, major_deg)
        if not ok:
            return False, 0.0, 0.0, 1.0, 1.0, keep, 0.0
        ellipse_residuals(px, py, cx, cy, d1, d2, major_deg, res)
    a = 0.0
    cnt = 0
    for i in range(n):
        if keep[i]:
            a += res[i] ** 2
            cnt += 1
    return True, cx, cy, d1, d2, keep, math.sqrt(a / max(cnt, 1))


@_compiled
def hidden_arc(px, py, usable, cx, cy, d1, d2, angle_deg, ratio, major_deg, blur_px, window_share, depth_px,
               depth_per_radius, depth_per_blur, min_share):
    """As :func:`.edge_fit._hidden_arc`: True when the deepest arc of ``window_share`` of the
    rays lies inside the outline refitted without it by more than the depth limit."""
    n = len(px)
    width = max(4, int(round(window_share * n)))
    res = np.empty(n)
    ellipse_residuals(px, py, cx, cy, d1, d2, angle_deg, res)
    best = np.inf
    jbest = -1
    for j in range(n):
        rs = 0.0
        ws = 0.0
        for q in range(width):
            i = (j + q) % n
            if usable[i]:
                rs += res[i]
                ws += 1.0
        if ws >= max(3, width // 2):
            m = rs / max(ws, 1.0)
            if m < best:
                best = m
                jbest = j
    if jbest < 0:
        return False
    window = np.zeros(n, np.bool_)
    for q in range(width):
        window[(jbest + q) % n] = True
    ok, c1x, c1y, e1, e2, _keep, rms1 = robust_outline(px, py, usable & ~window, ratio, major_deg, min_share)
    if not ok:
        return False
    ellipse_residuals(px, py, c1x, c1y, e1, e2, major_deg, res)
    a = 0.0
    cnt = 0
    for i in range(n):
        if window[i] and usable[i]:
            a -= res[i]
            cnt += 1
    if cnt == 0:
        return False
    depth = a / cnt
    radius = min(e1, e2) / 2.0
    limit = max(max(depth_px, depth_per_radius * radius), depth_per_blur * blur_px)
    return depth > limit and depth > 3.0 * rms1 / math.sqrt(cnt)


@_compiled
def shaped_fits(P, valid, usable, ratio, major_deg, min_share, blur_px, window_share, depth_px, depth_per_radius,
                depth_per_blur):
    """:func:`robust_outline` and :func:`hidden_arc` for m balls (padded ``P`` (m, R, 2)):
    (ok (m,), centre (m, 2), d1 (m,), d2 (m,), keep (m, R), rms (m,), cut (m,))."""
    m, R, _ = P.shape
    ok = np.zeros(m, np.bool_)
    cut = np.zeros(m, np.bool_)
    centre = np.zeros((m, 2))
    d1 = np.ones(m)
    d2 = np.ones(m)
    rms = np.zeros(m)
    keep = np.zeros((m, R), np.bool_)
    for b in range(m):
        n = 0
        for i in range(R):
            if valid[b, i]:
                n += 1
        px = P[b, :n, 0].copy()
        py = P[b, :n, 1].copy()
        use = usable[b, :n].copy()
        good, cx, cy, a1, a2, kp, r = robust_outline(px, py, use, ratio[b], major_deg[b], min_share)
        if not good:
            continue
        ok[b] = True
        centre[b, 0], centre[b, 1], d1[b], d2[b], rms[b] = cx, cy, a1, a2, r
        keep[b, :n] = kp
        cut[b] = hidden_arc(px, py, use, cx, cy, a1, a2, major_deg[b], ratio[b], major_deg[b], blur_px,
                            window_share, depth_px, depth_per_radius, depth_per_blur, min_share - window_share)
    return ok, centre, d1, d2, keep, rms, cut


# --- ray sampling (edge_fit._edge_points' geometry, cv2.remap, chroma smoothing) -------------


@_compiled
def ray_geometry(cx, cy, d1, d2, ang_deg, k, blur_px, img_h, img_w, max_rays=96):
    """The rays of m balls given by their coarse OpenCV ellipses (centre ``cx``, ``cy`` px, full
    axes ``d1``, ``d2`` px, ``ang_deg``), for blur ``blur_px`` px and ``k`` samples per ray: the
    edge fit's one ray layout (both bodies of :func:`.edge_fit._edge_points` take it from here,
    through ``edge_fit._ray_layout``). Per ball n = clip(2 pi a / 1.6, 32, ``max_rays``) rays (a the
    semi-major axis) at angles 2 pi i / n from +x towards +y; each starts ``w_in`` px inside the
    ellipse and ends ``w_out`` = 3 + b / 4 + ``blur_px`` px outside it (b the semi-minor axis),
    w_in = min(w_out, 0.65 x the shortest ray radius), k samples ``step`` apart; the window is
    the ball's square of half side ceil(a + w_out + 2) around floor(centre) (+2 on the far
    side). Returns (counts (m,) rays per ball, 0 for a ball whose window leaves the ``img_h`` x ``img_w`` image; boxes (m, 4) int x0, y0, x1, y1 of each ball's
    window; w_in (m,) px; step (m,) px per sample; phi (N,) ray direction rad; s0 (N,) px from
    the centre to each ray's first sample). N = counts.sum()."""
    m = len(cx)
    counts = np.zeros(m, np.int64)
    n_all = np.zeros(m, np.int64)
    boxes = np.zeros((m, 4), np.int64)
    w_in = np.zeros(m)
    step = np.zeros(m)
    N = 0
    for b in range(m):
        a_ = max(d1[b], d2[b]) / 2
        n = int(min(max(2 * np.pi * a_ / 1.6, 32.0), float(max(max_rays, 32))))
        n_all[b] = n
        w_out = 3.0 + 0.25 * (min(d1[b], d2[b]) / 2) + blur_px
        mm = int(math.ceil(a_ + w_out + 2))
        x0, y0 = int(math.floor(cx[b])) - mm, int(math.floor(cy[b])) - mm
        x1, y1 = int(math.floor(cx[b])) + mm + 2, int(math.floor(cy[b])) + mm + 2
        boxes[b, 0], boxes[b, 1], boxes[b, 2], boxes[b, 3] = x0, y0, x1, y1
        if x0 < 0 or y0 < 0 or x1 > img_w or y1 > img_h:
            continue
        counts[b] = n
        N += n
    phi = np.empty(N)
    s0 = np.empty(N)
    q = 0
    for b in range(m):
        n = counts[b]
        if n == 0:
            continue
        ea, eb = d1[b] / 2, d2[b] / 2
        th = np.radians(ang_deg[b])
        rmin = np.inf
        for i in range(n):
            ph = i * (2 * np.pi / n)
            t = ph - th
            r = 1.0 / math.sqrt((math.cos(t) / ea) ** 2 + (math.sin(t) / eb) ** 2)
            phi[q + i] = ph
            s0[q + i] = r
            rmin = min(rmin, r)
        w_out = 3.0 + 0.25 * min(ea, eb) + blur_px
        w_in[b] = min(w_out, 0.65 * rmin)
        step[b] = (w_in[b] + w_out) / (k - 1)
        for i in range(n):
            s0[q + i] -= w_in[b]
        q += n
    return counts, boxes, w_in, step, phi, s0


@_compiled
def contour_fit_rms(contour, ex, ey, d1, d2, ang_deg):
    """RMS (px) about its mean of the radial deviation of a blob's pixel contour (OpenCV int32
    (m, 1, 2)) from the ellipse fitted to it (centre ``ex``, ``ey`` px, full axes ``d1``, ``d2``
    px, ``ang_deg``), each point's (rho - 1) sqrt(a b): :func:`.detection.score_blob`'s fit term
    (its NumPy form before issue 29's round 3; ~2 us instead of ~60 us a blob)."""
    m = contour.shape[0]
    th = math.radians(ang_deg)
    c, s = math.cos(th), math.sin(th)
    au, av = d1 / 2, d2 / 2
    scale = math.sqrt(au * av)
    dev = np.empty(m)
    mean = 0.0
    for i in range(m):
        qx, qy = float(contour[i, 0, 0]) - ex, float(contour[i, 0, 1]) - ey
        u = qx * c + qy * s
        v = -qx * s + qy * c
        dev[i] = (math.sqrt((u / au) ** 2 + (v / av) ** 2) - 1.0) * scale
        mean += dev[i]
    mean /= m
    a = 0.0
    for i in range(m):
        a += (dev[i] - mean) ** 2
    return math.sqrt(a / m)


@_compiled
def luma_at(img, lut, cw0, x0, y0, x1, y1, xs, ys):
    """Linear luma at points (``xs``, ``ys`` px from the window's corner ``x0``, ``y0``, float32), sampled as ``cv2.remap`` samples
    the window ``img[y0:y1, x0:x1]`` linearised (``lut``, float32) and weighted (``cw0`` (3,)
    float32: linear BGR -> luma): bilinear at 1/32 px, round half to even, border replicated at
    the window's edge. (n,) float32. For :func:`.edge_fit._without_shadow_rays`: a few dozen
    points a ball, where linearising the whole window cost ~50 us a ball."""
    ww, hh = x1 - x0, y1 - y0
    one = np.float32(1.0)
    out = np.empty(len(xs), np.float32)
    for q in range(len(xs)):
        ix = np.int64(np.rint(xs[q] * np.float32(32.0)))
        iy = np.int64(np.rint(ys[q] * np.float32(32.0)))
        xi, yi = ix >> 5, iy >> 5
        ax, ay = np.float32(ix & 31) * np.float32(1.0 / 32), np.float32(iy & 31) * np.float32(1.0 / 32)
        xa, xb = min(max(xi, 0), ww - 1), min(max(xi + 1, 0), ww - 1)
        ya, yb = min(max(yi, 0), hh - 1), min(max(yi + 1, 0), hh - 1)
        v = np.float32(0.0)
        for ch in range(3):
            v += cw0[ch] * ((one - ay) * ((one - ax) * lut[img[y0 + ya, x0 + xa, ch]] + ax * lut[img[y0 + ya, x0 + xb, ch]])
                            + ay * ((one - ax) * lut[img[y0 + yb, x0 + xa, ch]] + ax * lut[img[y0 + yb, x0 + xb, ch]]))
        out[q] = v
    return out


@_compiled
def shadow_rays(img, lut, cw0, P, valid, usable, okfit, cx, cy, d1, d2, ang_deg, r_near, far_px, far_per_radius,
                out_px, nf, min_share, in_px):
    """The contact-shadow test of :func:`.edge_fit._without_shadow_rays` for m balls of known
    shape at once: edge points ``P`` (m, R, 2) px padded (``valid`` (m, R)), ``usable`` (m, R),
    each ball's fitted outline (``okfit`` (m,) bool: fitted at all; centre ``cx``, ``cy`` px, full
    axes ``d1``, ``d2`` px, major axis ``ang_deg``). A usable ray whose edge lies more than
    ``out_px`` outside the outline (or more than ``in_px`` inside it; inf = none) is a shadow's
    when the linear luma (``img`` uint8 BGR, ``lut``, ``cw0`` as :func:`luma_at`) ``r_near`` px
    beyond the outline along the ray is below ``nf`` x the luma max(``far_px``, ``far_per_radius`` x the
    outline's minor semi-axis) px further out. Returns (use (m, R): usable without the shadow rays,
    changed (m,): True where some were found, the ball's window lay inside the image and at least
    ``min_share`` of its rays remain; only there does ``use`` differ from what the fit used)."""
    m, R, _ = P.shape
    h, w = img.shape[0], img.shape[1]
    use_out = usable.copy()
    changed = np.zeros(m, np.bool_)
    res = np.empty(R)
    nfx = np.float32(nf)
    tiny = np.float32(1e-6)
    for b in range(m):
        if not okfit[b]:
            continue
        n = 0
        for i in range(R):
            if valid[b, i]:
                n += 1
        ellipse_residuals(P[b, :n, 0], P[b, :n, 1], cx[b], cy[b], d1[b], d2[b], ang_deg[b], res[:n])
        cand = np.zeros(n, np.bool_)
        mc = 0
        for i in range(n):
            if usable[b, i] and (res[i] > out_px or res[i] < -in_px):
                cand[i] = True
                mc += 1
        if mc == 0:
            continue
        ea, eb = d1[b] / 2.0, d2[b] / 2.0
        far_b = max(far_px, far_per_radius * min(ea, eb))
        th = math.radians(ang_deg[b])
        qx = np.empty(2 * mc)
        qy = np.empty(2 * mc)
        q = 0
        for i in range(n):
            if not cand[i]:
                continue
            dx, dy = P[b, i, 0] - cx[b], P[b, i, 1] - cy[b]
            nrm = max(math.sqrt(dx * dx + dy * dy), 1e-9)
            ux, uy = dx / nrm, dy / nrm
            t = math.atan2(uy, ux) - th
            rr = 1.0 / math.sqrt((math.cos(t) / ea) ** 2 + (math.sin(t) / eb) ** 2)
            qx[q] = cx[b] + (rr + r_near) * ux
            qy[q] = cy[b] + (rr + r_near) * uy
            qx[mc + q] = cx[b] + (rr + r_near + far_b) * ux
            qy[mc + q] = cy[b] + (rr + r_near + far_b) * uy
            q += 1
        x0 = int(math.floor(qx.min())) - 1
        y0 = int(math.floor(qy.min())) - 1
        x1 = int(math.ceil(qx.max())) + 2
        y1 = int(math.ceil(qy.max())) + 2
        if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
            continue
        xs = np.empty(2 * mc, np.float32)
        ys = np.empty(2 * mc, np.float32)
        for j in range(2 * mc):
            xs[j] = np.float32(qx[j] - x0)
            ys[j] = np.float32(qy[j] - y0)
        y = luma_at(img, lut, cw0, x0, y0, x1, y1, xs, ys)
        q = 0
        kept = 0
        any_shadow = False
        for i in range(n):
            sh = False
            if cand[i]:
                sh = y[q] < nfx * max(y[mc + q], tiny)
                q += 1
            if sh:
                any_shadow = True
            if usable[b, i] and not sh:
                kept += 1
        if any_shadow and kept >= min_share * n:
            changed[b] = True
            q = 0
            for i in range(n):
                if cand[i]:
                    if y[q] < nfx * max(y[mc + q], tiny):
                        use_out[b, i] = False
                    q += 1
    return use_out, changed


#: :func:`fine_lut`'s entries per display value
FINE_LUT_STEPS = 64


def fine_lut(gamma: float = 2.2) -> np.ndarray:
    """(255 * FINE_LUT_STEPS + 2,) float64: ``(v / 255) ** gamma`` at v = i / FINE_LUT_STEPS."""
    v = np.arange(255 * FINE_LUT_STEPS + 2) / FINE_LUT_STEPS
    return (np.minimum(v, 255.0) / 255.0) ** gamma


@_compiled
def _fine(lut_fine, v):
    """``lut_fine`` (:func:`fine_lut`) at display value ``v``, clipped to [0, 255], interpolated."""
    x = min(max(v, 0.0), 255.0) * FINE_LUT_STEPS
    i = int(x)
    return lut_fine[i] + (x - i) * (lut_fine[i + 1] - lut_fine[i])


@_compiled
def sample_rays(img, lut, cw, cx, cy, counts, boxes, step, phi, s0, k, smooth, sigma_px, lut_fine):
    """The ray profiles of :func:`.edge_fit._edge_points` for the rays of :func:`ray_geometry`:
    ``img`` (H, W, 3) uint8 BGR, ``lut`` (256,) float32 display value -> linear radiance, ``cw``
    (3, 3) float32 linear BGR -> the unmixing's colour space. Each ray is sampled (k samples,
    ``step`` px apart from ``s0``) as ``cv2.remap`` samples the ball's window (bilinear, at 1/32
    px, round half to even; border replicated at the window's edge), in linear light (``prof``)
    and, with ``smooth``, also in gamma-encoded values whose colour differences are smoothed
    along the ray by a Gaussian of ``sigma_px`` px and then linearised (``prof_e``,
    :func:`.edge_fit._smooth_chroma_along_rays`; ``lut_fine``: the linearisation at
    1/:data:`FINE_LUT_STEPS` of a display value, :func:`fine_lut`, interpolated: relative error
    < 1e-4 above value 1, where a power per sample would cost more than all the rest); without
    ``smooth`` ``prof_e`` is ``prof``.
    Returns (prof (N, k, 3) float32, prof_e)."""
    N = len(phi)
    prof = np.empty((N, k, 3), np.float32)
    prof_e = np.empty((N, k, 3), np.float32) if smooth else prof
    one = np.float32(1.0)
    wt = np.empty(32, np.float32)
    for i in range(32):
        wt[i] = np.float32(i) * np.float32(1.0 / 32)
    lin = np.empty(3)
    g = np.empty(k)
    ker_t = np.empty((k, k))     # ker_t[i, j]: weight of sample i in smoothed sample j
    q = 0
    for b in range(len(counts)):
        n = counts[b]
        if n == 0:
            continue
        x0, y0, x1, y1 = boxes[b, 0], boxes[b, 1], boxes[b, 2], boxes[b, 3]
        ww, hh = x1 - x0, y1 - y0
        ys = np.empty((n, k))
        diff = np.empty((2 * n, k))      # B - Y', R - Y' of the encoded samples, per ray
        for r in range(n):
            ux, uy = math.cos(phi[q + r]), math.sin(phi[q + r])
            for j in range(k):
                s = s0[q + r] + j * step[b]
                fx = np.float32(cx[b] - x0 + s * ux)
                fy = np.float32(cy[b] - y0 + s * uy)
                ix = np.int64(np.rint(fx * np.float32(32.0)))
                iy = np.int64(np.rint(fy * np.float32(32.0)))
                xi, yi, ax, ay = ix >> 5, iy >> 5, ix & 31, iy & 31
                xa, xb = min(max(xi, 0), ww - 1), min(max(xi + 1, 0), ww - 1)
                ya, yb = min(max(yi, 0), hh - 1), min(max(yi + 1, 0), hh - 1)
                w0 = (one - wt[ay]) * (one - wt[ax])
                w1 = (one - wt[ay]) * wt[ax]
                w2 = wt[ay] * (one - wt[ax])
                w3 = wt[ay] * wt[ax]
                e0 = e1 = e2 = 0.0
                for ch in range(3):
                    p0 = img[y0 + ya, x0 + xa, ch]
                    p1 = img[y0 + ya, x0 + xb, ch]
                    p2 = img[y0 + yb, x0 + xa, ch]
                    p3 = img[y0 + yb, x0 + xb, ch]
                    lin[ch] = np.float32(lut[p0] * w0 + lut[p1] * w1 + lut[p2] * w2 + lut[p3] * w3)
                    if smooth:
                        v = np.float32(np.float32(p0) * w0 + np.float32(p1) * w1 + np.float32(p2) * w2
                                       + np.float32(p3) * w3)
                        if ch == 0:
                            e0 = v
                        elif ch == 1:
                            e1 = v
                        else:
                            e2 = v
                for c in range(3):
                    prof[q + r, j, c] = cw[c, 0] * lin[0] + cw[c, 1] * lin[1] + cw[c, 2] * lin[2]
                if smooth:
                    y = 0.114 * e0 + 0.587 * e1 + 0.299 * e2
                    ys[r, j] = y
                    diff[2 * r, j] = e0 - y
                    diff[2 * r + 1, j] = e2 - y
        if smooth:     # edge_fit._ray_kernel(k, round(sigma, 2)): rows summing to 1
            sg = max(np.rint(sigma_px / step[b] * 100.0) / 100.0, 1e-6)
            for d in range(k):
                g[d] = math.exp(-0.5 * (d / sg) ** 2)
            for j in range(k):
                tot = 0.0
                for i in range(k):
                    tot += g[abs(i - j)]
                for i in range(k):
                    ker_t[i, j] = np.float32(g[abs(i - j)] / tot)
            # diff @ ker_t, the output index innermost (no BLAS threads); a ray's two rows at a time
            # (one load of the kernel's row for both; the same sums in the same order)
            sm = np.zeros((2 * n, k))
            for r in range(0, 2 * n, 2):
                sb = sm[r]
                sr = sm[r + 1]
                for i in range(k):
                    d0 = diff[r, i]
                    d1 = diff[r + 1, i]
                    kr = ker_t[i]
                    for j in range(k):
                        kv = kr[j]
                        sb[j] += d0 * kv
                        sr[j] += d1 * kv
            for r in range(n):
                for j in range(k):
                    y = ys[r, j]
                    b2 = y + sm[2 * r, j]
                    r2 = y + sm[2 * r + 1, j]
                    g2 = (y - 0.114 * b2 - 0.299 * r2) * (1.0 / 0.587)
                    lin[0] = _fine(lut_fine, b2)
                    lin[1] = _fine(lut_fine, g2)
                    lin[2] = _fine(lut_fine, r2)
                    for c in range(3):
                        prof_e[q + r, j, c] = cw[c, 0] * lin[0] + cw[c, 1] * lin[1] + cw[c, 2] * lin[2]
        q += n
    return prof, prof_e


def warm_up() -> None:
    """Compile (or load from the cache) every kernel on a tiny input: call it before the first
    frame, off the time-critical path (a first compile takes ~10-20 s)."""
    k = 48
    prof = np.random.default_rng(0).random((4, k, 3)).astype(np.float32)
    starts, counts = np.array([0], np.int64), np.array([4], np.int64)
    ray_edges(prof, prof, starts, counts, np.full(4, 0.3), 1.5, 0.12, 0.08, 0.25, True, 0.75, 1.0, 0.5, 2.0, 1.45)
    ray_edges(prof, prof.copy(), starts, counts, np.full(4, 0.3), 1.5, 0.12, 0.08, 0.25, False, 0.75, 1.0, 0.5, 2.0,
              1.45)
    phi = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    P = np.stack([10 * np.cos(phi), 10 * np.sin(phi)], -1)[None]
    shaped_fits(P, np.ones((1, 32), np.bool_), np.ones((1, 32), np.bool_), np.ones(1), np.zeros(1), 0.6, 1.5,
                0.125, 0.3, 0.04, 0.5)
    px = np.ascontiguousarray(P[0, :, 0])
    ellipse_residuals(px, np.ascontiguousarray(P[0, :, 1]), 0.0, 0.0, 20.0, 20.0, 0.0, np.empty(32))
    contour_fit_rms(np.zeros((8, 1, 2), np.int32), 0.0, 0.0, 2.0, 1.0, 0.0)
    img = np.random.default_rng(1).integers(0, 256, (64, 64, 3)).astype(np.uint8)
    lut32 = np.linspace(0, 1, 256).astype(np.float32)
    luma_at(img, lut32, lut32[:3].copy(), 2, 2, 30, 30, np.full(4, 10.5, np.float32), np.full(4, 9.25, np.float32))
    okb = np.ones(1, np.bool_)
    shadow_rays(img, lut32, lut32[:3].copy(), P + 32.0, np.ones((1, 32), np.bool_), okb.repeat(32).reshape(1, 32), okb,
                32.0 * np.ones(1), 32.0 * np.ones(1), 19.0 * np.ones(1), 19.0 * np.ones(1), np.zeros(1), 1.5, 3.0, 0.0,
                0.3, 0.9, 0.6, 0.6)
    lut = np.linspace(0, 1, 256).astype(np.float32)
    # as edge_fit passes them: the balls' ellipses as contiguous rows of a (5, m) array, max_rays
    # given (a frame with 2+ balls once compiled these again, ~5 CPU s after an install, because
    # edge_fit passed strided columns then: the demo's first pose came stale, issue 35)
    ell = np.ascontiguousarray(np.array([[20.0, 20.0, 20.0, 18.0, 0.0], [44.0, 44.0, 20.0, 18.0, 30.0]]).T)
    cnt, box, _w, st, ph, s0 = ray_geometry(ell[0], ell[1], ell[2], ell[3], ell[4], k, 1.5, 64, 64, 96)
    for smooth in (True, False):
        sample_rays(img, lut, np.eye(3, dtype=np.float32), ell[0], ell[1], cnt, box, st, ph, s0, k, smooth, 2.0,
                    fine_lut())
    Pm = np.repeat(P, 2, axis=0) + 32.0
    shadow_rays(img, lut32, lut32[:3].copy(), Pm, np.ones((2, 32), np.bool_), np.ones((2, 32), np.bool_),
                np.ones(2, np.bool_), ell[0], ell[1], ell[2], ell[3], ell[4], 1.5, 3.0, 0.0, 0.3, 0.9, 0.6, 0.6)
