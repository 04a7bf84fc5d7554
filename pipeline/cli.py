"""`sphshot` command line: parse, validate, dispatch. Every stage is callable without it."""
from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from pathlib import Path

from . import errors
from .errors import SphshotError, UsageError
from .stages import STAGES

EPILOG = f"""\
exit codes:
  {errors.EXIT_OK}  every requested frame is valid on disk
  {errors.EXIT_FAILURE}  runtime failure (unstable solver, failed frame, I/O error)
  {errors.EXIT_USAGE}  bad job file, --set, frame range or arguments, or a shot estimated to need more memory
     or disk than there is (see validate); nothing was written
  {errors.EXIT_STALE}  cached frames were made with other parameters (use --force or a new shot.version)
  {errors.EXIT_WAITING}  waiting on an upstream frame (sim frame N) or on another worker's sim; retry later
  {errors.EXIT_INTERRUPTED}  interrupted (SIGTERM/SIGUSR1/SIGINT) after a checkpoint; run again to resume
  {errors.EXIT_DEVICE}  the compute device failed (GPU out of memory, reset, driver); the frames before it are
     kept: retry, on another node or with sim.backend = "cpu"
"""

STAGE_CHOICES = (*STAGES, *(f"{s}+" for s in list(STAGES)[1:-1]), "all")


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, no usage dump, exit 2 through the normal path
        raise UsageError(message)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="sphshot", description="Headless SPH fluid shots: sim -> surface -> render.",
                epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"sphshot {_version()}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    def max_memory(sp):
        sp.add_argument("--max-memory", type=_gigabytes, metavar="GB",
                        help="the memory the shot may use (default: what this machine has available "
                             "now); a shot estimated to need more stops before anything is allocated")

    def common(sp):
        sp.add_argument("job", help="shot job file (TOML)")
        sp.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a job key with a TOML value, e.g. --set sim.particle_radius=0.02")

    v = sub.add_parser("validate", help="check a job file and that the shot fits this machine; print one "
                                         "line per problem and the memory and disk estimate",
                       epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    common(v)
    max_memory(v)

    r = sub.add_parser("run", help="run stages over frames, skipping frames already valid",
                       epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    common(r)
    r.add_argument("--stage", choices=STAGE_CHOICES, default="all",
                   help="one stage, all, or S+ for stage S and every stage after it (with --force: "
                        "recompute surface and render after a surface change in one command)")
    r.add_argument("--frames", help="A, A-B or A-BxSTEP (default: the whole shot)")
    r.add_argument("--chunk", type=_positive, metavar="N",
                   help="run N frames from the start frame given by --frames, CUE_IFRAME or "
                        "SLURM_ARRAY_TASK_ID (farm array tasks)")
    r.add_argument("--force", action="store_true", help="recompute frames even when valid")
    max_memory(r)
    r.add_argument("--executor", choices=("serial", "dask"), default="serial",
                   help="serial: stage after stage here; dask: surface and render tasks fan out over "
                        "a Dask cluster, streaming behind the sim (default: serial)")
    r.add_argument("--scheduler", metavar="ADDRESS",
                   help="with --executor dask: an existing scheduler (tcp://host:8786) instead of a "
                        "local cluster")
    r.add_argument("--workers", type=_positive, metavar="N",
                   help="with --executor dask and no --scheduler: local worker processes "
                        "(default: one per core this process may use, each bound to its share)")

    e = sub.add_parser("export", help="write a farm job (SLURM, OpenCue, OpenJD) that runs this shot",
                       epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    common(e)
    e.add_argument("--to", choices=("slurm", "opencue", "openjd"), required=True)
    e.add_argument("--chunk", type=_positive, default=4, metavar="N",
                   help="frames per surface/render task (default: 4)")
    e.add_argument("--show", help="OpenCue show (default: sphshot)")
    e.add_argument("--service", help="OpenCue service of every layer (default: shell)")
    e.add_argument("--cpus", type=_positive, metavar="N", help="SLURM: CPUs per task")
    e.add_argument("--mem", type=_gigabytes, metavar="GB",
                   help="memory per task (default: each stage's pre-flight estimate, in 256 MB steps)")
    e.add_argument("--time", metavar="D-HH:MM:SS", help="SLURM: time limit per task")
    e.add_argument("--gpus", type=_positive, metavar="N", help="SLURM: GPUs for the sim task")
    e.add_argument("-o", "--output", metavar="FILE",
                   help="where to write it (default: <shot folder>/farm/<name>.<slurm.sh|cue.xml|openjd.json>)")

    k = sub.add_parser("clean", help="remove a stage's frames: all of them, or with --stale those made with "
                                      "other parameters or corrupt; says what it removes")
    common(k)
    k.add_argument("--stage", choices=STAGE_CHOICES, default="all")
    k.add_argument("--stale", action="store_true", help="only frames that are stale or corrupt")
    k.add_argument("--dry-run", action="store_true", help="say what would go, remove nothing")

    s = sub.add_parser("status", help="per stage: frames valid, missing, stale or corrupt, and where")
    common(s)
    s.add_argument("--verify", action="store_true",
                   help="also read every file and compare its digest with its stamp (slow)")
    return p


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("sphshot")
    except PackageNotFoundError:       # run from a checkout that was never installed
        return "unknown (not installed)"


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise UsageError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise UsageError(f"expected a positive integer, got {value}")
    return value


def _gigabytes(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise UsageError(f"--max-memory: expected a number of gigabytes, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise UsageError(f"--max-memory: expected a positive number of gigabytes, got {text}")
    return value * 2 ** 30


def _preflight(spec, args):
    """The shot's memory and disk estimate; TooBig (exit 2) when it does not fit."""
    from .cache import output_problem
    from .errors import TooBig
    from .estimate import estimate, too_big
    bad = output_problem(spec.output_root)
    if bad:
        raise UsageError(f"{args.job}: shot.output: {bad}")
    est = estimate(spec)
    problem = too_big(spec, est, args.max_memory, _stages(getattr(args, "stage", None) or "all"))
    if problem:
        raise TooBig(f"{args.job}: {problem}")
    return est


def _stages(choice: str) -> list[str]:
    """`all`, one stage, or `S+`: stage S and every stage after it."""
    names = list(STAGES)
    if choice == "all":
        return names
    if choice.endswith("+"):
        return names[names.index(choice[:-1]):]
    return [choice]


def _load(args):
    """The job's spec; keys that validate but may surprise are one warning line each."""
    from .spec import load_spec
    spec = load_spec(args.job, args.overrides)
    for line in spec.warnings():
        print(f"sphshot: warning: {args.job}: {line}", file=sys.stderr)
    return spec


def cmd_validate(args) -> int:
    spec = _load(args)
    est = _preflight(spec, args)
    print(f"{args.job}: ok ({spec.shot.name} v{spec.shot.version:03d}, frames "
          f"{spec.shot.frame_start}-{spec.shot.frame_end}, {len(spec.fluids)} fluid(s), "
          f"{len(spec.colliders)} collider(s))")
    print(f"{args.job}: estimate: {est.line()}")
    return 0


def cmd_status(args) -> int:
    from . import cache
    from .frames import format_frames
    spec = _load(args)
    shot = cache.ShotCache(spec)
    paths = shot.paths
    print(f"{spec.shot.name} v{spec.shot.version:03d}: {paths.root}")
    for stage in STAGES:
        sc = shot.scan(stage, spec.frames, verify=args.verify)
        line = (f"  {stage:8s} valid {len(sc.valid):4d}  missing {len(sc.missing):4d}  "
                f"stale {len(sc.stale):4d}  corrupt {len(sc.corrupt):4d}  {paths.stage_dir(stage)}")
        if sc.missing and sc.valid:
            line += f"  (missing: {format_frames(sc.missing)})"
        if sc.stale:
            line += f"  (stale: {format_frames(sc.stale)})"
        if sc.corrupt:
            line += f"  (corrupt: {format_frames(sc.corrupt)})"
        print(line)
    ckpts = paths.checkpoints()
    if ckpts:
        print(f"  checkpoints: {format_frames(ckpts)}")
    for wanted, name, path in ((spec.render.movie, "movie", paths.movie),
                               (spec.render.contact_sheet, "contact sheet", paths.contact_sheet)):
        if wanted:
            print(f"  {name}: {path if path.exists() else 'not made (made once every render frame is valid)'}")
    return 0


def cmd_run(args) -> int:
    from .executor import make_executor
    from .frames import format_frames, select_frames
    from .progress import Progress
    from .runner import run_stages
    spec = _load(args)
    frames, source = select_frames(args.frames, args.chunk, spec.frames, os.environ)
    _preflight(spec, args)
    kind = "dask" if args.scheduler else args.executor
    if args.workers and (kind != "dask" or args.scheduler):
        raise UsageError("--workers: only with --executor dask and no --scheduler")
    progress = Progress()
    if source:
        progress.line(f"sphshot: frames {format_frames(frames)} from {source}")
    executor = make_executor(kind, scheduler=args.scheduler, workers=args.workers)
    try:
        run_stages(spec, _stages(args.stage), frames, force=args.force, executor=executor,
                   progress=progress)
    finally:
        executor.close()
    return 0


def cmd_clean(args) -> int:
    from . import cache
    from .frames import format_frames
    spec = _load(args)
    shot = cache.ShotCache(spec)
    verb = "would remove" if args.dry_run else "removed"
    for stage in _stages(args.stage):
        sc = shot.scan(stage, spec.frames)
        frames = sorted(sc.stale + sc.corrupt) if args.stale else sorted(sc.valid + sc.stale + sc.corrupt)
        if not frames:
            print(f"sphshot: clean: {stage}: nothing to remove")
            continue
        n = sum(len([p for p in shot.paths.frame_files(stage, f) if p.exists()]) for f in frames) \
            if args.dry_run else cache.remove_frames(shot.paths, stage, frames)
        what = "stale or corrupt " if args.stale else ""
        print(f"sphshot: clean: {stage}: {verb} {len(frames)} {what}frame(s) {format_frames(frames)} "
              f"({n} file(s)) in {shot.paths.stage_dir(stage)}")
        if stage == "render" and not args.dry_run:
            for p in (shot.paths.movie, shot.paths.contact_sheet):      # made of these frames
                p.unlink(missing_ok=True)
        if stage == "sim" and not args.stale and not args.dry_run:
            cache.clear_checkpoints(shot.paths)
    return 0


def cmd_export(args) -> int:
    from . import cache
    from .errors import StaleCacheError
    from .export import export_job
    from .frames import format_frames
    spec = _load(args)
    shot = cache.ShotCache(spec)
    for stage in STAGES:        # every farm task would refuse these (exit 3): say so now, once
        stale = shot.scan(stage, spec.frames).stale
        if stale:
            raise StaleCacheError(f"{args.job}: {stage} frame(s) {format_frames(stale)} in {shot.paths.stage_dir(stage)} "
                                  f"were made with other parameters, so every farm task of this export would "
                                  f"refuse them; run --stage {stage} --force (or sphshot clean --stale) first, "
                                  f"or raise shot.version")
    farm = {"show": args.show, "service": args.service, "cpus": args.cpus,
            "mem_gb": args.mem / 2 ** 30 if args.mem else None, "time": args.time, "gpus": args.gpus}
    path = export_job(spec, Path(args.job).resolve(), args.overrides, args.to, args.chunk,
                      Path(args.output) if args.output else None, farm)
    print(f"sphshot: wrote {args.to} job {path}")
    if args.to == "openjd":        # PATH parameters, for the workers' path mapping
        print(f"sphshot: its job parameters: -p JobFile={Path(args.job).resolve()} "
              f"-p ShotOutput={spec.output_root.parent.parent}")
    return 0


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=os.environ.get("SPHSHOT_LOG", "INFO"), format="sphshot: %(message)s",
                        stream=sys.stderr)
    os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if args.command is None:
            parser.print_help()
            return errors.EXIT_USAGE
        handler = {"validate": cmd_validate, "run": cmd_run, "status": cmd_status,
                   "export": cmd_export, "clean": cmd_clean}[args.command]
        return handler(args)
    except SphshotError as err:
        for line in str(err).splitlines() or [err.__class__.__name__]:
            print(f"sphshot: error: {line}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        print("sphshot: interrupted", file=sys.stderr)
        return errors.EXIT_INTERRUPTED
    except BrokenPipeError:    # `sphshot status JOB | head`: the reader left; nothing to say
        with contextlib.suppress(OSError):
            sys.stdout = open(os.devnull, "w")
        return errors.EXIT_OK
    except OSError as err:     # a full disk, a folder gone or not writable mid-run: one line
        where = f": {err.filename}" if getattr(err, "filename", None) else ""
        what = " ".join(str(err.strerror or err).split())      # one line, whatever a library said
        what = what if len(what) <= 300 else what[:300] + "..."
        print(f"sphshot: error: {what}{where} (nothing half-written was published)", file=sys.stderr)
        return errors.EXIT_FAILURE


if __name__ == "__main__":
    sys.exit(main())
