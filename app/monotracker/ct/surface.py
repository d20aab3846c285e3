"""The head's skin surface as a triangle mesh in LPS millimetres, for 3D views.

Marching cubes (scikit-image) on a block-averaged copy of the volume (voxels of about
``target_mm``, 2 mm by default: ample for display and ~0.2 s on the sample CT), at the
level half way between air and soft tissue (from the volume's own histogram, so it follows the
scanner). Only the largest connected piece is kept (the head; not the table, not the noise).
Vertices are mapped through the volume's spacing, origin and direction, so the mesh lies
exactly where the fiducials are reported. Faces are wound so that normals point outwards.
"""

from __future__ import annotations

import numpy as np
import trimesh
from skimage.measure import marching_cubes

from monotracker.ct.volume import Volume
from monotracker.errors import MonoTrackerError


def _block_mean(arr: np.ndarray, f: tuple[int, int, int]) -> np.ndarray:
    """Mean over non-overlapping blocks of ``f`` (z, y, x) voxels (edge remainder dropped)."""
    nz, ny, nx = (s // k for s, k in zip(arr.shape, f))
    a = arr[: nz * f[0], : ny * f[1], : nx * f[2]].astype(np.float32)
    return a.reshape(nz, f[0], ny, f[1], nx, f[2]).mean(axis=(1, 3, 5))


def head_surface(volume: Volume, target_mm: float = 2.0, level_hu: float | None = None) -> trimesh.Trimesh:
    """The head's skin as a triangle mesh (marching cubes on a block-averaged volume).

    Args:
        volume: the CT (:class:`~monotracker.ct.volume.Volume`, HU, LPS geometry).
        target_mm: approximate edge length of the averaging blocks, mm (larger: coarser, faster).
        level_hu: iso-level, HU; None picks the air/soft-tissue midpoint of the volume's levels.

    Returns:
        ``trimesh.Trimesh`` with vertices in CT LPS mm and outward normals: the largest
        connected surface (the head), closed where the head touches the volume's border.

    Raises:
        MonoTrackerError: the volume holds no surface at ``level_hu`` (all above or all below).
    """
    from monotracker.ct.fiducials import estimate_levels

    if level_hu is None:
        lv = estimate_levels(volume)
        level_hu = 0.5 * (lv["air"] + lv["tissue"])
    # block factors per array axis (z, y, x) = spacing (k, j, i)
    f = tuple(max(1, int(round(target_mm / s))) for s in volume.spacing_mm[::-1])
    small = _block_mean(volume.array, f)
    # pad with air so the surface is closed where the head touches the volume's border
    pad_val = float(min(small.min(), level_hu - 1.0))
    small = np.pad(small, 1, constant_values=pad_val)
    if not (small.min() < level_hu < small.max()):
        raise MonoTrackerError(f"no skin surface at {level_hu:.0f} HU in this volume")
    verts, faces, _, _ = marching_cubes(small, level=level_hu, allow_degenerate=False)
    # block (z, y, x) index -> voxel (k, j, i) continuous index: block centre minus the pad
    kji = (verts - 1.0) * np.array(f, float) + (np.array(f, float) - 1.0) / 2.0
    lps = volume.zyx_to_lps(kji)
    mesh = trimesh.Trimesh(vertices=lps, faces=np.ascontiguousarray(faces[:, ::-1]), process=True)
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        mesh = max(parts, key=lambda m: len(m.faces))
    # marching cubes winds faces by the array's index order; make normals point outwards
    tri = mesh.triangles
    signed_volume = float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()) / 6.0
    faces_out = np.ascontiguousarray(mesh.faces[:, ::-1] if signed_volume < 0 else mesh.faces)
    # a fresh mesh: no cached normals from before the winding fix
    return trimesh.Trimesh(vertices=np.array(mesh.vertices), faces=faces_out, process=False)
