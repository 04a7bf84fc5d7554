"""Run stages over frames: decide what is valid, stale or missing, and refuse to mix."""
from __future__ import annotations

from . import cache
from .cache import ShotPaths
from .errors import StageError, StaleCacheError, WaitingOnUpstream
from .frames import format_frames
from .progress import Progress
from .spec import ShotSpec
from .stages import STAGE_IMPLS


def plan_stage(sc: cache.StageScan, paths: ShotPaths, frames: list[int], force: bool) -> list[int]:
    """Frames the stage must compute; raises StaleCacheError when it would mix parameters."""
    stage = sc.stage
    if sc.stale and not force:
        raise StaleCacheError(
            f"{stage}: frame(s) {format_frames(sc.stale)} in {paths.stage_dir(stage)} were made with "
            f"other parameters; rerun with --stage {stage} --force to recompute them, or raise "
            f"shot.version to keep both")
    if force:
        return list(frames)
    return list(sc.missing)


def check_upstream(spec: ShotSpec, paths: ShotPaths, stage: str, frames: list[int]) -> None:
    up = cache.UPSTREAM[stage]
    if up is None or not frames:
        return
    sc = cache.scan(spec, paths, up, frames)
    if sc.stale:
        raise StaleCacheError(
            f"{stage}: {up} frame(s) {format_frames(sc.stale)} were made with other parameters; "
            f"rerun the {up} stage with --force first")
    if sc.missing:
        raise WaitingOnUpstream(
            f"{stage}: waiting on {up} frame {sc.missing[0]} ({len(sc.missing)} {up} frame(s) "
            f"missing: {format_frames(sc.missing)}); run --stage {up} first")


def run_stages(spec: ShotSpec, stages: list[str], frames: list[int], *, force: bool = False,
               executor=None, progress: Progress | None = None) -> None:
    from .executor import SerialExecutor

    executor = executor or SerialExecutor()
    progress = progress or Progress()
    paths = ShotPaths.for_spec(spec)
    for stage in stages:
        impl = STAGE_IMPLS[stage]
        for folder in (paths.stage_dir(stage), paths.checkpoint_dir, paths.root):
            cache.remove_dead_temporaries(folder)
        sc = cache.scan(spec, paths, stage, frames)
        todo = plan_stage(sc, paths, frames, force)
        check_upstream(spec, paths, stage, todo)
        if force and (sc.hash_changed or sc.stale):
            cache.clear_stage(paths, stage)
        cache.record_stage(spec, paths, stage)
        if todo:
            progress.start(stage, len(todo))
            try:
                executor.run_stage(impl, spec, todo, paths, progress)
            finally:
                progress.finish()
        else:
            progress.line(f"sphshot: {stage}: all {len(frames)} frame(s) valid, nothing to do")
        after = cache.scan(spec, paths, stage, frames)
        if after.missing or after.stale:
            bad = after.missing + after.stale
            raise StageError(f"{stage}: frame(s) {format_frames(bad)} not valid on disk after the run")
        if impl.finalize is not None and not cache.scan(spec, paths, stage, spec.frames).missing:
            for path in impl.finalize(spec, paths, force=force or bool(todo)):
                progress.file_written(path)
