"""How still DFSPH keeps water at rest: a resting column or oil resting on water, from the fill.

Prints, at each time, the mean vertical velocity, the rms and largest speeds, the top particle's
height and the density solve's sweeps a step. With --first-steps N it also prints, for the first
N steps, each lattice layer's mean vertical velocity (from the floor up): the fill lattice lets
every other layer fall freely, a velocity pattern the density constraint cannot see.

  .venv/bin/python bench/resting.py --case layers
  .venv/bin/python bench/resting.py --case column --first-steps 4 --max-density-error 1e-5
  .venv/bin/python bench/resting.py --case layers --damp 0.9 --damp-until 1.0   # v *= 0.9 a step
  .venv/bin/python bench/resting.py --case layers --ramp 0.3                     # gravity eased in

Not a test: figures and what they showed are in bench/RESULTS.md (fifteenth session).
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def job(case: str, physical: bool, density_error: float, divergence_error: float) -> dict:
    sim = {"particle_radius": 0.01, "max_density_error": density_error, "max_divergence_error": divergence_error}
    if case == "column":        # 0.2 x 0.3 x 0.2 m of water in a closed tank (tests/test_dfsph.py's column)
        fluids = ({"name": "water", "rest_density": 1000.0, "blocks": ({"min": (0, 0, 0), "max": (0.2, 0.3, 0.2)},)},)
        domain = {"min": (0, 0, 0), "max": (0.2, 0.4, 0.2)}
    else:                       # 10 cm of oil (800 kg/m^3) on 10 cm of water (tests/test_dfsph.py's layers)
        fluids = ({"name": "water", "rest_density": 1000.0, "blocks": ({"min": (0, 0, 0), "max": (0.2, 0.1, 0.1)},)},
                  {"name": "oil", "rest_density": 800.0, "blocks": ({"min": (0, 0.1, 0), "max": (0.2, 0.2, 0.1)},)})
        domain = {"min": (0, 0, 0), "max": (0.2, 0.26, 0.1)}
    for f in fluids:
        if physical:            # Pa s: water, and a light oil
            f.update(dynamic_viscosity=0.001 if f["name"] == "water" else 0.05, xsph=0.02)
        else:                   # the tests' particle-scale viscosity
            f.update(viscosity=1.0)
    return {"shot": {"name": "resting"}, "sim": sim, "domain": domain, "fluids": fluids}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", choices=("column", "layers"), default="layers")
    ap.add_argument("--physical", action="store_true", help="viscosities in Pa s instead of the tests' 1.0")
    ap.add_argument("--max-density-error", type=float, default=1e-3)
    ap.add_argument("--max-divergence-error", type=float, default=1e-3)
    ap.add_argument("--damp", type=float, default=1.0, help="scale velocities by this after every step ...")
    ap.add_argument("--damp-until", type=float, default=0.0, help="... until this time (s)")
    ap.add_argument("--ramp", type=float, default=0.0, help="ease gravity in over this long (s)")
    ap.add_argument("--first-steps", type=int, default=0)
    ap.add_argument("--times", default="0.01,0.02,0.05,0.1,0.25,0.5,1,1.5,2")
    a = ap.parse_args()

    from solver.backend import init_taichi
    init_taichi("cpu", 2)
    from pipeline.spec import ShotSpec
    from pipeline.stages.sim import fresh_solver
    from solver.types import P_GY

    spec = ShotSpec.model_validate(job(a.case, a.physical, a.max_density_error, a.max_divergence_error))
    params, s = fresh_solver(spec)
    prm = s.prm.to_numpy()
    g = float(prm[P_GY])
    layer = np.round(s.snapshot()["position"][:, 1], 4)

    def set_gravity(t: float) -> None:
        x = min(t / a.ramp, 1.0) if a.ramp > 0 else 1.0
        prm[P_GY] = g * x * x * (3.0 - 2.0 * x)
        s.prm.from_numpy(prm)

    t0 = time.time()
    for k in range(a.first_steps):
        s.step()
        v = s.snapshot()["velocity"][:, 1]
        print(f"step {k}: each layer's mean v_y (m/s), floor up:",
              " ".join(f"{v[layer == y].mean():+.3f}" for y in np.unique(layer)))
    s.frame_report()
    for t in (float(x) for x in a.times.split(",")):
        while s.time < t - 1e-9:
            if a.ramp > 0:
                set_gravity(s.time)
            s.step(t)
            if a.damp < 1.0 and s.time <= a.damp_until + 1e-9:
                s.velocity.from_numpy(s.velocity.to_numpy() * a.damp)
        d = s.snapshot()
        v = d["velocity"]
        speed = np.linalg.norm(v, axis=1)
        rep = s.frame_report()
        print(f"t = {s.time:5.3f} s: mean v_y {v[:, 1].mean() * 1000:+7.1f} mm/s, rms {np.sqrt((speed ** 2).mean()) * 1000:6.1f}"
              f" mm/s, max {speed.max() * 1000:6.1f} mm/s, top {d['position'][:, 1].max():.4f} m, "
              f"{rep['density_iterations']:4.1f} density sweeps a step ({time.time() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
