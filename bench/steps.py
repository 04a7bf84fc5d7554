#!/usr/bin/env python3
"""Where the steps go: sphshot's DFSPH and SPlisHSPlasH's on the anchor dam break, window by window.

Both take their step from a CFL on the fastest particle (bench/solver.py's scene: the anchor's
cflFactor 1, 5 ms cap), so a solver whose few fastest particles run faster than the other's takes
more steps for the same simulated time, whatever a step costs. This prints, for each window of
simulated time, each side's steps, mean step, its fastest particle's |v| after a step and where
it was (sphshot also its CFL speed, |v + a dt| over particles with a neighbour), and the 99.9th
percentile speed. Not a timing: SPlisHSPlasH's velocities are read every step through
pysplishsplash, one particle at a time.

    .venv/bin/python bench/steps.py                    # 0.5 s, windows of 0.05 s
    .venv/bin/python bench/steps.py --stop-at 0.2 --window 0.02
    .venv/bin/python bench/steps.py --only sphshot

The anchor side runs in the anchor's venv (../shared/anchors/solver/bench_splishsplash.sh makes it,
${ANCHOR_VENV:-/tmp/anchorvenv}); figures and what they showed: bench/RESULTS.md, thirty-eighth
session.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))     # the solver package and bench.*, ahead of this folder (bench/solver.py)
ANCHORS = ROOT.parent / "shared" / "anchors" / "solver"
GL_DISPATCH = "/usr/lib/x86_64-linux-gnu/libGLdispatch.so.0"     # the anchor script's libGL workaround


def ours(stop_at: float) -> np.ndarray:
    """(t, dt, fastest |v|, 99.9th percentile speed, x, y, z of the fastest, CFL speed) after every
    step."""
    from solver.backend import init_taichi

    init_taichi("cpu", 0)
    from bench.solver import scene
    from pipeline.stages.sim import fresh_solver

    _params, s = fresh_solver(scene(50_000, 0.006))
    rows = []
    while s.time < stop_at:
        dt = s.step(stop_at)
        v = s.velocity.to_numpy()
        speed = np.linalg.norm(v, axis=1)
        k = int(np.argmax(speed))
        rows.append((s.time, dt, speed[k], np.percentile(speed, 99.9), *s.position.to_numpy()[k], s.vmax))
    return np.array(rows)


# What every child run in the anchor's venv starts with (in_anchor puts it before the child's
# code): SPlisHSPlasH initialised on the scene in_anchor wrote, with its one step; then `base`,
# `sim`, `tm` (its TimeManager), `stop_at` and `out` (the file to leave results in).
ANCHOR_START = r"""
import json, os, sys
import numpy as np
import pysplishsplash as sph
scene, stop_at, out = sys.argv[1], float(sys.argv[2]), sys.argv[3]
base = sph.Exec.SimulatorBase()
base.init(sceneFile=scene, useGui=False, initialPause=False, useCache=False,
          outputDir=os.path.join(os.path.dirname(scene), "out"), stopAt=1e-6)
base.initSimulation()
base.runSimulation()
sim, tm = sph.Simulation.getCurrent(), sph.TimeManager.getCurrent()
"""

ANCHOR_CHILD = r"""
base.setValueFloat(base.STOP_AT, stop_at)
fm = sim.getFluidModel(0)
rows = []
while base.timeStepNoGUI():
    n = fm.numActiveParticles()
    v = np.array([fm.getVelocity(i) for i in range(n)])
    speed = np.linalg.norm(v, axis=1)
    k = int(np.argmax(speed))
    rows.append([tm.getTime(), tm.getTimeStepSize(), float(speed[k]), float(np.percentile(speed, 99.9)),
                 *map(float, fm.getPosition(k))])
np.save(out, np.array(rows))
base.cleanup()
"""


def in_anchor(code: str, stop_at: float, read=None, scene: dict | None = None, args: tuple = ()):
    """Run ANCHOR_START + `code` in the anchor's venv on `scene` (a SPlisHSPlasH scene; the
    anchor's DFSPH dam break without one) beside the anchor's tank_box.obj, as `python -c CODE
    SCENE STOP_AT OUT *args`; returns read(OUT), or the run's stdout without `read`, or None
    without the anchor. The scene is written with stopAt 1e-6: SPlisHSPlasH's init runs its
    deferred set-up (the walls' volume maps) and one step, and the child's own loop the rest."""
    venv = Path(os.environ.get("ANCHOR_VENV", Path(tempfile.gettempdir()) / "anchorvenv"))
    if not (ANCHORS / "dambreak_dfsph.json").exists():
        print(f"# no anchor at {ANCHORS}; SPlisHSPlasH skipped")
        return None
    if not (venv / "bin" / "python").exists():      # the anchor's own script makes its venv
        subprocess.run(["bash", str(ANCHORS / "bench_splishsplash.sh"), "--solvers", "dfsph", "--stop-at", "0.001"],
                       check=True, capture_output=True)
    work = Path(tempfile.mkdtemp(prefix="sphshot_anchor_"))
    try:
        shutil.copy(ANCHORS / "tank_box.obj", work)
        doc = scene or json.loads((ANCHORS / "dambreak_dfsph.json").read_text())
        doc["Configuration"]["stopAt"] = 1e-6
        (work / "scene.json").write_text(json.dumps(doc))
        env = dict(os.environ)
        probe = subprocess.run([str(venv / "bin" / "python"), "-c", "import pysplishsplash"], capture_output=True)
        if probe.returncode != 0 and Path(GL_DISPATCH).exists():
            env["LD_PRELOAD"] = GL_DISPATCH
        out = work / "out.npy"
        command = [str(venv / "bin" / "python"), "-c", ANCHOR_START + code, str(work / "scene.json"), str(stop_at),
                   str(out), *map(str, args)]
        proc = subprocess.run(command, check=True, capture_output=True, text=True, env=env, cwd=work)
        return read(out) if read else proc.stdout
    finally:
        shutil.rmtree(work, ignore_errors=True)


def anchor(stop_at: float) -> np.ndarray | None:
    """The same rows for SPlisHSPlasH's DFSPH on the anchor's scene, or None without the anchor."""
    return in_anchor(ANCHOR_CHILD, stop_at, np.load)


def window_table(name: str, rows: np.ndarray, stop_at: float, window: float) -> list[str]:
    lines = [f"{name}: {len(rows)} steps to {rows[-1, 0]:.3f} s"]
    for t0 in np.arange(0.0, stop_at - 1e-9, window):
        m = (rows[:, 0] > t0 + 1e-9) & (rows[:, 0] <= t0 + window + 1e-9)
        if not m.any():
            continue
        w = rows[m]
        k = int(np.argmax(w[:, 2]))
        lines.append(f"  {t0:.2f}-{t0 + window:.2f} s: {m.sum():3d} steps, dt {1e3 * w[:, 1].mean():.2f} ms, "
                     f"fastest {w[:, 2].max():.2f} m/s at ({w[k, 4]:.3f}, {w[k, 5]:.3f}, {w[k, 6]:+.3f}), "
                     f"99.9th percentile {w[:, 3].max():.2f} m/s"
                     + (f", CFL speed {w[:, 7].max():.2f} m/s" if w.shape[1] > 7 else ""))
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stop-at", type=float, default=0.5, help="simulated seconds (default 0.5)")
    ap.add_argument("--window", type=float, default=0.05, help="window of simulated time, s (default 0.05)")
    ap.add_argument("--only", choices=("sphshot", "anchor"), help="one side only")
    args = ap.parse_args()
    print(f"# command: {' '.join([Path(sys.executable).name, *sys.argv])}")
    sides = []
    if args.only != "anchor":
        sides.append(("sphshot DFSPH", ours(args.stop_at)))
    if args.only != "sphshot":
        rows = anchor(args.stop_at)
        if rows is not None:
            sides.append(("SPlisHSPlasH DFSPH", rows))
    for name, rows in sides:
        print("\n".join(window_table(name, rows, args.stop_at, args.window)))
    if len(sides) == 2:
        print(f"STEPS sphshot / SPlisHSPlasH: x{len(sides[0][1]) / len(sides[1][1]):.3f}")
    print("RESULT " + json.dumps({name: len(rows) for name, rows in sides}))


if __name__ == "__main__":
    main()
