"""Claims: many workers on one shared shot folder, each frame computed once.

Farm tasks overlap (a retried chunk, two nodes handed the same range, a Dask worker and a
SLURM task on the same shot). Publishing is atomic, so overlap can never corrupt a file; claims
make it cheap too. Before computing a frame a worker creates the frame's claim file with
``O_CREAT | O_EXCL`` (atomic on local disks and NFSv3+); a worker that finds a live claim leaves
the frame to its owner and, once its own frames are done, waits for the owner to publish it.

A claim is *dead* when its owner is gone: a process of this host that no longer exists, or a
claim from another host whose heartbeat (its mtime, touched every CLAIM_REFRESH_S) is older
than CLAIM_STALE_S. Dead claims are taken over. Two workers breaking the same dead claim at
the same instant may both compute the frame: wasted work at worst, never a corrupt file.
"""
from __future__ import annotations

import contextlib
import json
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from .cache import HOST, ShotPaths, check_file, pid_alive, stamped_digests, write_text_atomic
from .errors import StaleCacheError
from .stages import STAGES

CLAIM_REFRESH_S = 15.0
CLAIM_STALE_S = 90.0


@dataclass(frozen=True)
class Owner:
    host: str
    pid: int

    def __str__(self) -> str:
        return f"{self.host} pid {self.pid}"


def read_owner(claim: Path) -> Owner | None:
    try:
        host, pid = claim.read_text(encoding="ascii").split()[:2]
        return Owner(host, int(pid))
    except (FileNotFoundError, ValueError, OSError):
        return None


def claim_is_dead(claim: Path) -> bool:
    owner = read_owner(claim)
    if owner is None:                      # vanished, or a half-written claim: look again later
        return False
    if owner.host == HOST:
        return not pid_alive(owner.pid)
    try:
        age = time.time() - claim.stat().st_mtime
    except FileNotFoundError:
        return False
    return age > CLAIM_STALE_S


def try_claim(claim: Path) -> bool:
    """Create `claim` for this process; take it over when its owner is dead."""
    claim.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(2):
        try:
            fd = os.open(claim, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            if read_owner(claim) == Owner(HOST, os.getpid()):
                return True
            if not claim_is_dead(claim):
                return False
            with contextlib.suppress(FileNotFoundError):
                claim.unlink()
            continue
        with os.fdopen(fd, "w", encoding="ascii") as fh:
            fh.write(f"{HOST} {os.getpid()} {time.time():.0f}\n")
        return True
    return False


def release(claim: Path) -> None:
    if read_owner(claim) == Owner(HOST, os.getpid()):
        with contextlib.suppress(FileNotFoundError):
            claim.unlink()


def remove_dead_claims(folder: Path) -> int:
    removed = 0
    if folder.is_dir():
        for claim in folder.glob(".*.claim"):
            if claim_is_dead(claim):
                with contextlib.suppress(FileNotFoundError):
                    claim.unlink()
                    removed += 1
    return removed


@dataclass
class FrameClaims:
    """Iterate over the frames of a chunk that this process claimed and must compute.

    ``since``: with --force, a frame counts as done only when its files are newer than this
    time (the start of the run); otherwise a frame is done when its files exist.

    Usage::

        with FrameClaims(paths, "render", todo) as claims:
            stage.run(spec, claims, paths, progress)    # the stage loops `for frame in claims`
            orphaned = claims.wait_for_others()         # frames other workers were computing

    The claim on a frame is released when the stage asks for the next frame (it has
    published the previous one by then) and, at the latest, when the block exits.
    """
    paths: ShotPaths
    stage: str
    frames: list[int]
    since: float | None = None
    stage_hash: str | None = None
    deferred: list[int] = field(default_factory=list)   # held by another live worker
    by_others: list[int] = field(default_factory=list)  # found done by another worker
    _held: int | None = None
    _stop: threading.Event = field(default_factory=threading.Event)
    _beat: threading.Thread | None = None

    # ------------------------------------------------------------------------ context manager
    def __enter__(self) -> "FrameClaims":
        self._beat = threading.Thread(target=self._heartbeat, name="sphshot-claims", daemon=True)
        self._beat.start()
        return self

    def __exit__(self, *exc) -> None:
        self._release_held()
        self._stop.set()
        if self._beat is not None:
            self._beat.join(timeout=2)

    def _heartbeat(self) -> None:
        while not self._stop.wait(CLAIM_REFRESH_S):
            held = self._held
            if held is not None:
                with contextlib.suppress(OSError):
                    os.utime(self.paths.claim(self.stage, held))

    # ----------------------------------------------------------------------------- iteration
    def done(self, frame: int) -> bool:
        """The frame's files are published (and, given stage_hash, stamped valid for it: a
        corrupt or stale frame is not done) and, with `since`, newer than that."""
        files = self.paths.frame_files(self.stage, frame)
        try:
            mtimes = [p.stat().st_mtime for p in files]
        except FileNotFoundError:
            return False
        if self.stage_hash is not None:
            up = STAGES[self.stage].upstream
            inputs = stamped_digests(self.paths.frame_files(up, frame)) if up else None
            if any(check_file(p, self.stage_hash, upstream=inputs) != "valid" for p in files):
                return False
        return self.since is None or min(mtimes) >= self.since

    def __iter__(self) -> Iterator[int]:
        for frame in self.frames:
            self._release_held()
            if self.done(frame):
                self.by_others.append(frame)
                continue
            if not try_claim(self.paths.claim(self.stage, frame)):
                self.deferred.append(frame)
                continue
            if self.done(frame):          # published between the check and the claim
                release(self.paths.claim(self.stage, frame))
                self.by_others.append(frame)
                continue
            self._held = frame
            yield frame
        self._release_held()

    def _release_held(self) -> None:
        if self._held is not None:
            release(self.paths.claim(self.stage, self._held))
            self._held = None

    # ------------------------------------------------------------------------------- waiting
    def wait_for_others(self, poll_s: float = 0.5) -> list[int]:
        """Wait until every deferred frame is published by its owner (then in `by_others`).

        Returns the deferred frames whose owner died meanwhile: the caller computes them (with
        a fresh FrameClaims).
        """
        pending = list(self.deferred)
        self.deferred = []
        orphaned: list[int] = []
        while pending:
            still = []
            for frame in pending:
                if self.done(frame):
                    self.by_others.append(frame)
                    continue
                claim = self.paths.claim(self.stage, frame)
                if not claim.exists() or claim_is_dead(claim):
                    orphaned.append(frame)
                    continue
                still.append(frame)
            pending = still
            if pending:
                time.sleep(poll_s)
        return orphaned


class VersionRun:
    """This process, registered as a writer of one shot version with the parameter hashes of
    the stages it runs: `<version>/.runs/<host>-<pid>.json`, its mtime a heartbeat like a
    claim's. Entering fails with StaleCacheError (exit 3) when a live run registered earlier
    writes one of these stages with other parameters: two parameter sets never interleave in a
    version. Runs with the same parameters (farm tasks, a rerun) share it. When two register
    at the same instant the earlier registration wins and the later backs off."""

    def __init__(self, root: Path, hashes: dict[str, str]):
        self.folder = Path(root) / ".runs"
        self.path = self.folder / f"{HOST}-{os.getpid()}.json"
        self.hashes = dict(hashes)
        self.started = time.time()
        self._stop = threading.Event()
        self._beat: threading.Thread | None = None

    def __enter__(self) -> "VersionRun":
        self.folder.mkdir(parents=True, exist_ok=True)
        write_text_atomic(self.path, json.dumps({"host": HOST, "pid": os.getpid(), "started": self.started,
                                                 "hashes": self.hashes}))
        self._beat = threading.Thread(target=self._heartbeat, name="sphshot-version", daemon=True)
        self._beat.start()
        other = self._earlier_conflict()
        if other:
            self.__exit__()
            raise StaleCacheError(
                f"another run ({other['host']} pid {other['pid']}) is writing stage(s) {', '.join(other['stages'])} "
                f"of {self.folder.parent} with other parameters; wait for it to end, or raise shot.version")
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._beat is not None:
            self._beat.join(timeout=2)
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        with contextlib.suppress(OSError):
            self.folder.rmdir()             # only when no other run is registered

    def _heartbeat(self) -> None:
        while not self._stop.wait(CLAIM_REFRESH_S):
            with contextlib.suppress(OSError):
                os.utime(self.path)

    def _earlier_conflict(self) -> dict | None:
        for path in sorted(self.folder.glob("*.json")):
            if path == self.path:
                continue
            try:
                record = json.loads(path.read_text(encoding="utf-8"))
                age = time.time() - path.stat().st_mtime
            except (OSError, ValueError):
                continue                    # gone, or being written: its owner checks too
            dead = not pid_alive(record["pid"]) if record.get("host") == HOST else age > CLAIM_STALE_S
            if dead:
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()
                continue
            stages = [s for s, h in self.hashes.items() if record.get("hashes", {}).get(s, h) != h]
            if stages and (record.get("started", 0.0), path.name) < (self.started, self.path.name):
                return {**record, "stages": stages}
        return None
