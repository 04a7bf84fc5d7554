"""Executors decide where stage tasks run. Serial runs them here, in order."""
from __future__ import annotations

from .progress import Progress
from .stages import Stage


class SerialExecutor:
    name = "serial"

    def run_stage(self, stage: Stage, spec, frames: list[int], paths, progress: Progress) -> None:
        stage.run(spec, frames, paths, progress)

    def close(self) -> None:
        pass


def make_executor(kind: str, workers: int = 0, scheduler: str | None = None):
    if kind == "serial":
        return SerialExecutor()
    if kind == "dask":
        from .dask_executor import DaskExecutor
        return DaskExecutor(workers=workers, scheduler=scheduler)
    raise ValueError(kind)
