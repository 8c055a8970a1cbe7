"""The needle's render mesh for any radius and wire radius (trimesh): the renderer draws each
problem's own needle, and ``models/build_meshes.py`` writes the default one as ``needle_tube.stl``."""

from __future__ import annotations

import numpy as np
import trimesh


def needle_tube(radius: float, wire: float, n_arc: int = 96, n_ring: int = 16) -> trimesh.Trimesh:
    """A tube of radius ``wire`` along p(alpha) = (0, R cos a, R sin a), alpha in [pi/2, 3pi/2], R = ``radius`` [m]."""
    alpha = np.linspace(np.pi / 2, 3 * np.pi / 2, n_arc)
    ring = np.linspace(0.0, 2 * np.pi, n_ring, endpoint=False)
    centre = np.stack([np.zeros_like(alpha), radius * np.cos(alpha), radius * np.sin(alpha)], 1)
    radial = np.stack([np.zeros_like(alpha), np.cos(alpha), np.sin(alpha)], 1)  # in-plane normal
    normal = np.array([1.0, 0.0, 0.0])  # needle-plane normal
    verts = (
        centre[:, None, :]
        + wire * np.cos(ring)[None, :, None] * radial[:, None, :]
        + wire * np.sin(ring)[None, :, None] * normal[None, None, :]
    ).reshape(-1, 3)
    faces = []
    for i in range(n_arc - 1):
        for j in range(n_ring):
            a, b = i * n_ring + j, i * n_ring + (j + 1) % n_ring
            c, d = a + n_ring, b + n_ring
            faces += [[a, b, d], [a, d, c]]
    # Close both ends with a fan around an end-centre vertex.
    for i, flip in ((0, True), (n_arc - 1, False)):
        verts = np.vstack([verts, centre[i]])
        cidx = len(verts) - 1
        for j in range(n_ring):
            a, b = i * n_ring + j, i * n_ring + (j + 1) % n_ring
            faces.append([cidx, b, a] if flip else [cidx, a, b])
    mesh = trimesh.Trimesh(verts, np.array(faces), process=True)
    mesh.fix_normals()
    return mesh
