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


def make_executor(kind: str):
    """The executor for `kind`; only "serial" exists so far (Dask fan-out is issue 6)."""
    if kind == "serial":
        return SerialExecutor()
    raise ValueError(f"unknown executor {kind!r}")
