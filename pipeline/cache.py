"""The shot cache: file names, atomic publishing, parameter hashes and frame validity.

This is the only module that knows where files live. Layout of one shot version::

    <output>/<name>/v001/
        manifest.json                     stage -> parameter hash (chained sim <- surface <- render)
        sim/<name>.0001.h5                particles (position, velocity, density, pressure, id, fluid)
        checkpoints/<name>.ckpt.0010.h5   full solver state to resume from
        surface/<name>.0001.vdb           level set `surface`, fog `density`, vector `velocity`
        surface/<name>.0001.ply           mesh (or .<fluid>.0001.ply per fluid; .obj/.vtu on request)
        surface/<name>.0001.spray.ply     spray particles as points (surface.spray > 0)
        surface/<name>.0001.spray.vdb     the same as an OpenVDB PointDataGrid (and surface.grids set)
        render/<name>.0001.png            image
        render/<name>.mp4, render/<name>.contact.png

A frame of a stage is *valid* when every file it owns exists under its final name and the
manifest's hash for the stage equals the hash of the current spec. Files only ever appear
under a final name by an atomic rename, so existing means complete. What each stage owns and
hashes is described once, in pipeline/stages (STAGES).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from .spec import ShotSpec
from .stages import STAGES as _STAGES

STAGES = tuple(_STAGES)           # stage names in run order
HOST = socket.gethostname().split(".")[0].replace("-", "_") or "host"


# ------------------------------------------------------------------------------ atomic files
def _tmp_name(final: Path) -> Path:
    return final.with_name(f".{final.name}.{HOST}-{os.getpid()}.tmp")


@contextlib.contextmanager
def atomic_path(final: Path) -> Iterator[Path]:
    """Yield a temporary path beside `final`; on success fsync it and rename it into place.

    Two processes writing the same frame each write their own temporary file, and each rename is
    atomic, so readers see one complete file or none. On an exception the temporary is removed.
    """
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_name(final)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, final)
    except OSError as err:
        # a system error names the file it was writing: this one, not its hidden temporary
        # (Pillow's full-disk error named no file at all)
        if err.errno is not None and (not err.filename or str(err.filename) == str(tmp)):
            raise OSError(err.errno, err.strerror or str(err), str(final)) from err
        raise
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    with contextlib.suppress(OSError):  # make the rename itself durable
        dfd = os.open(final.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def write_text_atomic(final: Path, text: str) -> None:
    with atomic_path(final) as tmp:
        tmp.write_text(text, encoding="utf-8")


def remove_dead_temporaries(folder: Path) -> int:
    """Remove temporaries left by killed processes of this host (never another live writer's)."""
    removed = 0
    if not folder.is_dir():
        return 0
    for tmp in folder.glob(f".*.{HOST}-*.tmp"):
        try:
            pid = int(tmp.name.rsplit("-", 1)[1].split(".")[0])
        except ValueError:
            continue
        if pid == os.getpid() or not pid_alive(pid):
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
                removed += 1
    return removed


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# ------------------------------------------------------------------------------------ stamps
def stamp_path(file: Path) -> Path:
    """The stamp beside a published file (hidden: .<name>.stamp)."""
    return file.with_name(f".{file.name}.stamp")


def file_digest(file: Path) -> tuple[int, str]:
    """(size, blake2b hex digest) of a file, read in 1 MiB pieces."""
    h, size = hashlib.blake2b(digest_size=16), 0
    with open(file, "rb") as fh:
        for piece in iter(lambda: fh.read(1 << 20), b""):
            h.update(piece)
            size += len(piece)
    return size, h.hexdigest()


def stamp(file: Path, stage_hash: str, upstream: dict[str, str] | None = None) -> None:
    """Record beside a just-published frame file what it was made from (the stage's parameter
    hash, chained to its upstream stages', and the digests of the upstream frame's files) and
    what was written (size and digest). A frame counts as valid only when its stamps match its
    files, the current parameters and the upstream frame as it is now."""
    size, digest = file_digest(file)
    record = {"hash": stage_hash, "size": size, "blake2b": digest}
    if upstream:
        record["upstream"] = upstream
    write_text_atomic(stamp_path(file), json.dumps(record))


def stamped_digests(files) -> dict[str, str]:
    """{file name: the digest its stamp records} for files that have a readable stamp."""
    out = {}
    for f in files:
        try:
            out[Path(f).name] = json.loads(stamp_path(Path(f)).read_text(encoding="utf-8"))["blake2b"]
        except (OSError, ValueError, KeyError, TypeError):
            pass
    return out


def check_file(file: Path, stage_hash: str, verify: bool = False, upstream: dict[str, str] | None = None) -> str:
    """'missing'; 'corrupt' (no stamp, or not the size stamped -- a truncated copy, a write that
    failed without an error -- or with `verify` not the digest); 'stale' (made with other
    parameters, or, given `upstream` (the upstream frame's stamped digests now), from another
    upstream frame); or 'valid'."""
    try:
        size = file.stat().st_size
    except FileNotFoundError:
        return "missing"
    try:
        record = json.loads(stamp_path(file).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return "corrupt"
    if not isinstance(record, dict) or record.get("size") != size:
        return "corrupt"
    if verify and file_digest(file)[1] != record.get("blake2b"):
        return "corrupt"
    if upstream is not None and "upstream" in record and record["upstream"] != upstream:
        return "stale"          # made from an upstream frame that has been computed again since
    return "valid" if record.get("hash") == stage_hash else "stale"


# ------------------------------------------------------------------------------------ hashes
def _digest(obj) -> str:
    blob = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def stage_hashes(spec: ShotSpec) -> dict[str, str]:
    """Chained parameter hashes: a change upstream changes every hash below it."""
    out: dict[str, str] = {}
    for stage in _STAGES.values():
        out[stage.name] = _digest({"upstream": out.get(stage.upstream), "params": stage.hashed(spec),
                                   "format": stage.format_version})
    return out


# ------------------------------------------------------------------------------------- paths
@dataclass(frozen=True)
class ShotPaths:
    root: Path
    name: str
    mesh_ext: str
    fluids: tuple[str, ...]
    per_fluid: bool
    vdb: bool = True            # the surface stage writes a .vdb (surface.grids names some grid)
    spray: bool = False         # the surface stage writes a spray points file (surface.spray > 0)

    @property
    def spray_vdb(self) -> bool:
        """The surface stage writes the spray as VDB points too (spray on and some grid asked for)."""
        return self.spray and self.vdb

    @classmethod
    def for_spec(cls, spec: ShotSpec) -> "ShotPaths":
        return cls(root=spec.output_root, name=spec.shot.name, mesh_ext=spec.surface.format,
                   fluids=tuple(f.name for f in spec.fluids), per_fluid=spec.surface.per_fluid,
                   vdb=bool(spec.surface.grids), spray=spec.surface.spray > 0)

    def stage_dir(self, stage: str) -> Path:
        return self.root / stage

    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    @property
    def checkpoint_dir(self) -> Path:
        return self.root / "checkpoints"

    def sim_frame(self, frame: int) -> Path:
        return self.root / "sim" / f"{self.name}.{frame:04d}.h5"

    def checkpoint(self, frame: int) -> Path:
        return self.checkpoint_dir / f"{self.name}.ckpt.{frame:04d}.h5"

    def surface_vdb(self, frame: int) -> Path:
        return self.root / "surface" / f"{self.name}.{frame:04d}.vdb"

    def surface_spray(self, frame: int) -> Path:
        """The frame's spray particles: PLY points with velocity and pscale (radius)."""
        return self.root / "surface" / f"{self.name}.{frame:04d}.spray.ply"

    def surface_spray_vdb(self, frame: int) -> Path:
        """The frame's spray particles as an OpenVDB PointDataGrid `spray`."""
        return self.root / "surface" / f"{self.name}.{frame:04d}.spray.vdb"

    def surface_meshes(self, frame: int) -> dict[str | None, Path]:
        """Mesh files of a frame: {None: all fluids} or {fluid name: mesh} when per_fluid."""
        d = self.root / "surface"
        if self.per_fluid:
            return {f: d / f"{self.name}.{f}.{frame:04d}.{self.mesh_ext}" for f in self.fluids}
        return {None: d / f"{self.name}.{frame:04d}.{self.mesh_ext}"}

    def claim(self, stage: str, frame: int | None) -> Path:
        """Claim file of a frame (or of a whole sequential stage, frame None); see claims.py."""
        tag = stage if frame is None else f"{frame:04d}"
        return self.root / stage / f".{self.name}.{tag}.claim"

    def render_frame(self, frame: int) -> Path:
        return self.root / "render" / f"{self.name}.{frame:04d}.png"

    def render_depth(self, frame: int) -> Path:
        return self.root / "render" / f"{self.name}.depth.{frame:04d}.png"

    @property
    def movie(self) -> Path:
        return self.root / "render" / f"{self.name}.mp4"

    @property
    def contact_sheet(self) -> Path:
        return self.root / "render" / f"{self.name}.contact.png"

    def frame_files(self, stage: str, frame: int) -> list[Path]:
        """Every file a stage owns for one frame; the frame is valid when all exist."""
        return _STAGES[stage].frame_files(self, frame)

    def frame_leftovers(self, stage: str, frame: int) -> list[Path]:
        """Files this frame may hold from other settings of the same stage (a .vdb once
        surface.grids is empty, meshes in another format or split otherwise), which a
        recomputed frame replaces: the frame's files under every layout, less the current."""
        if stage != "surface":
            return []
        current = set(self.frame_files(stage, frame))
        d = self.root / "surface"
        others = [self.surface_vdb(frame), self.surface_spray(frame), self.surface_spray_vdb(frame)]
        for ext in ("ply", "obj", "vtu"):
            others.append(d / f"{self.name}.{frame:04d}.{ext}")
            others += [d / f"{self.name}.{f}.{frame:04d}.{ext}" for f in self.fluids]
        return [p for p in others if p not in current and p.exists()]

    def checkpoints(self) -> list[int]:
        """Frames that have a published checkpoint, ascending."""
        out = []
        for p in self.checkpoint_dir.glob(f"{self.name}.ckpt.*.h5"):
            with contextlib.suppress(ValueError):
                out.append(int(p.name.rsplit(".", 2)[1]))
        return sorted(out)


# ---------------------------------------------------------------------------------- manifest
def read_manifest(paths: ShotPaths) -> dict:
    try:
        return json.loads(paths.manifest.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):     # none yet, or unreadable: nothing recorded
        return {"stages": {}}


@dataclass(frozen=True)
class StageScan:
    stage: str
    valid: tuple[int, ...]
    missing: tuple[int, ...]
    stale: tuple[int, ...]      # files exist but were made with other parameters
    hash_changed: bool          # the manifest holds another hash for this stage
    corrupt: tuple[int, ...] = ()   # files exist but are not what was stamped (or never were)

    @property
    def complete(self) -> bool:
        """Every frame scanned is valid."""
        return not (self.missing or self.stale or self.corrupt)


class ShotCache:
    """One run's view of a shot version: the spec's hashes computed once and the manifest read
    once (and kept up to date by record())."""

    def __init__(self, spec: ShotSpec, paths: ShotPaths | None = None):
        self.spec = spec
        self.paths = paths or ShotPaths.for_spec(spec)
        self.hashes = stage_hashes(spec)
        self.manifest = read_manifest(self.paths)

    def recorded_hash(self, stage: str) -> str | None:
        return self.manifest.get("stages", {}).get(stage, {}).get("hash")

    def scan(self, stage: str, frames, verify: bool = False) -> StageScan:
        """Each frame by its files' stamps (check_file): missing, corrupt, stale or valid;
        `verify` also compares each file's digest with its stamp's (reads every byte)."""
        recorded, current = self.recorded_hash(stage), self.hashes[stage]
        changed = recorded is not None and recorded != current
        found: dict[str, list[int]] = {"valid": [], "missing": [], "stale": [], "corrupt": []}
        for f in frames:
            up = _STAGES[stage].upstream
            inputs = stamped_digests(self.paths.frame_files(up, f)) if up else None
            states = {check_file(p, current, verify, inputs) for p in self.paths.frame_files(stage, f)}
            state = next(s for s in ("missing", "corrupt", "stale", "valid") if s in states)
            found[state].append(f)
        return StageScan(stage, tuple(found["valid"]), tuple(found["missing"]), tuple(found["stale"]), changed,
                         tuple(found["corrupt"]))

    def record(self, stage: str) -> None:
        """Write the stage's current hash into the manifest (atomic; idempotent across workers)."""
        entry = json.loads(json.dumps({"hash": self.hashes[stage], "params": _STAGES[stage].hashed(self.spec)},
                                      default=str))
        manifest = read_manifest(self.paths)      # another worker may have recorded a stage since
        if manifest.get("stages", {}).get(stage) != entry:
            manifest.setdefault("stages", {})[stage] = entry
            manifest["shot"] = self.spec.shot.name
            self.paths.root.mkdir(parents=True, exist_ok=True)
            write_text_atomic(self.paths.manifest, json.dumps(manifest, indent=2, sort_keys=True, default=str))
        self.manifest = manifest


def scan(spec: ShotSpec, paths: ShotPaths, stage: str, frames) -> StageScan:
    """One stage's frames, valid, missing or stale (a one-off ShotCache)."""
    return ShotCache(spec, paths).scan(stage, frames)


def output_problem(root: Path) -> str | None:
    """Why a shot version's folder cannot be made or written to (one line), or None: a file
    where a folder must be, or no permission to write in the nearest folder that exists."""
    p = Path(root)
    while not p.exists():
        if p == p.parent:
            return f"{root}: no folder of it exists"
        p = p.parent
    if not p.is_dir():
        return f"{p} is a file, not a folder: the shot is written to {root}"
    if not os.access(p, os.W_OK | os.X_OK):
        return f"cannot write in {p} (no permission, or a read-only filesystem): the shot is written to {root}"
    return None


def first_missing(folder: Path) -> Path | None:
    """The outermost folder of `folder`'s path that does not exist yet (what a first run will
    make, its parents included), or None where `folder` exists."""
    folder = Path(folder)
    if folder.exists():
        return None
    while not folder.parent.exists() and folder.parent != folder:
        folder = folder.parent
    return folder


def remove_if_empty(paths: ShotPaths, made: Path | None = None) -> bool:
    """Remove a shot version that holds nothing but its manifest and empty folders (what a
    first run that failed before publishing a frame leaves), and its parents up to `made`
    (first_missing() before the run: <output>/<name> where the run made it) where they are
    empty. Any other file (a frame, a live worker's claim or temporary) keeps it. Returns
    whether the version was removed."""
    removed = _remove_version_if_empty(paths)
    if removed and made is not None and made in paths.root.parents:
        for folder in paths.root.parents:
            with contextlib.suppress(OSError):
                folder.rmdir()          # only an empty one goes
            if folder == made:
                break
    return removed


def _remove_version_if_empty(paths: ShotPaths) -> bool:
    root = paths.root
    if not root.is_dir():
        return False
    files = [p for p in root.rglob("*") if not p.is_dir()]
    if any(p != paths.manifest for p in files):
        return False
    with contextlib.suppress(FileNotFoundError):
        paths.manifest.unlink()
    for folder in sorted((p for p in root.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
        with contextlib.suppress(OSError):
            folder.rmdir()
    with contextlib.suppress(OSError):
        root.rmdir()
    return not root.exists()


def remove_frames(paths: ShotPaths, stage: str, frames) -> int:
    """Remove the frames' files of a stage (under every layout) and their stamps; returns how
    many files went (sphshot clean)."""
    removed = 0
    for f in frames:
        for p in [*paths.frame_files(stage, f), *paths.frame_leftovers(stage, f)]:
            for q in (p, stamp_path(p)):
                try:
                    q.unlink()
                    removed += 1
                except FileNotFoundError:
                    pass
    return removed


def clear_checkpoints(paths: ShotPaths) -> None:
    """Remove the sim's checkpoints (--force after the sim's parameters changed: a resume from
    them would continue the old run). Frames are never removed: stale ones stay, shown as
    stale, until recomputed."""
    if paths.checkpoint_dir.is_dir():
        for p in paths.checkpoint_dir.iterdir():
            if p.is_file():
                with contextlib.suppress(FileNotFoundError):
                    p.unlink()
