"""Martin & Moyce's collapsing column, the surge front and the column's height side by side.

Martin & Moyce 1952, "An experimental study of the collapse of liquid columns on a rigid
horizontal plane", Phil. Trans. R. Soc. A 244, 312-324, the n^2 = 2, a = 2.25 in column: the
surge front Z = z / a against T = t sqrt(2 g / a) (their Fig. 3, as digitised in PySPH's
pysph/examples/db_exp_data.py) and the residual column's height at the back wall H / (n^2 a)
against tau = t sqrt(g / a) (their Table 6). The column is a wide and 2a high in a slice of a
frictionless tank, inviscid, set up and measured as tests/test_dfsph.py does (tests/experiments.py
holds the data, the set-up and the measures; the tests check the first eight front points to 20 %
and the column down to H = 0.56 to 3 %). Besides the two comparisons it prints the release time
the column's height implies (the shift of the experiment's clock that fits the column best, with
its spread) and the shift each front point would need.

--stokes-floor F probes one explanation of the front's lead: each step, the particles touching
the floor (within 1.5 r) lose velocity to the floor's laminar boundary layer, which the
particles cannot resolve: Stokes' first problem, wall shear mu u / sqrt(pi nu t), t the time
since the floor under the particle was first wet (at least a particle's crossing time), nu
F times water's. A probe, not a model the solver has.

--water runs the experiment as it was instead of its Froude-scaled, inviscid twin: the
column 2.25 in wide, water's viscosity and surface tension, no slip at the tank's floor and
ends, the slice's sides free (planes of symmetry of a wide channel, domain.no_slip as a list).

  .venv/bin/python bench/martin_moyce.py                      # r = 5 mm, a 1.6 m tank, to T = 9.2
  .venv/bin/python bench/martin_moyce.py --radius 0.0025 --depth 0.02
  .venv/bin/python bench/martin_moyce.py --tank 0.8 --stokes-floor 1
  .venv/bin/python bench/martin_moyce.py --water --tank 0.92 --radius 0.000714 --depth 0.0071   # a / 80
  .venv/bin/python bench/martin_moyce.py --splishsplash --radius 0.0025

--splishsplash runs the same column through SPlisHSPlasH's DFSPH instead (the anchor's settings:
mean density error 0.05 %, divergence error 0.1 %, cflFactor 1, volume-map walls; inviscid, so its
walls hold nothing), in the anchor's venv (bench/steps.py's in_anchor). Its block sampling starts
the particles 3r from the walls (the water 2r clear of them; its volume-map walls reach the fluid
from h = 4r); it prints where its water starts and its front beside the experiment's.

Not a test: figures and what they showed are in bench/RESULTS.md (thirty-first session).
"""
import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import experiments as mm  # noqa: E402 - the data, the set-up and the measures the tests use


class StokesFloor:
    """The floor's unresolved laminar boundary layer, applied after each step (see the module's
    docstring): the floor is cut into cells 2r long that remember when they were first wet."""

    def __init__(self, nu: float, r: float, tank: float):
        self.nu, self.r = nu, r
        self.wet = np.full(int(tank / (2 * r)) + 2, np.inf)

    def __call__(self, s, t: float, dt: float) -> None:
        p, v = s.position.to_numpy(), s.velocity.to_numpy()
        low = np.where(p[:, 1] < 1.5 * self.r)[0]
        cell = np.clip((p[low, 0] / (2 * self.r)).astype(int), 0, len(self.wet) - 1)
        self.wet[cell] = np.minimum(self.wet[cell], t)
        u = np.hypot(v[low, 0], v[low, 2])
        wet_for = np.maximum(t - self.wet[cell], 2 * self.r / np.maximum(u, 1e-3))
        rate = self.nu / (2 * self.r * np.sqrt(np.pi * self.nu * wet_for))     # tau / (rho 2r u)
        keep = 1.0 / (1.0 + rate * dt)                                           # implicit: never reverses
        v[low, 0] *= keep
        v[low, 2] *= keep
        s.velocity.from_numpy(v.astype(np.float32))


SPLISHSPLASH_CHILD = r"""
fm = sim.getFluidModel(0)
def positions():
    return np.array([fm.getPosition(i) for i in range(fm.numActiveParticles())])
r = float(sys.argv[4])
rows = [[0.0, *positions().min(0), *positions().max(0)]]      # the particles' extent, then (t, front, 0...)
for t in json.loads(sys.argv[5]):
    base.setValueFloat(base.STOP_AT, t)
    while tm.getTime() < t - 1e-9 and base.timeStepNoGUI():
        pass
    rows.append([tm.getTime(), np.sort(positions()[:, 0])[-3] + r, 0, 0, 0, 0, 0])
np.save(out, np.array(rows))
base.cleanup()
"""


def column_scene(a: float, r: float, tank: float, depth: float) -> dict:
    """The column as a SPlisHSPlasH scene: the anchor's DFSPH settings, no viscosity, volume-map
    walls, the block sampled from (0, 0, 0) to (a, 2a, depth - 2r) shifted by r."""
    height = 2.5 * a
    return {"Configuration": {"particleRadius": r, "sim2D": False, "gravitation": [0, -9.81, 0],
                              "simulationMethod": 4, "boundaryHandlingMethod": 2, "cflMethod": 1, "cflFactor": 1.0,
                              "cflMaxTimeStepSize": 0.005, "enableZSort": True, "enablePartioExport": False,
                              "enableVTKExport": False,
                              "DFSPH": {"minIterations": 2, "maxIterations": 100, "maxError": 0.05,
                                        "enableDivergenceSolver": True, "maxIterationsV": 100, "maxErrorV": 0.1}},
            "Materials": [{"id": "Water", "density0": 1000.0, "viscosityMethod": 0, "surfaceTensionMethod": 0,
                           "vorticityMethod": 0}],
            "RigidBodies": [{"geometryFile": "tank_box.obj", "translation": [tank / 2, height / 2, depth / 2],
                             "scale": [tank, height, depth], "isDynamic": False, "isWall": True, "mapInvert": True,
                             "mapThickness": 0.0, "mapResolution": [int(tank / (4 * r)), int(height / (4 * r)),
                                                                    max(int(depth / (4 * r)), 2)]}],
            "FluidBlocks": [{"id": "Water", "denseMode": 0, "start": [0.0, 0.0, 0.0], "end": [a, 2 * a, depth - 2 * r],
                             "translation": [r, r, 0.0], "scale": [1, 1, 1]}]}


def splishsplash(args) -> None:
    """Martin & Moyce's front through SPlisHSPlasH's DFSPH (the module's docstring)."""
    import json

    from bench.steps import in_anchor

    a, r = args.a, args.radius
    reach = (args.tank - 4 * r) / a
    points = [(T, Z) for T, Z in mm.FRONT if Z < reach]
    times = json.dumps([mm.front_time(T, a) for T, _ in points])
    rows = in_anchor(SPLISHSPLASH_CHILD, 0.0, np.load, column_scene(a, r, args.tank, args.depth), (r, times))
    if rows is None:
        return
    lo, hi = rows[0, 1:4] - r, rows[0, 4:7] + r
    print(f"SPlisHSPlasH DFSPH, Martin & Moyce n^2 = 2: a = {a} m, r = {r} m, tank {args.tank} m, slice "
          f"{args.depth} m, inviscid; its water starts at x {lo[0]:.4f} ... {hi[0]:.4f}, y {lo[1]:.4f} ... "
          f"{hi[1]:.4f}, z {lo[2]:.4f} ... {hi[2]:.4f} m")
    for (T, Z), (t, x) in zip(points, rows[1:, :2]):
        print(f"  front  T = {T:.3f}: experiment {Z:.3f}, SPlisHSPlasH {x / a:.3f} ({100 * (x / a / Z - 1):+.1f} %)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", type=float, default=0.1, help="column width, m (default 0.1; height 2a)")
    ap.add_argument("--water", action="store_true",
                    help="the experiment as it was: a = 2.25 in (over --a), water's viscosity and surface "
                         "tension (Mueller's), the tank's floor and ends holding it, the slice's sides free")
    ap.add_argument("--radius", type=float, default=0.005, help="particle radius, m (default 0.005)")
    ap.add_argument("--tank", type=float, default=1.6, help="tank length, m (default 1.6)")
    ap.add_argument("--depth", type=float, default=0.05, help="the slice's depth, m (default 0.05)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--stokes-floor", type=float, default=0.0, metavar="F",
                    help="the floor's boundary layer at F times water's viscosity (default 0: none)")
    ap.add_argument("--splishsplash", action="store_true",
                    help="the same column through SPlisHSPlasH's DFSPH, as its block sampling places it (docstring)")
    args = ap.parse_args()
    if args.splishsplash:
        return splishsplash(args)

    from solver.backend import init_taichi
    init_taichi("cpu", args.threads)
    a, r = (mm.A_EXPERIMENT if args.water else args.a), args.radius
    water = {"fluid": mm.WATER, "domain": {"no_slip": ("-x", "+x", "-y")}} if args.water else {}
    _params, s = mm.collapsing_column(args.tank, a, r, args.depth, **water)
    floor = StokesFloor(1e-6 * args.stokes_floor, r, args.tank) if args.stokes_floor > 0 else None
    print(f"Martin & Moyce, n^2 = 2: a = {a} m, r = {r} m, {s.n} particles, tank {args.tank} m, "
          f"slice {args.depth} m, {'water' if args.water else 'inviscid'}, "
          f"floor boundary layer x{args.stokes_floor:g}")

    front_scale, column_scale = np.sqrt(2 * mm.G / a), np.sqrt(mm.G / a)
    reach = (args.tank - 4 * r) / a                       # the front points the tank holds
    samples = sorted([(mm.front_time(T, a), "front", T, Z) for T, Z in mm.FRONT if Z < reach] +
                     [(mm.column_time(tau, a), "column", tau, H) for tau, H in mm.COLUMN])
    rows = {"front": [], "column": []}
    for t_at, kind, x_exp, y_exp in samples:
        while s.time < t_at - 1e-9:
            dt = s.step(t_at)
            if floor:
                floor(s, s.time, dt)
        p = s.position.to_numpy()
        y_sim = mm.front(p, a, r) if kind == "front" else mm.column_height(p, a, r)
        rows[kind].append((x_exp, y_exp, y_sim))
        print(f"  {kind:6s} {'T' if kind == 'front' else 'tau'} = {x_exp:.3f}: experiment {y_exp:.3f}, "
              f"sphshot {y_sim:.3f} ({100 * (y_sim / y_exp - 1):+.1f} %)", flush=True)

    # The experiment's clock, from each measure: the shift d (s, at this a) with y_sim(t) ~ y_exp(t + d)
    for kind, scale in (("front", front_scale), ("column", column_scale)):
        x, y, y_sim = (np.array(c) for c in zip(*rows[kind]))
        slope = np.gradient(y, x)
        shift = (y_sim - y) / slope / scale * 1e3
        print(f"{kind}: sphshot ahead by {' '.join(f'{d:+.1f}' for d in shift)} ms of the experiment's time")
        if kind == "column":
            early = x <= 1.84 + 1e-9                            # while the column is many particles across
            d = np.sum(slope[early] * (y_sim - y)[early]) / np.sum(slope[early] ** 2)
            spread = np.sqrt(np.sum(((y_sim - y) - slope * d)[early] ** 2) / max(early.sum() - 1, 1)
                             / np.sum(slope[early] ** 2))
            print(f"column down to H = 0.56: the release fits at {d / scale * 1e3:+.2f} +- "
                  f"{spread / scale * 1e3:.2f} ms")


if __name__ == "__main__":
    main()
