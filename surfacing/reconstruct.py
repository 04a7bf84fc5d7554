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

log = logging.getLogger("sphshot")


@dataclass
class Field:
    colour: np.ndarray        # (nx, ny, nz) float32
    velocity: np.ndarray      # (nx, ny, nz, 3) float32
    index0: np.ndarray        # (3,) int, index of node (0,0,0)
    cell: float

    @property
    def origin(self) -> np.ndarray:
        return self.index0 * self.cell


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


def colour_field(positions, velocities, volumes, cell: float, support: float) -> Field:
    """Splat onto the nodes covering the particles' bounds plus one support (and a spare node)."""
    from .splat import splat     # Taichi: imported here so that reading meshes (render) stays light

    margin = support + 2 * cell
    lo = np.floor((positions.min(0) - margin) / cell).astype(int)
    hi = np.ceil((positions.max(0) + margin) / cell).astype(int)
    shape = tuple(int(v) for v in hi - lo + 1)
    c, u = splat(positions, velocities, volumes, lo * cell, shape, cell, support)   # cubic spline
    return Field(c, u, lo, cell)


def marching_cubes(field: Field, iso: float) -> Mesh:
    from scipy.ndimage import map_coordinates
    from skimage.measure import marching_cubes as mc

    if field.colour.max() <= iso:
        return Mesh.empty()
    # the field is zero on its border (margin > support), so every surface is closed
    verts, faces, _normals, _ = mc(field.colour, level=iso, allow_degenerate=False)
    points = (verts + field.index0) * field.cell
    faces = faces[:, ::-1].astype(np.int32)     # skimage winds inward for "inside = above iso"
    normals = vertex_normals(points, faces)
    vel = np.stack([map_coordinates(field.velocity[..., a], verts.T, order=1, mode="nearest")
                    for a in range(3)], axis=1)
    return Mesh(points.astype(np.float32), faces, normals, vel.astype(np.float32))


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals from face winding."""
    p = points.astype(np.float64)
    fn = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    vn = np.zeros_like(p)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return (vn / np.maximum(norm, 1e-30)).astype(np.float32)


def postprocess(mesh: Mesh, smoothing_iterations: int, decimate: float) -> Mesh:
    """Optional Taubin smoothing and decimation (VTK), keeping normals and velocities consistent."""
    if len(mesh.faces) == 0 or (smoothing_iterations == 0 and decimate == 0):
        return mesh
    import pyvista as pv
    from scipy.spatial import cKDTree

    poly = pv.PolyData(mesh.points, np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).ravel())
    if smoothing_iterations:
        poly = poly.smooth_taubin(n_iter=smoothing_iterations, pass_band=0.1)
    if decimate:
        poly = poly.decimate(decimate)
    pts = np.asarray(poly.points, np.float32)
    faces = np.asarray(poly.faces).reshape(-1, 4)[:, 1:].astype(np.int32)
    # velocities follow the nearest original vertex (smoothing moves points by well under a cell)
    _d, idx = cKDTree(mesh.points).query(pts)
    return Mesh(pts, faces, vertex_normals(pts, faces), mesh.velocity[idx])


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
