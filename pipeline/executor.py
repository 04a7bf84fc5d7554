"""Executors decide where stage tasks run.

- :class:`SerialExecutor` runs the stages here, one after the other.
- :class:`DaskExecutor` runs the sim here (it is one sequential task; on a GPU node) and fans
  per-frame surface and render tasks out over a Dask cluster, *streaming*: the surface task
  of frame N is submitted the moment sim frame N is published, and the render task of frame N
  waits on that surface task alone, so surfacing and rendering overlap the simulation.

Either way a stage task is :func:`run_here`: the stage's own ``run()`` over a chunk of frames,
under claims (claims.py), so tasks that overlap with other workers on the same shot folder
never compute a frame twice.
"""
from __future__ import annotations

import logging
import os
import uuid
from pathlib import Path
from dataclasses import dataclass

from .cache import stage_hashes, stamp, stamp_path, stamped_digests
from .claims import FrameClaims, read_owner, release, try_claim
from .errors import Busy, DeviceFailed, Interrupted, SphshotError, StageError
from .frames import format_frames
from .progress import Collect, Progress
from .stages import STAGES

log = logging.getLogger("sphshot")


@dataclass(frozen=True)
class StagePlan:
    """What one stage must compute in this run."""
    name: str
    todo: tuple[int, ...]


# ------------------------------------------------------------------------- one task, here
class _Stamping:
    """Stamps each finished frame's files (cache.stamp) before reporting the frame, and removes
    what the frame held from other settings of its stage (ShotPaths.frame_leftovers)."""

    def __init__(self, progress, stage: str, stage_hash: str, paths):
        self.progress, self.stage, self.stage_hash, self.paths = progress, stage, stage_hash, paths

    def frame_done(self, frame: int, files=()) -> None:
        up = STAGES[self.stage].upstream
        inputs = stamped_digests(self.paths.frame_files(up, frame)) if up and files else None
        for f in files:
            stamp(Path(f), self.stage_hash, inputs)
        if files:
            for old in self.paths.frame_leftovers(self.stage, frame):
                for p in (old, stamp_path(old)):
                    p.unlink(missing_ok=True)
        self.progress.frame_done(frame, files)


def run_here(stage: str, spec, frames, paths, progress, since: float | None = None) -> None:
    """Run `stage` over `frames` in this process. `progress` has ``frame_done(frame, files)``.

    Per-frame stages skip frames another worker holds and then wait for them (taking over any
    whose worker died); the sequential sim holds one claim on the whole stage.
    """
    impl = STAGES[stage]
    progress = _Stamping(progress, stage, stage_hashes(spec)[stage], paths)
    if not impl.per_frame:
        claim = paths.claim(stage, None)
        if not try_claim(claim):
            owner = read_owner(claim)
            raise Busy(f"{stage}: another worker ({owner or 'unknown'}) is running this shot's {stage}; "
                       f"retry when it ends")
        try:
            impl.run(spec, list(frames), paths, progress)
        finally:
            release(claim)
        return
    todo = list(frames)
    while todo:
        with FrameClaims(paths, stage, todo, since, progress.stage_hash) as claims:
            impl.run(spec, claims, paths, progress)
            todo = claims.wait_for_others()
        for frame in claims.by_others:
            progress.frame_done(frame, [])


# ------------------------------------------------------------------------------- serial
class SerialExecutor:
    name = "serial"

    def run(self, spec, paths, plans: list[StagePlan], progress: Progress, since=None) -> None:
        for plan in plans:
            if plan.todo:
                run_here(plan.name, spec, plan.todo, paths, progress.for_stage(plan.name), since)

    def close(self) -> None:
        pass


# --------------------------------------------------------------------------------- dask
@dataclass(frozen=True)
class TaskResult:
    """What a Dask task sends back: the frames it published, or why it failed."""
    stage: str
    frames: tuple[int, ...]
    published: tuple[tuple[int, tuple[str, ...]], ...] = ()
    error: str | None = None


def frame_task(stage: str, spec, frames, paths, since, after: "TaskResult | None" = None) -> TaskResult:
    """A Dask task: run a stage over frames on the worker. Failures come back as results, not
    exceptions, so Dask does not retry a frame that would fail the same way again; exceptions
    that escape (a lost worker, a crash, the worker's device failing: DeviceFailed) are retried
    by Dask."""
    if after is not None and after.error is not None:
        return TaskResult(stage, tuple(frames),
                          error=f"not run: {after.stage} frame(s) {format_frames(after.frames)} failed")
    collect = Collect()
    try:
        run_here(stage, spec, frames, paths, collect, since)
    except DeviceFailed:
        raise                # the worker's device, not the frame: Dask retries it, on another worker
    except SphshotError as exc:
        return TaskResult(stage, tuple(frames), tuple(collect.frames), error=str(exc))
    return TaskResult(stage, tuple(frames), tuple(collect.frames))


class DaskExecutor:
    """Per-frame tasks on a Dask cluster: an embedded LocalCluster, or `scheduler`'s."""
    name = "dask"

    def __init__(self, scheduler: str | None = None, workers: int | None = None, retries: int = 2):
        from dask.distributed import Client, LocalCluster

        from solver.backend import allowed_cpus

        from .workers import PinToShare, QuietLogs, cpu_shares, set_distributed_log_level

        # Dask logs every connection at INFO
        set_distributed_log_level(max(logging.WARNING, log.getEffectiveLevel()))
        self.retries = retries
        self.cluster = None
        if scheduler:
            try:
                self.client = Client(scheduler, timeout="10s")
            except (OSError, TimeoutError) as exc:
                raise StageError(f"--scheduler: cannot reach the Dask scheduler at {scheduler} ({exc})") from None
        else:
            cpus = allowed_cpus()
            n = workers or len(cpus)
            # Processes with one Dask thread each; Taichi, llvmpipe and OpenVDB's TBB inside a
            # worker use its share of the cores and no more (PinToShare), so n workers use the
            # cores once, not n times over.
            self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                        dashboard_address=None, scheduler_kwargs={"dashboard": False},
                                        silence_logs=logging.ERROR)
            self.client = Client(self.cluster)
            self.client.register_plugin(QuietLogs(), name="sphshot-quiet")
            if hasattr(os, "sched_setaffinity"):
                self.client.register_plugin(PinToShare(cpu_shares(cpus, n)), name="sphshot-pin")
        log.info("dask: %s, %d worker(s)", scheduler or "local cluster",
                 len(self.client.scheduler_info().get("workers", {})))

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()

    def run(self, spec, paths, plans: list[StagePlan], progress: Progress, since=None) -> None:
        from dask.distributed import as_completed

        order = [p.name for p in plans]
        todo = {p.name: set(p.todo) for p in plans}
        run_id = uuid.uuid4().hex[:8]
        futures: dict[tuple[str, int], object] = {}     # every task of the run
        pending: dict[str, tuple[str, int]] = {}        # future key -> (stage, frame), not harvested
        failures: list[str] = []

        def submit(frame: int, stages: list[str]) -> None:
            """Submit the per-frame tasks of one frame, each waiting on the one before it."""
            for stage in stages:
                if frame not in todo[stage]:
                    continue
                i = order.index(stage)
                after = futures.get((order[i - 1], frame)) if i > 0 else None
                fut = self.client.submit(frame_task, stage, spec, [frame], paths, since, after,
                                         key=f"{stage}-{frame:04d}-{run_id}", retries=self.retries)
                futures[(stage, frame)] = fut
                pending[fut.key] = (stage, frame)

        def handle(fut) -> None:
            stage, frame = pending.pop(fut.key)
            if fut.status == "finished":
                res: TaskResult = fut.result()
                for f, files in res.published:
                    progress.frame_done(res.stage, f, files)
                if res.error:
                    failures.append(f"{stage} frame {frame}: {res.error}")
            else:
                exc = fut.exception()
                failures.append(f"{stage} frame {frame}: {type(exc).__name__}: {exc}")

        def harvest() -> None:
            for fut in [futures[sf] for sf in pending.values()]:
                if fut.done():
                    handle(fut)

        sim = plans[0] if plans and not STAGES[plans[0].name].per_frame else None
        per_frame = [name for name in order if STAGES[name].per_frame]
        streamed = set(sim.todo) if sim else set()
        for frame in sorted(set().union(*todo.values()) - streamed):   # inputs already on disk
            submit(frame, per_frame)
        error: SphshotError | None = None
        if sim is not None and sim.todo:
            sim_progress = progress.for_stage(sim.name)

            class Streaming:
                """The sim's progress: each published frame releases that frame's tasks."""
                def frame_done(self, frame, files=()):
                    sim_progress.frame_done(frame, files)
                    submit(frame, per_frame)
                    harvest()

            try:
                run_here(sim.name, spec, sim.todo, paths, Streaming(), since)
            except Interrupted:
                self.client.cancel(list(futures.values()))
                raise
            except SphshotError as exc:
                error = exc                    # the frames published before it still finish
        for fut in as_completed([futures[sf] for sf in pending.values()]):
            handle(fut)
        if error is not None:
            raise error
        if failures:
            raise StageError("\n".join(f"failed: {line}" for line in sorted(failures)))


def make_executor(kind: str, scheduler: str | None = None, workers: int | None = None):
    if kind == "serial":
        return SerialExecutor()
    if kind == "dask":
        return DaskExecutor(scheduler=scheduler, workers=workers)
    raise ValueError(f"unknown executor {kind!r}")
