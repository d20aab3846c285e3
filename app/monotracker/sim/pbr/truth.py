"""Exact truth of a physically based scene, from its geometry alone (no renderer).

Per ball: the sphere centre in CT and camera mm, the projection of the sphere centre and the
centre of the sphere's image ellipse (distorted px, both through OpenCV's ``cv2.projectPoints``,
independent of the registration package's projection), the image radius (px) and the visible
fraction that the renderer's ray cast measured against the rays of :func:`visibility_rays`
(Mitsuba: :func:`~.mitsuba_render.visible_fractions`; Blender: the scene script's ray cast).
A ball is *whole* when at least :data:`WHOLE` of its silhouette is seen inside the frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from monotracker.sim.scenes import ellipse_centre_normalised

from .spec import SceneSpec, _perp_frame

#: a ball at least this visible (share of its silhouette, in the frame) counts as whole
WHOLE = 0.98


@dataclass
class SceneTruth:
    """Truth of one rendered scene. Pixels are distorted image px (OpenCV: integer pixel
    centres) of the frame as stored (a crop's offset already removed)."""

    T_cam_ct: np.ndarray            # (4, 4) CT LPS mm -> camera mm
    fiducials_ct: np.ndarray        # (n, 3) mm
    fiducials_cam: np.ndarray       # (n, 3) mm
    projected_centres_px: np.ndarray  # (n, 2) projections of the sphere centres
    ellipse_centres_px: np.ndarray  # (n, 2) centres of the sphere's image ellipses
    radius_px: np.ndarray           # (n,) image radius (minor semi-axis) px
    visible_fraction: np.ndarray    # (n,) in [0, 1]
    target_ct: np.ndarray           # (3,) the 80 mm deep target, CT mm
    radius_mm: float

    @property
    def whole(self) -> np.ndarray:
        return self.visible_fraction >= WHOLE

    def to_dict(self) -> dict:
        return {k: (v.round(6).tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "SceneTruth":
        return cls(**{k: (np.array(v, float) if k != "radius_mm" else float(v)) for k, v in d.items()})

    def shifted(self, dx: float, dy: float) -> "SceneTruth":
        """The same truth in a crop whose top-left pixel is (dx, dy) of the full frame."""
        off = np.array([dx, dy], float)
        return SceneTruth(self.T_cam_ct, self.fiducials_ct, self.fiducials_cam, self.projected_centres_px - off,
                          self.ellipse_centres_px - off, self.radius_px, self.visible_fraction, self.target_ct,
                          self.radius_mm)


def _project(xn: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    P = np.concatenate([xn, np.ones((len(xn), 1))], axis=1)
    px, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, dist)
    return px.reshape(-1, 2)


def scene_truth(spec: SceneSpec, visible_fraction) -> SceneTruth:
    """The truth of ``spec`` given the ray-cast visible fractions."""
    K, dist = np.array(spec.K, float), np.array(spec.dist, float)
    T = spec.T
    X = spec.fiducials
    Xc = X @ T[:3, :3].T + T[:3, 3]
    R = spec.radius_mm
    proj = _project(Xc[:, :2] / Xc[:, 2:3], K, dist)
    ell = _project(ellipse_centre_normalised(Xc, R), K, dist)
    d = np.linalg.norm(Xc, axis=1)
    r_px = K[0, 0] * R / np.sqrt(d**2 - R**2)
    return SceneTruth(T, X, Xc, proj, ell, r_px, np.asarray(visible_fraction, float), np.array(spec.target_ct, float),
                      float(R))


def sphere_centre_px(ellipse_px: np.ndarray, depth_mm: np.ndarray, radius_mm: float, K: np.ndarray,
                     dist: np.ndarray) -> np.ndarray:
    """Where the sphere centre projects, given a detected ellipse centre (distorted px) and the
    sphere's true depth z (camera mm): the ellipse centre's undistorted normalised point e maps
    to e (1 - R^2 / z^2) (the tangent cone's conic). Lets a detector's ellipse centre be
    compared with the true projected sphere centre."""
    p = np.asarray(ellipse_px, float).reshape(-1, 1, 2)
    if len(p) == 0:
        return np.zeros((0, 2))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
    e = cv2.undistortPointsIter(p, K, dist, None, None, crit).reshape(-1, 2)
    z = np.asarray(depth_mm, float).reshape(-1, 1)
    return _project(e * (1.0 - radius_mm**2 / z**2), K, dist)


def cone_samples(n: int = 2048) -> np.ndarray:
    """(n, 2) points uniform over the unit disc (a golden-angle spiral: deterministic, even)."""
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    a = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(a), r * np.sin(a)], -1)


@dataclass
class BallRays:
    """The rays that measure one ball's visible fraction: from the camera centre ``origin_ct``
    (CT mm) along ``directions_ct`` ((n, 3) unit, spread evenly over the cone tangent to the
    sphere, 0.9999 of its half-angle), each ray's analytic entry into the sphere ``t_entry``
    (mm) and ``counts`` (n,) bool: its pixel lies in the image and it meets the sphere."""

    origin_ct: np.ndarray
    directions_ct: np.ndarray
    t_entry: np.ndarray
    counts: np.ndarray


def visibility_rays(spec: SceneSpec, n: int = 2048) -> list[BallRays]:
    """Per ball of ``spec``, the rays a renderer intersects with its scene to measure the
    ball's visible fraction (the share of rays whose first hit is the ball, of ``n``)."""
    cam = spec.camera_model()
    T = spec.T
    eye = spec.eye_ct
    W, H = spec.image_size
    disc = cone_samples(n)
    out = []
    for c_ct in spec.fiducials:
        c = T[:3, :3] @ c_ct + T[:3, 3]                    # camera frame
        dist = np.linalg.norm(c)
        axis = c / dist
        e1, e2 = _perp_frame(axis)
        tan_r = spec.radius_mm / np.sqrt(dist**2 - spec.radius_mm**2)
        d_cam = axis[None, :] + tan_r * 0.9999 * (disc[:, :1] * e1 + disc[:, 1:] * e2)
        d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
        px = cam.project(d_cam)
        inside = (px[:, 0] >= -0.5) & (px[:, 0] <= W - 0.5) & (px[:, 1] >= -0.5) & (px[:, 1] <= H - 0.5)
        d_ct = d_cam @ T[:3, :3]                            # camera -> CT directions (R^T)
        oc = eye - c_ct
        b = d_ct @ oc
        disc_ = b**2 - (oc @ oc - spec.radius_mm**2)
        t_in = -b - np.sqrt(np.maximum(disc_, 0.0))
        out.append(BallRays(eye.copy(), d_ct, t_in, inside & (disc_ > 0)))
    return out
