"""The stage contract and registry.

A stage is a function ``run(spec, frames, paths, progress)`` that reads the previous stage's
per-frame files through `paths`, publishes its own files atomically, and calls
``progress.frame_done(frame, files)`` once per finished frame. Per-frame stages (surface,
render) can be handed any subset of frames in any chunking, which is what the executors do;
the sim stage is sequential and is always run as one task.

Implementations are imported lazily so that `sphshot validate` and `status` stay light.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Callable


@dataclass(frozen=True)
class Stage:
    name: str
    module: str            # module holding run(spec, frames, paths, progress) and maybe finalize()
    per_frame: bool        # frames are independent of each other (can fan out)

    def _mod(self):
        return importlib.import_module(self.module)

    @property
    def run(self) -> Callable:
        return self._mod().run

    @property
    def finalize(self) -> Callable | None:
        """Optional step after every frame of the shot is valid (movie, contact sheet)."""
        return getattr(self._mod(), "finalize", None)


STAGE_IMPLS = {
    "sim": Stage("sim", "solver.stage", per_frame=False),
    "surface": Stage("surface", "surfacing.stage", per_frame=True),
    "render": Stage("render", "pipeline.render", per_frame=True),
}
