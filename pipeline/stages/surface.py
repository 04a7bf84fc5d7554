"""The surface stage: one .vdb and one mesh (or one per fluid) per sim frame, and the spray as
points (PLY, and VDB points beside the .vdb).

The spec becomes surfacing's parameters here (surface_params), and the surfacer's errors
become one-line stage errors.
"""
from __future__ import annotations

import functools
import logging

import numpy as np

from solver.backend import BackendUnavailable, init_taichi
from surfacing.grid import SurfacingError
from surfacing.mesh import Mesh
from surfacing.reconstruct import SurfaceParams, particle_volumes, reconstruct

from ..errors import StageError
from ..formats import read_frame, vdb_points_tool, write_mesh, write_points, write_vdb, write_vdb_points
from . import device_failures

log = logging.getLogger("sphshot")


@functools.lru_cache(maxsize=4)
def surface_params(spec) -> SurfaceParams:
    """surfacing's parameters from the spec: the mesh is kept inside the domain and out of the
    colliders (solver.boundaries.project_outside, through the sim's collider tables: made once
    per spec, since a mesh collider's distance grid takes a while)."""
    s = spec.surface
    solids = None
    if spec.colliders:
        from solver.boundaries import project_outside
        from .sim import solver_params

        sp = solver_params(spec)
        solids = functools.partial(project_outside, sp)
    return SurfaceParams(cell=spec.surface_cell_m, kernel_radius=spec.surface_kernel_radius_m, iso=s.iso_value,
                         kernel=s.kernel, smoothing_iterations=s.smoothing_iterations, decimate=s.decimate,
                         method=s.method, spray_below=s.spray, center_smoothing=s.center_smoothing,
                         center_inflation=s.center_inflation,
                         inside=(spec.domain.min, spec.domain.max), outside_solids=solids)


def surface_frame(spec, data: dict, attrs: dict, frame: int):
    """Build (field, mesh, {fluid: mesh}, spray mask) for one frame of particles."""
    position = data["position"]
    if len(position) == 0:
        log.warning("frame %04d: surfacing: no particles; writing an empty mesh and empty grids", frame)
        return None, Mesh.empty(), {f.name: Mesh.empty() for f in spec.fluids}, np.zeros(0, bool)
    volume = particle_volumes(data, attrs)
    params = surface_params(spec)

    def build(mask):
        return reconstruct(position[mask], data["velocity"][mask], volume[mask], params)

    field, mesh = build(np.ones(len(position), bool))
    spray = field.spray if field.spray is not None else np.zeros(len(position), bool)
    per_fluid = {}
    if spec.surface.per_fluid:
        for fi, f in enumerate(spec.fluids):
            mask = data["fluid"] == fi
            per_fluid[f.name] = build(mask)[1] if mask.any() else Mesh.empty()
    return field, mesh, per_fluid, spray


def ready(spec, paths) -> None:
    """The spray's VDB points need the sphshot-vdb-points tool (scripts/setup.sh builds it)."""
    if paths.spray_vdb and vdb_points_tool() is None:
        raise StageError("surface.spray and surface.grids: the spray's VDB points need sphshot-vdb-points, "
                         "which scripts/setup.sh builds (g++, libopenvdb-dev); run it, or set surface.grids = [] "
                         "or surface.spray = 0")


def run(spec, frames, paths, progress) -> None:
    ready(spec, paths)
    try:
        init_taichi(spec.sim.backend, spec.sim.threads)
    except BackendUnavailable as exc:
        raise StageError(str(exc)) from exc
    for frame in frames:
        # one function call a frame: its particles, fields and meshes are freed before the next
        progress.frame_done(frame, _write_frame(spec, frame, paths))


def _write_frame(spec, frame: int, paths) -> list:
    from surfacing import vdb     # pyopenvdb: only where grids are written

    src = paths.sim_frame(frame)
    try:
        data, attrs = read_frame(src)
    except OSError as exc:
        raise StageError(f"frame {frame:04d}: surfacing: cannot read {src}: {exc}") from exc
    try:
        with device_failures(f"frame {frame:04d}: surfacing", "the frames done are kept: run again for the rest"):
            field, mesh, per_fluid, spray = surface_frame(spec, data, attrs, frame)
    except SurfacingError as exc:
        raise StageError(f"frame {frame:04d}: surfacing: {exc}") from exc
    written = []
    if paths.vdb:
        grids = vdb.build_grids(field, mesh, frame, float(attrs.get("time", spec.frame_time(frame))),
                                spec.surface.half_width, extra_surfaces=per_fluid.items(),
                                which=spec.surface.grids)
        written.append(write_vdb(paths.surface_vdb(frame), grids))
    for key, path in paths.surface_meshes(frame).items():
        written.append(write_mesh(path, mesh if key is None else per_fluid[key], spec.surface.format))
    if paths.spray:
        points = (data["position"][spray], data["velocity"][spray],
                  float(attrs.get("particle_radius", spec.sim.particle_radius)), data["fluid"][spray])
        written.append(write_points(paths.surface_spray(frame), *points))
        if paths.spray_vdb:
            written.append(write_vdb_points(paths.surface_spray_vdb(frame), *points))
    return written
