#!/usr/bin/env python3
"""Where a DFSPH step's time goes: sphshot's phases beside SPlisHSPlasH's own timers.

The anchor dam break (bench/solver.py's scene, 0.5 s), each solver alone on the machine, one after
the other: sphshot through `bench/solver.py --only sphshot --phases` (synchronised around each
phase), SPlisHSPlasH through pysplishsplash with its built-in timers (Utilities.Timing, the
averages its SimulatorBase prints at exit). Prints milliseconds a step per phase, side by side
where the two do the same work, and each solve's milliseconds a sweep (its time over its sweeps,
warm start included):

    phase          sphshot                    SPlisHSPlasH
    neighbours     the sort and the lists     neighborhood_search
    density        number density, factor,    computeVolumeAndBoundaryX + computeDFSPHFactor +
                   the pairs' gradients       precomputeValues (its densities are not timed apart)
    divergence     divergence solve           divergenceSolve
    forces         non-pressure forces        computeNonPressureForces
    kick           v* = v + dt a (viscosity   (in computeNonPressureForces: its viscosity is
                   implicit where it must be)  explicit)
    pressure       density solve              pressureSolve

    .venv/bin/python bench/phases.py
    .venv/bin/python bench/phases.py --stop-at 0.2

Not a test; figures and what they showed are in bench/RESULTS.md (thirty-ninth session).
"""
from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))     # bench.*, and the solver package ahead of bench/solver.py

from bench.solver import run_sphshot  # noqa: E402
from bench.steps import in_anchor  # noqa: E402


ANCHOR_CHILD = r"""
from pysplishsplash import Utilities
ts = sim.getTimeStep()
base.setValueFloat(base.STOP_AT, stop_at)
Utilities.Timing.reset()
steps = iters = iters_v = 0
while base.timeStepNoGUI():
    steps += 1
    iters += ts.getValueInt(sph.TimeStepDFSPH.SOLVER_ITERATIONS)
    iters_v += ts.getValueInt(sph.TimeStepDFSPH.SOLVER_ITERATIONS_V)
print(f"STEPS {steps} {iters} {iters_v}", flush=True)
Utilities.Timing.printTimeSums()
base.cleanup()
"""
ANCHOR_PHASES = {"neighbours": ("neighborhood_search",),
                 "density": ("computeVolumeAndBoundaryX", "computeDFSPHFactor", "precomputeValues"),
                 "divergence": ("divergenceSolve",), "forces": ("computeNonPressureForces",),
                 "pressure": ("pressureSolve",)}


def ours(stop_at: float) -> dict:
    args = SimpleNamespace(stop_at=stop_at, backend="cpu", threads=0, particles=50_000, radius=0.006,
                           solver="dfsph", fluid="anchor", phases=True, device_bytes=False, skin=None)
    r = run_sphshot(args)
    steps = r["steps"]
    ms = {k: 1e3 * v / steps for k, v in r["phase_s"].items()}
    ms["step"] = 1e3 * r["wall_s"] / steps
    return {"steps": steps, "ms": ms, "sweeps": {"pressure": r["avg_pressure_iters"],
                                                 "divergence": r["avg_divergence_iters"]}}


def anchor(stop_at: float) -> dict | None:
    out = in_anchor(ANCHOR_CHILD, stop_at)
    if out is None:
        return None
    steps, iters, iters_v = (int(x) for x in re.search(r"^STEPS (\d+) (\d+) (\d+)$", out, re.M).groups())
    sums = {m.group(1): float(m.group(2)) for m in re.finditer(r"^Time sum: (\w+): ([\d.eE+-]+) ms$", out, re.M)}
    ms = {k: sum(sums.get(n, 0.0) for n in names) / steps for k, names in ANCHOR_PHASES.items()}
    ms["step"] = sums["SimStep"] / steps
    return {"steps": steps, "ms": ms, "sweeps": {"pressure": iters / steps, "divergence": iters_v / steps}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stop-at", type=float, default=0.5, help="simulated seconds (default 0.5)")
    args = ap.parse_args()
    print(f"# {os.cpu_count()} cores, 1-min load {os.getloadavg()[0]:.2f}")
    print(f"# command: {' '.join([Path(sys.executable).name, *sys.argv])}")
    sides = {"sphshot": ours(args.stop_at)}
    theirs = anchor(args.stop_at)
    if theirs is not None:
        sides["SPlisHSPlasH"] = theirs
    names = list(sides)
    print(f"{'ms a step':22s}" + "".join(f"{n:>20s}" for n in names))
    for phase in ("neighbours", "density", "divergence", "forces", "kick", "pressure", "integrate", "collide",
                  "step"):
        cells = [f"{s['ms'][phase]:20.2f}" if phase in s["ms"] else f"{'-':>20s}" for s in sides.values()]
        print(f"{phase:22s}" + "".join(cells))
    print(f"{'steps':22s}" + "".join(f"{s['steps']:20d}" for s in sides.values()))
    for solve in ("divergence", "pressure"):
        cells = [f"{s['sweeps'][solve]:.2f} at {s['ms'][solve] / s['sweeps'][solve]:.2f} ms" for s in sides.values()]
        print(f"{solve + ' sweeps':22s}" + "".join(f"{c:>20s}" for c in cells))

if __name__ == "__main__":
    main()
