"""Builds the render meshes of the regrasp scene with trimesh.

Run from anywhere: ``python models/mjcf/build_meshes.py``. Writes ``meshes/needle_tube.stl`` and
``meshes/lnd_jaw.stl`` beside this file. Collision geometry is not made here: it is capsules in
``regrasp_scene.xml``, which MJX is fast with. These meshes are for rendering only (group 2).

Dimensions (metres) follow the scene file's notes: needle R = 5.4 mm, wire radius 0.25 mm; LND jaw
10.2 mm from the pivot to the tip, 2.0 mm wide at the pivot tapering to 1.2 mm, 1.2 mm thick.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent
NEEDLE_RADIUS = 0.0054
WIRE_RADIUS = 0.00025
JAW_LENGTH = 0.0102
JAW_WIDTH_BASE, JAW_WIDTH_TIP, JAW_THICKNESS = 0.0020, 0.0012, 0.0012


def needle_tube(n_arc: int = 96, n_ring: int = 16) -> trimesh.Trimesh:
    """A tube of the wire radius along p(alpha) = (0, R cos a, R sin a), alpha in [pi/2, 3pi/2]."""
    alpha = np.linspace(np.pi / 2, 3 * np.pi / 2, n_arc)
    ring = np.linspace(0.0, 2 * np.pi, n_ring, endpoint=False)
    centre = np.stack([np.zeros_like(alpha), NEEDLE_RADIUS * np.cos(alpha), NEEDLE_RADIUS * np.sin(alpha)], 1)
    radial = np.stack([np.zeros_like(alpha), np.cos(alpha), np.sin(alpha)], 1)  # in-plane normal
    normal = np.array([1.0, 0.0, 0.0])  # needle-plane normal
    verts = (
        centre[:, None, :]
        + WIRE_RADIUS * np.cos(ring)[None, :, None] * radial[:, None, :]
        + WIRE_RADIUS * np.sin(ring)[None, :, None] * normal[None, None, :]
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


def lnd_jaw() -> trimesh.Trimesh:
    """One jaw along +z from the pivot: a tapered slab, the hull of its eight corners."""
    corners = []
    for z, w in ((0.0, JAW_WIDTH_BASE), (JAW_LENGTH, JAW_WIDTH_TIP)):
        for sx in (-0.5, 0.5):
            for sy in (-0.5, 0.5):
                corners.append([sx * w, sy * JAW_THICKNESS, z])
    return trimesh.convex.convex_hull(np.array(corners))


def main() -> None:
    out = HERE / "meshes"
    out.mkdir(exist_ok=True)
    needle_tube().export(out / "needle_tube.stl")
    lnd_jaw().export(out / "lnd_jaw.stl")
    print(f"wrote {out / 'needle_tube.stl'} and {out / 'lnd_jaw.stl'}")


if __name__ == "__main__":
    main()
