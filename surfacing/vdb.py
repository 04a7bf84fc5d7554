"""OpenVDB output with Debian's pyopenvdb (OpenVDB 10, NumPy 1.x).

Grids: `surface` (level set, narrow band of `half_width` voxels, built from the mesh so the two
agree), `density` (fog, the colour field wherever particles reach) and `velocity` (Vec3, on the
band of 8^3 blocks the surface passes through, where the colour exceeds FOG_TOLERANCE). All share one linear transform
of voxel size `cell`; index (i, j, k) is at world cell * (i, j, k). Metadata: frame, time.
"""
from __future__ import annotations

import numpy as np
import pyopenvdb as vdb

from .reconstruct import B

FOG_TOLERANCE = 1e-4     # colour values below this are background (inactive)


def build_grids(field, mesh, frame: int, time_s: float, half_width: float, extra_surfaces=()):
    """`extra_surfaces`: (name, Mesh) pairs written as further level sets (one per fluid)."""
    xform = vdb.createLinearTransform(voxelSize=float(field.cell)) if field is not None else \
        vdb.createLinearTransform(voxelSize=1.0)
    grids = [_level_set("surface", mesh, xform, half_width)]
    grids += [_level_set(f"surface_{name}", m, xform, half_width) for name, m in extra_surfaces]

    density = vdb.FloatGrid(0.0)
    density.name = "density"
    density.gridClass = vdb.GridClass.FOG_VOLUME
    velocity = vdb.Vec3SGrid((0.0, 0.0, 0.0))
    velocity.name = "velocity"
    velocity.vectorType = vdb.VectorType.CONTRAVARIANT_RELATIVE
    if field is not None:
        # one copy per 8^3 block: each is exactly one leaf node of the grid
        for n, b in enumerate(field.blocks):
            density.copyFromArray(field.colour[n], ijk=tuple(int(v) * B for v in b), tolerance=FOG_TOLERANCE)
        if field.velocity is not None:
            for slot, n in enumerate(field.velocity_ids):
                vel = np.where((field.colour[n] > FOG_TOLERANCE)[..., None], field.velocity[slot], np.float32(0))
                velocity.copyFromArray(vel, ijk=tuple(int(v) * B for v in field.blocks[n]), tolerance=(0.0, 0.0, 0.0))
    for g in (density, velocity):
        g.transform = xform
    grids += [density, velocity]
    for g in grids:
        g["frame"] = int(frame)
        g["time"] = float(time_s)
    return grids


def _level_set(name, mesh, xform, half_width):
    if len(mesh.faces):
        grid = vdb.FloatGrid.createLevelSetFromPolygons(
            mesh.points.astype(np.float32), triangles=mesh.faces.astype(np.uint32),
            transform=xform, halfWidth=float(half_width))
    else:
        vs = xform.voxelSize()[0]
        grid = vdb.FloatGrid(float(half_width) * vs)
        grid.gridClass = vdb.GridClass.LEVEL_SET
        grid.transform = xform
    grid.name = name
    return grid


def write(path, grids) -> None:
    vdb.write(str(path), grids=grids)
