"""Farm behaviour: frame ranges from farm environments, claims between overlapping workers,
the Dask executor (same outputs as serial, failures by frame, retry on a lost worker) and
the SLURM / OpenCue / OpenJD exports, each run locally end to end."""
from __future__ import annotations

import json
import logging
import os
import shlex
import shutil
import subprocess
import sys
import threading
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from conftest import ROOT, small, spec_of, sphshot
from pipeline import cache, claims
from pipeline.errors import UsageError
from pipeline.frames import select_frames

SHOT = range(1, 49)


# ------------------------------------------------------------------------------ frame ranges
@pytest.mark.parametrize("arg, chunk, env, expected", [
    (None, None, {}, list(SHOT)),
    ("5-8", None, {}, [5, 6, 7, 8]),
    ("5", 4, {}, [5, 6, 7, 8]),
    ("45", 8, {}, [45, 46, 47, 48]),                                        # clipped at the shot's end
    (None, 4, {"SLURM_ARRAY_TASK_ID": "9"}, [9, 10, 11, 12]),
    (None, None, {"SLURM_ARRAY_TASK_ID": "9", "SPHSHOT_CHUNK": "2"}, [9, 10]),
    (None, None, {"SLURM_ARRAY_TASK_ID": "9"}, [9]),
    (None, None, {"CUE_IFRAME": "13", "CUE_CHUNK": "4", "CUE_RANGE": "1-48"}, [13, 14, 15, 16]),
    (None, None, {"CUE_IFRAME": "13", "CUE_CHUNK": "3", "CUE_RANGE": "1-48x4"}, [13, 17, 21]),
    (None, None, {"CUE_IFRAME": "47", "CUE_CHUNK": "4", "CUE_RANGE": "1-48"}, [47, 48]),
    ("2-3", None, {"SLURM_ARRAY_TASK_ID": "9"}, [2, 3]),                    # --frames wins
])
def test_frames_from_arguments_and_farm_environment(arg, chunk, env, expected):
    assert select_frames(arg, chunk, SHOT, env)[0] == expected


@pytest.mark.parametrize("arg, chunk, env, words", [
    ("5-8", 4, {}, "--frames: with --chunk, expected a single start frame"),
    (None, 4, {}, "--chunk: needs a start frame"),
    (None, None, {"SLURM_ARRAY_TASK_ID": "abc"}, "SLURM_ARRAY_TASK_ID: expected an integer, got 'abc'"),
    (None, None, {"SLURM_ARRAY_TASK_ID": "60"}, "SLURM_ARRAY_TASK_ID: frame 60 is outside"),
    (None, None, {"CUE_IFRAME": "3", "CUE_CHUNK": "0"}, "CUE_CHUNK: expected an integer >= 1, got 0"),
    (None, None, {"CUE_IFRAME": "2", "CUE_RANGE": "1-48x4"}, "CUE_IFRAME: frame 2 is outside"),
    (None, None, {"CUE_IFRAME": "1", "CUE_RANGE": "one"}, "CUE_RANGE: expected A, A-B or A-BxSTEP"),
])
def test_bad_farm_frame_ranges_name_the_variable(arg, chunk, env, words):
    with pytest.raises(UsageError, match=words.replace("(", r"\(")):
        select_frames(arg, chunk, SHOT, env)


def test_bad_farm_variable_through_the_cli_is_one_line_exit_2(job_copy, tmp_path):
    job = job_copy()
    proc = sphshot("run", job, *small(), "--stage", "surface", env={"SLURM_ARRAY_TASK_ID": "x"})
    assert proc.returncode == 2
    assert proc.stderr.strip() == "sphshot: error: SLURM_ARRAY_TASK_ID: expected an integer, got 'x'"
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------ claims
def test_claims_skip_live_owners_and_take_over_dead_ones(tmp_path):
    paths = cache.ShotPaths(root=tmp_path, name="s", mesh_ext="ply", fluids=("water",), per_fluid=False)
    live = paths.claim("render", 2)
    live.parent.mkdir(parents=True)
    live.write_text(f"{cache.HOST} {os.getppid()} 0\n")                  # our parent: alive
    dead = paths.claim("render", 3)
    dead.write_text(f"{cache.HOST} 999999999 0\n")                       # no such process
    far = paths.claim("render", 4)
    far.write_text("otherhost 1 0\n")                                    # another host, fresh
    old = paths.claim("render", 5)
    old.write_text("otherhost 2 0\n")
    t = time.time() - claims.CLAIM_STALE_S - 10                          # heartbeat stopped long ago
    os.utime(old, (t, t))
    with claims.FrameClaims(paths, "render", [1, 2, 3, 4, 5]) as fc:
        got = []
        for frame in fc:
            assert claims.read_owner(paths.claim("render", frame)).pid == os.getpid()
            got.append(frame)
    assert got == [1, 3, 5]
    assert fc.deferred == [2, 4]
    assert not paths.claim("render", 5).exists(), "a claim outlived its frame"
    assert live.exists() and far.exists()


def test_second_sim_on_the_same_shot_waits(job_copy):
    job = job_copy()
    args = small()
    paths = cache.ShotPaths.for_spec(spec_of(job, args))
    claim = paths.claim("sim", None)
    claim.parent.mkdir(parents=True)
    claim.write_text(f"{cache.HOST} {os.getppid()} 0\n")
    proc = sphshot("run", job, *args, "--stage", "sim")
    assert proc.returncode == 4, proc.stderr
    assert "another worker" in proc.stderr and f"pid {os.getppid()}" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


# ------------------------------------------------------------------------ shots to work on
@pytest.fixture(scope="module")
def simmed(tmp_path_factory):
    """A small shot with its sim done (surface and render not)."""
    d = tmp_path_factory.mktemp("simmed")
    job = d / "dambreak.toml"
    job.write_text((ROOT / "jobs" / "dambreak.toml").read_text())
    sphshot("run", job, *small(), "--stage", "sim", check=True)
    return d


def copy_shot(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst / "dambreak.toml"


def output_lines(stdout: str, folder: str) -> list[str]:
    return [ln for ln in stdout.splitlines() if ln.startswith("OUTPUT_FILE:") and f"/{folder}/" in ln]


def test_overlapping_render_workers_render_each_frame_once(simmed, tmp_path):
    job = copy_shot(simmed, tmp_path / "shot")
    args = small()
    sphshot("run", job, *args, "--stage", "surface", check=True)
    cmd = [sys.executable, "-m", "pipeline.cli", "run", str(job), *args, "--stage", "render"]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    procs = [subprocess.Popen(cmd + ["--frames", rng], cwd=ROOT, env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE) for rng in ("1-5", "2-6")]
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err
    rendered = [ln for out, _ in outs for ln in output_lines(out, "render") if ln.endswith(".png;")
                and ".contact." not in ln]
    names = sorted(Path(ln[len("OUTPUT_FILE:"):-1]).name for ln in rendered)
    assert names == [f"dambreak.{f:04d}.png" for f in range(1, 7)], \
        f"each frame must be rendered exactly once across both workers, got {names}"
    spec = spec_of(job, args)
    paths = cache.ShotPaths.for_spec(spec)
    assert cache.scan(spec, paths, "render", spec.frames).valid == tuple(spec.frames)
    assert [p for p in paths.stage_dir("render").glob(".*") if not p.name.endswith(".stamp")] == [], \
        "claims or temporaries left behind"


# ------------------------------------------------------------------------------------ dask
@pytest.mark.parametrize("cpus, n, expected", [
    ([0, 1], 2, [(0,), (1,)]),
    ([0, 1], 1, [(0, 1)]),
    (list(range(8)), 3, [(0, 1, 2), (3, 4, 5), (6, 7)]),
    ([4, 5, 6, 7, 9], 2, [(4, 5, 6), (7, 9)]),          # a SLURM allocation: not from 0, with a gap
    ([0, 1], 3, [(0,), (1,), (0,)]),                    # more workers than cores: one each, in turn
])
def test_cpu_shares_split_the_allowed_cores(cpus, n, expected):
    from pipeline.workers import cpu_shares
    assert cpu_shares(cpus, n) == expected


def worker_bindings(client) -> dict:
    """worker name -> (the cores its process may use, its LP_NUM_THREADS)."""
    names = {addr: w["name"] for addr, w in client.scheduler_info()["workers"].items()}
    bound = client.run(lambda: (tuple(sorted(os.sched_getaffinity(0))), os.environ.get("LP_NUM_THREADS")))
    return {int(names[addr]): b for addr, b in bound.items()}


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two cores to leave one out")
def test_local_cluster_sizes_itself_to_the_allowed_cores():
    """Inside a SLURM allocation (or under taskset) the process may use fewer cores than the
    machine has: the default local cluster has one worker per allowed core, not per core."""
    from pipeline.executor import DaskExecutor
    allowed = os.sched_getaffinity(0)
    one = min(allowed)
    os.sched_setaffinity(0, {one})
    try:
        ex = DaskExecutor()
        try:
            assert worker_bindings(ex.client) == {0: ((one,), "1")}
        finally:
            ex.close()
    finally:
        os.sched_setaffinity(0, allowed)


def test_dask_local_cluster_matches_serial(simmed, tmp_path):
    serial_job = copy_shot(simmed, tmp_path / "serial")
    dask_job = copy_shot(simmed, tmp_path / "dask")
    args = small()
    sphshot("run", serial_job, *args, check=True)
    proc = sphshot("run", dask_job, *args, "--executor", "dask", "--workers", "2", check=True)
    assert "dask: local cluster, 2 worker(s)" in proc.stderr
    assert "ALF_PROGRESS 100%" in proc.stdout
    a = cache.ShotPaths.for_spec(spec_of(serial_job, args))
    b = cache.ShotPaths.for_spec(spec_of(dask_job, args))
    import meshio
    for f in range(1, 7):
        ma, mb = meshio.read(a.surface_meshes(f)[None]), meshio.read(b.surface_meshes(f)[None])
        np.testing.assert_array_equal(ma.points, mb.points, err_msg=f"frame {f}: mesh differs")
        np.testing.assert_array_equal(ma.cells[0].data, mb.cells[0].data)
        ia = np.asarray(Image.open(a.render_frame(f)), np.int16)
        ib = np.asarray(Image.open(b.render_frame(f)), np.int16)
        assert np.abs(ia - ib).max() == 0, f"frame {f}: image differs"
    assert b.movie.exists() and b.contact_sheet.exists()


def test_dask_streams_and_reports_a_failed_frame_by_number(job_copy, monkeypatch):
    """All stages under Dask: surface/render tasks start behind the sim; a frame whose sim file
    is unreadable fails by number, and every other frame still finishes.

    Streaming is checked without timing: the sim (here, in this process) stops after publishing
    frame 1 until the surface task of frame 1 has published its volume. Were the surface tasks
    submitted only once the sim ends, it would wait out its deadline and fail."""
    from pipeline import executor as executor_mod
    from pipeline.executor import DaskExecutor
    from pipeline.progress import Progress
    from pipeline.runner import run_stages

    job = job_copy()
    args = small("shot.frame_end=6")
    spec = spec_of(job, args)
    paths = cache.ShotPaths.for_spec(spec)
    real_run_here, waited = executor_mod.run_here, []

    def sim_waits_for_surface(stage, spec, frames, paths, progress, since=None):
        if stage != "sim":
            return real_run_here(stage, spec, frames, paths, progress, since)

        class WaitAfterFrame1:
            def frame_done(self, frame, files=()):
                progress.frame_done(frame, files)
                if frame == 1:
                    t0, deadline = time.time(), time.time() + 120
                    while not cache.scan(spec, paths, "surface", [1]).complete and time.time() < deadline:
                        time.sleep(0.1)
                    waited.append(time.time() - t0)
        return real_run_here(stage, spec, frames, paths, WaitAfterFrame1(), since)

    monkeypatch.setattr(executor_mod, "run_here", sim_waits_for_surface)
    ex = DaskExecutor(workers=2)
    try:
        run_stages(spec, ["sim", "surface", "render"], list(spec.frames), executor=ex,
                   progress=Progress(stream=open(os.devnull, "w"), interactive=False))
        # the local workers print nothing of their own: a heartbeat racing the shutdown once put a
        # distributed traceback under the failure line checked below
        worker_levels = ex.client.run(
            lambda: __import__("logging").getLogger("distributed.worker").getEffectiveLevel())
    finally:
        ex.close()
    assert worker_levels and set(worker_levels.values()) == {logging.CRITICAL}, worker_levels
    assert waited and waited[0] < 120, "surface frame 1 was not published while the sim waited for it: " \
        "the surface stage did not stream behind the sim"
    assert paths.surface_vdb(1).stat().st_mtime < paths.sim_frame(2).stat().st_mtime
    assert cache.scan(spec, paths, "render", spec.frames).valid == tuple(spec.frames)
    # now break sim frame 3 and recompute surface and render. Stamped again as if its writer had
    # made it so (a truncated or edited file is caught before any work starts: see
    # test_pipeline's corrupt-frame test), so that the surface task itself fails
    paths.sim_frame(3).write_bytes(b"not an HDF5 file")
    cache.stamp(paths.sim_frame(3), cache.stage_hashes(spec)["sim"])
    proc = sphshot("run", job, *args, "--stage", "surface", "--force", "--executor", "dask", "--workers", "2")
    assert proc.returncode == 1
    assert "failed: surface frame 3: frame 0003: surfacing: cannot read" in proc.stderr
    assert "Traceback" not in proc.stderr
    since = paths.sim_frame(3).stat().st_mtime
    for f in (1, 2, 4, 5, 6):
        assert paths.surface_vdb(f).stat().st_mtime >= since, f"frame {f} was not recomputed"


def test_dask_with_an_existing_scheduler(simmed, tmp_path):
    """--scheduler: tasks run on a cluster the user started (here: one worker process)."""
    from dask.distributed import LocalCluster

    job = copy_shot(simmed, tmp_path / "shot")
    args = small()
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        proc = sphshot("run", job, *args, "--stage", "surface", "--scheduler", cluster.scheduler_address,
                       check=True)
        assert f"dask: {cluster.scheduler_address}, 1 worker(s)" in proc.stderr
    spec = spec_of(job, args)
    assert cache.scan(spec, cache.ShotPaths.for_spec(spec), "surface", spec.frames).valid == tuple(spec.frames)
    bad = sphshot("run", job, *args, "--stage", "render", "--scheduler", "tcp://127.0.0.1:9")
    assert bad.returncode == 1 and "--scheduler: cannot reach the Dask scheduler" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1, bad.stderr


def test_dask_task_survives_a_killed_worker(simmed, tmp_path):
    """Kill the worker process while it renders a frame: the scheduler reruns the task on
    another worker (the dead worker's claim is taken over) and every frame ends valid."""
    import psutil
    from pipeline.executor import DaskExecutor
    from pipeline.progress import Progress
    from pipeline.runner import run_stages

    job = copy_shot(simmed, tmp_path / "shot")
    args = small("shot.frame_end=6")
    sphshot("run", job, *args, "--stage", "surface", check=True)
    spec = spec_of(job, args)
    ex = DaskExecutor(workers=2)
    killed = {}
    try:
        pids = ex.client.run(os.getpid)                      # worker address -> pid
        errors = []

        def go():
            try:
                run_stages(spec, ["render"], list(spec.frames), executor=ex,
                           progress=Progress(stream=open(os.devnull, "w"), interactive=False))
            except Exception as exc:                          # noqa: BLE001 - reported below
                errors.append(exc)

        t = threading.Thread(target=go)
        t.start()
        deadline = time.time() + 120
        while time.time() < deadline and not killed:
            busy = {w: keys for w, keys in ex.client.processing().items() if keys}
            for worker, keys in busy.items():
                if any(k.startswith("render-") for k in keys):
                    time.sleep(0.2)                           # let it get into the render
                    psutil.Process(pids[worker]).kill()
                    killed[worker] = keys
                    break
            time.sleep(0.02)
        t.join(timeout=300)
        assert killed, "never saw a worker rendering"
        assert not errors, errors
        # every worker, the restarted one included, is bound to its own share of the cores
        from pipeline.workers import cpu_shares
        shares = cpu_shares(sorted(os.sched_getaffinity(0)), 2)
        assert set(ex.client.run(os.getpid).values()) != set(pids.values()), "no worker was restarted"
        assert worker_bindings(ex.client) == {i: (shares[i], str(len(shares[i]))) for i in range(2)}
    finally:
        ex.close()
    paths = cache.ShotPaths.for_spec(spec)
    assert cache.scan(spec, paths, "render", spec.frames).valid == tuple(spec.frames)


# ---------------------------------------------------------------------------------- exports
def export(job, args, to, chunk=4, extra=()) -> Path:
    proc = sphshot("export", job, *args, "--to", to, "--chunk", chunk, *extra, check=True)
    wrote = next(ln for ln in proc.stdout.splitlines() if ln.startswith("sphshot: wrote"))
    return Path(wrote.rsplit(" ", 1)[1])


def assert_shot_complete(job, args):
    spec = spec_of(job, args)
    paths = cache.ShotPaths.for_spec(spec)
    for stage in cache.STAGES:
        assert cache.scan(spec, paths, stage, spec.frames).valid == tuple(spec.frames), stage
    assert paths.movie.exists()


FAKE_SBATCH = r'''#!/usr/bin/env python3
"""A stand-in for sbatch: records the call, runs --wrap for each array task right away."""
import json, os, subprocess, sys
args, opts = sys.argv[1:], {}
for a in args:
    if a.startswith("--") and "=" in a:
        k, v = a[2:].split("=", 1); opts[k] = v
calls = os.environ["FAKE_SBATCH_LOG"]
n = sum(1 for _ in open(calls)) + 1 if os.path.exists(calls) else 1
tasks = [None]
if "array" in opts:
    rng, step = (opts["array"].split(":") + ["1"])[:2]
    a, b = map(int, rng.split("-"))
    tasks = list(range(a, b + 1, int(step)))
codes = []
for t in tasks:
    env = dict(os.environ, SLURM_JOB_ID=str(1000 + n))
    if t is not None:
        env["SLURM_ARRAY_TASK_ID"] = str(t)
    log = (opts["output"].replace("%x", opts["job-name"]).replace("%j", str(1000 + n))
           .replace("%A", str(1000 + n)).replace("%a", str(t)))
    with open(log, "a") as fh:
        codes.append(subprocess.run(["bash", "-c", opts["wrap"]], env=env, stdout=fh,
                                    stderr=subprocess.STDOUT).returncode)
with open(calls, "a") as fh:
    fh.write(json.dumps({"opts": opts, "args": args, "tasks": tasks, "codes": codes}) + "\n")
print(f"{1000 + n};cluster")
'''


def test_exports_ask_each_stage_for_its_estimated_memory(job_copy, tmp_path):
    """Without --mem each exported stage asks for the memory the pre-flight estimates for a task
    of that stage alone, in 256 MB steps (the small shot: the render's VTK and Mesa make it the
    largest; measured for the example: sim 177-215 MB, surface 380-408, render 553-573 resident), so a
    farm's default per-task memory cannot starve a render and a sim's gigabytes are not booked
    for every render task. In the SLURM script each job's --mem comes before the site's options,
    which win."""
    from pipeline.export import stage_memory_mb

    job = job_copy()
    args = small()
    mb = stage_memory_mb(spec_of(job, args), {})
    assert mb["sim"] < mb["render"] and all(v % 256 == 0 and v >= 256 for v in mb.values()), mb
    slurm = export(job, args, "slurm").read_text()
    for stage in ("sim", "surface", "render"):
        line = next(ln for ln in slurm.splitlines() if ln.startswith(f'{stage}=$("$SBATCH"'))
        assert line.index(f"--mem={mb[stage]}M") < line.index('"${common[@]}"'), line
    root = ET.parse(export(job, args, "opencue")).getroot()
    assert [el.findtext("memory") for el in root.iter("layer")] == [f"{mb[s]}m" for s in ("sim", "surface", "render")]
    steps = json.loads(export(job, args, "openjd").read_text())["steps"]
    assert [{a["name"]: a["min"] for a in st["hostRequirements"]["amounts"]} for st in steps] == \
        [{"amount.worker.memory": mb[s]} for s in ("sim", "surface", "render")]


def test_slurm_export_runs_locally(simmed, tmp_path):
    job = copy_shot(simmed, tmp_path / "shot")
    args = small()
    script = export(job, args, "slurm", extra=("--cpus", "2", "--mem", "1", "--time", "0:30:00", "--gpus", "2"))
    subprocess.run(["bash", "-n", str(script)], check=True)
    fake = tmp_path / "bin" / "sbatch"
    fake.parent.mkdir()
    fake.write_text(FAKE_SBATCH)
    fake.chmod(0o755)
    log = tmp_path / "sbatch.jsonl"
    env = dict(os.environ, PATH=f"{fake.parent}:{os.environ['PATH']}", FAKE_SBATCH_LOG=str(log),
               SPHSHOT_SBATCH='--comment="shot one"', SPHSHOT_SBATCH_SIM="--gres=gpu:1")
    out = subprocess.run(["bash", str(script)], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert "submitted dambreak_v001: sim 1001, surface 1002, render 1003" in out.stdout
    calls = [json.loads(ln) for ln in log.read_text().splitlines()]
    assert [c["opts"]["job-name"] for c in calls] == [f"dambreak_v001.{s}" for s in ("sim", "surface", "render")]
    assert calls[0]["opts"]["signal"] == "B:USR1@120" and "array" not in calls[0]["opts"]
    assert "--requeue" in calls[0]["args"]
    # site options are shell words: a quoted value stays one argument (it was split on spaces)
    assert all("--comment=shot one" in c["args"] for c in calls) and "--gres=gpu:1" in calls[0]["args"]
    # resource requests from the command line: every job, and GPUs for the sim alone
    for c in calls:
        assert {"--cpus-per-task=2", "--mem=1024M", "--time=0:30:00"} <= set(c["args"]), c["args"]
    assert "--gres=gpu:2" in calls[0]["args"] and not any("gpu" in a for c in calls[1:] for a in c["args"])
    # array indices are chunk numbers from 0 (frames 1001-1100 stay under MaxArraySize)
    assert calls[1]["opts"]["dependency"] == "afterok:1001" and calls[1]["tasks"] == [0, 1]
    assert calls[2]["opts"]["dependency"] == "aftercorr:1002" and calls[2]["tasks"] == [0, 1]
    assert all(code == 0 for c in calls for code in c["codes"]), calls
    logs = sorted(p.name for p in (script.parent / "logs").iterdir())
    assert logs == ["dambreak_v001.render.1003_0.log", "dambreak_v001.render.1003_1.log",
                    "dambreak_v001.sim.1001.log", "dambreak_v001.surface.1002_0.log",
                    "dambreak_v001.surface.1002_1.log"]
    task_log = (script.parent / "logs" / "dambreak_v001.surface.1002_1.log").read_text()
    assert "sphshot: surface: 2 frame(s) to do" in task_log, task_log
    assert_shot_complete(job, args)


def test_slurm_sim_requeues_itself_after_a_checkpoint(job_copy, tmp_path):
    """Issue 19, item 9: a sim stopped by SLURM's warning signal checkpointed and exited 5, and
    the jobs waiting on it (afterok) stayed pending forever. The exported sim task passes
    SIGUSR1 on to sphshot and, on exit 5, requeues its own job (a fake scontrol records it)."""
    import re
    import signal as sig

    job = job_copy()
    args = small("shot.frame_end=24", "shot.checkpoint_every=3")
    script = export(job, args, "slurm").read_text()
    wrap = re.search(r"--job-name=\S+\.sim .*?--wrap=('(?:[^']|'\"'\"')*')\)", script, re.S).group(1)
    sim_task = shlex.split(wrap)[0]
    fake = tmp_path / "bin" / "scontrol"
    fake.parent.mkdir()
    fake.write_text(f"#!/bin/sh\necho \"$@\" >> {tmp_path / 'scontrol.log'}\n")
    fake.chmod(0o755)
    env = dict(os.environ, PATH=f"{fake.parent}:{os.environ['PATH']}", SLURM_JOB_ID="4242", PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(["bash", "-c", sim_task], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    paths = cache.ShotPaths.for_spec(spec_of(job, args))
    deadline = time.time() + 300
    while not any(c >= 4 for c in paths.checkpoints()) and time.time() < deadline:
        assert proc.poll() is None, "the sim ended before it could be signalled"
        time.sleep(0.05)
    proc.send_signal(sig.SIGUSR1)            # what --signal=B:USR1 sends the batch shell
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 5, out
    assert "checkpoint written" in out
    assert (tmp_path / "scontrol.log").read_text().split() == ["requeue", "4242"]


# The structure of an OpenCue job spec (cjsl 1.14): children in order, ? optional, * repeated.
CJSL = {
    "spec": ["facility?", "dept?", "show", "shot", "user", "email?", "uid?", "job*", "depends*"],
    "job": ["paused?", "priority?", "maxretries?", "maxcores?", "maxgpus?", "autoeat?", "localbook?",
            "os?", "env*", "layers?"],
    "layers": ["layer+"],
    "layer": ["cmd", "range", "chunk", "cores?", "threadable?", "memory?", "gpus?", "gpu?", "gpu_memory?",
              "timeout?", "timeout_llu?", "tags?", "limits?", "env*", "services?", "outputs*"],
    "services": ["service+"],
    "depends": ["depend*"],
    "depend": ["depjob", "deplayer?", "depframe?", "onjob", "onlayer?", "onframe?"],
}
DEPEND_TYPES = {"LAYER_ON_SIM_FRAME", "PREVIOUS_FRAME", "JOB_ON_JOB", "JOB_ON_LAYER", "JOB_ON_FRAME",
                "LAYER_ON_JOB", "LAYER_ON_FRAME", "LAYER_ON_LAYER", "FRAME_ON_JOB", "FRAME_ON_LAYER",
                "FRAME_ON_FRAME", "FRAME_BY_FRAME"}


def check_cjsl(el: ET.Element) -> None:
    rule = CJSL.get(el.tag)
    if rule is None:
        assert len(el) == 0, f"<{el.tag}> holds text only"
        return
    tags = [c.tag for c in el]
    i = 0
    for item in rule:
        name, mult = (item[:-1], item[-1]) if item[-1] in "?*+" else (item, "")
        n = 0
        while i < len(tags) and tags[i] == name:
            i, n = i + 1, n + 1
        assert not (mult == "" and n != 1) and not (mult == "?" and n > 1) and not (mult == "+" and n < 1), \
            f"<{el.tag}>: expected {item} at position {i}, children are {tags}"
    assert i == len(tags), f"<{el.tag}>: unexpected <{tags[i]}> (children {tags})"
    if el.tag == "layer":
        assert el.get("type") in ("Render", "Util", "Post") and el.get("name")
    if el.tag == "depend":
        assert el.get("type") in DEPEND_TYPES
    for child in el:
        check_cjsl(child)


def test_opencue_export_is_well_formed_and_runs_locally(simmed, tmp_path):
    job = copy_shot(simmed, tmp_path / "shot")
    args = small()
    path = export(job, args, "opencue", extra=("--show", "fx_show", "--service", "sphshot_cpu", "--cpus", "2",
                                               "--mem", "1.5", "--gpus", "1"))
    assert "cjsl-1.14.dtd" in path.read_text()
    root = ET.parse(path).getroot()
    check_cjsl(root)
    assert root.findtext("show") == "fx_show"
    assert {s.text for s in root.iter("service")} == {"sphshot_cpu"}
    assert [el.findtext("cores") for el in root.iter("layer")] == ["2", "2", "2"]
    assert [el.findtext("memory") for el in root.iter("layer")] == ["1536m"] * 3      # cuebot: m = megabytes
    assert [el.findtext("gpus") for el in root.iter("layer")] == ["1", None, None]      # the sim's alone
    layers = {el.get("name"): el for el in root.iter("layer")}
    assert list(layers) == ["sim", "surface", "render"]
    deps = {(d.get("type"), d.findtext("deplayer"), d.findtext("onlayer")) for d in root.iter("depend")}
    assert deps == {("LAYER_ON_LAYER", "surface", "sim"), ("FRAME_BY_FRAME", "render", "surface")}
    # run it as RQD would: per layer in dependency order, each chunk with its tokens replaced
    for name, el in layers.items():
        frames = list(range(1, 7)) if el.findtext("range") == "1-6" else [int(el.findtext("range"))]
        size = int(el.findtext("chunk"))
        for k in range(0, len(frames), size):
            chunk = frames[k:k + size]
            cmd = (el.findtext("cmd").replace("#FRAME_START#", str(chunk[0]))
                   .replace("#FRAME_END#", str(chunk[-1])).replace("#IFRAME#", str(chunk[0])))
            env = dict(os.environ, CUE_IFRAME=str(chunk[0]), CUE_CHUNK=str(size), CUE_RANGE=el.findtext("range"))
            proc = subprocess.run(shlex.split(cmd), env=env, capture_output=True, text=True, timeout=300)
            assert proc.returncode == 0, f"{name} {chunk}: {proc.stderr}"
    assert_shot_complete(job, args)


def test_openjd_export_validates_and_runs_with_openjd_cli(simmed, tmp_path):
    openjd = Path(sys.executable).with_name("openjd")
    if not openjd.exists():
        pytest.fail("openjd-cli is not installed (it is in requirements.lock)")
    job = copy_shot(simmed, tmp_path / "shot")
    args = small()
    path = export(job, args, "openjd")
    template = json.loads(path.read_text())
    params = {p["name"]: p for p in template["parameterDefinitions"]}
    assert params["JobFile"]["type"] == "PATH" and str(job.resolve()) in params["JobFile"]["description"]
    assert params["ShotOutput"]["type"] == "PATH" and params["ShotOutput"]["dataFlow"] == "OUT"
    args_of = [s["script"]["actions"]["onRun"]["args"] for s in template["steps"]]
    assert all("{{Param.JobFile}}" in a and "shot.output='{{Param.ShotOutput}}'" in a for a in args_of)
    check = subprocess.run([str(openjd), "check", str(path)], capture_output=True, text=True)
    assert check.returncode == 0 and "passes validation" in check.stdout, check.stdout + check.stderr
    # resource requests become host requirements (GPUs for the sim alone), and still validate
    sized = export(job, args, "openjd", extra=("--cpus", "4", "--mem", "8", "--gpus", "1", "-o",
                                               str(tmp_path / "sized" / "t.json")))
    amounts = [{a["name"]: a["min"] for a in s["hostRequirements"]["amounts"]}
               for s in json.loads(sized.read_text())["steps"]]
    assert amounts[0] == {"amount.worker.vcpu": 4, "amount.worker.memory": 8192, "amount.worker.gpu": 1}
    assert amounts[1] == amounts[2] == {"amount.worker.vcpu": 4, "amount.worker.memory": 8192}
    check = subprocess.run([str(openjd), "check", str(sized)], capture_output=True, text=True)
    assert check.returncode == 0 and "passes validation" in check.stdout, check.stdout + check.stderr
    spec = spec_of(job, args)
    given = ["-p", f"JobFile={job.resolve()}", "-p", f"ShotOutput={spec.output_root.parent.parent}"]
    run = subprocess.run([str(openjd), "run", str(path), *given, "--step", "render", "--run-dependencies"],
                         capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert_shot_complete(job, args)


def test_export_refuses_a_version_with_stale_frames(simmed, tmp_path):
    """Issue 19, item 9: an export into a version whose frames were made with other parameters
    made a farm job whose every task exited 3. It is refused up front, in one line, exit 3."""
    job = copy_shot(simmed, tmp_path / "shot")
    proc = sphshot("export", job, *small("sim.gravity=[0.0, -5.0, 0.0]"), "--to", "slurm")
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("sphshot: error")]
    assert proc.returncode == 3 and len(lines) == 1 and "Traceback" not in proc.stderr
    assert "sim frame(s) 1-6" in lines[0] and "every farm task of this export would refuse them" in lines[0]
