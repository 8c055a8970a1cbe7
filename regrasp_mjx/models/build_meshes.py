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

from regrasp_mjx.world.needle_mesh import needle_tube

HERE = Path(__file__).resolve().parent
NEEDLE_RADIUS = 0.0054
WIRE_RADIUS = 0.00025
JAW_LENGTH = 0.0102
JAW_WIDTH_BASE, JAW_WIDTH_TIP, JAW_THICKNESS = 0.0020, 0.0012, 0.0012


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
    needle_tube(NEEDLE_RADIUS, WIRE_RADIUS).export(out / "needle_tube.stl")
    lnd_jaw().export(out / "lnd_jaw.stl")
    print(f"wrote {out / 'needle_tube.stl'} and {out / 'lnd_jaw.stl'}")


if __name__ == "__main__":
    main()
