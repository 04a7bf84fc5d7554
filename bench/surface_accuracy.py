"""How far the surfacer's mesh is from its own color field's iso surface, and what the grid adds.

Marching cubes samples the color on a grid and places each vertex on a grid edge; with the
anisotropic kernels the color falls to its iso within about two cells, so where a vertex sits
along its edge decides a good part of the surface's shape. This prints, for the edge
interpolations surfacing/mc.py can use (the color linear along the edge, as until 2026-11-28,
and its cube root, what the anisotropic field uses now) and the isotropic kernels for scale:

- terraces: tests/test_surfacing.py's pool with its lattice sheared so that the top falls
  `--slope` (5 degrees at 0.09) against the grid: the rms and span of the top-facing vertices
  about their straight line, in particle radii;
- a jittered pool (the same pool, every particle moved by 0.1 r rms, three draws): the top's
  rms height, with the surface stage's centre smoothing;
- a block in mid-air (0.1 m, cubic lattice, 1,000 particles): mesh volume over the particles';

each at the test's cell (0.75 r) and on grids 2 and 4 times finer, where every interpolation
converges to the field's own surface.

  .venv/bin/python bench/surface_accuracy.py
  .venv/bin/python bench/surface_accuracy.py --iso 0.2 --slope 0.05

Not a test: the figures and what they showed are in bench/RESULTS.md (2026-11-28).
"""
import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iso", type=float, default=None, help="anisotropic iso (default: the stage's)")
    ap.add_argument("--slope", type=float, default=0.09)
    args = ap.parse_args()

    from solver.backend import init_taichi
    init_taichi("cpu")
    import pyvista as pv

    import surfacing.reconstruct as RC
    from pipeline.spec import Surface
    from surfacing.reconstruct import SurfaceParams, reconstruct
    from test_surfacing import R_PART, SUPPORT, lattice_block, pool_top

    cell0 = 0.75 * R_PART
    iso_a = Surface.ISO["anisotropic"] if args.iso is None else args.iso
    stage = {"center_smoothing": Surface().center_smoothing, "center_inflation": Surface().center_inflation}
    pool = lattice_block((0, 0, 0), (0.2, 0.06, 0.2))
    tilted = pool.astype(np.float64)
    tilted[:, 1] *= 1 - args.slope * tilted[:, 0] / 0.06
    tilted = tilted.astype(np.float32)
    jittered = [pool + np.random.default_rng(s).normal(0, 0.1 * R_PART, pool.shape).astype(np.float32)
                for s in (1, 2, 3)]
    block = lattice_block((0.1, 0.1, 0.1), (0.2, 0.2, 0.2))
    vol = (2 * R_PART) ** 3

    def mesh(pos, method, cell, **kw):
        iso = iso_a if method == "anisotropic" else Surface.ISO["isotropic"]
        p = SurfaceParams(cell=cell, kernel_radius=SUPPORT, iso=iso, method=method, **kw)
        return reconstruct(pos, None, np.full(len(pos), vol, np.float32), p)[1]

    def terraces(m):
        p, n = m.points, m.normals
        top = p[(n[:, 1] > 0.9) & (np.abs(p[:, 2] - 0.1) < 0.05) & (p[:, 0] > 0.03) & (p[:, 0] < 0.17)]
        res = top[:, 1] - np.polyval(np.polyfit(top[:, 0], top[:, 1], 1), top[:, 0])
        return res.std() / R_PART, np.ptp(res) / R_PART

    print(f"anisotropic iso {iso_a}, isotropic iso {Surface.ISO['isotropic']}, r = {R_PART} m, "
          f"slope {args.slope}; lengths in r")
    print("| kernels, edge interpolation | cell | terraces rms / span | jittered pool rms (3 draws) | mid-air block volume |")
    print("| --- | --- | --- | --- | --- |")
    for name, method, power in (("anisotropic, color linear", "anisotropic", 1.0),
                                ("anisotropic, cube root", "anisotropic", 1 / 3),
                                ("isotropic, color linear", "isotropic", 1.0)):
        RC.ANISOTROPIC_EDGE_POWER = power
        for div in (1, 2, 4):
            cell = cell0 / div
            rms, span = terraces(mesh(tilted, method, cell))
            kw = stage if method == "anisotropic" else {}
            jit = [pool_top(mesh(j, method, cell, **kw)).std() / R_PART for j in jittered]
            m = mesh(block, method, cell)
            ratio = abs(pv.PolyData.from_regular_faces(m.points, m.faces).volume) / (len(block) * vol)
            print(f"| {name} | {cell / R_PART:.4g} r | {rms:.3f} / {span:.3f} | "
                  f"{' '.join(f'{x:.4f}' for x in jit)} | {ratio:.4f} |", flush=True)


if __name__ == "__main__":
    main()
