"""Each ball's disagreement with the others, read from one fit's residuals: a linearised
leave-one-out (no refits), for the trust model's per-ball cover.

A ball whose centre the detector read 1-2.5 px off while the others are right (partly hidden
by a thin instrument with its outline still looking smooth, a reflection on it) pulls the pose
towards it; the fit's residuals spread its error over all balls, so neither the RMS gate nor a
per-ball cover from its edge spread sees it, its shift in the CT is under the moved-fiducial
test's 1 mm, and the predicted error at the target stays small while the pose is 1-2 mm off
there (synthetic streams, docs/vision.md "A ball the others disagree with"; a ball whose error
the others share, as on fresh35's clutter scene, does not disagree and is not caught here). The
others predict where it should be: with the
fit's Jacobian ``J`` (2k x 6, px per pose parameter) and hat matrix ``H = J (J^T J)^-1 J^T``,
ball i's leave-one-out prediction error is ``e_i = (I - H_ii)^-1 r_i`` (``r_i`` its residual,
px; exact for the linearised fit), and ``d_i^2 = e_i^T (I - H_ii) e_i / s_i^2`` is chi-square
with 2 dof when its centre error has variance ``s_i^2`` per coordinate and the others are right.
A ball whose ``d_i^2`` is over the ``quantile`` of that law disagrees by more than its cover
allows: the pose tracker sets it aside for the frame (the pose from the others, when at least
:data:`MIN_BALLS` remain), or else raises its cover to its disagreement ``|e_i|`` per
coordinate, so the predicted error at the target carries what that ball can do to the pose.
Nothing here is permanent (a moved fiducial is :mod:`.consistency`'s business: it needs a shift
of >= 1 mm in the CT, and stays excluded).

Units: px; the rows of ``r`` and ``J`` are (u, v) per ball in ball order.
"""

from __future__ import annotations

import numpy as np

from .quantiles import chi2_ppf

#: fewest balls for the test: the other >= 4 must determine the pose with redundancy
MIN_BALLS = 5
#: a ball whose leverage leaves less than this of its own residual (smallest eigenvalue of
#: I - H_ii) is not tested: the others hardly constrain where it should be
MIN_FREEDOM = 0.05


def leave_one_out_errors(r: np.ndarray, J: np.ndarray, var_px2: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Per ball: its leave-one-out prediction error ``e_i`` (k, 2) px and ``d_i^2``, its
    chi-square statistic (2 dof; NaN without ``var_px2``), at the fit these residuals come from
    re-weighted by ``1 / var_px2`` (2k,, per row; None: equal weights, the residuals' own fit).
    A ball the others cannot predict (smallest eigenvalue of ``I - H_ii`` under
    :data:`MIN_FREEDOM`) has NaN. ``r`` (2k,) residuals px, ``J`` (2k, 6) px per pose parameter.
    Closed forms for the 2 x 2 blocks (no SVD)."""
    r = np.asarray(r, float).reshape(-1)
    J = np.asarray(J, float)
    k = len(r) // 2
    w = np.ones(2 * k) if var_px2 is None else 1.0 / np.sqrt(np.asarray(var_px2, float).reshape(-1))
    Jw, rw = J * w[:, None], r * w
    N = Jw.T @ Jw
    try:
        B = np.linalg.solve(N, Jw.T).T                  # (2k, 6): Jw N^-1
    except np.linalg.LinAlgError:
        B = Jw @ np.linalg.pinv(N)
    rw = rw - B @ (Jw.T @ rw)                          # the weighted fit's residuals (linearised step)
    Bu, Bv, Ju, Jv = B[0::2], B[1::2], Jw[0::2], Jw[1::2]
    a = 1.0 - np.einsum("ij,ij->i", Bu, Ju)            # I - H_ii = [[a, b], [b, c]]
    b = -0.5 * (np.einsum("ij,ij->i", Bu, Jv) + np.einsum("ij,ij->i", Bv, Ju))
    c = 1.0 - np.einsum("ij,ij->i", Bv, Jv)
    smallest = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)
    det = a * c - b * b
    free = (smallest >= MIN_FREEDOM) & (det > 0)
    ru, rv = rw[0::2], rw[1::2]
    e = np.full((k, 2), np.nan)
    d2 = np.full(k, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        eu = (c * ru - b * rv) / det                   # (I - H_ii)^-1 r_i
        ev = (a * rv - b * ru) / det
    e[free, 0] = eu[free] / w[0::2][free]
    e[free, 1] = ev[free] / w[1::2][free]
    if var_px2 is not None:
        d2[free] = (eu * ru + ev * rv)[free]           # e^T (I - H_ii) e = e^T r_i (whitened)
    return e, d2


def disagreement_cover(r: np.ndarray, J: np.ndarray, var_px2: np.ndarray, quantile: float
                       ) -> tuple[np.ndarray, list]:
    """(per-row variance floor (2k,) px^2, [(ball, |e| px)] of the balls it raised, in the
    order found). The floor is ``|e_i|^2`` on both rows of each ball whose
    disagreement with the others is over ``quantile`` (chi-square, 2 dof) for the centre error
    variances ``var_px2`` (2k,, per row), 0 elsewhere. One ball at a time, the worst first: its
    variance is raised to its disagreement and the others are tested again at the fit so
    re-weighted (a ball a pixel off pulls the pose, and the others' disagreements with that pose
    would name them too). Nothing is tested with fewer than :data:`MIN_BALLS` balls or
    ``quantile`` <= 0 (all zeros)."""
    r = np.asarray(r, float).reshape(-1)
    k = len(r) // 2
    out = np.zeros(2 * k)
    found: list = []
    if k < MIN_BALLS or not (quantile > 0):
        return out, found
    var = np.maximum(np.asarray(var_px2, float).reshape(-1).copy(), 1e-12)
    limit = chi2_ppf(float(quantile), 2)
    hit = np.zeros(k, bool)
    for _ in range(k - MIN_BALLS + 1):
        e, d2 = leave_one_out_errors(r, J, var)
        d2 = np.where(hit | ~np.isfinite(d2), -1.0, d2)
        i = int(np.argmax(d2))
        if not d2[i] > limit:
            break
        hit[i] = True
        out[2 * i:2 * i + 2] = float(e[i] @ e[i])
        var[2 * i:2 * i + 2] = np.maximum(var[2 * i:2 * i + 2], out[2 * i])
        found.append((i, float(np.sqrt(out[2 * i]))))
    return out, found
