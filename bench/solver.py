#!/usr/bin/env python3
"""Solver speed: sphshot vs SPlisHSPlasH on the same dam break, in one session.

The scene is the anchor's (../shared/anchors/solver): tank 1.6 x 0.67 x 0.6 m, particle radius
6 mm, about 50k particles, 0.5 s simulated. sphshot runs in a child process (so its peak memory
is its own), then the anchor script runs SPlisHSPlasH's WCSPH and DFSPH through pysplishsplash.
Prints one line per solver and the ratios: particle-steps per second and simulated seconds per
wall second, with peak resident memory.

    .venv/bin/python bench/solver.py                       # both, 0.5 s simulated
    .venv/bin/python bench/solver.py --only sphshot --stop-at 0.1
    .venv/bin/python bench/solver.py --backend cuda --particles 1000000   # on a GPU

Steps are timed after Taichi's kernel compilation (one warm-up step), like the anchor times
stepping after its init.

The step count is a draw: a CFL step follows the fastest particle, here a few thrown up the back
edges of the tank at 0.05-0.2 s (bench/steps.py), and the round-off of any change to the solver's
arithmetic moves them. Started 1 um off the lattice (`--seeds K`: K more runs of our side, each
particle moved by a uniform +-1 um, seeds 1 ... K), the same code took 319 to 354 steps
(bench/RESULTS.md, forty-third session). Judge a change to a step's cost by bench/phases.py's
milliseconds a step, and the shot's speed by the seeds' spread.

    .venv/bin/python bench/solver.py --only sphshot --seeds 4

The host's minute moves a run's wall time by up to 10 % either way (two quiet runs of the same code
on the 2-core CPU, 16.2 and 19.4 s); `--rounds N` runs both sides N times, alternately, and prints
each round's ratios and their median and range, the figure to quote for a target such as x1.5.

    .venv/bin/python bench/solver.py --anchor-solvers dfsph --rounds 5
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import os
import re
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[0] = str(ROOT)   # this file is bench/solver.py: keep it from shadowing the solver package
ANCHOR = ROOT.parent / "shared" / "anchors" / "solver" / "bench_splishsplash.sh"


# The anchor's water: 41 x 26 x 47 spacings of 12 mm (50,102 particles; scene's docstring)
ANCHOR_SPACINGS = (41, 26, 47)


def radius_for(particles: int) -> float:
    """The particle radius at which scene's block for `particles` is the anchor's in metres."""
    return 0.006 * (math.prod(ANCHOR_SPACINGS) / particles) ** (1 / 3)


def scene(particles: int, radius: float, solver: str = "dfsph", cfl: float = 0.8,
          max_density_error: float = 0.0005, fluid: str = "anchor"):
    """The anchor tank, with a water block of about `particles` particles where the anchor's is.

    The anchor's block (dambreak_dfsph.json's FluidBlocks, 0.012 ... 0.516 x 0.012 ... 0.336 x
    -0.288 ... 0.288 m) is filled with 41 x 26 x 47 particles whose centres lie from 24 mm off the
    back wall and the floor and 24 mm off each side (measured: bench/RESULTS.md, thirty-eighth
    session): the water they stand for fills 0.018 ... 0.510 x 0.018 ... 0.330 x -0.282 ... 0.282,
    18 mm clear of the back wall, the floor and both sides, and falls that far as it collapses.
    Ours is that water, its spacing counts scaled to the requested count (the block's size in
    metres follows the radius) and capped to the tank less the same margins. (Until the
    thirty-eighth session it was 42 x 26 x 46 spacings against the back wall, the floor and the
    -z side, 48 mm clear of the +z side: another dam break, whose side gap sent a sheet up the +z
    wall and along its foot 8-10 % faster than the anchor's fastest particles, and our CFL took
    9 % more steps for it.) The tank's walls hold nothing: friction 0, as the anchor's.

    DFSPH runs with the anchor's settings (../shared/anchors/solver/dambreak_dfsph.json):
    mean density error 0.05 %, divergence error 0.1 %, its CFL step (cflFactor 1: dt =
    0.4 x 2r / v_max, i.e. sim.cfl = 0.8 radii a step) capped at its cflMaxTimeStepSize
    (sim.max_dt = 5 ms; until the twenty-third session ours kept the default 1/240 s and took
    8-10 % more steps over the slow start) and its fluid: SPlisHSPlasH's "Standard
    viscosity" 0.01 is a kinematic viscosity (a_i = 10 nu sum_j V_j (v_ij . x_ij) /
    (r^2 + 0.01 h^2) grad W_ij, i.e. nu lap v), so 10 Pa s at 1000 kg/m^3, and its boundary
    viscosity 0, so free-slip walls. (Until the thirteenth session our side ran Müller's
    particle-scale viscosity 1.0 instead, a much thinner fluid: a few particles climbed the
    walls at 5-6.5 m/s and set 1.7x the anchor's steps.) WCSPH, and DFSPH with fluid="thin"
    (what bench/gpu.py's GPU figures have used from the start), keep Müller's viscosity 1.0."""
    from pipeline.spec import ShotSpec

    d = 2 * radius
    # The anchor's spacings, scaled uniformly to the requested count (scaling them by the radius
    # as well, as it once did, made the GPU script's "1M" and "4M" runs 6M and 25M particles)
    s = (particles / math.prod(ANCHOR_SPACINGS)) ** (1 / 3)
    nx, ny, nz = (max(1, round(k * s)) for k in ANCHOR_SPACINGS)
    gap = 0.018
    ext = (min(nx * d, 1.6 - 2 * gap), min(ny * d, 0.67 - 2 * gap), min(nz * d, 0.6 - 2 * gap))
    return ShotSpec.model_validate({
        "shot": {"name": "bench", "frame_end": 13, "fps": 24.0},
        "sim": {"particle_radius": radius, "solver": solver,
                **({"cfl": cfl, "max_density_error": max_density_error, "max_dt": 0.005} if solver == "dfsph" else {})},
        "domain": {"min": (0.0, 0.0, -0.3), "max": (1.6, 0.67, 0.3), "no_slip": False, "friction": 0.0},
        "fluids": ({"name": "water", **({"dynamic_viscosity": 10.0} if solver == "dfsph" and fluid == "anchor"
                                        else {"viscosity": 1.0}),
                    "blocks": ({"min": (gap, gap, -0.5 * ext[2]), "max": (gap + ext[0], gap + ext[1], 0.5 * ext[2])},)},)})


def child(args) -> None:
    from solver.backend import init_taichi

    arch = init_taichi(args.backend, args.threads)
    from pipeline.stages.sim import initial_state, make_solver, solver_params
    import numpy as np
    import taichi as ti

    if args.skin is not None:
        from solver.sph import SPHSolver
        SPHSolver.SKIN = args.skin
    spec = scene(args.particles, args.radius, args.solver, fluid=args.fluid)
    params = solver_params(spec)
    t0 = time.perf_counter()
    state = initial_state(spec, params)
    if args.seed:                 # the same water, 1 um off the lattice (the module docstring)
        rng = np.random.default_rng(args.seed)
        state["position"] = (state["position"] + rng.uniform(-1e-6, 1e-6, state["position"].shape)
                             ).astype(state["position"].dtype)
    s = make_solver(spec, params, state)
    s.step()                      # compile and warm up (one step, and a batch as the stage runs them)
    if args.solver == "dfsph":
        # DFSPH's first step has no divergence solve (no dt_{n-1/2} yet), so its sweeps compiled
        # (or loaded from the offline cache: 0.36 s) inside the timing: a second step compiles
        # them, and the timing starts again from the state after the first, resumed bit for bit
        state, clock_ = s.state(), s.controller()
        s.step()
        del s                     # its arrays go before the next one's come (peak memory)
        gc.collect()
        s = make_solver(spec, params, state, time_s=clock_["time"], step=clock_["step"], dt_prev=clock_["dt_prev"])
    if args.solver == "wcsph":
        # (not DFSPH: a 0.1 ms sliver step after its first 5 ms one threw a particle in the
        # tank's corner out at 5.8 m/s, as a density solve removes a compression within its
        # step, and that set the steps after it; the sim stage never takes a step under half
        # the stable one, and the bench's DFSPH took 311 steps to 0.5 s with the sliver)
        s.advance_to(s.time + 1e-4)
    ti.sync()
    init = time.perf_counter() - t0
    steps0, time0 = s.steps, s.time
    t1 = time.perf_counter()
    if args.phases:                   # synchronised around every phase: one step at a time
        while s.time < args.stop_at:
            s.step(args.stop_at, timed=True)
    else:                             # as the sim stage steps (WCSPH on a GPU: batches of gated steps)
        s.advance_to(args.stop_at)
    ti.sync()
    wall = time.perf_counter() - t1
    steps = s.steps - steps0
    pos = s.position.to_numpy()
    result = {"solver": f"sphshot-{args.solver}-{arch}", "particles": s.n, "steps": steps,
              "sim_time_s": round(s.time - time0, 4), "wall_s": round(wall, 3), "init_s": round(init, 2),
              "ms_per_step": round(1000 * wall / steps, 3),
              "particle_steps_per_s": round(s.n * steps / wall, 1),
              "sim_s_per_wall_s": round((s.time - time0) / wall, 5),
              "front_x_m": round(float(pos[:, 0].max()), 4)}
    report = s.frame_report()
    if report:
        result["avg_pressure_iters"] = round(report["density_iterations"], 2)
        result["avg_divergence_iters"] = round(report["divergence_iterations"], 2)
        if report["viscosity_steps"]:
            result["implicit_viscosity_steps"] = report["viscosity_steps"]
            result["avg_viscosity_iters"] = round(report["viscosity_iterations"], 2)
    if args.phases:
        result["phase_s"] = {k: round(v, 2) for k, v in s.timer.totals.items()}
    if args.device_bytes:
        result["device_bytes_per_particle"] = round(device_bytes(s) / s.n)
    # this process's own peak (the parent's RUSAGE_CHILDREN is the largest of all its children
    # so far: with --rounds or --seeds, every round after the first reported the worst one's)
    result["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
    print("RESULT " + json.dumps(result), flush=True)


def device_bytes(solver) -> int:
    """Bytes of the solver's Taichi arrays (particles, neighbour lists, grid, boundary tables)."""
    from taichi.lang._ndarray import Ndarray

    arrays = {id(a): a for a in vars(solver).values() if isinstance(a, Ndarray)}     # an alias counts once
    return sum(a._get_element_size() * a._get_nelement() for a in arrays.values())


def run_sphshot(args) -> dict:
    cmd = [sys.executable, __file__, "--child", "--stop-at", str(args.stop_at), "--backend", args.backend,
           "--threads", str(args.threads), "--particles", str(args.particles), "--radius", str(args.radius),
           "--solver", args.solver, "--fluid", args.fluid]
    if args.phases:
        cmd.append("--phases")
    if args.device_bytes:
        cmd.append("--device-bytes")
    if args.skin is not None:
        cmd += ["--skin", str(args.skin)]
    if getattr(args, "seed", 0):
        cmd += ["--seed", str(args.seed)]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    m = re.search(r"^RESULT (\{.*\})$", proc.stdout, re.M)
    if proc.returncode != 0 or not m:
        raise SystemExit(f"sphshot child failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return json.loads(m.group(1))


def run_anchor(args) -> list[dict]:
    if not ANCHOR.exists():
        print(f"# anchor script not found at {ANCHOR}; skipping SPlisHSPlasH")
        return []
    proc = subprocess.run(["bash", str(ANCHOR), "--solvers", args.anchor_solvers, "--stop-at", str(args.stop_at)],
                          capture_output=True, text=True)
    out = []
    for line in proc.stdout.splitlines():
        if line.startswith("#"):
            print(line)
        m = re.match(r"^SOLVER=(\w+) (.*)$", line)
        if m and "FAILED" not in line:
            kv = dict(item.split("=", 1) for item in m.group(2).split())
            out.append({"solver": f"splishsplash-{m.group(1)}", **kv})
    if not out:
        print(proc.stdout[-2000:], proc.stderr[-2000:])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stop-at", type=float, default=0.5, help="simulated seconds")
    ap.add_argument("--only", choices=("sphshot", "anchor"), help="run one side only")
    ap.add_argument("--backend", default="cpu", choices=("cpu", "cuda", "vulkan", "auto"))
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--particles", type=int, default=50_000)
    ap.add_argument("--radius", type=float, default=0.006)
    ap.add_argument("--solver", default="dfsph", choices=("dfsph", "wcsph"), help="sphshot's solver")
    ap.add_argument("--anchor-solvers", default="wcsph,dfsph")
    ap.add_argument("--fluid", default="anchor", choices=("anchor", "thin"),
                    help="DFSPH's fluid: the anchor's (nu 0.01 m^2/s, free slip) or Müller's viscosity 1.0")
    ap.add_argument("--phases", action="store_true", help="time each step phase (adds syncs)")
    ap.add_argument("--device-bytes", action="store_true", help="report the solver's device bytes per particle")
    ap.add_argument("--skin", type=float, help="Verlet skin in units of h (default: the solver's)")
    ap.add_argument("--seeds", type=int, default=0,
                    help="also run our side this many times from the lattice moved by +-1 um (the step count's spread)")
    ap.add_argument("--rounds", type=int, default=1,
                    help="run both sides this many times, alternately, and print the ratios' median and range")
    ap.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args)
    if args.rounds < 1:
        ap.error("--rounds must be at least 1")
    load = os.getloadavg()[0]
    print(f"# {os.cpu_count()} cores, 1-min load {load:.2f}{'  (busy machine: numbers are noisy)' if load > 0.5 else ''}")
    print(f"# command: {' '.join([Path(sys.executable).name, *sys.argv])}")
    ratios = []
    for k in range(args.rounds):
        if args.rounds > 1:
            print(f"# round {k + 1} of {args.rounds}, 1-min load {os.getloadavg()[0]:.2f}")
        ratios += one_round(args, with_seeds=(k == 0))
    if args.rounds > 1 and ratios:
        for name in sorted({r[0] for r in ratios}):
            ps = [r[1] for r in ratios if r[0] == name]
            ss = [r[2] for r in ratios if r[0] == name]
            print(f"RATIO {name}, median of {len(ss)} rounds: particle-steps/s x{statistics.median(ps):.2f} "
                  f"(x{min(ps):.2f}-x{max(ps):.2f}), simulated s per wall s x{statistics.median(ss):.2f} "
                  f"(x{min(ss):.2f}-x{max(ss):.2f})")


def one_round(args, with_seeds: bool) -> list[tuple[str, float, float]]:
    """Our side (and its seeds in the first round), then the anchor's; prints the rows and the
    ratios; returns (pair, particle-steps ratio, simulated-seconds ratio) for each pair."""
    rows = []
    if args.only != "anchor":
        rows.append(run_sphshot(args))
        for seed in range(1, (args.seeds if with_seeds else 0) + 1):
            r = run_sphshot(argparse.Namespace(**{**vars(args), "seed": seed}))
            r["solver"] += f"-seed{seed}"
            rows.append(r)
    if args.only != "sphshot":
        rows += run_anchor(args)
    keys = ["particles", "steps", "sim_time_s", "wall_s", "ms_per_step", "particle_steps_per_s",
            "sim_s_per_wall_s", "init_s", "peak_rss_mb", "avg_pressure_iters", "avg_divergence_iters",
            "device_bytes_per_particle"]
    for r in rows:
        extra = [k for k in ("implicit_viscosity_steps", "avg_viscosity_iters") if k in r]
        print(f"{r['solver']:22s} " + " ".join(f"{k}={r.get(k)}" for k in keys + extra)
              + (f" phases={r['phase_s']}" if "phase_s" in r else ""))
    ours = [r for r in rows if r["solver"].startswith("sphshot")]
    ratios = []
    for ref in (r for r in rows if r["solver"].startswith("splishsplash")):
        for o in ours:
            ps = float(o["particle_steps_per_s"]) / float(ref["particle_steps_per_s"])
            ss = float(o["sim_s_per_wall_s"]) / float(ref["sim_s_per_wall_s"])
            mem = float(o["peak_rss_mb"]) / float(ref["peak_rss_mb"]) if ref.get("peak_rss_mb") not in (None, "None") else float("nan")
            print(f"RATIO {o['solver']} / {ref['solver']}: particle-steps/s x{ps:.2f}, "
                  f"simulated s per wall s x{ss:.2f}, peak memory x{mem:.2f}")
            ratios.append((f"{o['solver']} / {ref['solver']}", ps, ss))
    return ratios


if __name__ == "__main__":
    main()
