"""The outline a whole sphere images as, at a given place in the image.

A sphere seen by a pinhole camera images as an ellipse whose major axis points away from the
principal point; its axis ratio depends only on the angle theta between the ball's viewing ray
and the optical axis and on the sphere's angular radius alpha (minor / major =
sqrt(cos^2 theta - sin^2 alpha) / cos alpha, ~cos theta), and lens distortion bends it a little
more. So the shape of a whole ball's outline is known from where it lies in the image, before
any pose, and the edge fit (:mod:`.edge_fit`) needs to find only its centre and size.

Why it matters: with a free ellipse (five parameters) a ball partly hidden behind a straight edge
(a glove's finger, an instrument, a drape's fold) was fitted with its ellipse squeezed onto the
chord and its centre pushed away from the hidden cap, 0.5-1.2 px, and passed every check of the
edge fit; with the shape known (three parameters) the chord's rays are outliers to a circle and
either drop out (an unbiased centre from the rest of the edge) or refuse the ball.
"""

from __future__ import annotations

import cv2
import numpy as np

#: silhouette samples per expected outline
_N_OUTLINE = 48


#: a centre whose undistorted ray does not project back within this (px) lies where the
#: calibration's distortion model folds (outside its valid field): no outline is claimed there
ROUND_TRIP_PX = 0.1


def _silhouette_rings(camera, centres_cam: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """(m, N, 2) float32 distorted px: :data:`_N_OUTLINE` points of the silhouette (tangent
    circle) of spheres centred at ``centres_cam`` ((m, 3), camera frame, any length unit) with
    angular radii ``alpha`` ((m,) rad). The silhouette circle of a sphere at distance D along
    the unit direction d: centre cos^2(alpha) D d, radius sin(alpha) cos(alpha) D."""
    C = np.asarray(centres_cam, float).reshape(-1, 3)
    dist = np.linalg.norm(C, axis=1, keepdims=True)
    d = C / np.maximum(dist, 1e-12)
    ref = np.where(np.abs(d[:, 1:2]) < 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(d, ref)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(d, u)
    t = np.linspace(0, 2 * np.pi, _N_OUTLINE, endpoint=False)
    ca, sa = np.cos(alpha)[:, None, None], np.sin(alpha)[:, None, None]
    ring = dist[:, None, :] * (ca**2 * d[:, None, :] + sa * ca * (np.cos(t)[None, :, None] * u[:, None, :]
                                                               + np.sin(t)[None, :, None] * v[:, None, :]))
    return camera.project(ring.reshape(-1, 3)).reshape(len(C), _N_OUTLINE, 2).astype(np.float32)


def _fit_ring(ring_px: np.ndarray):
    """((cx, cy), (semi-major, semi-minor), major axis deg) of an outline's points, or None."""
    if not np.all(np.isfinite(ring_px)):
        return None
    (cx, cy), (d1, d2), ang = cv2.fitEllipse(ring_px)
    if not min(d1, d2) > 0:
        return None
    major = float(ang) if d1 >= d2 else float(ang) + 90.0
    return (float(cx), float(cy)), (max(d1, d2) / 2.0, min(d1, d2) / 2.0), major


def sphere_ellipses(camera, centres_cam_mm, radius_mm: float):
    """The image ellipses of spheres of ``radius_mm`` centred at ``centres_cam_mm`` ((m, 3) mm,
    OpenCV camera frame), lens distortion included: (centres (m, 2) distorted px, semi-axes
    (m, 2) px (major, minor), major axis angles (m,) deg from +x towards +y, ok (m,) bool).
    Not ok: a sphere not fully in front of the camera, or whose outline does not project to
    finite points. ~25 us per sphere."""
    C = np.asarray(centres_cam_mm, float).reshape(-1, 3)
    m = len(C)
    cen, axes, ang, ok = np.full((m, 2), np.nan), np.full((m, 2), np.nan), np.zeros(m), np.zeros(m, bool)
    if m == 0:
        return cen, axes, ang, ok
    dist = np.linalg.norm(C, axis=1)
    front = C[:, 2] > 1.5 * float(radius_mm)
    alpha = np.arcsin(np.clip(float(radius_mm) / np.maximum(dist, 1e-9), 0.0, 0.999))
    rings = _silhouette_rings(camera, C, alpha)
    for i in np.flatnonzero(front):
        e = _fit_ring(rings[i])
        if e is not None:
            cen[i], axes[i], ang[i], ok[i] = e[0], e[1], e[2], True
    return cen, axes, ang, ok


class SphereEllipseCache:
    """:func:`sphere_ellipses` for a stream of poses, each sphere's outline reused from the last
    time it was computed while the sphere has moved little since: the pose tracker's hint
    predicts the same balls every frame, a few tenths of a px from where they were (issue 29:
    the outlines were ~1.5 ms of a 10 ms frame). A reused ellipse is the computed one moved by
    the shift of the projected sphere centre and scaled by the change of the sphere's distance;
    its major axis turned with the ball about the principal point (it points away from it); it is
    computed afresh when the projected centre has moved more than :attr:`max_shift_px` or
    the distance changed by more than :attr:`max_scale` since. Over a few px the outline's shape
    changes by ~1e-4 per px (module docstring) and the ellipse centre's offset from the projected
    sphere centre (~0.2 px at the image's edge for a 20 px ball) by ~1e-3 px: far below what a
    hint is used for (search windows, the edge fit's outline shape)."""

    #: recompute a sphere's outline when its projected centre moved more than this (px) ...
    max_shift_px: float = 2.0
    #: ... or its distance from the camera changed by more than this share
    max_scale: float = 0.003

    def __init__(self):
        self._key = None
        self._base = None

    def __call__(self, camera, centres_cam_mm, radius_mm: float):
        """As :func:`sphere_ellipses` (same arguments, same result to the tolerances above)."""
        C = np.asarray(centres_cam_mm, float).reshape(-1, 3)
        m = len(C)
        key = (id(camera), camera.K.tobytes(), camera.dist.tobytes(), float(radius_mm), m)
        dist = np.linalg.norm(C, axis=1)
        front = C[:, 2] > 1.5 * float(radius_mm)
        proj = np.full((m, 2), np.nan)
        if front.any():
            proj[front] = camera.project(C[front])
        if key != self._key or self._base is None:
            self._key = key
            self._base = (np.full((m, 2), np.nan), np.full(m, np.nan), np.full((m, 2), np.nan),
                          np.full((m, 2), np.nan), np.zeros(m), np.zeros(m, bool))
        b_proj, b_dist, b_cen, b_axes, b_ang, b_ok = self._base
        shift = np.hypot(proj[:, 0] - b_proj[:, 0], proj[:, 1] - b_proj[:, 1])
        reuse = front & b_ok & (shift <= self.max_shift_px) & (np.abs(dist / b_dist - 1.0) <= self.max_scale)
        redo = np.flatnonzero(~reuse)
        if len(redo):
            cen, axes, ang, ok = sphere_ellipses(camera, C[redo], radius_mm)
            b_proj[redo], b_dist[redo], b_cen[redo], b_axes[redo], b_ang[redo], b_ok[redo] = \
                proj[redo], dist[redo], cen, axes, ang, ok
        cen = b_cen + (proj - b_proj)
        axes = b_axes * (b_dist / np.maximum(dist, 1e-9))[:, None]
        # the major axis points away from the principal point: it turns with the ball about it
        pp = camera.K[:2, 2]
        turn = np.degrees(np.arctan2(proj[:, 1] - pp[1], proj[:, 0] - pp[0])
                          - np.arctan2(b_proj[:, 1] - pp[1], b_proj[:, 0] - pp[0]))
        ang = b_ang + turn
        ok = b_ok & front
        cen[redo], axes[redo], ang[redo] = b_cen[redo], b_axes[redo], b_ang[redo]
        cen[~ok], axes[~ok] = np.nan, np.nan
        return cen, axes, np.where(ok, ang, 0.0), ok


def expected_outlines(camera, centres_px, minors_px) -> list:
    """The image outlines of whole spheres seen at ``centres_px`` (m, 2) distorted px with minor
    semi-axes of about ``minors_px`` (m,) px (they set the angular radii): per sphere
    ((semi-major, semi-minor) px, angle of the major axis in deg from +x towards +y), or None
    where the calibration's distortion does not invert there (:data:`ROUND_TRIP_PX`) or the
    outline is not finite. ``camera``: a :class:`CameraModel` (intrinsics and distortion).
    ~25 us per sphere."""
    c = np.asarray(centres_px, float).reshape(-1, 2)
    if len(c) == 0:
        return []
    xn = camera.undistort_points(c)
    back = camera.project(np.column_stack([xn, np.ones(len(xn))]))
    valid = np.all(np.isfinite(back), axis=1) & (np.linalg.norm(back - c, axis=1) <= ROUND_TRIP_PX)
    d = np.column_stack([xn, np.ones(len(xn))])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
    alpha = np.arctan2(np.maximum(np.asarray(minors_px, float).reshape(-1), 0.5), f)
    px = _silhouette_rings(camera, d, alpha)
    out = []
    for ok, ring_px in zip(valid, px):
        e = _fit_ring(ring_px) if ok else None
        out.append(None if e is None else (e[1], e[2]))
    return out


def expected_shapes(camera, centres_px, minors_px) -> list:
    """Per sphere (minor / major, major axis angle deg) of :func:`expected_outlines`, or None
    (no outline claimed: the edge fit fits a free ellipse there): the ``shapes`` the edge fit
    takes (:func:`~.edge_fit.fit_ball_edges`)."""
    return [None if o is None else (o[0][1] / o[0][0], o[1])
            for o in expected_outlines(camera, centres_px, minors_px)]
