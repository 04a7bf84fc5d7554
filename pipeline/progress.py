"""Progress for people and for farm managers.

On a terminal: a rich progress bar. Otherwise plain lines that farm managers parse:
``ALF_PROGRESS nn%`` (Tractor/Deadline style) and one ``OUTPUT_FILE:<path>;`` per file written.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path


class Progress:
    def __init__(self, stream=None, interactive: bool | None = None):
        self.stream = stream or sys.stdout
        self.interactive = self.stream.isatty() if interactive is None else interactive
        self._bar = None
        self._task = None
        self._total = 0
        self._done = 0
        self._stage = ""
        self._last_pct = -1
        self._t0 = 0.0

    # --------------------------------------------------------------------------- stage scope
    def start(self, stage: str, total: int) -> None:
        self._stage, self._total, self._done, self._last_pct = stage, total, 0, -1
        self._t0 = time.perf_counter()
        if self.interactive:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress as Bar, TimeRemainingColumn
            self._bar = Bar("[bold]{task.description}", BarColumn(), MofNCompleteColumn(),
                            TimeRemainingColumn(), transient=False)
            self._bar.start()
            self._task = self._bar.add_task(stage, total=total)
        else:
            self.line(f"sphshot: {stage}: {total} frame(s) to do")
            self._percent()

    def frame_done(self, frame: int, files: list[Path] = ()) -> None:
        self._done += 1
        if self._bar is not None:
            self._bar.update(self._task, advance=1, description=f"{self._stage} {frame:04d}")
        else:
            for f in files:
                self.line(f"OUTPUT_FILE:{f};")
            self._percent()

    def finish(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None
        dt = time.perf_counter() - self._t0
        self.line(f"sphshot: {self._stage}: {self._done} frame(s) in {dt:.1f} s")

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
        pct = int(100 * self._done / self._total) if self._total else 100
        if pct != self._last_pct:
            self._last_pct = pct
            print(f"ALF_PROGRESS {pct}%", file=self.stream, flush=True)
