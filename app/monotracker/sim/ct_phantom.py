"""Synthetic head CT: voxelises the analytic :class:`~monotracker.sim.phantom.HeadPhantom`.

The phantom's geometry (skin ellipsoid with neck cut, 5 mm scalp, 7 mm skull, brain, the
fiducial spheres and the skin clip) comes from ``phantom.py`` unchanged; this module only turns
it into a CT as a scanner would, so that detectors can be tested against the analytic centres.

Image formation (choices the paper leaves open, written down):

* **Partial volume + PSF, analytically.** Every structure has a signed distance ``d`` (mm,
  negative inside). A voxel's fill fraction is ``0.5 * erfc(d / (sqrt(2) * s))`` where
  ``s**2 = psf_sigma**2 + sum_i (n_i * w_i)**2 / 12`` combines the scanner's Gaussian point
  spread (``psf_sigma_mm``) with the box average over the voxel (width ``w_i`` along grid axis
  ``i``, ``n`` the surface normal in grid axes). That is the exact response of a plane edge and
  an excellent one for the 4 mm balls; it is symmetric about each sphere centre, so the analytic
  centres remain the truth to well below 0.01 mm. Thick slices therefore blur more along z.
* **Noise.** Gaussian, correlated in-plane (a Gaussian reconstruction kernel of
  ``noise_corr_mm``), rescaled to ``noise_hu`` standard deviation, independent between slices,
  as filtered back-projection gives. Values are clipped to [-1024, 3071] HU like a 12-bit
  scanner and stored as int16 HU (rescale slope 1, intercept 0).
* **Reconstruction circle.** Voxels outside the in-plane circle inscribed in the grid are set to
  ``-1024`` with no noise (scanners pad outside the field of view); ``fov_circle=False`` keeps
  the whole square.
* **Metal streaks** (optional, ``metal_streak_hu``): the skin clip throws the usual
  alternating bright/dark radial streaks in the slices that cross it.
* **Oblique grid.** ``direction`` is the 3x3 matrix whose columns are the grid's i, j, k axes in
  LPS (a gantry tilt plus a small roll by default), so no detector can get away with indices.

Sample data (``make_sample_ct``) uses 0.8 x 0.8 mm in-plane and 1.25 mm slices: typical of a
clinical head protocol, anisotropic (the issue asks for it), and small enough that the
compressed NIfTI stays well under the ~8 MB repo budget (noise is incompressible, so the
voxel count sets the file size). The 0.5 x 0.5 x 1.0 mm case and a 512 x 512 x 300 volume are
generated in memory by the tests and the benchmark.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.special import erfc

from monotracker.geometry import rotation_about_axis
from monotracker.sim.phantom import HU, HeadPhantom, default_phantom

AIR_FLOOR_HU = -1024
CT_MAX_HU = 3071


def default_direction() -> np.ndarray:
    """Oblique grid axes (columns, LPS): 14 deg gantry tilt about L, then 6 deg about S."""
    R = rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.radians(6.0)) @ rotation_about_axis(
        np.array([1.0, 0.0, 0.0]), np.radians(-14.0)
    )
    return R


@dataclass(frozen=True)
class DenseBlob:
    """An extra dense ellipsoid (a distractor): centre LPS mm, semi-axes mm along the rotated
    axes ``axes`` (columns, LPS; identity = aligned with L, P, S), value in HU."""

    centre_lps: np.ndarray
    semi_axes_mm: np.ndarray
    hu: float
    axes: np.ndarray = field(default_factory=lambda: np.eye(3))
    name: str = "blob"
    #: Metal streaks thrown by this object (peak HU of the alternating radial pattern; 0 none).
    streak_hu: float = 0.0


@dataclass(frozen=True)
class ScanParams:
    """How the synthetic scanner samples the phantom. Spacing is (i, j, k) = (x, y, z) of the
    grid in mm; ``size`` (i, j, k) voxels or None to cover the head plus ``margin_mm``."""

    spacing_mm: tuple = (0.8, 0.8, 1.25)
    direction: np.ndarray = field(default_factory=default_direction)
    size: tuple | None = None
    grid_centre_lps: np.ndarray | None = None
    margin_mm: float = 6.0
    psf_sigma_mm: float = 0.45
    noise_hu: float = 18.0
    noise_corr_mm: float = 0.5
    metal_streak_hu: float = 0.0
    fov_circle: bool = True
    seed: int = 20250168
    distractors: tuple = ()
    #: Ball density, HU (None: the phantom's 3000 HU); ceramic/plastic kits are 1500-2000 HU.
    fiducial_hu: float | None = None
    #: How deep the balls sink into the scalp, mm (0: resting on the skin; R: half-embedded).
    fiducial_embed_mm: float = 0.0


def default_distractors(phantom: HeadPhantom | None = None) -> tuple[DenseBlob, ...]:
    """Distractors a detector must reject, beside the phantom's skin clip: a dense bony nodule
    (an osteoma: an elongated 2800 HU ellipsoid inside the skull near the fiducial patch) and a
    small 1.5 mm metal bead on the scalp (dense and round but far too small)."""
    ph = phantom or default_phantom()
    v = ph.view_direction_lps
    p, n = ph.skin_point(_rotate_towards(v, 25.0, 0.0), inset_mm=ph.scalp_thickness_mm + 3.5)
    axes = _frame_with_z(n)
    nodule = DenseBlob(p, np.array([2.5, 2.5, 5.5]), 2800.0, axes=axes[:, [1, 2, 0]], name="bone nodule")
    q, m = ph.skin_point(_rotate_towards(v, 20.0, 120.0))
    bead = DenseBlob(q + 1.5 * m, np.array([1.5, 1.5, 1.5]), 3000.0, name="small bead")
    return nodule, bead


def _rotate_towards(v: np.ndarray, theta_deg: float, phi_deg: float) -> np.ndarray:
    from monotracker.sim.phantom import _direction

    return _direction(v, theta_deg, phi_deg)


def _frame_with_z(n: np.ndarray) -> np.ndarray:
    from monotracker.sim.phantom import _tangent_frame

    e1, e2 = _tangent_frame(n)
    return np.column_stack([e1, e2, n])


@dataclass
class SyntheticCT:
    """A generated CT: int16 HU array (z, y, x) and its geometry, plus the truth."""

    array: np.ndarray
    spacing_mm: np.ndarray
    origin_mm: np.ndarray
    direction: np.ndarray
    phantom: HeadPhantom
    params: ScanParams

    @property
    def fiducial_centres_lps(self) -> np.ndarray:
        return fiducial_centres(self.phantom, self.params)

    def to_sitk(self):
        import SimpleITK as sitk

        img = sitk.GetImageFromArray(self.array)
        img.SetSpacing([float(s) for s in self.spacing_mm])
        img.SetOrigin([float(o) for o in self.origin_mm])
        img.SetDirection([float(x) for x in self.direction.ravel()])
        return img

    def truth(self) -> dict:
        """JSON-ready ground truth: the phantom summary plus the scan and distractors."""
        out = self.phantom.summary()
        out["distractors"] = [
            {"name": "skin clip", "segment_lps_mm": out["clip_segment_lps_mm"], "hu": HU["clip"]}
        ] + [
            {
                "name": b.name,
                "centre_lps_mm": np.round(b.centre_lps, 6).tolist(),
                "semi_axes_mm": np.asarray(b.semi_axes_mm).tolist(),
                "hu": b.hu,
            }
            for b in self.params.distractors
        ]
        p = self.params
        out["scan"] = {
            "spacing_mm": [float(s) for s in self.spacing_mm],
            "size_ijk": [int(s) for s in self.array.shape[::-1]],
            "origin_lps_mm": [float(o) for o in self.origin_mm],
            "direction_columns_lps": self.direction.round(12).tolist(),
            "psf_sigma_mm": p.psf_sigma_mm,
            "noise_hu": p.noise_hu,
            "noise_corr_mm": p.noise_corr_mm,
            "metal_streak_hu": p.metal_streak_hu,
            "seed": p.seed,
        }
        return out


def fiducial_centres(phantom: HeadPhantom, params: ScanParams) -> np.ndarray:
    """(n, 3) true ball centres of this scan, LPS mm: the phantom's, sunk into the scalp by
    ``params.fiducial_embed_mm`` along the skin normal."""
    c = phantom.fiducial_centres_lps
    if not params.fiducial_embed_mm:
        return c
    out = []
    for ci in c:
        _, nrm = phantom.skin_point(ci - phantom.centre_lps)
        out.append(ci - params.fiducial_embed_mm * nrm)
    return np.array(out)


def metal_distractors(phantom: HeadPhantom | None = None, streak_hu: float = 300.0) -> tuple[DenseBlob, ...]:
    """Metal denser than the balls near the fiducial patch, inside the head: three 3071 HU
    "fillings" (blocks ~6 x 4 x 4 mm) and a steel rod (2 x 2 x 18 mm), each throwing streaks of
    ``streak_hu``. What dental work and an implant do to a head CT's histogram."""
    ph = phantom or default_phantom()
    v = ph.view_direction_lps
    out = []
    for i, (th, phi) in enumerate(((18.0, 60.0), (22.0, 200.0), (12.0, 300.0))):
        p, n = ph.skin_point(_rotate_towards(v, th, phi), inset_mm=ph.scalp_thickness_mm + ph.skull_thickness_mm + 4.0)
        out.append(DenseBlob(p, np.array([3.0, 2.0, 2.0]), float(CT_MAX_HU), axes=_frame_with_z(n), name=f"filling {i + 1}",
                             streak_hu=streak_hu))
    p, n = ph.skin_point(_rotate_towards(v, 8.0, 130.0), inset_mm=ph.scalp_thickness_mm + ph.skull_thickness_mm + 6.0)
    out.append(DenseBlob(p, np.array([1.0, 1.0, 9.0]), float(CT_MAX_HU), axes=_frame_with_z(n)[:, [2, 0, 1]], name="steel rod",
                         streak_hu=streak_hu))
    return tuple(out)


# ---------------------------------------------------------------------------- geometry helpers
def _ellipsoid_sd(q: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Approximate signed distance (mm) to an axis-aligned ellipsoid; ``q`` (..., 3) relative
    to its centre. First-order (f (f-1) / |grad f|), exact for spheres, good near the surface."""
    qa = q / a
    f = np.sqrt(np.sum(qa * qa, axis=-1))
    g = np.sqrt(np.sum((q / (a * a)) ** 2, axis=-1))
    return f * (f - 1.0) / np.maximum(g, 1e-9)


def _ellipsoid_normal(q: np.ndarray, a: np.ndarray) -> np.ndarray:
    g = q / (a * a)
    return g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-9)


def _edge_sigma(normal_lps: np.ndarray, direction: np.ndarray, spacing: np.ndarray, psf: float) -> np.ndarray:
    """Effective Gaussian sigma (mm) of a surface with the given normals: PSF + voxel box."""
    n_grid = normal_lps @ direction  # components along the grid axes
    box = np.sum((n_grid * spacing) ** 2, axis=-1) / 12.0
    return np.sqrt(psf * psf + box)


def _fill(d: np.ndarray, s: np.ndarray) -> np.ndarray:
    return 0.5 * erfc(d / (np.sqrt(2.0) * s))


def _grid_for(phantom: HeadPhantom, params: ScanParams) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Origin (LPS mm), spacing, size (i, j, k) covering the head in the oblique grid."""
    D = np.asarray(params.direction, float)
    sp = np.asarray(params.spacing_mm, float)
    c = phantom.centre_lps
    if params.size is not None:
        size = tuple(int(s) for s in params.size)
        half = (np.array(size) - 1) * sp / 2.0
        centre = c if params.grid_centre_lps is None else np.asarray(params.grid_centre_lps, float)
        origin = centre - D @ half
        return origin, sp, size
    # sample the skin surface (above the neck cut) and the fiducials
    u = np.random.default_rng(0).normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pts = c + u * phantom.skin_semi_axes_mm
    pts = pts[pts[:, 2] >= phantom.neck_cut_z_mm]
    cut = c + np.c_[u[:, :2] * phantom.skin_semi_axes_mm[:2], np.zeros(len(u))]
    cut[:, 2] = phantom.neck_cut_z_mm
    pts = np.vstack([pts, cut, phantom.fiducial_centres_lps])
    g = (pts - c) @ D  # grid-frame coordinates
    lo = g.min(axis=0) - params.margin_mm - phantom.fiducial_radius_mm
    hi = g.max(axis=0) + params.margin_mm + phantom.fiducial_radius_mm
    size = tuple(int(np.ceil((h - l) / s)) + 1 for l, h, s in zip(lo, hi, sp))
    origin = c + D @ lo
    return origin, sp, size


# ---------------------------------------------------------------------------- generator
def generate_ct(phantom: HeadPhantom | None = None, params: ScanParams | None = None) -> SyntheticCT:
    """Voxelise ``phantom`` as a CT with ``params`` (see the module docstring). Deterministic
    for a given seed. Returns int16 HU, array axes (z, y, x) = (k, j, i)."""
    ph = phantom or default_phantom()
    p = params or ScanParams()
    D = np.asarray(p.direction, float)
    if not np.allclose(D.T @ D, np.eye(3), atol=1e-6):
        raise ValueError("direction must be orthonormal")
    origin, sp, (ni, nj, nk) = _grid_for(ph, p)
    rng = np.random.default_rng(p.seed)
    out = np.empty((nk, nj, ni), np.int16)

    ii, jj = np.meshgrid(np.arange(ni, dtype=np.float32), np.arange(nj, dtype=np.float32))
    # in-plane physical offsets of slice k=0 (float64 for sub-micron accuracy near spheres)
    base = (origin[None, None, :] + ii[..., None] * (sp[0] * D[:, 0]) + jj[..., None] * (sp[1] * D[:, 1]))
    if p.fov_circle:
        ci, cj = (ni - 1) / 2.0, (nj - 1) / 2.0
        r2 = ((ii - ci) * sp[0]) ** 2 + ((jj - cj) * sp[1]) ** 2
        outside = r2 > (max(ni * sp[0], nj * sp[1]) / 2.0) ** 2
    else:
        outside = None

    a0 = ph.skin_semi_axes_mm
    shells = [  # (semi-axes, value inside minus value outside)
        (a0, HU["scalp"] - HU["air"]),
        (a0 - ph.scalp_thickness_mm, HU["bone"] - HU["scalp"]),
        (a0 - ph.scalp_thickness_mm - ph.skull_thickness_mm, HU["brain"] - HU["bone"]),
    ]
    zcut = ph.neck_cut_z_mm
    s_cut = float(_edge_sigma(np.array([0.0, 0.0, 1.0]), D, sp, p.psf_sigma_mm))

    # local dense objects: fiducials, extra blobs, the clip
    ball_hu = HU["fiducial"] if p.fiducial_hu is None else float(p.fiducial_hu)
    blobs = [(c, np.full(3, ph.fiducial_radius_mm), np.eye(3), ball_hu) for c in fiducial_centres(ph, p)]
    blobs += [(b.centre_lps, np.asarray(b.semi_axes_mm, float), np.asarray(b.axes, float), b.hu) for b in p.distractors]
    streaky = [b for b in p.distractors if b.streak_hu > 0]
    ca, cb = ph.clip_segment_lps

    def k_range(points_lps: np.ndarray, reach: float) -> tuple[int, int]:
        kk = ((points_lps - origin) @ D[:, 2]) / sp[2]
        return int(np.floor(kk.min() - reach / sp[2])), int(np.ceil(kk.max() + reach / sp[2]))

    blob_k = [k_range(np.array([c]), float(np.max(a)) + 4.0) for c, a, _, _ in blobs]
    clip_k = k_range(np.array([ca, cb]), ph.clip_radius_mm + 4.0)
    corr_px = (p.noise_corr_mm / sp[1], p.noise_corr_mm / sp[0])
    # gain that brings filtered white noise back to unit variance
    probe = gaussian_filter(np.random.default_rng(1).normal(size=(128, 128)), corr_px)
    noise_gain = 1.0 / probe[16:-16, 16:-16].std()
    clip_mid = 0.5 * (ca + cb)

    for k in range(nk):
        pts = base + (k * sp[2]) * D[:, 2]
        q = pts - ph.centre_lps
        v = np.full(pts.shape[:2], HU["air"], np.float64)
        for a, dv in shells:
            d = _ellipsoid_sd(q, a)
            if d.min() > 6.0:
                continue
            s = _edge_sigma(_ellipsoid_normal(q, a), D, sp, p.psf_sigma_mm)
            v += dv * _fill(d, s) * _fill(zcut - pts[..., 2], s_cut)
        for (c, a, R, hu), (k0, k1) in zip(blobs, blob_k):
            if k0 <= k <= k1:
                ql = (pts - c) @ R
                d = _ellipsoid_sd(ql, a)
                m = d < 4.0
                if m.any():
                    n_l = _ellipsoid_normal(ql[m], a) @ R.T
                    f = _fill(d[m], _edge_sigma(n_l, D, sp, p.psf_sigma_mm))
                    v[m] += f * (hu - v[m])
        if clip_k[0] <= k <= clip_k[1]:
            ab = cb - ca
            t = np.clip(((pts - ca) @ ab) / (ab @ ab), 0.0, 1.0)
            r = pts - (ca + t[..., None] * ab)
            dist = np.linalg.norm(r, axis=-1)
            d = dist - ph.clip_radius_mm
            m = d < 4.0
            if m.any():
                n_l = r[m] / np.maximum(dist[m, None], 1e-9)
                f = _fill(d[m], _edge_sigma(n_l, D, sp, p.psf_sigma_mm))
                v[m] += f * (HU["clip"] - v[m])
            if p.metal_streak_hu > 0:
                v += _streaks(pts, clip_mid, ab, D, p.metal_streak_hu, rng)
        for b in streaky:
            if k_range(np.array([b.centre_lps]), float(np.max(b.semi_axes_mm)))[0] <= k <= k_range(np.array([b.centre_lps]), float(np.max(b.semi_axes_mm)))[1]:
                ext = 2.0 * float(np.max(b.semi_axes_mm)) * D[:, 2]
                v += _streaks(pts, b.centre_lps, ext, D, b.streak_hu, rng)
        if p.noise_hu > 0:
            v += (p.noise_hu * noise_gain) * gaussian_filter(rng.normal(size=v.shape), corr_px)
        np.clip(v, AIR_FLOOR_HU, CT_MAX_HU, out=v)
        if outside is not None:
            v[outside] = AIR_FLOOR_HU
        out[k] = np.rint(v).astype(np.int16)
    return SyntheticCT(out, sp.copy(), origin, D.copy(), ph, p)


def _streaks(pts, centre, axis_vec, D, amplitude, rng) -> np.ndarray:
    """Alternating radial streaks in the slice plane around the clip, decaying with distance."""
    rel = pts - centre
    # in-plane polar coordinates (grid i, j axes)
    x, y = rel @ D[:, 0], rel @ D[:, 1]
    z = rel @ D[:, 2]
    half_len = 0.5 * np.linalg.norm(axis_vec) + 1.0
    r = np.hypot(x, y)
    ang = np.arctan2(y, x)
    phase = 0.7  # fixed so the pattern is deterministic
    pattern = np.cos(6.0 * ang + phase) * np.abs(np.cos(6.0 * ang + phase)) ** 6
    fall = np.exp(-r / 25.0) * (r > 2.5)
    inside = np.abs(z) < half_len
    return amplitude * pattern * fall * inside


def patch_scan_params(phantom: HeadPhantom | None = None, margin_mm: float = 7.0, **kw) -> ScanParams:
    """ScanParams for a grid that covers only the fiducials and the clip (plus ``margin_mm``),
    with the same spacing/direction conventions: quick to generate for tests and sweeps.
    Defaults: 0.5 x 0.5 x 1.0 mm, the default oblique direction; ``kw`` overrides any field."""
    ph = phantom or default_phantom()
    base = ScanParams(spacing_mm=(0.5, 0.5, 1.0), fov_circle=False)
    D = np.asarray(kw.get("direction", base.direction), float)
    sp = np.asarray(kw.get("spacing_mm", base.spacing_mm), float)
    pts = np.vstack([ph.fiducial_centres_lps, *ph.clip_segment_lps]
                    + [np.atleast_2d(b.centre_lps) for b in kw.get("distractors", ())])
    g = pts @ D
    lo, hi = g.min(axis=0) - margin_mm, g.max(axis=0) + margin_mm
    size = tuple(int(np.ceil((h - l) / s)) + 1 for l, h, s in zip(lo, hi, sp))
    args = dict(spacing_mm=tuple(float(x) for x in sp), size=size, grid_centre_lps=D @ ((lo + hi) / 2.0), fov_circle=False)
    args.update(kw)
    return ScanParams(**args)


# ---------------------------------------------------------------------------- sample data
#: Scan parameters of the bundled sample CT (see the module docstring for why).
SAMPLE_PARAMS = ScanParams()


def make_sample_ct(out_dir: Path | str, phantom: HeadPhantom | None = None, params: ScanParams | None = None) -> tuple[Path, Path]:
    """Write ``phantom_ct.nii.gz`` and ``phantom_truth.json`` (LPS mm) into ``out_dir``."""
    import SimpleITK as sitk

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ct = generate_ct(phantom, params or SAMPLE_PARAMS)
    ct_path = out_dir / "phantom_ct.nii.gz"
    sitk.WriteImage(ct.to_sitk(), str(ct_path), useCompression=True)
    truth_path = out_dir / "phantom_truth.json"
    truth = ct.truth()
    truth["ct_file"] = ct_path.name
    truth["generator"] = "monotracker.sim.ct_phantom.make_sample_ct"
    truth_path.write_text(json.dumps(truth, indent=2) + "\n", encoding="utf-8")
    return ct_path, truth_path


def with_radius(phantom: HeadPhantom, radius_mm: float) -> HeadPhantom:
    """The same head with balls of another radius (still resting on the scalp)."""
    return replace(phantom, fiducial_radius_mm=float(radius_mm))


def ball_grid_array(centres_mm, radius_mm: float, shape=(40, 60, 60), spacing_mm=(0.5, 0.5, 1.0),
                    ball_hu: float = 2500.0, tissue_hu: float = 20.0, noise_hu: float = 15.0,
                    seed: int = 5) -> np.ndarray:
    """A small plain scan for the scan's-edge cases: int16 HU array of ``shape`` (k, j, i) on a
    grid with origin 0, identity direction and ``spacing_mm`` (i, j, k): soft tissue with air
    where y < 4 mm and a 3 mm bone slab at y 24-27 mm, and balls of ``radius_mm`` at
    ``centres_mm`` (grid mm = LPS mm; edge blur 0.55 mm), Gaussian noise of ``noise_hu``. A ball
    placed within its radius of the grid's box is cut by the edge of the scan."""
    sp = np.asarray(spacing_mm, float)
    kk, jj, ii = np.meshgrid(*[np.arange(n) * s for n, s in zip(shape, sp[::-1])], indexing="ij")
    p = np.stack([ii, jj, kk], -1).reshape(-1, 3)
    v = np.full(len(p), tissue_hu)
    v[p[:, 1] < 4.0] = -1000.0
    v[(p[:, 1] > 24.0) & (p[:, 1] < 27.0)] = 1200.0
    for c in np.atleast_2d(np.asarray(centres_mm, float)):
        v += (ball_hu - tissue_hu) * 0.5 * erfc((np.linalg.norm(p - c, axis=1) - radius_mm) / (np.sqrt(2.0) * 0.55))
    v = v.reshape(shape) + np.random.default_rng(seed).normal(0, noise_hu, shape)
    return np.rint(np.clip(v, -1024, 3071)).astype(np.int16)
