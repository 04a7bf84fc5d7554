"""Progress for people and for farm managers.

On a terminal: a rich progress bar per stage. Otherwise plain lines that farm managers parse:
``ALF_PROGRESS nn%`` (Tractor/Deadline style, over every frame of every stage in the run) and
one ``OUTPUT_FILE:<path>;`` per file written.

Stages may run at the same time (the Dask executor streams sim -> surface -> render), so a
frame is reported with its stage. A stage's ``run()`` gets a :class:`StageProgress`, which
only knows ``frame_done(frame, files)``.
"""
from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path


class Progress:
    def __init__(self, stream=None, interactive: bool | None = None):
        self.stream = stream or sys.stdout
        self.interactive = self.stream.isatty() if interactive is None else interactive
        self._lock = threading.Lock()
        self._bar = None
        self._tasks: dict[str, int] = {}
        self._totals: dict[str, int] = {}
        self._done: dict[str, int] = {}
        self._found: dict[str, int] = {}        # frames found valid already (no file written)
        self._last: dict[str, float] = {}
        self._start: dict[str, float] = {}
        self._last_pct = -1
        self._t0 = 0.0

    # ------------------------------------------------------------------------------ run scope
    def begin(self, totals: dict[str, int]) -> None:
        """Start reporting; `totals` maps each stage with work to its frame count, in order."""
        self._totals = {s: n for s, n in totals.items() if n}
        self._done = {s: 0 for s in self._totals}
        self._found = {s: 0 for s in self._totals}
        self._last_pct = -1
        self._t0 = time.perf_counter()
        self._last = {s: self._t0 for s in self._totals}
        self._start = {}
        if not self._totals:
            return
        if self.interactive:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress as Bar, TimeRemainingColumn
            self._bar = Bar("[bold]{task.description:>12}", BarColumn(), MofNCompleteColumn(),
                            TimeRemainingColumn(), transient=False)
            self._bar.start()
            self._tasks = {s: self._bar.add_task(s, total=n) for s, n in self._totals.items()}
        else:
            for stage, n in self._totals.items():
                self.line(f"sphshot: {stage}: {n} frame(s) to do")
            self._percent()

    def frame_done(self, stage: str, frame: int, files=()) -> None:
        """A frame of the stage is valid on disk: `files` written here, or none when it was
        found valid (another worker's, or its upstream frame came out the same bytes)."""
        with self._lock:
            self._done[stage] = self._done.get(stage, 0) + 1
            if not files:
                self._found[stage] = self._found.get(stage, 0) + 1
            self._last[stage] = time.perf_counter()
            if self._bar is not None:
                self._bar.update(self._tasks[stage], advance=1, description=f"{stage} {frame:04d}")
            else:
                for f in files:
                    self.line(f"OUTPUT_FILE:{f};")
                self._percent()

    def end(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None
        now = time.perf_counter()
        for stage in self._totals:
            # from the stage's start (streamed Dask stages: from the run's, as they overlap it)
            # to its last frame, or to now when it finished none (it failed, or never started)
            last = self._last[stage] if self._done[stage] else now
            dt = max(0.0, last - self._start.get(stage, self._t0))
            found = self._found.get(stage, 0)
            self.line(f"sphshot: {stage}: {self._done[stage]} frame(s) in {dt:.1f} s"
                      + (f" ({found} found valid already)" if found else ""))
        self._totals = {}

    def for_stage(self, stage: str) -> "StageProgress":
        """The progress of one stage, which starts now (its time is counted from here)."""
        self._start.setdefault(stage, time.perf_counter())
        return StageProgress(self, stage)

    def file_written(self, path: Path) -> None:
        if not self.interactive:
            self.line(f"OUTPUT_FILE:{path};")

    # --------------------------------------------------------------------------------- lines
    def line(self, text: str) -> None:
        if self._bar is not None:
            self._bar.console.print(text, markup=False, highlight=False)
        else:
            print(text, file=self.stream, flush=True)

    def _percent(self) -> None:
        total = sum(self._totals.values())
        pct = int(100 * sum(self._done.values()) / total) if total else 100
        if pct != self._last_pct:
            self._last_pct = pct
            print(f"ALF_PROGRESS {pct}%", file=self.stream, flush=True)


@dataclass(frozen=True)
class StageProgress:
    """What a stage reports through: one call per published frame."""
    progress: Progress
    stage: str

    def frame_done(self, frame: int, files=()) -> None:
        self.progress.frame_done(self.stage, frame, files)


class Collect:
    """A stage progress that records frames (on a Dask worker; the client reports them)."""

    def __init__(self):
        self.frames: list[tuple[int, tuple[str, ...]]] = []

    def frame_done(self, frame: int, files=()) -> None:
        self.frames.append((frame, tuple(str(f) for f in files)))
