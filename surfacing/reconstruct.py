"""Particles -> color field on a grid -> marching-cubes mesh and OpenVDB grids.

Grid convention, shared by the mesh and every VDB grid: node (i, j, k) of the arrays sits at
world position cell * (i0 + i, j0 + j, k0 + k), where (i0, j0, k0) is an integer index offset.
The VDB transform is a plain linear transform of voxel size `cell`, so the level set, the fog
density, the velocity grid, the mesh and the particles line up in Houdini or Blender.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import device as D, mc
from .grid import Field
from .mesh import Mesh
from .splat import Splat


# marching cubes places an anisotropic field's vertices where the cube root of the color,
# linear along an edge, reaches the iso's: that field falls to its iso as the cube of the
# distance to its squashed kernels' edge (surfacing/mc.py); an isotropic one is about linear
# there, and interpolated linearly (a resting block: -0.3 % of the converged volume at the
# default cell, against -0.8 % through the cube root)
ANISOTROPIC_EDGE_POWER = 1.0 / 3.0


@dataclass(frozen=True)
class SurfaceParams:
    """How to surface particles. Lengths in metres."""
    cell: float                         # grid node spacing
    kernel_radius: float                # splat kernel support
    iso: float = 0.5                    # color-field iso value of the surface
    kernel: str = "cubic"               # splat kernel: cubic, poly6 or wendland
    smoothing_iterations: int = 0       # Taubin smoothing passes
    decimate: float = 0.0               # fraction of triangles removed
    method: str = "isotropic"           # or "anisotropic" (Yu & Turk 2013: surfacing/anisotropy.py)
    spray_below: int = 0                # fewer neighbours than this within 2 supports: spray
    center_smoothing: float = 0.0       # anisotropic: Yu & Turk's lambda
    center_inflation: float = 0.0       # anisotropic, with center_smoothing: Taubin's second pass (-mu)
    inside: tuple | None = None         # (lo, hi): the mesh is kept inside this box (the domain)
    outside_solids: Callable | None = None   # points -> points moved out of the solids (colliders)


def reconstruct(positions, velocities, volumes, params: SurfaceParams) -> tuple[Field, Mesh]:
    """(field, mesh) of one set of particles: the color (and velocity) field, and the surface
    mesh after smoothing and decimation."""
    field = color_field(positions, velocities, volumes, params.cell, params.kernel_radius, params.iso,
                        params.kernel, anisotropic=params.method == "anisotropic", spray_below=params.spray_below,
                        center_smoothing=params.center_smoothing, center_inflation=params.center_inflation)
    return field, surface_mesh(field, params.iso, params.smoothing_iterations, params.decimate, params.inside,
                               params.outside_solids)


def particle_volumes(data: dict, attrs: dict) -> np.ndarray:
    """V_j = m_j / max(rho_j, rho0_j) from the sim frame; (2r)^3 where the density is missing
    or zero. The SPH density of a particle at a free surface is short of the fluid beyond it
    (DFSPH's on the fill lattice: 0.85 of rest on a face, 0.72 on an edge, 0.61 at a corner),
    which says nothing of its own volume, so below rest it is read as rest: with m / rho a
    block's faces, edges and corners swelled in turn (the two-fluid example's first frame: mesh
    1.6 % over its particles' volume, corners standing out as knobs; with the rest density
    0.0 %). A frame written before the rest densities were in its attributes keeps m / rho."""
    r = float(attrs["particle_radius"])
    lattice = (2 * r) ** 3
    if "fluid_mass" not in attrs or "density" not in data:
        return np.full(len(data["position"]), lattice, np.float32)
    mass = np.asarray(attrs["fluid_mass"], np.float64)[data["fluid"]]
    rho = data["density"].astype(np.float64)
    if "fluid_rest_density" in attrs:
        rho = np.maximum(rho, np.asarray(attrs["fluid_rest_density"], np.float64)[data["fluid"]])
    with np.errstate(divide="ignore"):
        vol = np.where(rho > 0, mass / rho, lattice)
    return vol.astype(np.float32)


def color_field(positions, velocities, volumes, cell: float, support: float, iso: float = 0.5,
                 kernel: str = "cubic", method: str = "auto", anisotropic: bool = False,
                 spray_below: int = 0, center_smoothing: float = 0.0, center_inflation: float = 0.0) -> Field:
    """Splat the particles onto the blocks their supports reach (`kernel`: cubic, poly6 or
    wendland; `anisotropic`: stretched after Yu & Turk 2013). With `velocities`, the velocity
    field too, on the blocks the `iso` surface crosses and their upper neighbours (what the
    mesh's vertices and a motion-blur band need), from only the particles that reach them.
    `method`: the scatter (surfacing/splat.py: "auto" picks by the backend). Particles with
    fewer than `spray_below` neighbours are left out; field.spray is their mask."""
    sp = Splat(positions, volumes, cell, support, kernel, method, anisotropic, spray_below, center_smoothing,
               center_inflation)
    field = Field(sp.color(), sp.blocks, sp.lookup, sp.base_block, cell)
    field.spray = sp.spray
    field.edge_power = ANISOTROPIC_EDGE_POWER if anisotropic else 1.0
    if velocities is not None and field.n_blocks:
        ids, upper = field.crossing_blocks(iso)
        band = np.union1d(ids, upper[upper < field.n_blocks])
        field.velocity_rows, field.velocity_ids = sp.velocity(velocities, band, field.rows), band
    return field


def marching_cubes(field: Field, iso: float) -> Mesh:
    """The `iso` surface of the field as a mesh with vertex normals and velocities."""
    points, faces, velocity, points_dev, faces_dev = _triangulate(field, iso)
    normals = mc.normals_on_device(points_dev, faces_dev, len(points), len(faces))
    return Mesh(points, faces, D.host(normals)[:len(points)], velocity)


def surface_mesh(field: Field, iso: float, smoothing_iterations: int, decimate: float,
                 inside: tuple | None = None, outside_solids: Callable | None = None) -> Mesh:
    """What the surface stage writes: marching cubes, then optional Taubin smoothing and
    decimation, then with `inside` = (lo, hi) every vertex moved into that box and with
    `outside_solids` out of the solids (water meets a wall or an obstacle instead of passing
    into it: the kernels reach past the particles next to it), with the vertex normals computed
    once, at the end."""
    points, faces, velocity, _, _ = _triangulate(field, iso)
    if len(faces) and (smoothing_iterations or decimate):
        points, faces, velocity = _smooth(points, faces, velocity, smoothing_iterations, decimate)
    if inside is not None and len(points):
        points = np.clip(points, np.asarray(inside[0], np.float32), np.asarray(inside[1], np.float32))
    if outside_solids is not None and len(points):
        points = np.asarray(outside_solids(points), np.float32)
    return _with_normals(points, faces, velocity)


def _with_normals(points: np.ndarray, faces: np.ndarray, velocity: np.ndarray) -> Mesh:
    return Mesh(points, faces, vertex_normals(points, faces), velocity)


def _triangulate(field: Field, iso: float):
    """(points, faces, velocity, points and faces on the device) of the `iso` surface: marching cubes
    (surfacing/mc.py) over the blocks whose cells cross `iso`, one vertex per crossed grid
    edge, its velocity interpolated along the edge."""
    empty = Mesh.empty()
    todo = field.crossing_blocks(iso)[0] if field.n_blocks else ()
    if len(todo) == 0:
        return empty.points, empty.faces, empty.velocity, None, None
    slot = None if field.velocity_ids is None else field.velocity_slot.astype(np.int32)
    if slot is not None and field.velocity_rows is None:       # a Field made from numpy (tests)
        field.velocity_rows = D.vec3s(field.velocity.reshape(-1, 3))
    return mc.marching_cubes(field.rows, field.upper, field.blocks, todo, iso, field.cell, field.velocity_rows,
                             slot, field.edge_power)


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals from face winding (a Taichi loop: surfacing/mc.py)."""
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
