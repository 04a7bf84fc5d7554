#!/usr/bin/env python3
"""Here (with OpenVDB): the mesh colliders' level sets that the GPU machine's pyopenvdb stand-in
(bench/gpu_site) serves there: those of the given jobs and of tests/test_gpu.py's boulder.

    .venv/bin/python bench/gpu_levelsets.py jobs/showcase.toml     # -> .gpu/levelsets/
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[0] = str(ROOT)
sys.path.insert(1, str(ROOT / "tests"))

spec_ = importlib.util.spec_from_file_location("standin", ROOT / "bench" / "gpu_site" / "pyopenvdb.py")
standin = importlib.util.module_from_spec(spec_)
spec_.loader.exec_module(standin)


class _Recording:
    """pyopenvdb as solver.meshsdf uses it, saving each level set it copies out under the key
    the stand-in will look it up by."""

    def __init__(self, real):
        self.real = real
        self.createLinearTransform = real.createLinearTransform
        outer = self

        class FloatGrid:
            @staticmethod
            def createLevelSetFromPolygons(verts, triangles, transform, halfWidth):
                grid = real.FloatGrid.createLevelSetFromPolygons(verts, triangles=triangles, transform=transform,
                                                                  halfWidth=halfWidth)
                return outer.Saving(grid, standin.key(verts, triangles, transform.voxelSize()[0], halfWidth))

        self.FloatGrid = FloatGrid

    class Saving:
        def __init__(self, grid, k):
            self.grid, self.k = grid, k

        def copyToArray(self, phi, ijk):
            self.grid.copyToArray(phi, ijk=ijk)
            out = standin.STORE / standin.file_name(self.k, ijk, phi.shape)
            np.save(out, phi)
            print(f"gpu_levelsets: {out} ({out.stat().st_size / 2**20:.1f} MiB)", flush=True)


def main() -> None:
    import pyopenvdb

    sys.modules["pyopenvdb"] = _Recording(pyopenvdb)
    standin.STORE.mkdir(parents=True, exist_ok=True)
    from pipeline.spec import load_spec
    from pipeline.stages.sim import solver_params
    from test_gpu import small_dambreak

    solver_params(small_dambreak(mesh=True))
    for job in sys.argv[1:]:
        solver_params(load_spec(job))


if __name__ == "__main__":
    main()
