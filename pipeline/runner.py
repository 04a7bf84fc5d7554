"""Run stages over frames: decide what is valid, stale or missing, refuse to mix, then hand
the work to an executor and check that every requested frame is valid on disk afterwards."""
from __future__ import annotations

import time

from . import cache, claims
from .cache import ShotCache, ShotPaths
from .errors import StageError, StaleCacheError, WaitingOnUpstream
from .executor import SerialExecutor, StagePlan
from .frames import format_frames
from .progress import Progress
from .spec import ShotSpec
from .stages import STAGES


def _since(stage: str) -> str:
    up = STAGES[stage].upstream
    return f" (or from {up} frames computed again since)" if up else ""


def plan_stage(sc: cache.StageScan, paths: ShotPaths, frames: list[int], force: bool) -> list[int]:
    """Frames the stage must compute; raises StaleCacheError when it would mix parameters."""
    stage = sc.stage
    if sc.stale and not force:
        raise StaleCacheError(
            f"{stage}: frame(s) {format_frames(sc.stale)} in {paths.stage_dir(stage)} were made with "
            f"other parameters{_since(stage)}; rerun with --stage {stage} --force to recompute them, or raise "
            f"shot.version to keep both")
    if force:
        return list(frames)
    return sorted(sc.missing + sc.corrupt)          # corrupt frames are computed again


def check_upstream(shot: ShotCache, stage: str, frames: list[int]) -> None:
    up = STAGES[stage].upstream
    if up is None or not frames:
        return
    sc = shot.scan(up, frames)
    if sc.corrupt:
        raise StageError(
            f"{stage}: {up} frame(s) {format_frames(sc.corrupt)} are corrupt (not the files that were "
            f"written: truncated or changed since); run --stage {up} to compute them again")
    if sc.stale:
        raise StaleCacheError(
            f"{stage}: {up} frame(s) {format_frames(sc.stale)} were made with other parameters; "
            f"rerun the {up} stage with --force first")
    if sc.missing:
        raise WaitingOnUpstream(
            f"{stage}: waiting on {up} frame {sc.missing[0]} ({len(sc.missing)} {up} frame(s) "
            f"missing: {format_frames(sc.missing)}); run --stage {up} first")


def plan_run(shot: ShotCache, stages: list[str], frames: list[int], force: bool) -> list[StagePlan]:
    """Scan and plan every stage before any work starts, so a stale cache refuses up front.

    Only the first stage's upstream must already be on disk: the frames of later stages'
    upstreams are either valid or computed earlier in this same run.
    """
    paths = shot.paths
    plans = []
    for i, stage in enumerate(stages):
        for folder in (paths.stage_dir(stage), paths.checkpoint_dir, paths.root):
            cache.remove_dead_temporaries(folder)
        claims.remove_dead_claims(paths.stage_dir(stage))
        sc = shot.scan(stage, frames)
        todo = plan_stage(sc, paths, frames, force)
        if plans and STAGES[stage].per_frame:   # frames whose upstream this run computes again
            todo = sorted(set(todo) | (set(plans[-1].todo) & set(frames)))
        if i == 0:
            check_upstream(shot, stage, todo)
        if force and stage == "sim" and (sc.hash_changed or sc.stale):
            cache.clear_checkpoints(paths)
        shot.record(stage)
        plans.append(StagePlan(stage, tuple(todo)))
    return plans


def run_stages(spec: ShotSpec, stages: list[str], frames: list[int], *, force: bool = False,
               executor=None, progress: Progress | None = None) -> None:
    executor = executor or SerialExecutor()
    progress = progress or Progress()
    shot = ShotCache(spec)
    made = cache.first_missing(shot.paths.root)
    try:
        with claims.VersionRun(shot.paths.root, {s: shot.hashes[s] for s in stages}):
            _run(spec, shot, stages, frames, force, executor, progress)
    except BaseException:
        if made is not None:    # a failed first run leaves no empty folders behind
            cache.remove_if_empty(shot.paths, made)
        raise


def _run(spec: ShotSpec, shot: ShotCache, stages: list[str], frames: list[int], force: bool, executor,
         progress: Progress) -> None:
    plans = plan_run(shot, stages, frames, force)
    for plan in plans:
        if not plan.todo:
            progress.line(f"sphshot: {plan.name}: all {len(frames)} frame(s) valid, nothing to do")
    for plan in plans:                          # a stage that cannot run here stops the run before it starts
        ready = STAGES[plan.name].ready
        if plan.todo and ready is not None:
            ready(spec, shot.paths)
    since = time.time() if force else None     # with --force only files newer than this count
    progress.begin({p.name: len(p.todo) for p in plans})
    try:
        executor.run(spec, shot.paths, plans, progress, since)
    finally:
        progress.end()
    for plan in plans:
        stage = STAGES[plan.name]
        after = shot.scan(plan.name, frames)
        if not after.complete:
            bad = sorted(after.missing + after.stale + after.corrupt)
            raise StageError(f"{plan.name}: frame(s) {format_frames(bad)} not valid on disk after the run")
        if stage.finalize is None:
            continue
        whole = shot.scan(plan.name, spec.frames)
        if whole.complete:
            for path in stage.finalize(spec, shot.paths, force=force or bool(plan.todo)):
                progress.file_written(path)
        elif not whole.missing:       # every frame there, some made otherwise: no mixed movie
            bad = sorted(whole.stale + whole.corrupt)
            progress.line(f"sphshot: {plan.name}: the shot's frame(s) {format_frames(bad)} were made with other "
                          f"parameters (or are corrupt): no movie or contact sheet until they are computed again")
