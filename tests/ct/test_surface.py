"""Head surface mesh against the analytic skin ellipsoid."""

import numpy as np

from monotracker.ct import head_surface, load_volume
from monotracker.paths import sample_ct_path
from monotracker.sim.phantom import default_phantom


def test_skin_mesh_lies_on_the_analytic_skin_in_lps():
    mesh = head_surface(load_volume(sample_ct_path()))
    ph = default_phantom()
    assert mesh.is_watertight and mesh.volume > 0  # closed, normals outwards
    v = mesh.vertices
    above = v[:, 2] > ph.neck_cut_z_mm + 3.0
    # radial distance from the ellipsoid, mm (approx.: (f - 1) * local radius)
    q = (v[above] - ph.centre_lps) / ph.skin_semi_axes_mm
    f = np.linalg.norm(q, axis=1)
    r_local = np.linalg.norm(v[above] - ph.centre_lps, axis=1) / f
    dist = (f - 1.0) * r_local
    assert np.median(np.abs(dist)) < 0.3
    assert np.percentile(np.abs(dist), 90) < 0.8  # the rest: fiducial bumps and the neck rim
    # the mesh spans the head (bounding box of the ellipsoid above the neck cut)
    u = np.random.default_rng(0).normal(size=(200000, 3))
    skin = ph.centre_lps + u / np.linalg.norm(u, axis=1, keepdims=True) * ph.skin_semi_axes_mm
    skin = skin[skin[:, 2] >= ph.neck_cut_z_mm]
    balls = np.vstack([ph.fiducial_centres_lps + s * ph.fiducial_radius_mm * np.eye(3)[i] for i in range(3) for s in (-1, 1)])
    pts = np.vstack([skin, balls])
    assert np.allclose(mesh.bounds, [pts.min(axis=0), pts.max(axis=0)], atol=1.5)
    # normals point away from the head centre
    n = mesh.face_normals
    out = np.sum(n * (mesh.triangles_center - ph.centre_lps), axis=1) > 0
    assert out.mean() > 0.95
