"""Cache, invalidation and resume through the real CLI, on a small dam break."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from conftest import ROOT, mounted_tmpfs, small, spec_of, sphshot
from pipeline import cache

pytestmark = pytest.mark.slow


def mtimes(folder: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in sorted(folder.iterdir()) if p.is_file()}


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    """One small shot run through every stage; tests below work on copies or read only."""
    d = tmp_path_factory.mktemp("shot")
    job = d / "dambreak.toml"
    job.write_text((ROOT / "jobs" / "dambreak.toml").read_text())
    proc = sphshot("run", job, *small(), check=True)
    return job, proc


def test_full_run_writes_every_frame(shot):
    job, proc = shot
    spec = spec_of(job, small())
    paths = cache.ShotPaths.for_spec(spec)
    for stage in cache.STAGES:
        sc = cache.scan(spec, paths, stage, spec.frames)
        assert sc.valid == tuple(spec.frames), f"{stage}: {sc}"
    with h5py.File(paths.sim_frame(3)) as f:
        assert f["position"].shape[1] == 3 and f["position"].dtype == "float32"
        for name in ("velocity", "density", "pressure", "id", "fluid"):
            assert name in f
        assert f.attrs["frame"] == 3
        assert abs(f.attrs["time"] - 2 / 24) < 1e-9
    assert paths.movie.exists() and paths.contact_sheet.exists()
    # farm-manager lines: progress and one OUTPUT_FILE per published file
    assert "ALF_PROGRESS 100%" in proc.stdout
    assert f"OUTPUT_FILE:{paths.render_frame(6)};" in proc.stdout


def test_second_run_does_no_work(shot):
    job, _ = shot
    spec = spec_of(job, small())
    root = spec.output_root
    before = {s: mtimes(root / s) for s in ("sim", "surface", "render", "checkpoints")}
    proc = sphshot("run", job, *small(), check=True)
    for stage in cache.STAGES:
        assert f"sphshot: {stage}: all 6 frame(s) valid, nothing to do" in proc.stdout
    after = {s: mtimes(root / s) for s in before}
    assert after == before, "a second run rewrote files"


def test_render_key_change_leaves_sim_and_surface_valid(shot, tmp_path):
    job, _ = shot
    args = small()
    spec = spec_of(job, args)
    root = spec.output_root
    sim_before, surf_before = mtimes(root / "sim"), mtimes(root / "surface")
    changed = [*args, "--set", "render.background=[0.5,0.1,0.1]"]
    refused = sphshot("run", job, *changed)
    assert refused.returncode == 3, refused.stderr
    assert "render: frame(s) 1-6" in refused.stderr and "--stage render --force" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
    status = sphshot("status", job, *changed, check=True).stdout
    assert "sim      valid    6" in status and "surface  valid    6" in status
    assert "render   valid    0  missing    0  stale    6" in status
    forced = sphshot("run", job, *changed, "--stage", "render", "--force", check=True)
    assert "sphshot: render: 6 frame(s) in" in forced.stdout
    # and the whole shot is now valid again without touching sim or surface
    again = sphshot("run", job, *changed, check=True)
    for stage in cache.STAGES:
        assert f"sphshot: {stage}: all 6 frame(s) valid, nothing to do" in again.stdout
    assert mtimes(root / "sim") == sim_before and mtimes(root / "surface") == surf_before


def test_a_color_is_the_renders_parameter():
    """A fluid's or a collider's color (or a fluid's transmission depth) changes only the render
    stage's hash (a look tweak after
    the sim re-renders, it does not make the sim and surface frames stale); a fluid's physics
    changes every stage's."""
    from pipeline.spec import load_spec

    job = ROOT / "jobs" / "dambreak.toml"
    base = cache.stage_hashes(load_spec(job))
    for change in ("fluids.0.color=[0.85, 0.52, 0.1]", "colliders.0.color=[0.2, 0.2, 0.2]",
                   "fluids.0.transmission_depth=0.02"):
        h = cache.stage_hashes(load_spec(job, [change]))
        assert h["sim"] == base["sim"] and h["surface"] == base["surface"] and h["render"] != base["render"], change
    h = cache.stage_hashes(load_spec(job, ["fluids.0.dynamic_viscosity=0.002"]))
    assert all(h[s] != base[s] for s in base)


def test_surface_grids_choose_what_the_vdb_holds(job_copy):
    """surface.grids names the OpenVDB grids written; with none the stage writes no .vdb at all
    (only meshes), and its frames are still valid and render."""
    import pyopenvdb as vdb

    job = job_copy()
    only_density = small("shot.frame_end=2", 'surface.grids=["density"]')
    sphshot("run", job, *only_density, "--stage", "sim", check=True)
    sphshot("run", job, *only_density, "--stage", "surface", check=True)
    paths = cache.ShotPaths.for_spec(spec_of(job, only_density))
    assert [g["name"] for g in vdb.readAllGridMetadata(str(paths.surface_vdb(1)))] == ["density"]

    no_vdb = small("shot.frame_end=2", "surface.grids=[]")
    proc = sphshot("run", job, *no_vdb, "--stage", "surface", "--force", check=True)
    spec = spec_of(job, no_vdb)
    paths = cache.ShotPaths.for_spec(spec)
    assert list(paths.stage_dir("surface").glob("*.vdb")) == [], "a .vdb written (or an old one left)"
    assert ".vdb" not in proc.stdout
    assert cache.scan(spec, paths, "surface", spec.frames).valid == (1, 2)
    sphshot("run", job, *no_vdb, "--stage", "render", check=True)
    assert all(paths.render_frame(f).exists() for f in spec.frames)


def test_surface_waits_on_missing_sim_frames(job_copy):
    """Exit 4, and a first run that waits leaves no folder behind: neither the shot's version
    nor the <output>/<name> folders above it that it made (an empty shots/dambreak was left)."""
    job = job_copy()
    (job.parent / "out" / "kept").mkdir(parents=True)
    proc = sphshot("run", job, *small(), "--stage", "surface", "--frames", "3-4")
    assert proc.returncode == 4, proc.stderr
    assert "waiting on sim frame 3" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert sorted(p.name for p in (job.parent / "out").iterdir()) == ["kept"]


def test_unstable_sim_stops_naming_frame_and_parameter_and_keeps_earlier_frames(job_copy):
    """WCSPH with a speed of sound of 1 m/s lets the collapsing column compress past the
    density bound."""
    job = job_copy()
    args = small("sim.speed_of_sound=1.0", 'sim.solver="wcsph"', 'sim.surface_tension_model="mueller"')
    proc = sphshot("run", job, *args, "--stage", "sim")
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("sphshot: error:")]
    assert proc.returncode == 1, proc.stderr
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "frame 0002: sim unstable: density reached" in lines[0]
    assert "sim.max_density_ratio" in lines[0] and "raise sim.speed_of_sound" in lines[0]
    # where: the densest particle, and the solid nearest to it, as the job names it
    assert re.search(r"x rest, at \(-?\d+\.\d{3}, -?\d+\.\d{3}, -?\d+\.\d{3}\) m, \d+\.\d mm (inside|from) "
                     r"(the domain's [+-][xyz] wall|colliders\[0\] \(sphere\))", lines[0]), lines[0]
    spec = spec_of(job, args)
    assert cache.scan(spec, cache.ShotPaths.for_spec(spec), "sim", spec.frames).valid == (1,)


def test_a_blow_up_says_where_and_next_to_what():
    """The sim stage's blow-up messages give the place (the fastest or densest particle) and the
    solid nearest to it, by the job's own names: a domain wall, or colliders[i] with its type
    (a mesh by its file), and whether the point is inside it."""
    from conftest import tiny_spec
    from pipeline.spec import ShotSpec
    from pipeline.stages.sim import place, solver_params
    from solver.backend import init_taichi

    init_taichi("cpu", 1)
    spec = ShotSpec.model_validate(tiny_spec(((0.1, 0.1, 0.1), (0.2, 0.2, 0.2)), ((0, 0, 0), (1.0, 0.6, 0.4)),
                                             colliders=({"type": "sphere", "center": (0.45, 0.25, 0.2), "radius": 0.08},)))
    params = solver_params(spec)
    assert place(spec, params, (0.45, 0.335, 0.2)) == ", at (0.450, 0.335, 0.200) m, 5.0 mm from colliders[0] (sphere)"
    assert place(spec, params, (0.45, 0.25, 0.13)) == ", at (0.450, 0.250, 0.130) m, 10.0 mm inside colliders[0] (sphere)"
    assert place(spec, params, (0.9, 0.003, 0.2)) == ", at (0.900, 0.003, 0.200) m, 3.0 mm from the domain's -y wall"
    assert place(spec, params, None) == "" and place(spec, params, (float("nan"), 0, 0)) == ""


@pytest.mark.parametrize("fault, message", [
    ("nan", "frame 0002: sim unstable: NaN/inf in particle state; lower sim.cfl or sim.max_dt"),
    ("escape", "frame 0002: sim unstable: 1 particle(s) escaped the domain; lower sim.cfl"),
])
def test_corrupt_state_stops_naming_frame_and_keeps_earlier_frames(job_copy, monkeypatch, capsys, fault, message):
    """The other two checks on every finished frame. The solver's own clamps keep a healthy run
    finite and inside the domain, so the fault is injected into the second frame's snapshot; the
    real sim stage must then refuse to write that frame, keep frame 1, and say why in one line."""
    from pipeline import cli
    from solver.sph import SPHSolver

    job = job_copy()
    args = small()
    spec = spec_of(job, args)
    real, calls = SPHSolver.snapshot, []

    def snapshot(self):
        data = real(self)
        calls.append(1)
        if len(calls) == 2:                                  # frame 2 (frame 1 is the fill)
            if fault == "nan":
                data["velocity"][7, 1] = float("nan")
            else:
                data["position"][7] = np.add(spec.domain.max, [0.0, 0.01, 0.0])
        return data

    monkeypatch.setattr(SPHSolver, "snapshot", snapshot)
    code = cli.main(["run", str(job), *args, "--stage", "sim"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("sphshot: error:")]
    assert code == 1, err
    assert lines == [f"sphshot: error: {message}"], err
    paths = cache.ShotPaths.for_spec(spec)
    assert cache.scan(spec, paths, "sim", spec.frames).valid == (1,)
    assert not paths.sim_frame(2).exists()


# What Taichi's runtime raises when the device fails (its logger's "[file:function@line] what",
# as RuntimeError): out of device memory mid-shot here, the message CUDA's driver gives.
DEVICE_ERROR = ("[cuda_driver.h:operator()@92] CUDA Error CUDA_ERROR_OUT_OF_MEMORY: out of memory while "
                "calling mem_alloc (cuMemAlloc_v2)")


def test_a_device_failure_mid_shot_is_one_line_and_the_run_resumes(job_copy, monkeypatch, capsys, caplog):
    """A GPU that runs out of memory, is reset or loses its driver mid-shot fails inside a Taichi
    call with a RuntimeError. The sim stage must say so in one line naming the frame and the
    device, exit 6 (not the shot's doing: worth a retry elsewhere), keep the frames before it,
    and a second run resume from the last checkpoint. The failure is injected into the third
    frame's step (no device fails on request)."""
    from pipeline import cli
    from solver.sph import SPHSolver

    job, args = job_copy(), small("shot.checkpoint_every=1")
    real, calls = SPHSolver.advance_to, []

    def advance_to(self, t, should_stop=None):
        calls.append(t)
        if len(calls) == 2:                   # frame 3: frame 1 is the fill, frame 2 the first call
            raise RuntimeError(DEVICE_ERROR)
        return real(self, t, should_stop)

    monkeypatch.setattr(SPHSolver, "advance_to", advance_to)
    code = cli.main(["run", str(job), *args, "--stage", "sim"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("sphshot: error:")]
    assert code == 6 and "Traceback" not in err, err
    assert lines == ["sphshot: error: frame 0003: sim: the cpu device failed: CUDA Error CUDA_ERROR_OUT_OF_MEMORY: "
                     "out of memory while calling mem_alloc (cuMemAlloc_v2); the frames before it are kept: run "
                     'again to resume from the last checkpoint, or run on another device (sim.backend = "cpu")'], err
    spec = spec_of(job, args)
    paths = cache.ShotPaths.for_spec(spec)
    assert cache.scan(spec, paths, "sim", spec.frames).valid == (1, 2)

    monkeypatch.setattr(SPHSolver, "advance_to", real)
    caplog.clear()
    with caplog.at_level("INFO", logger="sphshot"):
        assert cli.main(["run", str(job), *args, "--stage", "sim"]) == 0
    assert "sim: resuming from checkpoint at frame 2" in caplog.text
    assert cache.scan(spec, paths, "sim", spec.frames).valid == tuple(spec.frames)


def test_a_device_failure_while_surfacing_is_one_line_and_anything_else_a_traceback(job_copy, monkeypatch, capsys):
    """The surfacer runs on the device too: its failure is one line naming the frame, exit 6, and
    the frames before it stay published. A RuntimeError that is not the device's (a bug) is not
    dressed up as one: it reaches the caller whole, traceback and all."""
    from pipeline import cli
    from pipeline.stages import surface

    job, args = job_copy(), small()
    assert cli.main(["run", str(job), *args, "--stage", "sim"]) == 0
    real, calls = surface.surface_frame, []

    def failing(message):
        def surface_frame(spec, data, attrs, frame):
            calls.append(frame)
            if len(calls) == 2:
                raise RuntimeError(message)
            return real(spec, data, attrs, frame)
        return surface_frame

    monkeypatch.setattr(surface, "surface_frame", failing(DEVICE_ERROR))
    capsys.readouterr()
    code = cli.main(["run", str(job), *args, "--stage", "surface"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("sphshot: error:")]
    assert code == 6 and "Traceback" not in err, err
    assert len(lines) == 1 and lines[0].startswith(
        f"sphshot: error: frame {calls[1]:04d}: surfacing: the cpu device failed: CUDA Error CUDA_ERROR_OUT_OF_MEMORY"), err
    spec = spec_of(job, args)
    assert cache.scan(spec, cache.ShotPaths.for_spec(spec), "surface", spec.frames).valid == (calls[0],)

    calls.clear()
    monkeypatch.setattr(surface, "surface_frame", failing("dictionary changed size during iteration"))
    with pytest.raises(RuntimeError, match="dictionary changed size"):
        cli.main(["run", str(job), *args, "--stage", "surface"])


def test_a_dask_task_whose_device_failed_is_raised_for_dask_to_retry(job_copy, monkeypatch):
    """On a Dask worker a frame's failure comes back as the task's result (Dask must not run a
    frame that fails the same way again), but a device's failure is the worker's, not the
    frame's: frame_task raises it, so that Dask retries the task, on another worker."""
    from pipeline import executor
    from pipeline.errors import DeviceFailed, StageError

    spec = spec_of(job_copy(), small())
    paths = cache.ShotPaths.for_spec(spec)
    for error, raised in ((DeviceFailed("frame 0002: surfacing: the cuda device failed: ..."), True),
                          (StageError("frame 0002: surfacing: no particles"), False)):
        def run_here(*_args, error=error):
            raise error
        monkeypatch.setattr(executor, "run_here", run_here)
        if raised:
            with pytest.raises(DeviceFailed):
                executor.frame_task("surface", spec, [2], paths, None)
        else:
            assert executor.frame_task("surface", spec, [2], paths, None).error == str(error)


def test_too_many_particles_for_the_neighbour_lists_is_one_error_line(job_copy, monkeypatch, capsys):
    """Past 2^31 list entries (about 22M particles at the default smoothing radius) the solver
    cannot index its neighbour lists; the limit is lowered here so a small shot reaches it."""
    from pipeline import cli
    from solver import sph

    job = job_copy()
    monkeypatch.setattr(sph, "MAX_LIST_ENTRIES", 1000)
    code = cli.main(["run", str(job), *small(), "--stage", "sim"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("sphshot: error:")]
    assert code == 1, err
    assert len(lines) == 1 and "Traceback" not in err, err
    assert "over the limit of 1,000; use fewer particles (a larger sim.particle_radius" in lines[0]
    spec = spec_of(job, small())
    assert cache.scan(spec, cache.ShotPaths.for_spec(spec), "sim", spec.frames).valid == ()


def _all_final_files_complete(root: Path) -> int:
    """Every file under a final name opens and holds its datasets; returns how many."""
    n = 0
    for folder in ("sim", "checkpoints"):
        for p in (root / folder).glob("*.h5"):
            with h5py.File(p, "r") as f:
                assert f["position"].shape[0] > 0, p
                assert "velocity" in f and "id" in f, p
            n += 1
    return n


def start_sim(tmp_path, *overrides, **popen):
    """Start `sphshot run --stage sim` of a small dam break in the background."""
    job = tmp_path / "dambreak.toml"
    job.write_text((ROOT / "jobs" / "dambreak.toml").read_text())
    args = small(*overrides)
    spec = spec_of(job, args)
    cmd = [sys.executable, "-m", "pipeline.cli", "run", str(job), "--stage", "sim", *args]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=dict(os.environ, PYTHONUNBUFFERED="1"), **popen)
    return job, args, spec, cache.ShotPaths.for_spec(spec), proc


def test_sigkill_resumes_from_checkpoint(tmp_path):
    """Kill the sim with SIGKILL part-way; rerun resumes from the last checkpoint, never frame 1."""
    job, args, spec, paths, proc = start_sim(tmp_path, "shot.frame_end=24", "shot.checkpoint_every=3",
                                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sim_hash = cache.stage_hashes(spec)["sim"]

    def stamped():        # checkpoints a resume takes: published and stamped
        return [c for c in paths.checkpoints() if cache.check_file(paths.checkpoint(c), sim_hash) == "valid"]
    deadline = time.time() + 300
    try:
        while time.time() < deadline:
            if any(c >= 7 for c in stamped()):
                break
            assert proc.poll() is None, "the sim finished before it could be killed; make it longer"
            time.sleep(0.05)
        else:
            pytest.fail("no checkpoint at frame >= 7 within 300 s")
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    killed_at = max(stamped())
    assert killed_at < 24
    assert _all_final_files_complete(spec.output_root) > 0
    early = {f: paths.sim_frame(f).stat().st_mtime_ns for f in range(1, killed_at + 1)
             if paths.sim_frame(f).exists()}
    first_missing = min(f for f in spec.frames if f not in early)
    resumed = max(c for c in stamped() if c < first_missing) if early else 1
    rerun = sphshot("run", job, "--stage", "sim", *args, check=True)
    assert f"sim: resuming from checkpoint at frame {resumed}" in rerun.stderr
    assert resumed > 1, "resumed from the beginning"
    assert cache.scan(spec, paths, "sim", spec.frames).valid == tuple(spec.frames)
    assert {f: paths.sim_frame(f).stat().st_mtime_ns for f in early} == early, "frames before the kill were rewritten"
    assert _all_final_files_complete(spec.output_root) >= 24
    leftovers = list((spec.output_root / "sim").glob(".*.tmp")) + list(paths.checkpoint_dir.glob(".*.tmp"))
    assert leftovers == [], f"temporary files left behind: {leftovers}"


def test_atomic_path_never_publishes_a_partial_file(tmp_path):
    final = tmp_path / "f.0001.h5"
    with pytest.raises(RuntimeError):
        with cache.atomic_path(final) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("killed")
    assert not final.exists() and list(tmp_path.iterdir()) == []
    with cache.atomic_path(final) as tmp:
        tmp.write_bytes(b"whole")
    assert final.read_bytes() == b"whole"
    assert [p.name for p in tmp_path.iterdir()] == ["f.0001.h5"]


def test_a_writers_system_error_names_the_file_it_was_writing(tmp_path):
    """An OSError inside atomic_path that names no file (Pillow's full-disk error did not: the
    CLI said only "No space left on device"), or names the hidden temporary, names the final
    file; an error that already names another file, or has no errno (its own message), passes
    as it is."""
    import errno

    final = tmp_path / "x.contact.png"
    for raised in (OSError(errno.ENOSPC, "No space left on device"), None):
        with pytest.raises(OSError) as caught:
            with cache.atomic_path(final) as tmp:
                raise raised or OSError(errno.ENOSPC, "No space left on device", str(tmp))
        assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(final)
        assert caught.value.strerror == "No space left on device"
    other = OSError(errno.ENOENT, "No such file or directory", "/elsewhere/in.png")
    own = OSError(f"{final}: the movie written could not be read")
    for raised in (other, own):
        with pytest.raises(OSError) as caught:
            with cache.atomic_path(final):
                raise raised
        assert caught.value is raised
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_under_hdf5_is_the_systems_error_naming_the_frame(tmp_path):
    """HDF5 reports a failed write as a long message holding the system's errno (the CLI printed
    "Unable to synchronously create file (file write failed: time = ..., filename = <the
    temporary>, ..."), and where the disk filled as the file closed, as a RuntimeError, its
    objects' finalisers printing tracebacks after it (the 12 MB disk of
    test_a_disk_too_small_is_refused... once caught a checkpoint so). write_h5 on a full 64 kB
    tmpfs (skipped where none can be mounted), for files from 4 kB (which fit) past the disk's
    size, stepped so that some fill it in their data and some in the metadata HDF5 writes at
    close: every failure is ENOSPC naming the frame, nothing is left behind, and nothing is
    raised from a finaliser."""
    import errno
    import gc

    from conftest import mounted_tmpfs

    from pipeline.formats import write_h5

    unraisable = []
    hook, sys.unraisablehook = sys.unraisablehook, unraisable.append
    try:
        with mounted_tmpfs(tmp_path / "disk", "size=64k") as disk:
            failed = 0
            for n in range(100, 8000, 150):
                final = disk / "f.0001.h5"
                datasets = {f"d{k}": np.ones((n // 10 + 1, 3), np.float32) for k in range(10)}
                try:
                    write_h5(final, datasets, {f"a{k}": np.arange(20) for k in range(30)})
                except OSError as err:
                    failed += 1
                    assert (err.errno, err.strerror, err.filename) == \
                        (errno.ENOSPC, "No space left on device", str(final))
                    assert list(disk.iterdir()) == []
                else:
                    final.unlink()
            gc.collect()
            assert 0 < failed < len(range(100, 8000, 150))
            with pytest.raises(OSError) as caught:
                write_h5(final, {"position": np.ones((100_000, 3), np.float32)}, {"frame": 1})
            assert (caught.value.errno, caught.value.filename) == (errno.ENOSPC, str(final))
            assert list(disk.iterdir()) == []
    finally:
        sys.unraisablehook = hook
    assert not unraisable, [str(u.exc_value) for u in unraisable]


def test_dead_temporaries_are_removed_but_live_ones_kept(tmp_path):
    dead = tmp_path / f".a.0001.h5.{cache.HOST}-999999999.tmp"
    live = tmp_path / f".a.0002.h5.{cache.HOST}-{os.getppid()}.tmp"
    other_host = tmp_path / ".a.0003.h5.otherhost-1.tmp"
    for p in (dead, live, other_host):
        p.write_text("x")
    assert cache.remove_dead_temporaries(tmp_path) == 1
    assert not dead.exists() and live.exists() and other_host.exists()


def test_sigterm_writes_checkpoint_and_exits_5(tmp_path):
    """SIGTERM (or SLURM's SIGUSR1 warning) during the sim: checkpoint, exit 5, clean resume."""
    job, args, spec, paths, proc = start_sim(tmp_path, "shot.frame_end=40", "shot.checkpoint_every=100",
                                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while time.time() < deadline and not paths.sim_frame(4).exists():
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 5, err
    assert "stopped by SIGTERM" in err and "Traceback" not in err
    written = [f for f in spec.frames if paths.sim_frame(f).exists()]
    assert max(paths.checkpoints()) == max(written) >= 4, "the checkpoint holds the last finished frame"
    rerun = sphshot("run", job, "--stage", "sim", *args, check=True)
    assert f"sim: resuming from checkpoint at frame {max(written)}" in rerun.stderr
    assert cache.scan(spec, paths, "sim", spec.frames).valid == tuple(spec.frames)


def test_a_fluid_block_inside_a_collider_is_one_line(job_copy):
    """Every lattice site of the block lies inside the sphere: the sim says so in one line
    (it was a traceback)."""
    job = job_copy()
    proc = sphshot("run", job, *small("colliders.0.radius=2.0"), "--stage", "sim")
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("sphshot: error:")]
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert len(lines) == 1 and "expected at least one particle, got 0" in lines[0], proc.stderr
    spec = spec_of(job, small("colliders.0.radius=2.0"))
    assert not spec.output_root.exists(), "the failed first run left its version folder behind"


def test_stage_timing_lines_count_from_each_stage_start():
    """The closing lines give each stage's own time (they were cumulative from the run's
    start, so the render line included the sim's and the surface's time)."""
    import io

    from pipeline.progress import Progress

    out = io.StringIO()
    p = Progress(stream=out, interactive=False)
    p.begin({"sim": 1, "surface": 1})
    sim = p.for_stage("sim")
    time.sleep(0.3)
    sim.frame_done(1)
    surface = p.for_stage("surface")
    time.sleep(0.1)
    surface.frame_done(1)
    p.end()
    times = {ln.split(":")[1].strip(): float(ln.rsplit(" in ", 1)[1].split()[0])
             for ln in out.getvalue().splitlines() if " frame(s) in " in ln}
    assert times["sim"] >= 0.3 and 0.1 <= times["surface"] < 0.3, times
    # a stage that started late and finished no frame (it failed) reads its own time, not a
    # negative one (it read "render: 0 frame(s) in -5.2 s")
    out = io.StringIO()
    p = Progress(stream=out, interactive=False)
    p.begin({"sim": 1, "render": 1})
    time.sleep(0.1)
    p.for_stage("sim").frame_done(1)
    p.for_stage("render")
    time.sleep(0.3)
    p.end()
    render_line = [ln for ln in out.getvalue().splitlines() if "render: 0 frame(s) in" in ln]
    assert render_line and 0.3 <= float(render_line[0].rsplit(" in ", 1)[1].split()[0]) < 0.6, out.getvalue()


def test_background_writer_keeps_order_and_reports_errors():
    """The sim stage's writer: each write's callback right after it, on the writer thread and in
    submission order; at most MAX_PENDING writes outstanding; a write's error raised on the
    calling thread at the next drain; everything submitted before an error still written when
    it closes quietly."""
    import threading
    import time as _time

    from pipeline.stages.sim import BackgroundWriter

    main, seen, written = threading.get_ident(), [], []

    def slow(n):
        _time.sleep(0.01)
        written.append(n)
        return n

    w = BackgroundWriter()
    for n in range(6):
        w.submit(slow, n, done=lambda r: seen.append((r, written[-1] == r, threading.get_ident() != main)))
        assert len(w._pending) <= w.MAX_PENDING
    w.close()
    assert seen == [(n, True, True) for n in range(6)] and written == list(range(6))

    def fail(_):
        raise OSError("disk full")

    w = BackgroundWriter()
    with pytest.raises(OSError, match="disk full"):   # at the submit if already failed, else here
        w.submit(fail, 0)
        w.drain()
    w.submit(slow, 7)
    w.submit(fail, 0)                  # (7 is still being written: nothing raises yet)
    w.close(quiet=True)                # an error is already on its way: this one is dropped
    assert written[-1] == 7


def _copy_shot(shot, dst: Path) -> Path:
    """A copy of the module's shot, every stage valid for small() (tests before may have
    rendered it with other settings)."""
    import shutil
    job, _ = shot
    shutil.copytree(job.parent, dst)
    job = dst / job.name
    if not cache.scan(spec_of(job, small()), cache.ShotPaths.for_spec(spec_of(job, small())), "render",
                      spec_of(job, small()).frames).complete:
        sphshot("run", job, *small(), "--stage", "render", "--force", check=True)
    return job


def _status_line(stdout: str, stage: str) -> str:
    return next(ln for ln in stdout.splitlines() if ln.strip().startswith(stage + " "))


def test_a_truncated_frame_is_corrupt_and_computed_again(shot, tmp_path):
    """Issue 19, item 5: a truncated sim frame, mesh and render (a copy cut short, a writer that
    failed without an error) counted as valid. Each frame's files are stamped with their size
    and digest when published: status says corrupt, and run computes exactly those frames again
    (and what was made from them); `status --verify` also finds a file changed at its own
    size."""
    job = _copy_shot(shot, tmp_path / "copy")
    spec = spec_of(job, small())
    paths = cache.ShotPaths.for_spec(spec)
    for path in (paths.surface_meshes(4)[None], paths.render_frame(5)):
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    status = sphshot("status", job, *small(), check=True).stdout
    assert "corrupt    1" in _status_line(status, "surface") and "(corrupt: 4)" in _status_line(status, "surface")
    assert "(corrupt: 5)" in _status_line(status, "render"), status
    before = mtimes(spec.output_root / "render")
    mesh4 = paths.surface_meshes(4)[None]
    proc = sphshot("run", job, *small(), check=True)
    # surface 4 again; render 5 (corrupt), and 4 planned (its surface frame is computed again)
    # but left as it was: the surface frame came out the same bytes as the one it was made from
    assert "sphshot: surface: 1 frame(s) in" in proc.stdout and "sphshot: render: 2 frame(s) in" in proc.stdout
    render_line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("sphshot: render: 2 frame(s) in"))
    assert render_line.endswith("(1 found valid already)"), render_line
    assert cache.check_file(mesh4, cache.stage_hashes(spec)["surface"], verify=True) == "valid"
    after = mtimes(spec.output_root / "render")
    changed = {name for name in after if after[name] != before.get(name)}
    frames_changed = {n for n in changed if n.endswith(".png") and ".contact." not in n}
    assert frames_changed == {f"{spec.shot.name}.0005.png"}, changed
    for stage in cache.STAGES:
        assert cache.scan(spec, paths, stage, spec.frames).complete, stage
    # same size, other bytes: only a full read finds it
    frame = paths.render_frame(2)
    data = bytearray(frame.read_bytes())
    data[-20] ^= 0xFF
    frame.write_bytes(bytes(data))
    assert "corrupt    0" in _status_line(sphshot("status", job, *small(), check=True).stdout, "render")
    assert "(corrupt: 2)" in _status_line(sphshot("status", job, *small(), "--verify", check=True).stdout, "render")


def test_a_sequence_of_two_parameter_sets_is_never_valid(shot, tmp_path):
    """Issue 19, items 1 and 3: frames 4-6 rendered at another resolution marked all six valid
    and the movie was made of both sizes; --force on some frames deleted the others. Validity
    is per frame: the first three show stale, no movie or contact sheet is made from the mix,
    a plain run refuses (exit 3), and --force --frames 1 recomputes frame 1 alone, leaving 2
    and 3 on disk, stale."""
    job = _copy_shot(shot, tmp_path / "copy")
    spec = spec_of(job, small())
    paths = cache.ShotPaths.for_spec(spec)
    other = small("render.resolution=[120, 72]")
    paths.movie.unlink()
    paths.contact_sheet.unlink()
    proc = sphshot("run", job, *other, "--stage", "render", "--frames", "4-6", "--force", check=True)
    assert "no movie or contact sheet until they are computed again" in proc.stdout
    assert not paths.movie.exists() and not paths.contact_sheet.exists()
    sc = cache.scan(spec_of(job, other), paths, "render", spec.frames)
    assert sc.valid == (4, 5, 6) and sc.stale == (1, 2, 3)
    refused = sphshot("run", job, *other, "--stage", "render")
    assert refused.returncode == 3 and "frame(s) 1-3" in refused.stderr
    kept = {f: paths.render_frame(f).stat().st_mtime_ns for f in (2, 3)}
    sphshot("run", job, *other, "--stage", "render", "--frames", "1", "--force", check=True)
    sc = cache.scan(spec_of(job, other), paths, "render", spec.frames)
    assert sc.valid == (1, 4, 5, 6) and sc.stale == (2, 3)
    assert {f: paths.render_frame(f).stat().st_mtime_ns for f in (2, 3)} == kept, "stale frames were touched"


def test_resume_takes_only_checkpoints_made_for_these_parameters(job_copy):
    """Checkpoints are stamped like frames: a resume skips one that is corrupt (here cut short)
    and goes back to the one before, and skips ones made with other sim parameters."""
    job = job_copy()
    args = small()
    spec = spec_of(job, args)
    paths = cache.ShotPaths.for_spec(spec)
    sphshot("run", job, *args, "--stage", "sim", check=True)
    assert paths.checkpoints() == [1, 3, 5, 6]
    for f in (5, 6):
        paths.sim_frame(f).unlink()
    ckpt = paths.checkpoint(3)
    ckpt.write_bytes(ckpt.read_bytes()[:1000])
    rerun = sphshot("run", job, *args, "--stage", "sim", check=True)
    assert "sim: resuming from checkpoint at frame 1" in rerun.stderr, rerun.stderr
    assert cache.scan(spec, paths, "sim", spec.frames).complete
    # the same checkpoints, stamped as if made with other parameters: the run starts afresh
    for c in paths.checkpoints():
        cache.stamp(paths.checkpoint(c), "another-hash")
    paths.sim_frame(6).unlink()
    rerun = sphshot("run", job, *args, "--stage", "sim", check=True)
    assert "resuming from checkpoint" not in rerun.stderr and "sim: dfsph," in rerun.stderr


def test_a_stage_and_its_downstream_in_one_command(shot, tmp_path):
    """Issue 19, item 8: a surface change took two forced runs (surface, then render).
    `--stage surface+ --force` recomputes surface and render and leaves the sim alone; status
    names the movie and contact sheet."""
    job = _copy_shot(shot, tmp_path / "copy")
    spec = spec_of(job, small())
    root = spec.output_root
    sim_before, render_before = mtimes(root / "sim"), mtimes(root / "render")
    changed = small("surface.iso=0.55")
    proc = sphshot("run", job, *changed, "--stage", "surface+", "--force", check=True)
    assert "sphshot: surface: 6 frame(s) in" in proc.stdout and "sphshot: render: 6 frame(s) in" in proc.stdout
    assert mtimes(root / "sim") == sim_before
    after = mtimes(root / "render")
    assert all(after[f"{spec.shot.name}.{f:04d}.png"] != render_before[f"{spec.shot.name}.{f:04d}.png"]
               for f in spec.frames)
    status = sphshot("status", job, *changed, check=True).stdout
    paths = cache.ShotPaths.for_spec(spec)
    assert f"movie: {paths.movie}" in status and f"contact sheet: {paths.contact_sheet}" in status


def test_a_full_disk_is_one_line_and_publishes_nothing(job_copy, monkeypatch, capsys):
    """Issue 19, items 5 and 7: on a full disk pyopenvdb wrote a truncated .vdb without an
    error and it was published; other writers' OSErrors were tracebacks. The .vdb is read back
    before it is published, and an OSError anywhere in a run is one line, exit 1."""
    import errno
    import importlib

    import pyopenvdb

    from pipeline import formats
    from pipeline.cli import main

    # the sim stage imported before the patches below: imported under them (as a -k selection
    # of tests can leave it), it would bind the failing writer for the rest of the session
    importlib.import_module("pipeline.stages.sim")

    # a writer that "succeeds" but leaves a cut-short file
    real_write = pyopenvdb.write

    def short_write(path, grids):
        real_write(path, grids=grids)
        with open(path, "r+b") as fh:
            fh.truncate(100)
    monkeypatch.setattr(pyopenvdb, "write", short_write)
    grid = pyopenvdb.FloatGrid()
    grid.name = "density"
    final = job_copy().parent / "x.vdb"
    with pytest.raises(OSError, match="could not be read back"):
        formats.write_vdb(final, [grid])
    assert not final.exists() and not list(final.parent.glob(".x.vdb*"))

    # ENOSPC from the sim's frame writer, through the CLI in this process
    job = job_copy()

    def full(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device", str(job.parent / "out"))
    monkeypatch.setattr(formats, "write_h5", full)
    monkeypatch.setattr("pipeline.stages.sim.write_h5", full)
    monkeypatch.setattr("pipeline.stages.sim.write_frame", full)
    code = main(["run", str(job), *small(), "--stage", "sim"])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("sphshot: error")]
    assert code == 1 and "Traceback" not in err
    assert lines == [f"sphshot: error: No space left on device: {job.parent / 'out'} (nothing half-written was "
                     f"published)"], err


def test_clean_removes_stale_frames_and_says_so(shot, tmp_path):
    """Issue 19: stale frames stay until recomputed or removed by `sphshot clean`, which says
    what it removes (--dry-run: what it would) and touches nothing else."""
    job = _copy_shot(shot, tmp_path / "copy")
    other = small("render.resolution=[120, 72]")
    sphshot("run", job, *other, "--stage", "render", "--frames", "4-6", "--force", check=True)
    spec = spec_of(job, other)
    paths = cache.ShotPaths.for_spec(spec)
    dry = sphshot("clean", job, *other, "--stage", "render", "--stale", "--dry-run", check=True).stdout
    assert "render: would remove 3 stale or corrupt frame(s) 1-3 (3 file(s))" in dry
    assert all(paths.render_frame(f).exists() for f in spec.frames)
    out = sphshot("clean", job, *other, "--stage", "render", "--stale", check=True).stdout
    assert "render: removed 3 stale or corrupt frame(s) 1-3 (6 file(s))" in out      # frames and stamps
    sc = cache.scan(spec, paths, "render", spec.frames)
    assert sc.missing == (1, 2, 3) and sc.valid == (4, 5, 6)
    assert not any(cache.stamp_path(paths.render_frame(f)).exists() for f in (1, 2, 3))
    assert cache.scan(spec, paths, "surface", spec.frames).complete, "another stage was touched"
    assert "surface: nothing to remove" in sphshot("clean", job, *other, "--stage", "surface", "--stale",
                                                   check=True).stdout


def test_two_runs_with_other_parameters_never_share_a_version(shot, tmp_path):
    """Issue 19, item 2: two surface runs at once, iso 0.3 and 0.7, interleaved their frames in
    one version and both exited 0. The second is refused (exit 3, one line naming the first);
    a run with the same parameters may join; the first finishes with every frame its own."""
    job = _copy_shot(shot, tmp_path / "copy")
    first_args = small("surface.iso=0.3")
    spec = spec_of(job, first_args)
    runs = spec.output_root / ".runs"
    cmd = [sys.executable, "-m", "pipeline.cli", "run", str(job), *first_args, "--stage", "surface", "--force"]
    first = subprocess.Popen(cmd, cwd=ROOT, env=dict(os.environ, PYTHONUNBUFFERED="1"), text=True,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 60
        while not (runs.is_dir() and list(runs.glob("*.json"))) and time.time() < deadline:
            assert first.poll() is None, first.communicate()
            time.sleep(0.02)
        other = sphshot("run", job, *small("surface.iso=0.7"), "--stage", "surface", "--force")
        lines = [ln for ln in other.stderr.splitlines() if ln.startswith("sphshot: error")]
        assert other.returncode == 3 and len(lines) == 1, other.stderr
        assert f"another run ({cache.HOST} pid {first.pid}) is writing stage(s) surface" in lines[0]
        same = sphshot("status", job, *first_args, check=True)      # readers are never refused
        assert "surface" in same.stdout
    finally:
        out, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    assert cache.scan(spec, cache.ShotPaths.for_spec(spec), "surface", spec.frames).complete
    assert not runs.exists(), "the registration was left behind"


def test_a_disk_too_small_is_refused_and_one_filling_up_is_one_line(job_copy, tmp_path):
    """On real tmpfs disks (skipped where this machine cannot mount one), the small shot (6.6 MB
    written; estimated 9 MB):
    - on 3 MB it is refused before anything is written: exit 2, one line saying how much it
      would write and how much is free (the estimate left out the surface's meshes and grids
      and the renders, 0.58 MB, and the run started and failed half-way);
    - on 12 MB, filled by another writer once the first sim frame is out (as another job on a
      farm's disk), it stops at its next write: one short line, exit 1, no traceback, no
      temporary left, every file on disk a whole, stamped frame (the cut-short .vdb that
      OpenVDB read back once made that line 1.4 GB long: formats.vdb_cut_short);
    - with the filler gone it resumes to the end, and then runs again with nothing to do, though
      the whole estimate is now more than the disk's free space: what is written counts."""
    job = job_copy()
    with mounted_tmpfs(tmp_path / "small", "size=3m") as disk:
        args = small(f'shot.output="{disk}"')
        proc = sphshot("run", job, *args)
        errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("sphshot: error")]
        assert proc.returncode == 2 and len(errors) == 1, proc.stderr
        assert re.search(r"would write about [\d.]+ MB to .* which has 3 MB free", errors[0]), errors[0]
        assert list(disk.iterdir()) == []

    with mounted_tmpfs(tmp_path / "disk", "size=12m") as disk:
        args = small(f'shot.output="{disk}"')
        spec = spec_of(job, args)
        paths = cache.ShotPaths.for_spec(spec)
        run = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "run", str(job), *args], cwd=ROOT,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.time() + 120
        while not paths.sim_frame(1).exists() and run.poll() is None and time.time() < deadline:
            time.sleep(0.02)
        filler = disk / "filler"
        try:
            with open(filler, "wb") as fh:      # everything that is left (if any: opening fails on a full disk)
                while True:
                    fh.write(b"\0" * 2 ** 16)
                    fh.flush()
        except OSError:
            pass
        try:
            _out, err = run.communicate(timeout=300)
        finally:
            if run.poll() is None:              # never leave it writing to the disk, which then cannot unmount
                run.kill()
                run.wait()
        errors = [ln for ln in err.splitlines() if ln.startswith("sphshot: error")]
        assert run.returncode == 1 and len(errors) == 1 and "Traceback" not in err, err[:2000]
        assert len(errors[0]) < 400 and ("No space left on device" in errors[0] or "could not be read" in errors[0]), \
            errors[0][:2000]
        assert not [p for p in spec.output_root.rglob("*.tmp")], "a temporary was left"
        for stage in cache.STAGES:
            sc = cache.ShotCache(spec, paths).scan(stage, spec.frames, verify=True)
            assert not sc.corrupt and not sc.stale, (stage, sc)

        filler.unlink(missing_ok=True)
        sphshot("run", job, *args, check=True)
        from pipeline.estimate import estimate, free_disk
        assert estimate(spec).disk > free_disk(disk)
        again = sphshot("run", job, *args, check=True)
        assert again.stdout.count("nothing to do") == 3, again.stdout


def test_a_frame_made_from_an_upstream_frame_since_recomputed_is_stale(shot, tmp_path):
    """Issue 19: each file records its upstream frame's identity too. A sim frame computed
    again into other bytes (here: edited and stamped as if its writer had made it) leaves the
    surface frame made from the old one stale (its render follows once that is computed
    again); the others stay valid, and `--stage surface+ --frames 3 --force` mends it."""
    job = _copy_shot(shot, tmp_path / "copy")
    spec = spec_of(job, small())
    paths = cache.ShotPaths.for_spec(spec)
    sim3 = paths.sim_frame(3)
    with h5py.File(sim3, "r+") as f:
        f["position"][0] += np.float32(1e-4)
    cache.stamp(sim3, cache.stage_hashes(spec)["sim"])
    shot_cache = cache.ShotCache(spec, paths)
    assert shot_cache.scan("sim", spec.frames).complete
    surface = shot_cache.scan("surface", spec.frames)
    assert surface.stale == (3,) and surface.valid == (1, 2, 4, 5, 6)
    refused = sphshot("run", job, *small())
    assert refused.returncode == 3 and "or from sim frames computed again since" in refused.stderr
    sphshot("run", job, *small(), "--stage", "surface+", "--frames", "3", "--force", check=True)
    for stage in cache.STAGES:
        assert cache.scan(spec, paths, stage, spec.frames).complete, stage


def test_a_frame_computed_again_from_the_same_input_is_the_same_bytes(shot, tmp_path):
    """The surface stage run again over frames of a finished shot (`--force`) writes every file
    byte for byte as before (meshio's time of writing blanked, OpenVDB's UUID derived from the content),
    so the renders made from them stay valid: before, meshio's clock and OpenVDB's random UUID
    made every re-surfaced frame new bytes, and `status` called its renders stale (all of them
    after a `--force` over the shot) though nothing in them had changed. The sim frames and
    checkpoints (HDF5, one thread or two: the solver's sums are ordered) were already so."""
    job = _copy_shot(shot, tmp_path / "copy")
    spec = spec_of(job, small())
    paths = cache.ShotPaths.for_spec(spec)
    folders = {stage: paths.root / stage for stage in ("sim", "surface", "render")}
    before = {f: f.read_bytes() for d in folders.values() for f in sorted(d.glob("*.*")) if f.is_file()}
    assert any(f.suffix == ".vdb" for f in before) and any(f.suffix == ".ply" for f in before)
    sphshot("run", job, *small(), "--stage", "surface", "--frames", "2-3", "--force", check=True)
    after = {f: f.read_bytes() for f in before}
    changed = [f.name for f in before if before[f] != after[f]]
    assert not changed, changed
    for stage in cache.STAGES:
        assert cache.scan(spec, paths, stage, spec.frames).complete, stage
    again = sphshot("run", job, *small(), check=True)
    assert again.stdout.count("nothing to do") == 3, again.stdout


def test_status_into_a_closed_pipe_says_nothing(shot, monkeypatch, capsys):
    """`sphshot status JOB | head -1`: the reader leaves early and the next write raises
    BrokenPipeError; that is no error (it was "sphshot: error: Broken pipe"): exit 0, nothing
    on stderr."""
    from pipeline.cli import main

    class ClosedPipe:
        def write(self, _text):
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            pass

    job, _ = shot
    monkeypatch.setattr(sys, "stdout", ClosedPipe())
    code = main(["status", str(job), *small()])
    assert code == 0 and capsys.readouterr().err == ""


def test_an_open_top_lets_particles_leave_and_counts_them(tmp_path, caplog):
    """domain.open = ["+y"]: a block thrown upward at 2 m/s (it would rise 0.2 m) in a tank
    0.4 m high with no lid: its upper part flies out. The particles past the top are removed at
    each frame's end and the log counts them; a frame holds only particles inside the domain,
    and the rest keep their ids. With the lid (no open face) every particle stays."""
    from pipeline import cli
    from pipeline.formats import read_frame

    def job(name: str, open_faces: str) -> Path:
        path = tmp_path / f"{name}.toml"
        path.write_text(f"""
[shot]
name = "{name}"
frame_end = 5
output = "out"
[sim]
particle_radius = 0.02
threads = 1
[domain]
min = [0.0, 0.0, 0.0]
max = [0.4, 0.4, 0.4]
open = [{open_faces}]
[[fluids]]
name = "water"
[[fluids.blocks]]
min = [0.1, 0.05, 0.1]
max = [0.3, 0.25, 0.3]
velocity = [0.0, 2.0, 0.0]
[render]
resolution = [64, 36]
ssaa = false
""")
        return path

    counts = {}
    for name, faces in (("lid", ""), ("open", '"+y"')):
        with caplog.at_level("INFO", logger="sphshot"):
            assert cli.main(["run", str(job(name, faces)), "--stage", "sim"]) == 0
        spec = spec_of(job(name, faces), [])
        paths = cache.ShotPaths.for_spec(spec)
        frames = [read_frame(paths.sim_frame(f))[0] for f in spec.frames]
        counts[name] = [len(d["id"]) for d in frames]
        for d in frames:
            assert d["position"][:, 1].max() <= 0.4 + 1e-6
    assert len(set(counts["lid"])) == 1, counts
    assert counts["open"][0] == counts["lid"][0] and 0 < counts["open"][-1] < 0.9 * counts["open"][0], counts
    assert "left through the open face(s) +y and were removed" in caplog.text
    assert set(frames[-1]["id"]) <= set(range(counts["open"][0]))
