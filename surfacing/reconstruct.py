"""Particles -> colour field on a grid -> marching-cubes mesh and OpenVDB grids.

Grid convention, shared by the mesh and every VDB grid: node (i, j, k) of the arrays sits at
world position cell * (i0 + i, j0 + j, k0 + k), where (i0, j0, k0) is an integer index offset.
The VDB transform is a plain linear transform of voxel size `cell`, so the level set, the fog
density, the velocity grid, the mesh and the particles line up in Houdini or Blender.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .mc_table import CORNER

log = logging.getLogger("sphshot")
B = 8                   # nodes per block edge of the sparse grid: one OpenVDB leaf node


class GridTooLarge(ValueError):
    """The particles are spread too far for the block index at this cell size."""


@dataclass
class Field:
    """The colour and velocity fields on a block-sparse grid (see surfacing/splat.py).

    Block n holds nodes blocks[n] * 8 + (0..7)^3 of the global grid, node (i, j, k) at world
    position cell * (i, j, k). `colour` covers every block; `velocity` only the blocks
    velocity_ids (the band the iso surface passes through). Both arrays end with one all-zero
    block, the stand-in for blocks that are missing (or outside the band)."""
    colour: np.ndarray                # (nb + 1, 8, 8, 8) float32
    blocks: np.ndarray                # (nb, 3) int64 block coordinates
    lookup: np.ndarray                # int32 block ids over the blocks' bounding box, -1 = none
    base_block: np.ndarray            # (3,) block coordinates of lookup[0, 0, 0]
    cell: float
    velocity: np.ndarray | None = None        # (len(velocity_ids) + 1, 8, 8, 8, 3) float32, m/s
    velocity_ids: np.ndarray | None = None    # the block ids that carry velocity

    @property
    def n_blocks(self) -> int:
        return len(self.blocks)

    @property
    def velocity_slot(self) -> np.ndarray:
        """(nb + 1,): where each block's velocity is in `velocity` (the zero block if nowhere)."""
        slot = np.full(self.n_blocks + 1, len(self.velocity_ids), np.int64)
        slot[self.velocity_ids] = np.arange(len(self.velocity_ids))
        return slot

    def neighbour(self, offset, ids=None) -> np.ndarray:
        """Id of each block's (or of blocks `ids`') neighbour at block offset (dx, dy, dz); nb
        (the zero block) if none."""
        blocks = self.blocks if ids is None else self.blocks[ids]
        return self.block_of((blocks + np.asarray(offset)) * B)

    def block_of(self, nodes: np.ndarray) -> np.ndarray:
        """Block id of integer global node indices (N, 3); nb (the zero block) where missing."""
        b = nodes // B - self.base_block
        inside = ((b >= 0) & (b < self.lookup.shape)).all(1)
        ids = np.full(len(nodes), self.n_blocks, np.int64)
        ids[inside] = self.lookup[b[inside, 0], b[inside, 1], b[inside, 2]]
        ids[ids < 0] = self.n_blocks
        return ids

    def crossing_blocks(self, iso: float) -> tuple[np.ndarray, np.ndarray]:
        """(ids, upper): the blocks owning a grid cell with corners on both sides of `iso`, and
        the (7, len(ids)) ids of their upper neighbours in _UPPER's order, whose first node
        layers those cells reach (nb where missing)."""
        nb = self.n_blocks
        flat = self.colour[:nb].reshape(nb, -1)
        above = np.r_[flat.max(1) > iso, False]          # the zero block: all below
        below = np.r_[flat.min(1) <= iso, True]
        nbrs = np.stack([self.neighbour(o) for o in _UPPER])
        crosses = (above[:nb] | above[nbrs].any(0)) & (below[:nb] | below[nbrs].any(0))
        ids = np.flatnonzero(crosses)
        return ids, nbrs[:, ids]

    def dense(self):
        """(array, index0): the colour as one dense array over the blocks' bounding box (tests)."""
        lo, hi = self.blocks.min(0), self.blocks.max(0) + 1
        out = np.zeros(tuple((hi - lo) * B), np.float32)
        for n, b in enumerate(self.blocks - lo):
            out[b[0] * B:(b[0] + 1) * B, b[1] * B:(b[1] + 1) * B, b[2] * B:(b[2] + 1) * B] = self.colour[n]
        return out, lo * B


# the 7 blocks (besides the block itself) whose nodes the cells of a block touch, at the block
# offsets of a cell's corners 1 to 7: the columns surfacing/mc.py expects
_UPPER = [tuple(int(v) for v in c) for c in CORNER[1:]]


@dataclass
class Mesh:
    points: np.ndarray        # (V, 3) float32, world
    faces: np.ndarray         # (F, 3) int32, outward-facing (counter-clockwise seen from outside)
    normals: np.ndarray       # (V, 3) float32, outward unit
    velocity: np.ndarray      # (V, 3) float32, m/s

    @classmethod
    def empty(cls) -> "Mesh":
        z = np.zeros((0, 3), np.float32)
        return cls(z, np.zeros((0, 3), np.int32), z, z)


def particle_volumes(data: dict, attrs: dict) -> np.ndarray:
    """V_j = m_j / rho_j from the sim frame; (2r)^3 where the density is missing or zero."""
    r = float(attrs["particle_radius"])
    lattice = (2 * r) ** 3
    if "fluid_mass" not in attrs or "density" not in data:
        return np.full(len(data["position"]), lattice, np.float32)
    mass = np.asarray(attrs["fluid_mass"], np.float64)[data["fluid"]]
    rho = data["density"].astype(np.float64)
    with np.errstate(divide="ignore"):
        vol = np.where(rho > 0, mass / rho, lattice)
    return vol.astype(np.float32)


def colour_field(positions, velocities, volumes, cell: float, support: float, iso: float = 0.5,
                 kernel: str = "cubic") -> Field:
    """Splat the particles onto the blocks their supports reach (`kernel`: cubic, poly6 or
    wendland). With `velocities`, the velocity field too, on the blocks the `iso` surface
    crosses and their upper neighbours (what the mesh's vertices and a motion-blur band need),
    from only the particles that reach them."""
    from .splat import Splat     # Taichi: imported here so that reading meshes (render) stays light

    sp = Splat(positions, volumes, cell, support, kernel)
    field = Field(sp.colour(), sp.blocks, sp.lookup, sp.base_block, cell)
    if velocities is not None and field.n_blocks:
        ids, upper = field.crossing_blocks(iso)
        band = np.union1d(ids, upper[upper < field.n_blocks])
        field.velocity, field.velocity_ids = sp.velocity(velocities, band, field.colour), band
    return field


def marching_cubes(field: Field, iso: float) -> Mesh:
    """The `iso` surface of the field as a mesh with vertex normals and velocities."""
    return _with_normals(*_triangulate(field, iso))


def surface_mesh(field: Field, iso: float, smoothing_iterations: int, decimate: float) -> Mesh:
    """What the surface stage writes: marching cubes, then optional Taubin smoothing and
    decimation, with the vertex normals computed once, at the end."""
    points, faces, velocity = _triangulate(field, iso)
    if len(faces) and (smoothing_iterations or decimate):
        points, faces, velocity = _smooth(points, faces, velocity, smoothing_iterations, decimate)
    return _with_normals(points, faces, velocity)


def _with_normals(points: np.ndarray, faces: np.ndarray, velocity: np.ndarray) -> Mesh:
    return Mesh(points, faces, vertex_normals(points, faces), velocity)


def _triangulate(field: Field, iso: float):
    """(points, faces, velocity) of the `iso` surface: marching cubes (surfacing/mc.py) over
    the blocks whose cells cross `iso`, one vertex per crossed grid edge."""
    from . import mc     # Taichi: imported here so that reading meshes (render) stays light

    empty = Mesh.empty()
    if field.n_blocks == 0:
        return empty.points, empty.faces, empty.velocity
    todo, upper = field.crossing_blocks(iso)
    if len(todo) == 0:
        return empty.points, empty.faces, empty.velocity
    g, faces = mc.marching_cubes(field.colour, field.blocks, todo, upper.T, field.neighbour, iso)
    points = g * field.cell
    if field.velocity is None:
        vel = np.zeros_like(points)
    else:
        # each vertex lies on a grid edge: linear interpolation between the edge's two nodes
        base = np.floor(g).astype(np.int64)
        axis = np.argmax(g - base, axis=1)
        rows = np.arange(len(g))
        frac = (g - base)[rows, axis][:, None]
        step = np.zeros_like(base)
        step[rows, axis] = 1
        vel = (1 - frac) * _node_velocity(field, base) + frac * _node_velocity(field, base + step)
    return points.astype(np.float32), faces, vel.astype(np.float32)


def _node_velocity(field: Field, nodes: np.ndarray) -> np.ndarray:
    slot = field.velocity_slot[field.block_of(nodes)]
    loc = nodes % B
    return field.velocity[slot, loc[:, 0], loc[:, 1], loc[:, 2]]


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals from face winding (a Taichi loop: surfacing/mc.py)."""
    from . import mc

    return mc.vertex_normals(points, faces)


def postprocess(mesh: Mesh, smoothing_iterations: int, decimate: float) -> Mesh:
    """Optional Taubin smoothing and decimation of a mesh, its normals made anew."""
    if len(mesh.faces) == 0 or (smoothing_iterations == 0 and decimate == 0):
        return mesh
    return _with_normals(*_smooth(mesh.points, mesh.faces, mesh.velocity, smoothing_iterations, decimate))


def _smooth(points: np.ndarray, faces: np.ndarray, velocity: np.ndarray, smoothing_iterations: int,
            decimate: float):
    """(points, faces, velocity) after Taubin smoothing and decimation (VTK)."""
    import pyvista as pv
    from scipy.spatial import cKDTree

    poly = pv.PolyData.from_regular_faces(points, faces)
    if smoothing_iterations:
        poly = poly.smooth_taubin(n_iter=smoothing_iterations, pass_band=0.1)
    if decimate:
        poly = poly.decimate(decimate)
    pts = np.asarray(poly.points, np.float32)
    new_faces = np.asarray(poly.faces).reshape(-1, 4)[:, 1:].astype(np.int32)
    # velocities follow the nearest original vertex (smoothing moves points by well under a cell)
    _d, idx = cKDTree(points).query(pts)
    return pts, new_faces, velocity[idx]


def write_mesh(path, mesh: Mesh, fmt: str) -> None:
    """PLY keeps normals (nx, ny, nz) and velocity (vx, vy, vz) as vertex properties; OBJ keeps
    normals; VTU keeps both as point arrays."""
    import meshio

    cells = [("triangle", mesh.faces.astype(np.int32))]
    if fmt == "ply":
        pd = {"nx": mesh.normals[:, 0], "ny": mesh.normals[:, 1], "nz": mesh.normals[:, 2],
              "vx": mesh.velocity[:, 0], "vy": mesh.velocity[:, 1], "vz": mesh.velocity[:, 2]}
    elif fmt == "obj":
        pd = {"obj:vn": mesh.normals}
    else:
        pd = {"Normals": mesh.normals, "velocity": mesh.velocity}
    meshio.write(str(path), meshio.Mesh(mesh.points, cells, point_data=pd), file_format=fmt)


def read_mesh(path) -> Mesh:
    import meshio

    m = meshio.read(str(path))
    faces = m.cells_dict.get("triangle", np.zeros((0, 3), np.int32))
    pd = m.point_data
    if "nx" in pd:
        normals = np.stack([pd["nx"], pd["ny"], pd["nz"]], 1)
        vel = np.stack([pd["vx"], pd["vy"], pd["vz"]], 1)
    else:
        normals = pd.get("Normals", pd.get("obj:vn", np.zeros_like(m.points)))
        vel = pd.get("velocity", np.zeros_like(m.points))
    return Mesh(np.asarray(m.points, np.float32), np.asarray(faces, np.int32),
                np.asarray(normals, np.float32), np.asarray(vel, np.float32))
