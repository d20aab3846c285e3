"""The compiled edge-fit kernels (edge_kernels) give the NumPy reference's edges, fits and
refusals (edge_fit.COMPILED = False), on rendered frames and on random balls."""

import numpy as np
import pytest

from monotracker.sim.camera_sim import SimulatedCamera
from monotracker.vision import edge_fit
from monotracker.vision.detect_classical import ClassicalDetector
from monotracker.vision.detection import BlobRules

from independent_render import Imaging, Occluder, render_in_frame


def _ball(rng, n, cut: bool):
    """Edge points of one ball of a known shape: n rays, noise, some rays unusable, an
    outlier, and (``cut``) an arc pushed inwards like a chord."""
    ratio = rng.uniform(0.85, 1.0)
    major = rng.uniform(-90, 90)
    r = rng.uniform(4, 25)
    c = rng.uniform(100, 500, 2)
    phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    t = phi - np.radians(major)
    rad = 1.0 / np.sqrt((np.cos(t) / (r / ratio)) ** 2 + (np.sin(t) / r) ** 2) + rng.normal(0, 0.15, n)
    if cut:
        arc = (np.arange(n) - rng.integers(n)) % n < max(4, n // 6)
        rad[arc] -= rng.uniform(0.5, 2.0)
    rad[rng.integers(n)] += 3.0
    pts = c + rad[:, None] * np.column_stack([np.cos(phi), np.sin(phi)])
    return pts, rng.random(n) > 0.1, (ratio, major)


def _both(fn):
    old = edge_fit.COMPILED
    try:
        edge_fit.COMPILED = True
        a = fn()
        edge_fit.COMPILED = False
        b = fn()
    finally:
        edge_fit.COMPILED = old
    return a, b


@pytest.mark.parametrize("seed", range(4))
def test_compiled_fits_equal_the_reference(seed):
    rng = np.random.default_rng(seed)
    balls = {k: _ball(rng, int(rng.integers(32, 97)), cut=bool(k % 3 == 0)) for k in range(12)}
    balls[12] = (balls[0][0][:40], np.zeros(40, bool), (0.9, 10.0))          # nothing usable
    shapes = [b[2] for b in balls.values()]
    got, ref = _both(lambda: edge_fit._shaped_fits({k: b[:2] for k, b in balls.items()}, shapes, 1.5))
    n_cut = 0
    for k in balls:
        (fa, ca), (fb, cb) = got[k], ref[k]
        assert (fa is None) == (fb is None)
        if fa is None:
            continue
        assert np.allclose(fa[0][0], fb[0][0], atol=1e-9) and np.allclose(fa[0][1], fb[0][1], atol=1e-9)
        assert np.array_equal(fa[1], fb[1]) and fa[2] == pytest.approx(fb[2], abs=1e-9)
        assert ca == cb
        n_cut += ca
    assert 1 <= n_cut < len(balls) - 1          # both outcomes of the cut test were seen


def _centres(det, images):
    return [det.detect(img) for img in images]


@pytest.mark.parametrize("optics", [None, "photo", "degraded"])
def test_compiled_detector_finds_the_reference_centres(optics):
    """Our simulator's frames (sharp, photo-like, degraded): the same balls accepted and rejected
    (same reasons) and centres within 1e-3 px."""
    cam = SimulatedCamera(seed=5, optics=optics)
    images = [cam.render(t)[0] for t in (0.0, 0.7)]
    got, ref = _both(lambda: _centres(ClassicalDetector(BlobRules(camera=cam.camera)), images))
    for a, b in zip(got, ref):
        assert len(a.fiducials) == len(b.fiducials) >= 8
        assert np.abs(a.centres - b.centres).max() < 1e-3
        assert sorted(r.reason for r in a.rejected) == sorted(r.reason for r in b.rejected)


def test_compiled_edges_equal_the_reference_on_independent_renders():
    """Balls rendered independently of our simulator (Bayer, defocus, JPEG, occluders): per ray
    the same usable flags (all but a few rays at a threshold) and the same edges."""
    rng = np.random.default_rng(11)
    n_rays = n_diff = 0
    for q in range(12):
        imaging = Imaging(defocus_px=1.5, jpeg_quality=85) if q % 2 else Imaging(defocus_px=0.0, jpeg_quality=0)
        occ = Occluder(depth=0.25) if q % 3 == 0 else None
        img, c = render_in_frame(rng, imaging, occluder=occ)
        ell = [((float(c[0]), float(c[1])), (20.0, 19.0), 0.0)]
        for blur in (1.0, 2.0):
            a, b = _both(lambda img=img, ell=ell, blur=blur: edge_fit._edge_points(img, ell, blur))
            (pa, ua), (pb, ub) = a[0], b[0]
            both = ua & ub
            n_rays += len(ua)
            n_diff += int((ua != ub).sum())
            assert np.abs(pa[both] - pb[both]).max() < 1e-3
    assert n_diff <= 0.01 * n_rays, (n_diff, n_rays)


def test_ray_layout_hand_checked():
    """edge_kernels.ray_geometry (the edge fit's one ray layout) against values worked out by
    hand from its rule, and each ray's crossing of the ellipse checked with the ellipse's own
    equation in its axes' frame."""
    from monotracker.vision import edge_kernels

    k, blur = 48, 1.5
    # (cx, cy, d1, d2, angle deg): a circle of radius 10, an ellipse 20 x 15 at 30 deg, a small
    # ball (radius 4: the 32-ray floor, w_in = 0.65 r), a big one (radius 40: the 96-ray cap),
    # and one whose window leaves the 300 x 200 image
    e = np.array([(100.3, 80.7, 20.0, 20.0, 0.0), (150.0, 100.0, 40.0, 30.0, 30.0), (40.5, 40.5, 8.0, 8.0, 0.0),
                  (200.0, 100.0, 80.0, 80.0, 0.0), (3.0, 100.0, 20.0, 20.0, 0.0)])
    counts, boxes, w_in, step, phi, s0 = edge_kernels.ray_geometry(e[:, 0], e[:, 1], e[:, 2], e[:, 3], e[:, 4],
                                                                   k, blur, 200, 300)
    # rays: int(2 pi 10 / 1.6) = 39, int(2 pi 20 / 1.6) = 78, 2 pi 4 / 1.6 = 15.7 -> 32, 157 -> 96
    assert counts.tolist() == [39, 78, 32, 96, 0]
    # w_out = 3 + b / 4 + blur: 7.0, 8.25, 5.5, 14.5; w_in = min(w_out, 0.65 r_min): 6.5, 8.25, 2.6, 14.5
    w_out = np.array([7.0, 8.25, 5.5, 14.5])
    assert w_in[:4] == pytest.approx([6.5, 8.25, 2.6, 14.5])
    assert step[:4] == pytest.approx((w_in[:4] + w_out) / 47)
    # the circle's window: half side ceil(10 + 7 + 2) = 19 around (100, 80), +2 on the far side
    assert boxes[0].tolist() == [81, 61, 121, 101]
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    for b in range(4):
        n = counts[b]
        ph, st = phi[first[b]:first[b] + n], s0[first[b]:first[b] + n]
        assert ph == pytest.approx(np.arange(n) * 2 * np.pi / n)
        # each ray crosses the ellipse w_in px after its start: (u / a)^2 + (v / b)^2 = 1 there
        r = st + w_in[b]
        th = np.radians(e[b, 4])
        u = r * np.cos(ph) * np.cos(th) + r * np.sin(ph) * np.sin(th)
        v = -r * np.cos(ph) * np.sin(th) + r * np.sin(ph) * np.cos(th)
        assert (u / (e[b, 2] / 2)) ** 2 + (v / (e[b, 3] / 2)) ** 2 == pytest.approx(np.ones(n))
        # ... and ends w_out beyond it; every sample's 2 x 2 bilinear neighbourhood inside the window
        assert st + (k - 1) * step[b] == pytest.approx(r + w_out[b])
        x0, y0, x1, y1 = boxes[b]
        for s in (st, st + (k - 1) * step[b]):
            x, y = e[b, 0] + s * np.cos(ph), e[b, 1] + s * np.sin(ph)
            assert x.min() >= x0 and x.max() < x1 - 1 and y.min() >= y0 and y.max() < y1 - 1
    assert len(phi) == len(s0) == counts.sum()
    # a cap on the rays (edge_fit.MAX_RAYS) caps only the balls above it: 78 -> 48, 96 -> 48
    capped = edge_kernels.ray_geometry(e[:, 0], e[:, 1], e[:, 2], e[:, 3], e[:, 4], k, blur, 200, 300, 48)
    assert capped[0].tolist() == [39, 48, 32, 48, 0]
    assert capped[2][:4] == pytest.approx(w_in[:4]) and capped[3][:4] == pytest.approx(step[:4])


def test_luma_at_matches_remap():
    """edge_kernels.luma_at (the contact-shadow test's luma samples) against cv2.remap of the
    linearised window (the NumPy body of edge_fit._without_shadow_rays), at random points."""
    import cv2

    from monotracker.vision import edge_kernels

    rng = np.random.default_rng(4)
    img = rng.integers(0, 256, (120, 160, 3)).astype(np.uint8)
    x0, y0, x1, y1 = 20, 10, 90, 70
    q = np.column_stack([rng.uniform(0, x1 - x0 - 2, 400), rng.uniform(0, y1 - y0 - 2, 400)]).astype(np.float32)
    q[:8] = np.round(q[:8] * 32) / 32 + 1 / 64       # ties of the 1/32 px grid
    lin = (edge_fit.LINEAR_LUT[img[y0:y1, x0:x1]] @ edge_fit.COLOUR_WEIGHTS[0]).astype(np.float32)
    ref = cv2.remap(lin, q[None, :, 0], q[None, :, 1], cv2.INTER_LINEAR)[0]
    got = edge_kernels.luma_at(img, edge_fit.LINEAR_LUT, edge_fit._LUMA_WEIGHTS, x0, y0, x1, y1,
                               np.ascontiguousarray(q[:, 0]), np.ascontiguousarray(q[:, 1]))
    assert np.abs(got - ref).max() < 1e-6


@pytest.mark.parametrize("inside_px, far_per_radius", [(float("inf"), 0.0), (0.6, 0.0), (0.6, 0.6)])
def test_shadow_rays_equal_the_reference(inside_px, far_per_radius):
    """edge_kernels.shadow_rays (the contact-shadow test of all balls in one call) leaves out the
    same rays of the same balls as the per-ball NumPy loop with cv2.remap (edge_fit.COMPILED
    False): on balls with a contact shadow drawn by test_edge_fit_shadow (the shadow rays found),
    and on random edge points over a random image, some balls' windows leaving it; with only rays
    outside the outline tested (the rule before 2026-12-01) and with rays inside too (SHADOW_IN_PX,
    the default); the far background 3 px beyond the near one, or in proportion to each ball's
    radius (SHADOW_FAR_PER_RADIUS)."""
    from test_edge_fit_shadow import shadowed_ball

    rng = np.random.default_rng(7)
    changed = 0
    for _ in range(6):
        radius = float(rng.uniform(8, 18))
        size = int(2 * radius + 40)
        c = size / 2 + rng.uniform(-1, 1, 2)
        img, _ = shadowed_ball(c, radius, size, shadow_deg=float(rng.uniform(0, 360)))
        ells = [((c[0] + 0.4, c[1] - 0.3), (2 * radius + 0.8, 2 * radius + 0.8), 0.0),
                ((c[0] - 0.3, c[1] + 0.5), (2 * radius + 0.2, 2 * radius - 0.4), 10.0)]
        balls = {b: got for b, got in enumerate(edge_fit._edge_points(img, ells, 1.5)) if got is not None}
        fits = edge_fit._shaped_fits(balls, [(1.0, 0.0)] * len(ells), 1.5)
        got, ref = _both(lambda img=img, balls=balls, fits=fits: edge_fit._without_shadow_rays(img, balls, fits, 1.5,
                                                                                                 inside_px, far_per_radius))
        assert got.keys() == ref.keys()
        for i in got:
            assert np.array_equal(got[i], ref[i])
        changed += len(got)
    assert changed >= 4                     # the shadow rays were found, not only the empty answer
    img = rng.integers(0, 256, (90, 120, 3)).astype(np.uint8)
    balls, fits = {}, {}
    for i in range(40):
        n = int(rng.integers(32, 65))
        c = rng.uniform(-5, 125, 2) * [1.0, 0.75]
        r = rng.uniform(4, 15)
        ratio, major = rng.uniform(0.85, 1.0), rng.uniform(-90, 90)
        phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
        rad = r + rng.normal(0, 0.4, n) + rng.uniform(0, 2, n) * (rng.random(n) < 0.3)
        balls[i] = (c + rad[:, None] * np.column_stack([np.cos(phi), np.sin(phi)]), rng.random(n) > 0.1)
        ell = ((float(c[0]), float(c[1])), (2 * r / ratio, 2 * r), float(major))
        fits[i] = (None if i % 9 == 0 else (ell, np.ones(n, bool), 0.1), False)
    got, ref = _both(lambda: edge_fit._without_shadow_rays(img, balls, fits, 1.8, inside_px, far_per_radius))
    assert got.keys() == ref.keys() and 5 <= len(got) < 40
    for i in got:
        assert np.array_equal(got[i], ref[i])


def _reference_profiles(img, balls, layout, smooth):
    """The ray profiles of the rays ``layout`` (edge_kernels.ray_geometry's, checked by hand in
    test_ray_layout_hand_checked) as edge_fit._edge_points' NumPy body samples them (cv2.remap
    per ball, chroma smoothed along the rays with NumPy), for the balls inside the image."""
    import cv2

    k = edge_fit.SAMPLES
    counts, boxes, _w_in, step_b, phi_all, s0_all = layout
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    profs, sprofs = [], []
    for i, ((cx, cy), _axes, _ang) in enumerate(balls):
        if counts[i] == 0:
            continue
        phi, s0, step = phi_all[first[i]:first[i] + counts[i]], s0_all[first[i]:first[i] + counts[i]], step_b[i]
        x0, y0, x1, y1 = boxes[i]
        roi = img[y0:y1, x0:x1]
        s = s0[:, None] + (np.arange(k) * step)[None, :]
        mx = (cx - x0 + s * np.cos(phi)[:, None]).astype(np.float32)
        my = (cy - y0 + s * np.sin(phi)[:, None]).astype(np.float32)
        profs.append(cv2.remap(edge_fit.LINEAR_LUT[roi], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
        enc = cv2.remap(roi.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        sprofs.append(edge_fit._smooth_chroma_along_rays(enc, edge_fit.CHROMA_SIGMA_PX / step))
    W = edge_fit.COLOUR_WEIGHTS.T
    return np.concatenate(profs) @ W, (np.concatenate(sprofs) @ W if smooth else None)


@pytest.mark.parametrize("optics", ["photo", None])
def test_compiled_ray_sampling_equals_remap(optics):
    """edge_kernels.sample_rays (the compiled sampling of the edge fit's rays) gives the profiles
    of cv2.remap and the NumPy chroma smoothing on the same rays (the layout is checked by hand
    in test_ray_layout_hand_checked): the same samples (OpenCV's 1/32 px bilinear), to float32
    rounding; balls near the border left out."""
    from monotracker.vision import edge_kernels

    cam = SimulatedCamera(seed=2, optics=optics)
    img, tr = cam.render(0.4)
    rng = np.random.default_rng(3)
    balls = [((float(c[0]) + rng.uniform(-1, 1), float(c[1]) + rng.uniform(-1, 1)),
              (float(2 * a + rng.uniform(0, 2)), float(2 * a)), float(rng.uniform(-90, 90)))
             for c, a in zip(tr.ellipse_centres_px, rng.uniform(4, 22, len(tr.ellipse_centres_px)))]
    balls.append(((3.0, 200.0), (20.0, 20.0), 0.0))                   # its window leaves the image
    e = np.array([(c[0], c[1], d[0], d[1], a) for c, d, a in balls])
    for blur in (1.2, 2.5):
        layout = edge_kernels.ray_geometry(e[:, 0], e[:, 1], e[:, 2], e[:, 3], e[:, 4], edge_fit.SAMPLES, blur,
                                           *img.shape[:2])
        counts, boxes, _w, step, phi, s0 = layout
        assert counts[-1] == 0 and (counts[:-1] >= 32).all()
        prof, prof_e = edge_kernels.sample_rays(img, edge_fit.LINEAR_LUT, edge_fit.COLOUR_WEIGHTS, e[:, 0], e[:, 1],
                                                counts, boxes, step, phi, s0, edge_fit.SAMPLES, True,
                                                edge_fit.CHROMA_SIGMA_PX, edge_kernels.fine_lut())
        ref, ref_e = _reference_profiles(img, balls, layout, True)
        assert prof.shape == ref.shape
        assert np.abs(prof - ref).max() < 1e-5
        assert np.abs(prof_e - ref_e).max() < 2e-4


def test_contour_fit_rms_is_the_radial_deviation_about_its_mean():
    """edge_kernels.contour_fit_rms (score_blob's fit term) against the formula written out here
    with NumPy: a pixel contour of a dented ellipse, its OpenCV fit, each point's (rho - 1)
    sqrt(a b) with rho the point's normalised radius in the ellipse's axes, RMS about the mean."""
    import cv2

    from monotracker.vision import edge_kernels

    rng = np.random.default_rng(8)
    for _ in range(5):
        img = np.zeros((120, 140), np.uint8)
        c = (int(rng.integers(50, 90)), int(rng.integers(45, 75)))
        cv2.ellipse(img, c, (int(rng.integers(12, 30)), int(rng.integers(10, 25))), float(rng.uniform(0, 180)), 0, 360,
                    255, -1)
        cv2.circle(img, (c[0] + 15, c[1]), 6, 0, -1)                      # a dent
        cnt = max(cv2.findContours(img, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0], key=len)
        (ex, ey), (d1, d2), ang = cv2.fitEllipse(cnt)
        p = cnt.reshape(-1, 2) - [ex, ey]
        th = np.radians(ang)
        u = p[:, 0] * np.cos(th) + p[:, 1] * np.sin(th)
        v = -p[:, 0] * np.sin(th) + p[:, 1] * np.cos(th)
        dev = (np.hypot(u / (d1 / 2), v / (d2 / 2)) - 1.0) * np.sqrt(d1 * d2 / 4)
        want = np.std(dev)
        assert edge_kernels.contour_fit_rms(cnt, ex, ey, d1, d2, ang) == pytest.approx(want, rel=1e-12)
        assert want > 0.1


def test_selection_gives_the_sorted_arrays_values():
    """The compiled order statistic and median (written out instead of numba's np.partition /
    np.sort, which cost seconds of every cold compile) against NumPy: duplicates, NaNs (sorted
    last), every k, odd and even lengths, the empty array."""
    from monotracker.vision.edge_kernels import _kth_smallest, _median

    rng = np.random.default_rng(5)
    for n in list(range(1, 12)) + [31, 64, 200]:
        for kind in ("uniform", "ties", "nan"):
            x = rng.normal(size=n)
            if kind == "ties":
                x = np.round(x * 2) / 2
            if kind == "nan":
                x[rng.random(n) < 0.3] = np.nan
            s, before = np.sort(x), x.copy()
            for k in range(n):
                got = _kth_smallest(x, k)
                assert (np.isnan(got) and np.isnan(s[k])) or got == s[k], (kind, n, k, got, s[k])
            if kind != "nan":
                assert _median(x) == np.median(x), (kind, n)
            assert np.array_equal(x, before, equal_nan=True)   # the input is not reordered
    assert np.isnan(_median(np.zeros(0)))
