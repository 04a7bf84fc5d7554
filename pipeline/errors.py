"""One exception type per failure family, each carrying its documented exit code.

The CLI catches :class:`SphshotError` once and prints ``str(err)`` as a single line; nothing
else in the code base turns exceptions into exit codes.
"""
from __future__ import annotations

# Exit codes, documented in `sphshot --help` and the README.
EXIT_OK = 0            # every requested frame is valid on disk
EXIT_FAILURE = 1       # runtime failure (solver unstable, a frame failed, I/O error)
EXIT_USAGE = 2         # bad job file, bad --set, bad frame range, missing input file
EXIT_STALE = 3         # cached frames were made with other parameters; use --force or a new version
EXIT_WAITING = 4       # an upstream frame (sim frame N) is not there yet, or another worker holds
                       # the stage; a farm retries later
EXIT_INTERRUPTED = 5   # stopped by SIGTERM/SIGUSR1/SIGINT after writing a checkpoint; run again to resume
EXIT_DEVICE = 6        # the compute device failed (GPU out of memory, reset, driver): the frames before
                       # it are kept; retry, on another node or with sim.backend = "cpu"


class SphshotError(Exception):
    exit_code = EXIT_FAILURE


class UsageError(SphshotError):
    """Bad command-line arguments (frame range, stage name, ...)."""
    exit_code = EXIT_USAGE


class SpecError(SphshotError):
    """A job file that does not validate; carries one line per problem."""
    exit_code = EXIT_USAGE

    def __init__(self, source: str, problems: list[str]):
        self.source = source
        self.problems = problems
        super().__init__("\n".join(f"{source}: {p}" for p in problems))


class TooBig(SphshotError):
    """The shot's estimated memory or disk is beyond this machine (or --max-memory)."""
    exit_code = EXIT_USAGE


class StaleCacheError(SphshotError):
    exit_code = EXIT_STALE


class WaitingOnUpstream(SphshotError):
    exit_code = EXIT_WAITING


class Busy(SphshotError):
    """Another live worker holds this shot's sequential stage (the sim)."""
    exit_code = EXIT_WAITING


class StageError(SphshotError):
    """A stage failed at run time; the message names the frame and what to change."""
    exit_code = EXIT_FAILURE


class Interrupted(SphshotError):
    exit_code = EXIT_INTERRUPTED


class DeviceFailed(StageError):
    """The compute device failed under a stage: not the shot's doing, so worth a retry (Dask
    retries such a task on another worker)."""
    exit_code = EXIT_DEVICE
