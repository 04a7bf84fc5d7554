"""Where a resting pool's volume goes: the example's water, filling the example's tank floor.

A 1.0 x 0.14 x 0.4 m pool from the fill lattice (r = 1 cm, the example's fluid and surface keys),
left alone. At each time it prints the rms and largest speeds, how far the layer touching the
floor and the side walls sits from them (the lattice puts it at 1 r; the walls' clamp at 0.5 r),
the top particles' height, the surface stage's mesh volume against the first frame's, and how
flat the mesh's top is (span and rms of the top-facing vertices' heights, 8 r or more from the
walls: issue 20 asks for a span under 0.1 r on a resting pool). With
--profile it prints, at the end, the particle count per r of height near the top, as a share of
one lattice layer, with the layer's mean SPH density: a settled top layer packs 1.2-1.3 layers'
worth of particles at rest density, where the lattice has one layer at 0.85 of rest.

  .venv/bin/python bench/pool_volume.py
  .venv/bin/python bench/pool_volume.py --seconds 2 --profile
  .venv/bin/python bench/pool_volume.py --set fluids.0.surface_tension=0   # any job key, as sphshot's --set

Not a test: figures and what they showed are in bench/RESULTS.md (sixteenth session).
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def pool_spec(depth: float, overrides: list[str]):
    """The example's job with its block spread over the whole floor, `depth` deep, no collider,
    then the `overrides` (KEY=VALUE, as sphshot's --set)."""
    from pipeline.spec import load_spec

    return load_spec(ROOT / "jobs" / "dambreak.toml", ['shot.name="pool"', f"fluids.0.blocks.0.max=[1.0, {depth}, 0.4]",
                                                       "colliders=[]", *overrides])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--depth", type=float, default=0.14)
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--times", default="0.02,0.05,0.1,0.25,0.5,1,1.5,2")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    a = ap.parse_args()

    from solver.backend import init_taichi
    init_taichi("cpu", 2)
    import pyvista as pv

    from pipeline.stages.sim import frame_attrs, fresh_solver
    from pipeline.stages.surface import surface_frame

    spec = pool_spec(a.depth, a.set)
    params, s = fresh_solver(spec)
    r, lo, hi = params.particle_radius, np.array(params.domain_min), np.array(params.domain_max)

    def mesh_volume():
        d = s.snapshot()
        _f, mesh, _pf, _spray = surface_frame(spec, d, frame_attrs(spec, params, 1, s, {}), 1)
        # the top's flatness: top-facing vertices 8 r or more from the walls (issue 20's measure)
        q, nrm = mesh.points, mesh.normals
        mid = ((q[:, [0, 2]] > lo[[0, 2]] + 8 * r) & (q[:, [0, 2]] < hi[[0, 2]] - 8 * r)).all(1)
        top = q[mid & (nrm[:, 1] > 0.95) & (q[:, 1] > 0.5 * q[:, 1].max()), 1]
        flat = (np.ptp(top) / r, top.std() / r) if len(top) else (np.nan, np.nan)
        return abs(pv.PolyData.from_regular_faces(mesh.points, mesh.faces).volume), d, flat

    v0, _, _ = mesh_volume()
    print(f"pool {a.depth} m deep, {s.n} particles, r = {r} m; mesh volume at 0: {v0 * 1e3:.2f} L "
          f"(N (2r)^3 = {s.n * (2 * r) ** 3 * 1e3:.2f} L)")
    print("   t s | rms mm/s | max m/s | floor layer / r | side layers / r | top particle y / r | mesh vs 0 "
          "| top span / r | top rms / r")
    t0 = time.perf_counter()
    d = None
    for t in [float(x) for x in a.times.split(",") if float(x) <= a.seconds]:
        s.advance_to(t)
        v, d, (span, rms) = mesh_volume()
        p, speed = d["position"], np.linalg.norm(d["velocity"], axis=1)
        floor = p[:, 1] - lo[1]
        side = np.minimum(np.minimum(p[:, 0] - lo[0], hi[0] - p[:, 0]), np.minimum(p[:, 2] - lo[2], hi[2] - p[:, 2]))
        print(f"{t:6.2f} | {np.sqrt((speed ** 2).mean()) * 1e3:8.1f} | {speed.max():7.2f} | "
              f"{floor[floor < 1.5 * r].mean() / r:15.3f} | {side[side < 1.5 * r].mean() / r:15.3f} | "
              f"{np.percentile(p[:, 1], 99) / r:18.2f} | {100 * (v / v0 - 1):+6.2f} % | {span:12.3f} | {rms:11.4f}",
              flush=True)
    print(f"({time.perf_counter() - t0:.0f} s)")
    if a.profile and d is not None:
        p, rho = d["position"], d["density"]
        mid = (p[:, 0] > 0.1) & (p[:, 0] < 0.9) & (p[:, 2] > 0.1) & (p[:, 2] < 0.3)
        layer = 0.8 * 0.2 / (2 * r) ** 2              # one lattice layer's particles in that area
        y = p[mid, 1] / r
        top = a.depth / r
        print("height / r | layers | mean density kg/m^3")
        for k in np.arange(np.floor(top) - 6, np.ceil(top) + 1):
            m = (y >= k) & (y < k + 1)
            print(f"[{k:4.0f},{k + 1:4.0f}) | {m.sum() / layer:6.2f} | {rho[mid][m].mean() if m.any() else 0:7.1f}")


if __name__ == "__main__":
    main()
