"""Signed distance of a closed triangle mesh, sampled on a regular grid, for mesh colliders.

OpenVDB's mesh-to-level-set (the same conversion Houdini's VDB from Polygons uses) gives the
distance to the triangles within its narrow band and the sign from a flood fill, so it copes
with self-intersecting or non-manifold but closed meshes. Distances are exact outside and within
a voxel of the surface; deeper inside, where OpenVDB grows the band from its neighbours' closest
triangles, they were measured within 0.1 voxel (tests/test_solver.py, an icosphere). The band
is made wide enough to hold every point within one kernel radius outside the mesh and as deep
inside; deeper voxels keep
the band's far value, -band, which still pushes a stray particle out along the gradient it has
near the band's edge. Node (i, j, k) of the returned grid is at origin + voxel * (i, j, k).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SDFGrid:
    origin: np.ndarray       # (3,) world position of node (0, 0, 0)
    voxel: float
    phi: np.ndarray          # (nx, ny, nz) float32, negative inside the mesh


def sample_sdf(verts: np.ndarray, tris: np.ndarray, lo: np.ndarray, hi: np.ndarray, voxel: float,
               depth: float) -> SDFGrid:
    """The signed distance on the nodes of multiples of `voxel` covering [lo, hi], exact within
    `depth` metres of the surface on either side."""
    import pyopenvdb as vdb

    first = np.floor(np.asarray(lo) / voxel).astype(np.int64)
    last = np.ceil(np.asarray(hi) / voxel).astype(np.int64)
    half_width = max(3.0, math.ceil(depth / voxel) + 1.0)
    grid = vdb.FloatGrid.createLevelSetFromPolygons(
        np.ascontiguousarray(verts, np.float32), triangles=np.ascontiguousarray(tris, np.int32),
        transform=vdb.createLinearTransform(voxelSize=float(voxel)), halfWidth=half_width)
    phi = np.empty(tuple(int(n) for n in last - first + 1), np.float32)
    grid.copyToArray(phi, ijk=tuple(int(i) for i in first))
    return SDFGrid(origin=(first * voxel).astype(np.float64), voxel=float(voxel), phi=phi)
