#!/usr/bin/env python3
"""Every GPU benchmark in one run, each section under its own time limit; prints the lines as
they come and, at the end, one markdown table in bench/RESULTS.md's format. Run by
bench/gpu.sh on a lent GPU machine (which also runs the GPU tests first).

Sections (issue 21's targets in brackets):
  solver    particle-steps/s, WCSPH and DFSPH at 1M and 4M particles on CUDA [WCSPH: 6e8 at
            1M, 1e9 at 4M], and bytes per particle on the device
  dambreak  DFSPH, 1M-particle dam break, simulated seconds per wall second [0.1]
  profile   Taichi's kernel profiler over 20 DFSPH steps at 1M: the kernels that cost most
  profile_wcsph  the same over 20 WCSPH steps at 4M
  surface   the surfacer's splat and marching cubes at 500k and 4M particles [4M: 0.3 s]
  host      a DFSPH step of 1,000 particles: ms a step (the host's launches and reads, which
            keep the GPU idle), launches and reads a step
  stage     the sim stage through the CLI: jobs/dambreak.toml at 435k particles, 24 frames,
            with the GPU's utilisation sampled every 100 ms by nvidia-smi [busy >= 95%]
  showcase  (only when named) jobs/showcase.toml's sim stage for SHOWCASE_S seconds, a few
            frames packed into SHOWCASE_PACK (bench/showcase_frames.py) to render elsewhere

    python3 bench/gpu.py                      # all
    python3 bench/gpu.py --only surface,stage
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[0] = str(ROOT)
from bench.solver import radius_for  # noqa: E402 - the bench scene's radius for a count

PY = sys.executable
BACKEND, SCALE = "cuda", 1.0          # --dry: cpu, particle counts / 200 (to check the script here)
ROWS: list[tuple[str, str, str]] = []          # (what, figure, target)


FUSED = ("k_step", "k_sweeps", "k_rebuild")      # kernels of several passes (see solver/)


def kernel_ms() -> dict[str, float]:
    """{kernel: total ms} from Taichi's kernel profiler (ti.init(kernel_profiler=True)), the
    offloaded tasks of one kernel added up; for the profiled children below."""
    import contextlib
    import io
    import re

    import taichi as ti
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        ti.profiler.print_kernel_profiler_info("count")
    out: dict[str, float] = {}
    for m in re.finditer(r"\[\s*[\d.]+%\s+[\d.]+ s\s+(\d+)x \|\s*[\d.]+\s+([\d.]+)\s+[\d.]+ ms\] (\S+)",
                         buf.getvalue()):
        # k_apply_kappa_c80_0_kernel_0_range_for: the kernel; the fused ones by their tasks
        task = re.match(r"(.*?)_c\d+_\d+_kernel_(\d+)", m.group(3))
        name = m.group(3) if task is None else f"{task[1]}[{task[2]}]" if task[1] in FUSED else task[1]
        out[name] = out.get(name, 0.0) + int(m.group(1)) * float(m.group(2))
    return out


def row(what: str, figure: str, target: str = "") -> None:
    ROWS.append((what, figure, target))
    print(f"ROW | {what} | {figure} | {target}", flush=True)


def run(cmd: list[str], limit: float, env=None) -> tuple[int, str]:
    """(returncode, output) of a child, killed after `limit` seconds (returncode 124)."""
    try:
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=limit, env=env)
        return p.returncode, p.stdout + p.stderr
    except subprocess.TimeoutExpired as exc:
        out = (exc.stdout or b"").decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        return 124, out


def solver_section(limit: float) -> None:
    for solver in ("wcsph", "dfsph"):
        for n in (int(1_000_000 * SCALE), int(4_000_000 * SCALE)):
            rc, out = run([PY, "bench/solver.py", "--only", "sphshot", "--solver", solver, "--backend", BACKEND,
                           "--fluid", "thin", "--particles", str(n), "--radius", str(radius_for(n)), "--stop-at", "0.02",
                           "--device-bytes"], limit / 4)
            line = next((l for l in out.splitlines() if l.startswith("sphshot")), None)
            print(line or out[-1500:], flush=True)
            if line:
                kv = dict(x.split("=", 1) for x in line.split()[1:] if "=" in x)
                target = {("wcsph", 1_000_000): "6e8", ("wcsph", 4_000_000): "1e9"}.get((solver, round(n / SCALE)), "")
                row(f"{solver.upper()} {int(kv['particles']):,} particles: particle-steps/s",
                    f"{float(kv['particle_steps_per_s']):.3g} ({kv['ms_per_step']} ms/step, "
                    f"{kv.get('device_bytes_per_particle', '?')} B/particle on the device)", target)
            else:
                row(f"{solver.upper()} {n:,} particles", f"failed (rc {rc})")


def dambreak_section(limit: float) -> None:
    n = int(1_000_000 * SCALE)
    rc, out = run([PY, "bench/solver.py", "--only", "sphshot", "--solver", "dfsph", "--backend", BACKEND,
                   "--fluid", "thin", "--particles", str(n), "--radius", str(radius_for(n)), "--stop-at", "0.25"], limit)
    line = next((l for l in out.splitlines() if l.startswith("sphshot")), None)
    print(line or out[-1500:], flush=True)
    if line:
        kv = dict(x.split("=", 1) for x in line.split()[1:] if "=" in x)
        row("DFSPH 1M dam break, 0.25 s: simulated s per wall s",
            f"{float(kv['sim_s_per_wall_s']):.3g} ({kv['steps']} steps, {kv['avg_pressure_iters']} + "
            f"{kv['avg_divergence_iters']} iterations a step)", "0.1")
    else:
        row("DFSPH 1M dam break, 0.25 s", f"did not finish in {limit:.0f} s (rc {rc})", "0.1")


PROFILE = r"""
import sys, taichi as ti
sys.path[0] = sys.argv[1]
backend, n, solver = sys.argv[2], int(sys.argv[3]), sys.argv[4]
ti.init(getattr(ti, backend), kernel_profiler=True, log_level=ti.WARN)
import solver.backend as sb
sb._current, sb._arch_name = (backend, 0), backend
sys.argv = sys.argv[:1]
from bench.solver import radius_for, scene
from pipeline.stages.sim import fresh_solver
_params, s = fresh_solver(scene(n, radius_for(n), solver, fluid="thin"))
steps = s.steps
while s.steps < steps + 5:           # compile and warm up the path the stage runs
    s.advance_some(1e30)
ti.sync(); ti.profiler.clear_kernel_profiler_info()
steps = s.steps
while s.steps < steps + 20:          # as the sim stage steps (WCSPH: batches of fused steps)
    s.advance_some(1e30)
ti.sync()
steps = s.steps - steps
from bench.gpu import kernel_ms
recs = kernel_ms()
total = sum(recs.values())
for name, ms in sorted(recs.items(), key=lambda kv: -kv[1])[:8]:
    print(f"PROFILE {name} {ms / steps:.3f} ms/step {100 * ms / total:.0f}%")
print(f"PROFILE total {total / steps:.3f} ms/step in kernels ({steps} steps)")
"""


def profile_section(limit: float, solver: str = "dfsph", n: int = 1_000_000) -> None:
    rc, out = run([PY, "-c", PROFILE, str(ROOT), BACKEND, str(int(n * SCALE)), solver], limit)
    lines = [l for l in out.splitlines() if l.startswith("PROFILE")]
    print("\n".join(lines) or out[-1500:], flush=True)
    if lines:
        top = ", ".join(f"{l.split()[1]} {l.split()[2]}" for l in lines[:4])
        row(f"{solver.upper()} {n // 1_000_000}M: kernel ms per step (top 4)", f"{lines[-1].split()[2]} in all; {top}")


HOST = r"""
import collections, sys, time, taichi as ti
sys.path[0] = sys.argv[1]
ti.init(getattr(ti, sys.argv[2]), log_level=ti.WARN)
import solver.backend as sb
sb._current, sb._arch_name = (sys.argv[2], 0), sys.argv[2]
sys.argv = sys.argv[:1]
from bench.solver import radius_for, scene
from pipeline.stages.sim import fresh_solver
_params, s = fresh_solver(scene(1000, radius_for(1000), "dfsph", fluid="thin"))
while s.steps < 10:                   # compile and warm up
    s.advance_some(1e30)
ti.sync()
import taichi.lang.kernel_impl as K
calls, call = collections.Counter(), K.Kernel.__call__
def counted(self, *a, **k):
    calls[self.func.__name__] += 1
    return call(self, *a, **k)
K.Kernel.__call__ = counted
import solver.sph as sph
read = sph.SPHSolver.read
def counted_read(self, *a, **k):               # on the CPU a read is element by element, no copy kernel
    calls["element_read"] += self.on_cpu
    return read(self, *a, **k)
sph.SPHSolver.read = counted_read
steps, t = s.steps, time.perf_counter()
while s.steps < steps + 200:
    s.advance_some(1e30)
ti.sync()
n = s.steps - steps
reads = calls.pop("ndarray_to_ext_arr", 0) + calls.pop("element_read", 0)   # to_numpy's copy, or element reads
print(f"HOST {(time.perf_counter() - t) / n * 1e3:.2f} ms a step, {sum(calls.values()) / n:.1f} launches and "
      f"{reads / n:.1f} reads a step ({s.n} particles)")
"""


def host_section(limit: float) -> None:
    """A DFSPH step of 1,000 particles, whose kernels take next to nothing on a GPU: what its
    launches and reads cost the host each step, over its steps 10-210 (`--dry` on the 2-core CPU:
    7.9 ms, 17.0 launches and 6.0 reads a step at the thirty-eighth session's end; 6.7 ms, 13.0 and 6.0
    at the thirty-ninth's, whose solves launch their warm start and first sweeps as one kernel and
    whose CPU reads are element by element). The sim stage's GPU is idle while the host works."""
    rc, out = run([PY, "-c", HOST, str(ROOT), BACKEND], limit)
    line = next((l for l in out.splitlines() if l.startswith("HOST")), None)
    print(line or out[-1500:], flush=True)
    row("DFSPH step of 1,000 particles: the host's part", line[5:] if line else f"failed (rc {rc})")


SURFACE = r"""
import sys, time, numpy as np
sys.path[0] = sys.argv[1]
from solver.backend import init_taichi
print("backend", init_taichi(sys.argv[2], 0))
from surfacing.reconstruct import color_field, marching_cubes
rng = np.random.default_rng(0)
for n in (int(500_000 * float(sys.argv[3])), int(4_000_000 * float(sys.argv[3]))):
    side = round(n ** (1 / 3)); ax = np.arange(side) * 0.02
    P = (np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
         + rng.uniform(-0.003, 0.003, (side ** 3, 3))).astype(np.float32)
    vel = rng.normal(size=P.shape).astype(np.float32); vol = np.full(len(P), 0.02 ** 3, np.float32)
    marching_cubes(color_field(P[:5000], vel[:5000], vol[:5000], 0.0075, 0.04, 0.6), 0.6)   # compile
    marching_cubes(color_field(P[:5000], None, vol[:5000], 0.0075, 0.04, 0.14, anisotropic=True), 0.14)   # the stage's iso
    best = None
    for _ in range(3):
        t = time.perf_counter(); f = color_field(P, None, vol, 0.0075, 0.04, 0.6); t1 = time.perf_counter()
        m = marching_cubes(f, 0.6); t2 = time.perf_counter()
        tv = time.perf_counter(); fv = color_field(P, vel, vol, 0.0075, 0.04, 0.6); mv = marching_cubes(fv, 0.6)
        t3 = time.perf_counter()
        ta = time.perf_counter(); ma = marching_cubes(color_field(P, None, vol, 0.0075, 0.04, 0.14, anisotropic=True), 0.14)
        r = (t2 - t, t1 - t, t2 - t1, t3 - tv, time.perf_counter() - ta)
        best = r if best is None or r[0] < best[0] else best
    print(f"SURFACE {len(P)} mesh_s={best[0]:.3f} splat_s={best[1]:.3f} marching_cubes_s={best[2]:.3f} "
          f"with_velocity_s={best[3]:.3f} anisotropic_s={best[4]:.3f} tris={len(m.faces)}")
"""


SURFACE_PROFILE = r"""
import sys, numpy as np, taichi as ti
sys.path[0] = sys.argv[1]
ti.init(getattr(ti, sys.argv[2]), kernel_profiler=True, log_level=ti.WARN)
import solver.backend as sb
sb._current, sb._arch_name = (sys.argv[2], 0), sys.argv[2]
from surfacing.reconstruct import color_field, marching_cubes
n = int(4_000_000 * float(sys.argv[3])); side = round(n ** (1 / 3)); ax = np.arange(side) * 0.02
rng = np.random.default_rng(0)
P = (np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
     + rng.uniform(-0.003, 0.003, (side ** 3, 3))).astype(np.float32)
vel = rng.normal(size=P.shape).astype(np.float32); vol = np.full(len(P), 0.02 ** 3, np.float32)
marching_cubes(color_field(P[:5000], vel[:5000], vol[:5000], 0.0075, 0.04, 0.6), 0.6)
ti.sync(); ti.profiler.clear_kernel_profiler_info()
marching_cubes(color_field(P, vel, vol, 0.0075, 0.04, 0.6), 0.6); ti.sync()
from bench.gpu import kernel_ms
recs = kernel_ms()
for name, ms in sorted(recs.items(), key=lambda kv: -kv[1])[:8]:
    print(f"SPROFILE {name} {ms:.1f} ms")
print(f"SPROFILE total {sum(recs.values()):.1f} ms in kernels (with velocities)")
"""


def surface_section(limit: float) -> None:
    rc, out = run([PY, "-c", SURFACE_PROFILE, str(ROOT), BACKEND, str(SCALE)], limit / 3)
    lines = [l for l in out.splitlines() if l.startswith("SPROFILE")]
    print("\n".join(lines) or out[-1500:], flush=True)
    if lines:
        top = ", ".join(f"{l.split()[1]} {l.split()[2]}" for l in lines[:4])
        row("surfacer 4M with velocities: kernel ms (top 4)", f"{lines[-1].split()[2]} in all; {top}")
    rc, out = run([PY, "-c", SURFACE, str(ROOT), BACKEND, str(SCALE)], limit)
    lines = [l for l in out.splitlines() if l.startswith("SURFACE")]
    print("\n".join(lines) or out[-2500:], flush=True)
    for l in lines:
        kv = dict(x.split("=", 1) for x in l.split()[2:])
        n = int(l.split()[1])
        row(f"surfacer {n:,} particles: mesh s (splat + marching cubes; with velocities)",
            f"{kv['mesh_s']} ({kv['splat_s']} + {kv['marching_cubes_s']}; {kv['with_velocity_s']}; anisotropic "
            f"{kv['anisotropic_s']}), {int(kv['tris']):,} triangles", "0.3" if n > 1_000_000 * SCALE else "")
    if not lines:
        row("surfacer", f"failed (rc {rc})")


def sampled_stage(cmd: list[str], limit: float, out_dir: Path) -> tuple[float, int, list[int], list[str]]:
    """Run a sim stage through the CLI under `limit` seconds with the GPU's utilisation sampled
    every 100 ms: (wall s, returncode (124: stopped at the limit), utilisation % from the first
    busy sample to the last, the log's lines)."""
    util_log, log = out_dir / "util.csv", out_dir / "stage.log"
    smi = subprocess.Popen(["nvidia-smi" if BACKEND == "cuda" else "true", "--query-gpu=utilization.gpu",
                            "--format=csv,noheader,nounits", "-lms", "100"],
                           stdout=open(util_log, "w"), stderr=subprocess.DEVNULL)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        child = subprocess.Popen(cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT)
        try:
            rc = child.wait(timeout=limit)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
            rc = 124
    wall = time.perf_counter() - t0
    smi.terminate()
    smi.wait()
    util = [int(x) for x in util_log.read_text().split() if x.strip().isdigit()]
    busy = [i for i, u in enumerate(util) if u > 0]          # from the first busy sample to the last
    return wall, rc, (util[busy[0]:busy[-1] + 1] if busy else []), log.read_text().splitlines()


def busy_text(run_util: list[int]) -> str:
    mean = sum(run_util) / len(run_util)
    over = sum(u >= 50 for u in run_util) / len(run_util)
    return f"GPU busy {mean:.0f}% mean, >= 50% in {100 * over:.0f}% of {len(run_util)} samples"


def stage_section(limit: float, solver: str = "dfsph", extra: tuple = ()) -> None:
    out_dir = Path(tempfile.mkdtemp(prefix="sphshot_gpu_stage_"))
    frames = 25 if SCALE == 1 else 3
    cmd = [PY, "-m", "pipeline.cli", "run", "jobs/dambreak.toml", "--stage", "sim",
           "--set", f"sim.backend=\"{BACKEND}\"", "--set", f"sim.particle_radius={0.0025 if SCALE == 1 else 0.01}",
           "--set", f"shot.frame_end={frames}", "--set", f"shot.output=\"{out_dir}\"",
           "--set", f"sim.solver=\"{solver}\"", *[a for e in extra for a in ("--set", e)]]
    if solver == "wcsph":           # the example's Akinci tension is DFSPH's: WCSPH's runs as before, without
        cmd += ["--set", 'sim.surface_tension_model="mueller"', "--set", "fluids.0.surface_tension=0"]
    wall, rc, run_util, lines = sampled_stage(cmd, limit, out_dir)
    sim_lines = [l for l in lines if "sim:" in l and "ALF" not in l]
    print("\n".join(sim_lines[:3] + ["..."] + sim_lines[-4:]), flush=True)
    done = sum("OUTPUT_FILE" in l for l in lines)
    if run_util:
        row(f"sim stage, dambreak.toml at 435k particles, {frames - 1} frames (CLI, {solver.upper()}"
            f"{', ' + ', '.join(extra) if extra else ''})",
            f"{wall:.1f} s wall (rc {rc}, {done} frames written); {busy_text(run_util)}", ">= 95% busy")
    else:
        row(f"sim stage ({solver})", f"{wall:.1f} s wall, rc {rc}, {done} frames written, no GPU samples")


def showcase_section(limit: float) -> None:
    """jobs/showcase.toml's sim stage as a user runs it on a GPU node, for as long as `limit`
    (SHOWCASE_S overrides it, SHOWCASE_UNTIL ends it at that epoch second); then, with SHOWCASE_PACK set to a folder, a few of its frames
    packed by bench/showcase_frames.py to be surfaced and rendered elsewhere (at most
    SHOWCASE_PACK_MB in all: the device's transfer limits)."""
    import os
    import re

    limit = float(os.environ.get("SHOWCASE_S", limit))
    if "SHOWCASE_UNTIL" in os.environ:          # a wall-clock end (epoch s) for the sim, packing after it
        limit = max(10.0, min(limit, float(os.environ["SHOWCASE_UNTIL"]) - time.time()))
    out_dir = Path(tempfile.mkdtemp(prefix="sphshot_showcase_"))
    sets = [f"shot.output=\"{out_dir}\"", f"sim.backend=\"{BACKEND}\""]
    if SCALE != 1:
        sets += ["sim.particle_radius=0.024", "shot.frame_end=6"]
    cmd = [PY, "-m", "pipeline.cli", "run", "jobs/showcase.toml", "--stage", "sim",
           *[a for s in sets for a in ("--set", s)]]
    wall, rc, run_util, lines = sampled_stage(cmd, limit, out_dir)
    sim_lines = [l for l in lines if ("sim:" in l or "Error" in l or "error" in l) and "ALF" not in l]
    print("\n".join(sim_lines if len(sim_lines) <= 16 else sim_lines[:4] + ["..."] + sim_lines[-12:]), flush=True)
    written = sorted(int(m[1]) for l in lines if (m := re.search(r"OUTPUT_FILE:.*\.(\d{4})\.h5;", l)))
    last = written[-1] if written else 0
    steps = sum(int(m[1]) for l in lines if (m := re.search(r"frame \d+: (\d+) steps", l)))
    row(f"showcase sim stage (jobs/showcase.toml, {'1.25M particles' if SCALE == 1 else 'dry'}, CLI, "
        f"{limit:.0f} s allowed)",
        f"{wall:.1f} s wall, rc {rc}, frames 1-{last} of 120 written ({(last - 1) / 24:.2f} simulated s, "
        f"{(last - 1) / 24 / max(wall, 1e-9):.4f} simulated s per wall s){f', {steps} steps' if steps else ''}; "
        + (busy_text(run_util) if run_util else "no GPU samples"), "")
    pack_dir = os.environ.get("SHOWCASE_PACK")
    if not pack_dir or not written:
        return
    budget = float(os.environ.get("SHOWCASE_PACK_MB", 60)) * 2**20
    wanted = [last] + [f for f in (24, 48, 72, 96, 12, 36, 60, 84, 108) if f < last and f in written]
    used = 0
    for f in wanted[:7]:
        if used + 16 * 2**20 > budget:
            break
        rc, out = run([PY, "bench/showcase_frames.py", "pack", str(out_dir / "showcase" / "v001" / "sim"), pack_dir,
                       "--frames", str(f)], 60)
        print(out.strip(), flush=True)
        used = sum(p.stat().st_size for p in Path(pack_dir).glob("*.sphpack"))


SECTIONS = {"solver": (solver_section, 100), "dambreak": (dambreak_section, 45), "profile": (profile_section, 40),
            "profile_wcsph": (lambda limit: profile_section(limit, "wcsph", 4_000_000), 60),
            "surface": (surface_section, 75), "host": (host_section, 40), "stage": (stage_section, 150),
            # the same run as the first GPU measurement (WCSPH then), and DFSPH at its default
            # bound (which blew up at this resolution until the twelfth session: see RESULTS.md)
            "stage_wcsph": (lambda limit: stage_section(limit, "wcsph"), 100),
            "stage_dfsph": (lambda limit: stage_section(limit, "dfsph"), 110),
            "showcase": (showcase_section, 300)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default=",".join(s for s in SECTIONS if s not in ("stage", "showcase")))
    ap.add_argument("--dry", action="store_true", help="on the CPU at 1/200 of the sizes: checks the script")
    args = ap.parse_args()
    global BACKEND, SCALE
    if args.dry:
        BACKEND, SCALE = "cpu", 1 / 200
    t0 = time.perf_counter()
    for name in args.only.split(","):
        fn, limit = SECTIONS[name]
        print(f"## {name} (limit {limit} s)", flush=True)
        t = time.perf_counter()
        try:
            fn(limit)
        except Exception as exc:            # one broken section must not cost the others
            row(name, f"section failed: {type(exc).__name__}: {exc}")
        print(f"## {name}: {time.perf_counter() - t:.0f} s", flush=True)
    print("\n| what | figure | target |\n| --- | --- | --- |")
    for what, fig, target in ROWS:
        print(f"| {what} | {fig} | {target} |")
    print(f"\n(all sections: {time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
