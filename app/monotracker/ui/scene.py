"""The 3D view of one tab (``client.scene``), in the frame its step needs:

* CT, Plan: CT LPS frame; head surface, numbered fiducials (green confirmed, yellow detected,
  red rejected), the path (entry cyan, target magenta). A click on the head does what the step's
  "Click on head" selector shows (add fiducial / set entry / set target / nothing).
* Register: camera frame (OpenCV, z forward); camera frustum, the head, fiducials and path
  placed with the latest trusted ``T_cam_ct``.
* Robot: robot base frame; the UR10 drawn from its joint state, the camera (hand-eye), the head
  and path (``T_base_ct``), the needle.

Units: the scene is in metres (viser's unit); CT/camera millimetres are scaled by ``MM``.

On a live step the page's main view is the camera overlay; the 3D view beside it is context, and
what moves in it (the head placed by the newest pose, the arm, the needle) is sent at most every
:data:`LIVE_SCENE_PERIOD_S`. Every change makes the browser draw the whole 3D view again; at the
pose rate (~8 Hz) that starved the live image in a browser without a GPU (one tab on the live
frames, quiet 2-core machine, ``benchmarks/web_overlay.py``: 4-9 fps, 110-170 ms median at 8 Hz;
20.5 fps, 34 ms at 1 Hz; 26 fps, 30 ms with no 3D updates at all).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from monotracker.geometry import apply_transform
from monotracker.ui.step_ct import FID_RGB

log = logging.getLogger(__name__)

MM = 1e-3  # scene metres per millimetre

#: on a live step, the moving parts of the 3D context view are sent at most this often (s)
LIVE_SCENE_PERIOD_S = 1.0
#: the steps whose main view is the live camera overlay (``view.LIVE_STEPS`` with a 3D view)
LIVE_SCENE_STEPS = ("register", "robot")


def wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> quaternion (w, x, y, z)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def world_from_ct(snap, step: str):
    """``T_world_ct`` (mm) for this step's 3D view, or None when the view cannot place the head."""
    if step in ("ct", "plan"):
        return np.eye(4)
    if step == "register":
        return None if snap.scene.T_cam_ct is None else np.asarray(snap.scene.T_cam_ct)
    return None if snap.scene.T_base_ct is None else np.asarray(snap.scene.T_base_ct)


def ray_hits(head_mesh, origin_mm, direction) -> np.ndarray:
    """All hits (k, 3) CT LPS mm of a ray (origin mm, direction) with the head surface, nearest
    first (trimesh's ray test; needs ``rtree``)."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(head_mesh.vertices), np.asarray(head_mesh.faces), process=False)
    o = np.asarray(origin_mm, float)
    d = np.asarray(direction, float)
    locs, _, _ = mesh.ray.intersects_location(o[None, :], (d / np.linalg.norm(d))[None, :])
    locs = np.asarray(locs, float).reshape(-1, 3)
    return locs[np.argsort(np.linalg.norm(locs - o, axis=1))]


def pick_head(head_mesh, origin_mm, direction):
    """First hit (CT LPS mm) of a ray with the head surface (the skin under the pointer), or None."""
    hits = ray_hits(head_mesh, origin_mm, direction)
    return hits[0] if len(hits) else None


def pick_inside(head_mesh, origin_mm, direction):
    """A point inside the head under the pointer: halfway between where the ray enters the skin
    and where it leaves it (CT LPS mm), or None when it does not pass through the head."""
    hits = ray_hits(head_mesh, origin_mm, direction)
    if len(hits) < 2:
        return None
    return (hits[0] + hits[1]) / 2


def _reset_group(scene, name: str) -> None:
    """Empty the scene group ``name`` (remove it if present) and create it again, hidden axes."""
    try:
        scene.remove_by_name(name)
    except Exception:  # noqa: BLE001 - viser raises when the group does not exist yet
        pass
    scene.add_frame(name, show_axes=False)


class SceneView:
    def __init__(self, view):
        self.view = view
        scene = view.scene
        scene.set_up_direction("+z")
        self._frames_for: str | None = None

    # ------------------------------------------------------------------ camera
    def aim(self, step: str, snap) -> None:
        """Point this tab's 3D camera at what the step shows (metres, world of that view)."""
        try:
            T_wc = world_from_ct(snap, step)
            centre = np.array([4.0, -12.0, 38.0])  # phantom head centre as a fallback, CT mm
            if snap.head_mesh is not None:
                v = np.asarray(snap.head_mesh.vertices)
                centre = (v.min(axis=0) + v.max(axis=0)) / 2
            if step in ("ct", "plan"):
                look = centre * MM
                pos = look + np.array([-0.22, -0.42, 0.22])
                up = (0.0, 0.0, 1.0)
            elif step == "register":
                look = apply_transform(T_wc, centre) * MM if T_wc is not None else np.array([0.0, 0.0, 0.4])
                pos = np.array([0.25, -0.2, -0.25])
                up = (0.0, -1.0, 0.0)
            else:
                look = apply_transform(T_wc, centre) * MM if T_wc is not None else np.array([0.6, 0.0, 0.3])
                pos = look + np.array([0.5, -0.7, 0.45])  # ~1 m: head, needle and the wrist fill the view
                up = (0.0, 0.0, 1.0)
            client = self.view.client
            with client.atomic():
                client.camera.up_direction = up
                client.camera.position = tuple(pos)
                client.camera.look_at = tuple(look)
        except Exception:
            log.debug("aim failed", exc_info=True)

    # ------------------------------------------------------------------ render
    def _set_pose(self, handle, T_mm) -> None:
        handle.wxyz = wxyz(T_mm[:3, :3])
        handle.position = T_mm[:3, 3] * MM

    def render(self, snap, step: str) -> None:
        # one writer of this tab's scene at a time: the navigation worker resets it for its tiles
        with self.view.nav_scene.scene_lock:
            self._render(snap, step)

    def _render(self, snap, step: str) -> None:
        scene = self.view.scene
        keys = self.view.scene_keys
        nav = self.view.nav_panel(step)
        if nav is not None and nav.state()[0]:
            # the navigation view (slices) has the canvas: its worker draws it
            keys["view"] = "nav"
            self.view.nav_scene.post(snap, nav)
            return
        T_wc = world_from_ct(snap, step)
        if keys.get("view") != step or (T_wc is not None) != keys.get("placed"):
            keys["placed"] = T_wc is not None
            self.aim(step, snap)
        if keys.get("view") != step:
            keys["view"] = step
            for k in ("mesh", "fids", "path", "robot_q", "frustum", "moved_t", "layout"):
                keys.pop(k, None)
            self.view.nav_scene.leave()  # no slice tile stays in the 3D view
            scene.reset()
            self._ct_frame = scene.add_frame("/ct", show_axes=False)
            self._cam_frame = scene.add_frame("/cam", show_axes=False, visible=step in ("register", "robot"))
            self._robot_frame = scene.add_frame("/robot", show_axes=False, visible=step == "robot")
        now = time.monotonic()
        # what moves is sent on every tick off the live steps; on them at most every
        # LIVE_SCENE_PERIOD_S, and at once when the head appears or vanishes
        move = (step not in LIVE_SCENE_STEPS or now - keys.get("moved_t", -1e9) >= LIVE_SCENE_PERIOD_S
                or self._ct_frame.visible != (T_wc is not None))
        if move:
            keys["moved_t"] = now
            self._ct_frame.visible = T_wc is not None
            if T_wc is not None:
                self._set_pose(self._ct_frame, T_wc)
        self._render_ct_group(scene, keys, snap, step)
        if step == "plan":  # the planned ball and camera layout (ui/layout_panel.py)
            self.view.steps["plan"].layout.render_scene(scene, keys, snap)
        if step in ("register", "robot"):
            self._render_camera(scene, keys, snap, step, move)
        if step == "robot" and move:
            self._render_robot(scene, keys, snap)

    def _render_ct_group(self, scene, keys, snap, step) -> None:
        """Head, fiducials, path in CT mm scaled to m, under /ct (placed by T_world_ct)."""
        mesh = snap.head_mesh
        if mesh is not None and keys.get("mesh") is not mesh:
            keys["mesh"] = mesh
            h = scene.add_mesh_simple("/ct/head", np.asarray(mesh.vertices) * MM, np.asarray(mesh.faces, np.int32),
                                      color=(230, 190, 160), opacity=0.55 if step != "ct" else 0.8,
                                      side="double", cast_shadow=False, receive_shadow=False)

            @h.on_click
            def _(event) -> None:
                self.on_head_click(event)
        elif mesh is None and keys.get("mesh") is not None:
            keys.pop("mesh")
            _reset_group(scene, "/ct/head")
        fkey = tuple((f.id, f.status, tuple(np.round(f.centre_lps_mm, 2))) for f in snap.fiducials)
        if keys.get("fids") != fkey:
            keys["fids"] = fkey
            _reset_group(scene, "/ct/fids")
            for f in snap.fiducials:
                c = np.asarray(f.centre_lps_mm) * MM
                scene.add_icosphere(f"/ct/fids/f{f.id}", radius=f.radius_mm * MM, color=FID_RGB.get(f.status, (200, 200, 200)),
                                    position=c, cast_shadow=False, receive_shadow=False)
                scene.add_label(f"/ct/fids/l{f.id}", str(f.id), position=c + np.array([0, 0, 1.6 * f.radius_mm * MM]))
        e, t = snap.plan.entry_lps_mm, snap.plan.target_lps_mm
        pkey = (None if e is None else tuple(e), None if t is None else tuple(t))
        if keys.get("path") != pkey:
            keys["path"] = pkey
            _reset_group(scene, "/ct/path")
            if e is not None:
                scene.add_icosphere("/ct/path/entry", radius=2.5 * MM, color=(0, 200, 255), position=np.asarray(e) * MM)
            if t is not None:
                scene.add_icosphere("/ct/path/target", radius=2.5 * MM, color=(255, 0, 255), position=np.asarray(t) * MM)
            if e is not None and t is not None:
                d = np.asarray(e) - np.asarray(t)
                ext = np.asarray(e) + 60.0 * d / np.linalg.norm(d)  # the needle's way out, 60 mm
                pts = np.array([[t, e], [e, ext]]) * MM
                cols = np.array([[[255, 0, 255], [0, 200, 255]], [[0, 200, 255], [0, 200, 255]]], np.uint8)
                scene.add_line_segments("/ct/path/line", pts, cols, thickness=4.0, thickness_units="screen")

    def _render_camera(self, scene, keys, snap, step, move: bool = True) -> None:
        """The camera (frustum) in the step's world; its pose only when ``move`` or just shown."""
        T_w_cam = np.eye(4) if step == "register" else (None if snap.scene.T_base_cam is None else np.asarray(snap.scene.T_base_cam))
        shown = self._cam_frame.visible
        self._cam_frame.visible = T_w_cam is not None
        if T_w_cam is None:
            return
        if move or not shown:
            self._set_pose(self._cam_frame, T_w_cam)
        if "frustum" not in keys:
            keys["frustum"] = True
            K, size = snap.camera.K, snap.camera.image_size
            if K is not None and size is not None:
                fov = 2 * np.arctan2(size[1] / 2, K[1, 1])
                aspect = size[0] / size[1]
            else:
                fov, aspect = np.radians(45), 16 / 9
            scene.add_camera_frustum("/cam/frustum", fov=float(fov), aspect=float(aspect),
                                     scale=0.06, thickness=0.0015, color=(40, 40, 200))

    def _render_robot(self, scene, keys, snap) -> None:
        if snap.scene.q is None:
            return
        q = np.asarray(snap.scene.q)
        if keys.get("robot_q") is None or np.abs(keys["robot_q"] - q).max() > 1e-4:
            keys["robot_q"] = q.copy()
            from monotracker.ui.robot_view import joint_chain_mm

            pts = joint_chain_mm(q) * MM
            segs = np.stack([pts[:-1], pts[1:]], axis=1)
            scene.add_line_segments("/robot/links", segs, (90, 110, 140), thickness=0.07)  # UR10 links ~ 7 cm across
            scene.add_point_cloud("/robot/joints", pts, colors=(40, 60, 90), point_size=0.05, point_shape="circle")
        if snap.scene.T_base_tip is not None:
            tip = np.asarray(snap.scene.T_base_tip)
            a = tip[:3, 3]
            b = a - 120.0 * tip[:3, 2]  # needle axis back along -z, 120 mm
            scene.add_line_segments("/robot/needle", np.array([[b, a]]) * MM, (250, 250, 250), thickness=5.0,
                                    thickness_units="screen")

    # ------------------------------------------------------------------ clicks
    def on_head_click(self, event) -> None:
        """A click on the head surface: what the shown step's "Click on head" selector says."""
        view = self.view
        try:
            with view.lock:
                step = view.step
            if step not in ("ct", "plan"):
                return
            panel = view.steps[step]
            mode = panel.h_click.value
            if mode == "nothing":
                return
            snap = view.session.snapshot()
            if snap.head_mesh is None:
                return
            origin, direction = np.asarray(event.ray_origin) / MM, np.asarray(event.ray_direction)
            p = (pick_inside if mode == "set target" else pick_head)(snap.head_mesh, origin, direction)
            if p is None:
                view.say(False, "Click: no skin under the pointer")
                return
            if mode == "add fiducial":
                # the picked surface point goes to the typed field: the operator checks it on the
                # slices and corrects it (a ball's centre lies one radius inside its surface)
                panel.h_new_fid.value = tuple(float(v) for v in p)
                view.say(True, f"Picked ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm: check and press 'Add fiducial here'")
            elif mode == "set entry":
                panel.h_entry.value = tuple(float(v) for v in p)
                view.run("Set entry", view.session.set_entry, p)
            elif mode == "set target":
                # a click gives no depth: the target goes halfway through the head under the
                # pointer; the operator checks it on the slices and corrects the typed value
                panel.h_target.value = tuple(float(v) for v in p)
                r = view.run("Set target", view.session.set_target, p)
                if r is not None and r.ok:
                    view.say(True, f"Target set halfway through the head under the pointer ({p[0]:.1f}, "
                                   f"{p[1]:.1f}, {p[2]:.1f}) mm: check the depth on the slices")
        except Exception as exc:
            log.exception("click failed")
            view.say(False, f"Click: internal error ({type(exc).__name__}: {exc})")
