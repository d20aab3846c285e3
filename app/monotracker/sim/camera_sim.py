"""Simulated camera: renders the analytic head phantom as a calibrated camera would see it.

Geometry is exact where it matters (the ray casting is in :mod:`.ray_geometry`):

* Fiducials: an exact ray-sphere rasteriser. Each pixel centre's ray comes from the camera
  model with distortion (undistorted once at start-up), so every sphere's silhouette is the
  true cone of rays tangent to the sphere, distorted as the lens would. Edges are
  anti-aliased with the angular signed distance to the silhouette cone; each sphere is
  rendered only in its own region of interest. Depth is tested against the skin ellipsoid
  per pixel, so the head hides a sphere behind its own silhouette.
* Skin: exact ray-ellipsoid intersection (Lambert shading, neck cut honoured) at a quarter
  of the resolution, composited on the drape background and upsampled: the silhouette is the
  true conic, slightly soft (like mild defocus); fine texture is irrelevant to the detectors.
* Skin clip: an anti-aliased grey bar along the projected clip axis (metal, not green).

Scene effects (all deterministic for a given seed and frame index): head trajectory
(:mod:`monotracker.sim.trajectories`), scripted events (:mod:`.scene_events`): occluders
(hand / instrument polygons sweeping over fiducials), stray green blobs (round and irregular),
global lighting changes; motion blur from
the head's image motion during the exposure, sensor noise (a bank of precomputed Gaussian
noise images, never the same one twice in a row, and one pixel's lowest bit flipped at a place
that moves on every frame: a still head never gives two bit-identical frames, which the engine
would read as a frozen camera). Faults for tests: ``freeze_at_frame``
(the same image again and again) and ``disconnect_at_frame`` (``read()`` raises
:class:`CameraDisconnected`).

Ground truth per frame (:class:`FrameTruth`): ``T_cam_ct``; for each fiducial the exact
ellipse centre (the centre of the sphere's image ellipse, distorted), the projection of the
sphere centre, the visible fraction of its silhouette and whether it is fully visible.

Photo-like frames (``optics=``, off by default so that the live app and the tests keep the
simple, fast render): gloss on balls and skin, surgical drapes of several colours, hair, glove
colours and steel instruments, then lens blur, Bayer mosaic, raw-space sensor noise,
demosaicing and JPEG (:mod:`monotracker.sim.optics`). The truth is computed from the geometry
alone, so it is the same with and without optics.

Edges mix in linear light: a sensor pixel integrates photons, so a pixel that a ball covers to a
share ``a`` records ``a * ball + (1 - a) * background`` in linear radiance, and lens and motion
blur mix linear radiance too. Photo-like frames draw everything from the balls on (balls, strays,
gloves, instruments; then motion blur) in linear radiance (the optics' ``gamma``); the skin, hair
and clip layers below them are still composited in display values. The simple render mixes the
ball edges in linear light (gamma 2.2) and keeps display values for the rest (it is the fast
render). Mixing gamma-encoded values instead made a dark ball's silhouette ~4 % too large in
area (~0.2 px of radius; ``tests/sim/test_optics.py``).

Camera placement (a choice; the paper says "about half a metre"): 520 mm from the mean of the
fiducial centres along the phantom's view direction, looking at it, image top towards anterior.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from monotracker.geometry import apply_transform, invert_transform, look_at
from monotracker.sim import optics as _optics
from monotracker.sim.phantom import HeadPhantom, default_phantom
from monotracker.sim.ray_geometry import RayGeometry
from monotracker.sim.scene_events import (Occluder, SceneEvents, Stray, _finger,  # noqa: F401 - public names
                                          random_events)
from monotracker.sim.trajectories import Still, Trajectory
from monotracker.vision.camera_model import CameraModel, default_camera
from monotracker.vision.frames import CameraDisconnected, Frame, FrameSource

#: A fiducial is "fully visible" when at least this fraction of its silhouette is unoccluded.
FULLY_VISIBLE = 0.98

FIDUCIAL_BGR = np.array([45.0, 160.0, 40.0])     # matte green dye
SKIN_BGR = np.array([140.0, 165.0, 205.0])
CLIP_BGR = (150, 150, 155)
GLOVE_BGR = (175, 195, 215)                        # latex glove
INSTRUMENT_BGR = (120, 118, 115)                   # steel
STRAY_BGR = (90, 250, 120)                         # bright green (an LED, a marker pen cap)


@dataclass
class FrameTruth:
    """Simulator ground truth for one frame (px are distorted image pixels)."""

    t_s: float
    T_cam_ct: np.ndarray
    ellipse_centres_px: np.ndarray        # (9, 2) exact centres of the sphere image ellipses
    projected_centres_px: np.ndarray      # (9, 2) projections of the sphere centres
    visible_fraction: np.ndarray          # (9,) unoccluded fraction of each silhouette, 0 if off image
    visible: np.ndarray                   # (9,) bool, visible_fraction >= FULLY_VISIBLE
    radius_px: np.ndarray                 # (9,) approximate image radius of each sphere
    stray_centres_px: np.ndarray          # (k, 2) stray blobs present in this frame
    occluders: list = field(default_factory=list)  # polygons (n, 2) px drawn in this frame
    #: (h, w) float32 visible-ball coverage in [0, 1] (occluders removed); only when asked for
    fiducial_mask: np.ndarray | None = None


class SimulatedCamera(RayGeometry, FrameSource):
    """The default frame source. ``read()`` renders frame ``index`` at simulated time
    ``index / fps``; with ``realtime=True`` it also paces itself to ``fps``.

    Parameters: ``camera`` (:class:`CameraModel`, default 1280x720 f=1100 px with distortion),
    ``phantom``, ``trajectory``, ``events`` (:class:`SceneEvents`), ``distance_mm`` (camera to
    fiducial patch), ``noise_sigma`` (grey levels), ``exposure_s`` (motion blur window; 0 = off), ``T_cam_world`` (4x4, maps the
    trajectory's world frame (CT at rest) into the camera; None = ``distance_mm`` straight along the
    phantom's view direction, looking at the fiducial patch),
    ``max_frames`` (None = endless), ``freeze_at_frame`` / ``disconnect_at_frame`` /
    ``stall_at_frame`` (faults: repeated image, ``read()`` raises, ``read()`` blocks),
    ``seed``, ``optics`` (None = the simple render; an :class:`~monotracker.sim.optics.Optics`
    or a preset name of :data:`~monotracker.sim.optics.PRESETS` such as ``"photo"`` or
    ``"degraded"`` = photo-like frames; ``noise_sigma`` is then unused, the sensor model makes
    the noise), ``ball_bgr`` (the balls' dye, BGR 0-255; default matte green),
    ``camera_motion`` (the camera moving in the room after calibration, a fault:
    :class:`monotracker.sim.faults.CameraMotion`; the drape background is a room-fixed plane
    ``background_depth_mm`` away, so it moves in the image with the camera).
    """

    name = "simulated camera"

    def __init__(self, camera: CameraModel | None = None, phantom: HeadPhantom | None = None,
                 trajectory: Trajectory | None = None, events: SceneEvents | None = None,
                 fps: float = 30.0, distance_mm: float = 520.0, noise_sigma: float = 2.0,
                 exposure_s: float = 1 / 60, realtime: bool = False, max_frames: int | None = None,
                 freeze_at_frame: int | None = None, disconnect_at_frame: int | None = None,
                 stall_at_frame: int | None = None, seed: int = 0, start_index: int = 0,
                 T_cam_world: np.ndarray | None = None, optics: "_optics.Optics | str | None" = None,
                 ball_bgr=None, camera_motion=None):
        super().__init__()
        if isinstance(optics, str):
            if optics not in _optics.PRESETS:
                raise ValueError(f"optics preset must be one of {sorted(_optics.PRESETS)}, got {optics!r}")
            optics = _optics.PRESETS[optics]
        self.optics = optics
        self.ball_bgr = np.asarray(FIDUCIAL_BGR if ball_bgr is None else ball_bgr, float).reshape(3)
        self.camera = camera or default_camera()
        self.phantom = phantom or default_phantom()
        self.trajectory = trajectory or Still()
        self.events = events or SceneEvents()
        self.fps = float(fps)
        self.noise_sigma = float(noise_sigma)
        self.exposure_s = float(exposure_s)
        self.realtime = realtime
        self.max_frames = max_frames
        self.freeze_at_frame = freeze_at_frame
        self.disconnect_at_frame = disconnect_at_frame
        self.stall_at_frame = stall_at_frame
        self.seed = seed
        self._index = start_index
        self._frozen_image = None
        self._t0 = None

        ph = self.phantom
        self.fiducials_ct = ph.fiducial_centres_lps
        patch = self.fiducials_ct.mean(axis=0)
        if T_cam_world is None:
            eye = patch + distance_mm * ph.view_direction_lps
            T_cam_world = invert_transform(look_at(eye, patch, up=np.array([0.0, -1.0, 0.0])))
        self.T_cam_world = np.array(T_cam_world, float).reshape(4, 4)
        self.K = self.camera.K
        self.dist = self.camera.dist
        w, h = self.camera.image_size
        self._rays = self.camera.pixel_rays(1.0)                  # (h, w, 3) float32
        self._low_scale = 0.25
        self._rays_low = self.camera.pixel_rays(self._low_scale).reshape(-1, 3).astype(np.float64)
        self._low_shape = (int(round(h * self._low_scale)), int(round(w * self._low_scale)))
        rng = np.random.default_rng(seed + 12345)
        self._background_low = self._make_background(rng)
        self._noise_pos, self._noise_neg = self._make_noise(rng, 6) if optics is None else ([], [])
        self._noise_rng = np.random.default_rng(seed + 999)
        self._last_noise = -1
        self._noise_frame = 0  # frames rendered: where the flipped bit sits (never a repeat)
        self._light_cam = np.array([-0.3, -0.5, -1.0]) / np.linalg.norm([-0.3, -0.5, -1.0])  # towards light
        self._chain = self._hair = None
        self._skin_cache = None       # (pose bytes, skin render) of the last frame
        #: the camera's own motion in the room (a fault: ``sim.faults.CameraMotion``) or None
        self.camera_motion = camera_motion
        #: the drape behind the head: a room-fixed plane this far (mm) along the resting optical axis
        self.background_depth_mm = float(apply_transform(self.T_cam_world, ph.centre_lps)[2]) + 150.0
        self._bg_cache = None         # (camera motion bytes, background) of the last moved frame
        if optics is not None:
            orng = np.random.default_rng(seed + 777)
            self._background_low = _optics.drape_background(optics, self._low_shape, orng).astype(np.float32)
            self._hair = _optics.hair_layer(optics, (w, h), orng) if optics.hair_density > 0 else None
            self._chain = _optics.OpticsChain(optics, (w, h), seed)

    # ------------------------------------------------------------------ set-up helpers
    def _make_background(self, rng) -> np.ndarray:
        h, w = self._low_shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        base = np.array([120.0, 95.0, 60.0], np.float32)  # blue surgical drape (BGR)
        shade = 0.75 + 0.25 * (xx / w) * (1 - 0.4 * yy / h)
        folds = 1 + 0.06 * np.sin(xx / 9.0 + 0.7 * np.sin(yy / 13.0))
        tex = cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 2.0) * 0.05
        return (base[None, None, :] * (shade * folds + tex)[..., None]).astype(np.float32)

    def _make_noise(self, rng, n: int):
        w, h = self.camera.image_size
        pos, neg = [], []
        for _ in range(n):
            z = rng.normal(0, max(self.noise_sigma, 1e-6), (h, w, 3))
            pos.append(np.clip(np.rint(z), 0, 255).astype(np.uint8))
            neg.append(np.clip(np.rint(-z), 0, 255).astype(np.uint8))
        return pos, neg

    # ------------------------------------------------------------------ geometry helpers
    def pose_tracker(self):
        """A :class:`~monotracker.vision.pose_tracker.PoseTracker` for this camera's phantom (its
        fiducial centres, LPS mm, ball radius and sample target) and calibration: what
        :class:`~monotracker.vision.pose_stream.PoseStream` uses when given no tracker."""
        from monotracker.vision.pose_tracker import PoseTracker

        ph = self.phantom
        return PoseTracker(ph.fiducial_centres_lps, self.camera, radius_mm=ph.fiducial_radius_mm,
                           target_ct=ph.sample_target_lps)

    def T_cam_ct_at(self, t: float) -> np.ndarray:
        """True CT-to-camera transform at simulated time ``t`` (s), with the camera's own motion
        (``camera_motion``, a fault) when it moved."""
        T = self.T_cam_world @ self.trajectory.pose(t)
        if self.camera_motion is not None:
            T = self.camera_motion.T_now_rest(t) @ T
        return T

    def _room_background(self, t: float) -> np.ndarray:
        """The low-resolution drape background as the camera sees it at time ``t``: the drape is
        a plane fixed in the room (``background_depth_mm`` from the camera at rest, facing it),
        so when the camera moves (``camera_motion``) it moves in the image like the head does.
        At rest this is the background image itself; moved, each low-resolution pixel's ray
        meets the plane and reads the texture where the camera at rest saw that point."""
        M = np.eye(4) if self.camera_motion is None else self.camera_motion.T_now_rest(t)
        if np.array_equal(M, np.eye(4)):
            return self._background_low
        key = M.tobytes()
        if self._bg_cache is not None and self._bg_cache[0] == key:
            return self._bg_cache[1]
        R, tr = M[:3, :3], M[:3, 3]
        o = -R.T @ tr                               # camera centre now, in the rest camera frame
        d = self._rays_low @ R                      # ray directions now -> rest frame (R^T d)
        s = (self.background_depth_mm - o[2]) / np.where(np.abs(d[:, 2]) > 1e-9, d[:, 2], 1e-9)
        X = o + d * s[:, None]
        px = self.camera.project(X)                 # where the camera at rest saw that drape point
        sc = self._low_scale
        mx = ((px[:, 0] + 0.5) * sc - 0.5).reshape(self._low_shape).astype(np.float32)
        my = ((px[:, 1] + 0.5) * sc - 0.5).reshape(self._low_shape).astype(np.float32)
        bg = cv2.remap(self._background_low, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        self._bg_cache = (key, bg)
        return bg

    def rest_projection(self) -> np.ndarray:
        """(9, 2) projected fiducial centres at t = 0 (for placing scripted events)."""
        return self.camera.project(apply_transform(self.T_cam_ct_at(0.0), self.fiducials_ct))

    # ------------------------------------------------------------------ FrameSource
    def read(self) -> Frame | None:
        if self._closed:
            from monotracker.errors import MonoTrackerError

            raise MonoTrackerError("simulated camera: read() after close()")
        i = self._index
        if self.realtime:
            now = time.monotonic()
            if self._t0 is None:
                self._t0 = now - i / self.fps
            due = int(np.floor((now - self._t0) * self.fps))
            if due > i:          # the consumer fell behind: like a camera, deliver the newest frame
                i = self._index = due
            wait = self._t0 + i / self.fps - now
            if wait > 0:
                time.sleep(wait)
        if self.max_frames is not None and i >= self.max_frames:
            return None
        if self.disconnect_at_frame is not None and i >= self.disconnect_at_frame:
            raise CameraDisconnected("simulated camera disconnected (fault injected)")
        if self.stall_at_frame is not None and i >= self.stall_at_frame:
            while not self._closed:          # a driver that blocks forever, until closed
                time.sleep(0.005)
            raise CameraDisconnected("simulated camera closed while stalled")
        if self.freeze_at_frame is not None and i >= self.freeze_at_frame and self._frozen_image is not None:
            img, truth = self._frozen_image
        else:
            img, truth = self.render(i / self.fps)
            if self.freeze_at_frame is not None and i >= self.freeze_at_frame - 1:
                self._frozen_image = (img, truth)
        self._index += 1
        return Frame(img, time.monotonic(), i, truth)

    # ------------------------------------------------------------------ rendering
    def render(self, t: float, with_mask: bool = False) -> tuple[np.ndarray, FrameTruth]:
        """Render the scene at simulated time ``t`` (s): (BGR uint8 image, FrameTruth).
        ``with_mask`` also fills ``truth.fiducial_mask`` (training labels for the segmenter)."""
        T = self.T_cam_ct_at(t)
        R, tr = T[:3, :3], T[:3, 3]
        ph = self.phantom
        gain = self.events.gain(t)
        h, w = self.camera.image_size[1], self.camera.image_size[0]

        # --- skin at low resolution, composited on the background, then upsampled
        low = self._room_background(t).copy()
        key = T.tobytes()
        if self._skin_cache is not None and self._skin_cache[0] == key:
            cov, shade, spec = self._skin_cache[1]        # a still head: same skin as last frame
        else:
            cov, shade, spec = self._skin(self._rays_low, R, tr, self.K[0, 0] * self._low_scale)
            self._skin_cache = (key, (cov, shade, spec))
        lowf = low.reshape(-1, 3)
        m = cov > 0
        skin = SKIN_BGR[None, :] * shade[m, None] + (255.0 * spec[m, None] if spec is not None else 0.0)
        lowf[m] = lowf[m] * (1.0 - cov[m, None]) + skin * cov[m, None]
        img = cv2.resize(low, (w, h), interpolation=cv2.INTER_LINEAR)
        if self._hair is not None and m.any():
            self._add_hair(img, cov.reshape(self._low_shape).astype(np.float32))

        # --- skin clip (grey bar)
        a, b = ph.clip_segment_lps
        ends = apply_transform(T, np.array([a, b]))
        normal = ph.skin_point(0.5 * (a + b) - ph.centre_lps)[1]
        if np.all(ends[:, 2] > 10) and (R @ normal) @ (0.5 * (ends[0] + ends[1])) < 0:
            px = self.camera.project(ends)
            thick = max(1, int(round(2 * ph.clip_radius_mm * self.K[0, 0] / ends[:, 2].mean())))
            p0, p1 = (np.round(px * 16).astype(int))
            cv2.line(img, tuple(p0), tuple(p1), CLIP_BGR, thick, cv2.LINE_AA, shift=4)

        # photo-like frames: from here on the scene is linear radiance (1.0 = white), so that
        # every edge drawn below is anti-aliased, motion-blurred and defocused in linear light,
        # as a sensor pixel integrates photons (mixing gamma-encoded values puts a dark ball's
        # edge ~0.2 px outside its silhouette)
        lin = self._chain is not None
        if lin:
            img = self._chain.to_linear(img)

        # --- fiducial spheres (exact, per ROI)
        C_all = apply_transform(T, self.fiducials_ct)
        rad = ph.fiducial_radius_mm
        nfid = len(C_all)
        proj = self.camera.project(C_all)
        ell = self._ellipse_centres(C_all, rad)
        radius_px = self.K[0, 0] * rad / np.sqrt(np.maximum(np.sum(C_all**2, 1) - rad**2, 1e-9))
        cov_store = {}
        for k in range(nfid):
            roi = self._sphere_roi(proj[k], radius_px[k], w, h)
            if roi is None or C_all[k, 2] <= rad:
                continue
            cov, col = self._render_sphere(C_all[k], rad, roi, R, tr)
            y0, y1, x0, x1 = roi
            patch = img[y0:y1, x0:x1]
            if lin:
                col = self._chain.to_linear(col)
                patch *= (1.0 - cov)[..., None]
                patch += (cov[..., None] * col)
            else:       # simple render: mix the edge in linear light too (gamma 2.2), as a pixel does
                mixed = (1.0 - cov)[..., None] * cv2.pow(patch * np.float32(1 / 255), 2.2) \
                    + cov[..., None] * cv2.pow(np.maximum(col, 0.0) * np.float32(1 / 255), 2.2)
                patch[:] = cv2.pow(mixed, 1 / 2.2) * np.float32(255.0)
            cov_store[k] = (roi, cov)

        # --- strays
        strays, active = [], []
        for s in self.events.strays:
            if s.t_start <= t < s.t_end:
                self._draw_stray(img, s, colour=self._paint(STRAY_BGR))
                strays.append(s.centre_px)
                active.append(s)

        # --- occluders (in front of everything)
        polys = []
        for oc in self.events.occluders:
            poly = oc.at(t)
            if poly is not None:
                self._draw_occluder(img, oc, poly, len(polys))
                polys.append(poly)

        label = None
        if with_mask:
            label = np.zeros((h, w), np.float32)
            for roi, cov in cov_store.values():
                y0, y1, x0, x1 = roi
                label[y0:y1, x0:x1] = np.maximum(label[y0:y1, x0:x1], cov)
            for st in active:
                self._draw_stray(label, st, colour=0.0)
            for poly in polys:
                cv2.fillPoly(label, [np.round(poly * 16).astype(np.int32)], 0.0, cv2.LINE_AA, shift=4)

        # --- visibility truth
        vis = np.zeros(nfid)
        for k, (roi, cov) in cov_store.items():
            total = self._full_coverage(C_all[k], rad, roi)
            if total <= 0:
                continue
            y0, y1, x0, x1 = roi
            if polys or active:     # hands, instruments and stray blobs are all in front of the balls
                m = np.zeros((y1 - y0, x1 - x0), np.uint8)
                for st in active:
                    self._draw_stray(m, st, offset=(x0, y0), colour=255)
                for poly in polys:
                    cv2.fillPoly(m, [np.round((poly - [x0, y0]) * 16).astype(np.int32)], 255, cv2.LINE_AA, shift=4)
                seen = float(np.sum(cov * (1.0 - m / 255.0)))
            else:
                seen = float(cov.sum())
            vis[k] = seen / total

        # --- motion blur over the exposure
        if self.exposure_s > 0:
            img = self._motion_blur(img, t, C_all, proj)

        # --- lighting gain, quantise, noise
        if lin:         # the lighting gain scales display values as before: gain^gamma in linear light
            out = self._chain.apply(img * np.float32(gain ** self.optics.gamma), key=t, linear=True)
        else:
            out = cv2.convertScaleAbs(img, alpha=gain)
        if self._chain is None and self.noise_sigma > 0:
            n = len(self._noise_pos)
            k = (self._last_noise + 1 + int(self._noise_rng.integers(n - 1))) % n
            self._last_noise = k
            cv2.add(out, self._noise_pos[k], dst=out)
            cv2.subtract(out, self._noise_neg[k], dst=out)
            # a still head's frames never repeat bit for bit, even two frames apart (a busy machine
            # skips frames, and a bank of 6 noise images alone gave the engine identical frames: a
            # false camera_freeze), as a real sensor's noise makes them: one pixel's lowest bit,
            # at a place that moves one byte on per frame. (Rolling the noise image instead moved
            # its pattern by a few rows between uses: a coherent shift the camera-motion watch saw.)
            self._noise_frame += 1
            i = self._noise_frame % out.size
            out.flat[i] = out.flat[i] ^ 1

        truth = FrameTruth(
            t_s=t, T_cam_ct=T, ellipse_centres_px=ell, projected_centres_px=proj,
            visible_fraction=vis, visible=vis >= FULLY_VISIBLE, radius_px=radius_px,
            stray_centres_px=np.array(strays, float).reshape(-1, 2), occluders=polys, fiducial_mask=label)
        return out, truth

    def _add_hair(self, img: np.ndarray, cov_low: np.ndarray) -> None:
        """Blend the hair layer into ``img`` (in place) where the skin covers it; only inside
        the skin's bounding box (the hair layer is fixed in the image: texture, not geometry)."""
        s = 1.0 / self._low_scale
        ys, xs = np.nonzero(cov_low > 0)
        h, w = img.shape[:2]
        x0, x1 = max(int(xs.min() * s) - 4, 0), min(int((xs.max() + 1) * s) + 4, w)
        y0, y1 = max(int(ys.min() * s) - 4, 0), min(int((ys.max() + 1) * s) + 4, h)
        full = cv2.resize(cov_low, (w, h), interpolation=cv2.INTER_LINEAR)[y0:y1, x0:x1]
        hair = cv2.multiply(full, self._hair[y0:y1, x0:x1])
        hair3 = cv2.merge([hair, hair, hair])
        patch = img[y0:y1, x0:x1]
        img[y0:y1, x0:x1] = patch - cv2.multiply(patch, hair3) + hair3 * np.float32(_optics.HAIR_BGR)

    def _draw_occluder(self, img, oc: Occluder, poly: np.ndarray, k: int) -> None:
        """A hand (glove) or instrument polygon; with optics, gloves take one of several glove
        colours and instruments are steel with a specular streak along the shaft."""
        pts = [np.round(poly * 16).astype(np.int32)]
        if self.optics is None:
            colour = GLOVE_BGR if oc.kind == "hand" else INSTRUMENT_BGR
            cv2.fillPoly(img, pts, colour, cv2.LINE_AA, shift=4)
            return
        if oc.kind == "hand":
            colour = _optics.GLOVE_BGR[(k + int(oc.t_start * 7)) % len(_optics.GLOVE_BGR)]
            cv2.fillPoly(img, pts, self._paint(colour), cv2.LINE_AA, shift=4)
            return
        cv2.fillPoly(img, pts, self._paint(_optics.STEEL_BGR), cv2.LINE_AA, shift=4)
        if len(poly) == 11:            # a _finger polygon: tip at index 4, shaft end between 9 and 10
            tip, end = poly[4], 0.5 * (poly[9] + poly[10])
            axis = (end - tip) / (np.linalg.norm(end - tip) + 1e-9)
            side = np.array([-axis[1], axis[0]]) * 0.2 * np.linalg.norm(poly[9] - poly[10]) / 2
            p0, p1 = np.round((tip + 4 * axis + side) * 16).astype(int), np.round((end + side) * 16).astype(int)
            cv2.line(img, tuple(p0), tuple(p1), self._paint((245.0, 245.0, 245.0)), 2, cv2.LINE_AA, shift=4)

    def _paint(self, bgr) -> tuple:
        """A display-space colour (BGR 0-255) in the space the scene is drawn in: linear
        radiance for photo-like frames (see ``render``), else as it is."""
        return self._chain.linear_colour(bgr) if self._chain is not None else tuple(bgr)

    def _draw_stray(self, img, s: Stray, offset=(0.0, 0.0), colour=STRAY_BGR):
        """Draw stray ``s`` (px) into ``img`` whose pixel (0, 0) is image pixel ``offset``."""
        c = np.asarray(s.centre_px, float) - np.asarray(offset, float)
        rng = np.random.default_rng(s.seed)
        if s.shape == "round":
            cv2.circle(img, tuple(np.round(c * 16).astype(int)), int(round(s.size_px * 16)), colour,
                       -1, cv2.LINE_AA, shift=4)
        elif s.shape == "streak":
            d = rng.normal(size=2)
            d = d / np.linalg.norm(d) * s.size_px * 2.5
            p0, p1 = np.round((c - d) * 16).astype(int), np.round((c + d) * 16).astype(int)
            cv2.line(img, tuple(p0), tuple(p1), colour, max(2, int(s.size_px / 3)), cv2.LINE_AA, shift=4)
        else:
            ang = np.sort(rng.uniform(0, 2 * np.pi, 9))
            r = s.size_px * rng.uniform(0.4, 1.4, 9)
            poly = c + np.column_stack([r * np.cos(ang), r * np.sin(ang)])
            cv2.fillPoly(img, [np.round(poly * 16).astype(np.int32)], colour, cv2.LINE_AA, shift=4)

    def _motion_blur(self, img, t, C_all, proj):
        """Blur along the image motion of the fiducial patch during the exposure (centred on t)."""
        e = self.exposure_s
        Ta = self.T_cam_ct_at(t - e / 2)
        Tb = self.T_cam_ct_at(t + e / 2)
        pa = self.camera.project(apply_transform(Ta, self.fiducials_ct)).mean(0)
        pb = self.camera.project(apply_transform(Tb, self.fiducials_ct)).mean(0)
        d = pb - pa
        L = float(np.linalg.norm(d))
        if L < 0.75:
            return img
        n = int(np.ceil(L)) | 1
        ksz = n + 2
        k = np.zeros((ksz, ksz), np.float32)
        c = (ksz - 1) / 2
        u = d / L
        for s in np.linspace(-L / 2, L / 2, 2 * n + 1):
            x, y = c + s * u[0], c + s * u[1]
            xi, yi = int(np.floor(x)), int(np.floor(y))
            fx, fy = x - xi, y - yi
            for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                                (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
                if 0 <= yi + dy < ksz and 0 <= xi + dx < ksz:
                    k[yi + dy, xi + dx] += wgt
        k /= k.sum()
        return cv2.filter2D(img, -1, k, borderType=cv2.BORDER_REPLICATE)
