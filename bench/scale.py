#!/usr/bin/env python3
"""Scale-out: serial vs Dask for surface+render, and the streaming gain, on jobs/dambreak.toml.

Every measurement runs the real CLI in a fresh copy of the shot, in one session:

1. the sim once (serial), kept as the input of (2) and (3);
2. surface + render with the serial executor (`--stage surface`, then `--stage render`);
3. surface + render with `--executor dask`, one worker and N workers (a LocalCluster each,
   start-up included; each worker bound to its share of the cores): the serial run already
   uses every core inside a frame (Taichi threads, OpenVDB's TBB, llvmpipe), so xN over serial
   is what splitting the cores between frames adds over splitting them inside a frame;
4. surface + render as one command on the simulated shot (`sphshot run JOB`, the sim frames
   already valid: a resume), serial vs N workers; one cluster start-up and one set of imports
   on each side, and Dask runs frame N's render beside frame N+1's surface;
5. the whole shot in sequence (serial: sim, then surface, then render) vs streamed
   (`--executor dask`: surface/render tasks start behind the sim).

Prints wall seconds and the ratios serial/dask and sequence/streamed.

    .venv/bin/python bench/scale.py                 # 48 frames of the example, 2 workers
    .venv/bin/python bench/scale.py --frames 12     # quicker
    .venv/bin/python bench/scale.py --repeat 3      # the one-command pair three times, medians
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SPHSHOT = [sys.executable, "-m", "pipeline.cli"]


def run(job: Path, sets: list[str], *extra: str) -> float:
    cmd = [*SPHSHOT, "run", str(job), *sets, *extra]
    t = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True,
                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
    dt = time.perf_counter() - t
    if proc.returncode != 0:
        sys.exit(f"bench: {' '.join(cmd)} exited {proc.returncode}\n{proc.stderr[-2000:]}")
    return dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--job", default=str(ROOT / "jobs" / "dambreak.toml"))
    ap.add_argument("--frames", type=int, default=48, help="shot length (frame_end)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=1,
                    help="rounds of the one-command pair (serial, then dask), medians printed")
    args = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="sphshot-scale-"))
    sets = ["--set", f"shot.frame_end={args.frames}", "--set", 'shot.output="out"']

    def fresh(name: str, with_sim_from: Path | None = None) -> Path:
        d = work / name
        d.mkdir()
        job = d / "job.toml"
        shutil.copy(args.job, job)
        if with_sim_from is not None:
            shutil.copytree(with_sim_from / "out", d / "out")
        return job

    try:
        base = fresh("base")
        t_sim = run(base, sets, "--stage", "sim")
        serial = fresh("serial", base.parent)
        t_serial = run(serial, sets, "--stage", "surface") + run(serial, sets, "--stage", "render")
        def fan_out(workers: int) -> float:
            job = fresh(f"dask{workers}", base.parent)
            opts = ["--executor", "dask", "--workers", str(workers)]
            return run(job, sets, "--stage", "surface", *opts) + run(job, sets, "--stage", "render", *opts)

        t_dask1 = fan_out(1)
        t_dask = fan_out(args.workers)
        ones = []                 # (serial, dask) pairs, interleaved: the host's noise hits both
        for k in range(args.repeat):
            ones.append((run(fresh(f"one-serial-{k}", base.parent), sets),
                         run(fresh(f"one-dask-{k}", base.parent), sets,
                             "--executor", "dask", "--workers", str(args.workers))))
        t_one_serial = statistics.median(a for a, _ in ones)
        t_one_dask = statistics.median(b for _, b in ones)
        seq = fresh("sequence")
        t_seq = run(seq, sets)
        stream = fresh("stream")
        t_stream = run(stream, sets, "--executor", "dask", "--workers", str(args.workers))
    finally:
        shutil.rmtree(work, ignore_errors=True)

    print(f"# bench/scale.py --frames {args.frames} --workers {args.workers}  ({os.cpu_count()} cores, "
          f"job {Path(args.job).name}, load {os.getloadavg()[0]:.2f} at the end)")
    print(f"sim alone                        {t_sim:7.1f} s")
    print(f"surface+render  serial           {t_serial:7.1f} s")
    print(f"surface+render  dask x1          {t_dask1:7.1f} s   (one worker, all cores)")
    print(f"surface+render  dask x{args.workers}          {t_dask:7.1f} s   speed-up x{t_serial / t_dask:.2f}"
          f" over serial (target >= 1.7), x{t_dask1 / t_dask:.2f} over one worker")
    each = "; ".join(f"{a:.1f}/{b:.1f}" for a, b in ones)
    print(f"surface+render  one command      {t_one_serial:7.1f} s   serial, sim frames cached"
          f"{f' (median of {len(ones)}: {each})' if len(ones) > 1 else ''}")
    print(f"surface+render  one command      {t_one_dask:7.1f} s   dask x{args.workers}, speed-up x{t_one_serial / t_one_dask:.2f}")
    print(f"whole shot      in sequence      {t_seq:7.1f} s")
    print(f"whole shot      streamed (dask)  {t_stream:7.1f} s   speed-up x{t_seq / t_stream:.2f}")


if __name__ == "__main__":
    main()
