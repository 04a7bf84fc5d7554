"""The surface stage: one .vdb and one mesh (or one per fluid) per sim frame."""
from __future__ import annotations

import logging

import numpy as np

from pipeline.cache import atomic_path
from pipeline.errors import StageError
from pipeline.particles import read_frame

log = logging.getLogger("sphshot")


def surface_frame(spec, data: dict, attrs: dict, frame: int):
    """Build (field, mesh, {fluid: mesh}) for one frame of particles."""
    from .reconstruct import Mesh, colour_field, particle_volumes, surface_mesh

    pos = data["position"]
    if len(pos) == 0:
        log.warning("frame %04d: surfacing: no particles; writing an empty mesh and empty grids", frame)
        return None, Mesh.empty(), {f.name: Mesh.empty() for f in spec.fluids}
    vol = particle_volumes(data, attrs)
    cell, support, s = spec.surface_cell, spec.surface_support, spec.surface

    def build(mask):
        field = colour_field(pos[mask], data["velocity"][mask], vol[mask], cell, support, s.iso, s.kernel)
        mesh = surface_mesh(field, s.iso, s.smoothing_iterations, s.decimate)
        return field, mesh

    field, mesh = build(np.ones(len(pos), bool))
    per_fluid = {}
    if s.per_fluid:
        for fi, f in enumerate(spec.fluids):
            mask = data["fluid"] == fi
            per_fluid[f.name] = build(mask)[1] if mask.any() else Mesh.empty()
    return field, mesh, per_fluid


def run(spec, frames, paths, progress) -> None:
    from solver.backend import BackendUnavailable, init_taichi

    try:
        init_taichi(spec.sim.backend, spec.sim.threads)
    except BackendUnavailable as exc:
        raise StageError(str(exc)) from None
    for frame in frames:
        # one function call a frame: its particles, fields and meshes are freed before the next
        progress.frame_done(frame, _write_frame(spec, frame, paths))


def _write_frame(spec, frame: int, paths) -> list:
    from . import vdb
    from .reconstruct import GridTooLarge, write_mesh

    src = paths.sim_frame(frame)
    try:
        data, attrs = read_frame(src)
    except OSError as exc:
        raise StageError(f"frame {frame:04d}: surfacing: cannot read {src}: {exc}") from None
    try:
        field, mesh, per_fluid = surface_frame(spec, data, attrs, frame)
    except GridTooLarge as exc:
        raise StageError(f"frame {frame:04d}: surfacing: {exc}") from None
    written = []
    if paths.vdb:
        grids = vdb.build_grids(field, mesh, frame, float(attrs.get("time", spec.frame_time(frame))),
                                spec.surface.half_width, extra_surfaces=per_fluid.items(),
                                which=spec.surface.grids)
        with atomic_path(paths.surface_vdb(frame)) as tmp:
            vdb.write(tmp, grids)
        written.append(paths.surface_vdb(frame))
    for key, path in paths.surface_meshes(frame).items():
        with atomic_path(path) as tmp:
            write_mesh(tmp, mesh if key is None else per_fluid[key], spec.surface.format)
        written.append(path)
    return written
