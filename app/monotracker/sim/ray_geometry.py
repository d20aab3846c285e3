"""Exact ray geometry of the simulated camera (:mod:`.camera_sim`): skin ellipsoid coverage and
shading, depth along pixel rays, the spheres' silhouettes (anti-aliased with the angular
distance to the tangent cone), their coverage and the exact centres of their image ellipses.

:class:`RayGeometry` is a mixin of :class:`~.camera_sim.SimulatedCamera`; it uses the camera's
``phantom``, ``optics``, ``ball_bgr``, ``K``, ``dist``, ``_rays`` and ``_light_cam``."""

from __future__ import annotations

import numpy as np

from monotracker.sim import optics as _optics
from monotracker.vision.camera_model import distort_normalised


class RayGeometry:
    """Ray casting against the head phantom's skin and fiducial spheres (camera frame, mm;
    rays are unit vectors from the camera centre)."""

    def _skin(self, rays: np.ndarray, R: np.ndarray, tr: np.ndarray, px_per_rad: float):
        """Skin coverage and shade for (n, 3) unit rays from the camera centre (low-res grid).
        Returns (coverage (n,) in [0, 1], Lambert shade (n,), specular (n,) fraction of white or
        None without optics). Coverage is anti-aliased with the
        ray's closest approach to the ellipsoid in its unit-sphere coordinates (silhouette at
        distance 1), converted to pixels; the neck cut is honoured (hard edge there).

        Only the rays that can touch the skin are cast: a ray whose line passes farther from the
        head's centre than its largest semi-axis plus the anti-aliasing band has coverage 0
        whatever the rest says (its shade is 0 there and never used); the head covers ~12 % of
        the sample scene's frame, and the cast was ~40 % of a frame's render."""
        ph = self.phantom
        axes = ph.skin_semi_axes_mm
        c_cam = R @ ph.centre_lps + tr
        c_norm = float(np.linalg.norm(c_cam))
        px_scale = float(np.mean(axes)) / c_norm * px_per_rad      # unit-sphere distance -> px
        # the line of a covered ray passes within (1 + 0.5 px) unit-sphere radii of the centre:
        # within that times the largest semi-axis (mm) in the camera frame (+1 mm of slack)
        reach = float(np.max(axes)) * (1.0 + 0.5 / max(px_scale, 1e-9)) + 1.0
        if c_norm > reach:          # the camera outside that ball: the cone around the centre
            along = rays @ c_cam
            near = np.flatnonzero((along > 0) & (c_norm * c_norm - along * along <= reach * reach))
            cast = self._skin_rays(rays[near], R, c_cam, px_scale)
            out = []
            for part in cast:                       # coverage, shade, specular (None without it)
                if part is not None:
                    full = np.zeros(len(rays))
                    full[near] = part
                    part = full
                out.append(part)
            return tuple(out)
        return self._skin_rays(rays, R, c_cam, px_scale)

    def _skin_rays(self, rays: np.ndarray, R: np.ndarray, c_cam: np.ndarray, scale: float):
        """:meth:`_skin` for every ray given: ``c_cam`` the head's centre in the camera frame
        (mm), ``scale`` px per unit-sphere distance at the silhouette."""
        ph = self.phantom
        axes = ph.skin_semi_axes_mm
        o = (R.T @ (-c_cam)) / axes                     # origin in unit-sphere coords
        d = (rays @ R) / axes                           # (n, 3): R^T d per row
        A = np.einsum("ij,ij->i", d, d)
        B = 2.0 * (d @ o)
        Cq = o @ o - 1.0
        disc = B * B - 4 * A * Cq
        hit = disc > 0
        sq = np.sqrt(np.where(hit, disc, 0.0))
        t_ca = -B / (2 * A)                             # closest approach
        t = np.where(hit, (-B - sq) / (2 * A), t_ca)
        local = (o[None, :] + t[:, None] * d)           # unit-sphere coords of the hit / approach
        dmin = np.sqrt(np.maximum(Cq + 1.0 - B * B / (4 * A), 0.0))
        cov = np.clip(0.5 - (dmin - 1.0) * scale, 0.0, 1.0)
        cov[(t <= 0) | (local[:, 2] * axes[2] + ph.centre_lps[2] < ph.neck_cut_z_mm)] = 0.0
        n_local = local / axes
        n_cam = n_local @ R.T
        n_cam /= np.linalg.norm(n_cam, axis=1, keepdims=True) + 1e-12
        lam = np.clip(n_cam @ self._light_cam, 0, 1)
        facing = np.clip(-np.einsum("ij,ij->i", n_cam, rays), 0, 1)
        shade = 0.35 + 0.5 * lam + 0.15 * facing
        spec = None
        if self.optics is not None and self.optics.skin_specular > 0:
            spec = self.optics.skin_specular * _optics.specular(n_cam, rays, self._light_cam, 12.0)
        return cov, shade, spec

    def _skin_depth(self, rays: np.ndarray, R: np.ndarray, tr: np.ndarray) -> np.ndarray:
        """Distance along each unit ray (n, 3) to the skin (inf where it misses)."""
        ph = self.phantom
        axes = ph.skin_semi_axes_mm
        c_cam = R @ ph.centre_lps + tr
        o = (R.T @ (-c_cam)) / axes
        d = (rays @ R) / axes
        A = np.einsum("ij,ij->i", d, d)
        B = 2.0 * (d @ o)
        Cq = o @ o - 1.0
        disc = B * B - 4 * A * Cq
        t = np.full(len(rays), np.inf)
        ok = disc > 0
        t[ok] = (-B[ok] - np.sqrt(disc[ok])) / (2 * A[ok])
        t[t <= 0] = np.inf
        return t

    @staticmethod
    def _sphere_roi(c_px, r_px, w, h):
        m = 1.35 * r_px + 3
        x0, x1 = int(np.floor(c_px[0] - m)), int(np.ceil(c_px[0] + m)) + 1
        y0, y1 = int(np.floor(c_px[1] - m)), int(np.ceil(c_px[1] + m)) + 1
        if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
            return None  # touching the image border: not rendered as visible (documented)
        return y0, y1, x0, x1

    def _render_sphere(self, C, rad, roi, R, tr):
        y0, y1, x0, x1 = roi
        d = self._rays[y0:y1, x0:x1].astype(np.float64)          # (hh, ww, 3) unit rays
        Cn = np.linalg.norm(C)
        cos_t = d @ (C / Cn)
        theta = np.arccos(np.clip(cos_t, -1, 1))
        alpha = np.arcsin(rad / Cn)
        px_per_rad = self.K[0, 0] / max(C[2] / Cn, 0.3)
        cov = np.clip(0.5 - (theta - alpha) * px_per_rad, 0.0, 1.0)
        # hit distance (closest approach where the ray misses: only used in the AA band)
        along = Cn * cos_t
        perp2 = np.maximum(Cn**2 - along**2, 0.0)
        t_hit = along - np.sqrt(np.maximum(rad**2 - perp2, 0.0))
        # the head may hide part of the sphere
        flat = d.reshape(-1, 3)
        skin_t = self._skin_depth(flat, R, tr).reshape(cov.shape)
        cov = np.where(skin_t < t_hit - 1e-6, 0.0, cov)
        nrm = (t_hit[..., None] * d - C) / rad
        lam = np.clip(nrm @ self._light_cam, 0, 1)
        shade = 0.3 + 0.6 * lam + 0.1 * np.clip(-(nrm * d).sum(-1), 0, 1)
        col = shade[..., None] * self.ball_bgr
        if self.optics is not None and self.optics.ball_specular > 0:
            o = self.optics
            col = col + 255.0 * o.ball_specular * _optics.specular(nrm, d, self._light_cam, o.ball_shininess)[..., None]
        return cov.astype(np.float32), col.astype(np.float32)

    def _full_coverage(self, C, rad, roi) -> float:
        """Silhouette area (px) without any occlusion, on the same ROI grid."""
        y0, y1, x0, x1 = roi
        d = self._rays[y0:y1, x0:x1].astype(np.float64)
        Cn = np.linalg.norm(C)
        theta = np.arccos(np.clip(d @ (C / Cn), -1, 1))
        px_per_rad = self.K[0, 0] / max(C[2] / Cn, 0.3)
        return float(np.clip(0.5 - (theta - np.arcsin(rad / Cn)) * px_per_rad, 0, 1).sum())

    def _ellipse_centres(self, C: np.ndarray, rad: float) -> np.ndarray:
        """Exact centres of the spheres' image ellipses on the normalised plane,
        (a c, b c) / (c^2 - R^2), then distorted into pixels."""
        c = C[:, 2]
        xn = C[:, :2] * (c / (c**2 - rad**2))[:, None]
        return distort_normalised(xn, self.K, self.dist)
