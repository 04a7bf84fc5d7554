"""What a stage is, said once: the cache, runner, executors, CLI and exports all read STAGES.

A stage's module holds ``run(spec, frames, paths, progress)``, which reads the upstream stage's
per-frame files through `paths`, publishes its own files atomically and calls
``progress.frame_done(frame, files)`` once per finished frame, and optionally
``ready(spec, paths)``, which raises StageError where the stage could not run here (checked
before any stage of a run starts), and ``finalize(spec, paths, force)`` (movie, contact sheet)
once every frame of the shot is valid.
Per-frame stages (surface, render) can be handed any subset of frames in any chunking, which
is what the executors do; the sim is sequential and always runs as one task.

Stage modules are imported lazily, so that `sphshot validate` and `status` stay light.
"""
from __future__ import annotations

import contextlib
import importlib
import logging
from dataclasses import dataclass
from typing import Any, Callable

from ..errors import DeviceFailed

log = logging.getLogger("sphshot")


@dataclass(frozen=True)
class Stage:
    name: str
    upstream: str | None        # the stage whose per-frame files this one reads
    module: str                 # holds run() and maybe finalize()
    per_frame: bool             # frames are independent of each other (can fan out)
    frame_files: Callable       # (paths, frame) -> every file the stage owns for that frame
    hashed: Callable            # spec -> the spec sections its output depends on
    format_version: int         # bump when the files or the algorithm change incompatibly

    def _mod(self):
        return importlib.import_module(self.module)

    @property
    def run(self) -> Callable:
        return self._mod().run

    @property
    def ready(self) -> Callable | None:
        """Optional check that the stage can run on this machine, before anything runs."""
        return getattr(self._mod(), "ready", None)

    @property
    def finalize(self) -> Callable | None:
        """Optional step after every frame of the shot is valid (movie, contact sheet)."""
        return getattr(self._mod(), "finalize", None)


def device_failed(exc: BaseException, where: str, then: str) -> DeviceFailed | None:
    """A failure of the compute device (out of device memory, a GPU lost or reset, a driver's
    error: solver.backend.device_failure) as one DeviceFailed line naming `where`, the device and
    what it said, then `then` and the other way out (another device); the traceback goes to the
    debug log (SPHSHOT_LOG=DEBUG). None for any other exception."""
    if not isinstance(exc, RuntimeError):
        return None
    from solver.backend import current_arch, device_failure

    what = device_failure(exc)
    if what is None:
        return None
    log.debug("%s: the device's error", where, exc_info=exc)
    return DeviceFailed(f"{where}: the {current_arch()} device failed: {what}; {then}, "
                        f'or run on another device (sim.backend = "cpu")')


@contextlib.contextmanager
def device_failures(where: str, then: str):
    """device_failed() for the block: a device's failure raised as DeviceFailed."""
    try:
        yield
    except RuntimeError as exc:
        failure = device_failed(exc, where, then)
        if failure is None:
            raise
        raise failure from exc


def _sim_sections(spec) -> dict[str, Any]:
    """What the particles depend on. Fluids' and colliders' colors (and a fluid's transmission
    depth) are the render's (a color changed after the sim re-renders; until 2026-11-26 it made
    the whole sim stale)."""
    return {"shot": {"frame_start": spec.shot.frame_start, "fps": spec.shot.fps},
            "sim": spec.sim.model_dump(exclude={"backend", "threads"}),
            "domain": spec.domain.model_dump(),
            "fluids": [f.model_dump(exclude={"color", "transmission_depth"}) for f in spec.fluids],
            "colliders": [c.model_dump(exclude={"color"}) for c in spec.colliders],
            "meshes": spec.mesh_hashes()}


def _render_sections(spec) -> dict[str, Any]:
    """What the images depend on beside the surface; a fluid's transmission depth only where
    one is set (so the renders of shots without one stay valid)."""
    colors = {"fluids": [f.color for f in spec.fluids], "colliders": [c.color for c in spec.colliders]}
    if any(f.transmission_depth is not None for f in spec.fluids):
        colors["transmission_depth"] = [f.transmission_depth for f in spec.fluids]
    return {"render": spec.render.model_dump(), "colors": colors}


def _surface_files(paths, frame: int) -> list:
    return (([paths.surface_vdb(frame)] if paths.vdb else []) + list(paths.surface_meshes(frame).values())
            + ([paths.surface_spray(frame)] if paths.spray else [])
            + ([paths.surface_spray_vdb(frame)] if paths.spray_vdb else []))


STAGES: dict[str, Stage] = {s.name: s for s in (
    Stage("sim", None, "pipeline.stages.sim", per_frame=False,
          frame_files=lambda paths, frame: [paths.sim_frame(frame)],
          hashed=_sim_sections, format_version=3),
    Stage("surface", "sim", "pipeline.stages.surface", per_frame=True,
          frame_files=_surface_files,
          hashed=lambda spec: {"surface": spec.surface.model_dump()}, format_version=4),   # 3: spray file; 4: cube-root vertices
    Stage("render", "surface", "pipeline.stages.render", per_frame=True,
          frame_files=lambda paths, frame: [paths.render_frame(frame)],
          hashed=_render_sections, format_version=1),
)}
"""The stages in the order they run; each one's upstream comes before it."""

