"""GPU backends (run by bench/gpu.sh on a lent GPU machine; skipped elsewhere)."""
from __future__ import annotations

import glob

import numpy as np
import pytest

from pipeline.spec import ShotSpec

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(not glob.glob("/dev/nvidia[0-9]*"), reason="no NVIDIA GPU on this machine")]


def small_dambreak():
    return ShotSpec.model_validate({
        "shot": {"name": "g"}, "sim": {"particle_radius": 0.01},
        "domain": {"min": (0, 0, 0), "max": (0.6, 0.4, 0.3)},
        "fluids": ({"name": "w", "blocks": ({"min": (0, 0, 0), "max": (0.2, 0.3, 0.3)},)},)})


def run_on(backend: str, t_end: float):
    from solver.backend import init_taichi
    init_taichi(backend, 1 if backend == "cpu" else 0)
    from solver.sph import SolverConfig, SPHSolver, fill_blocks
    spec = small_dambreak()
    cfg = SolverConfig.from_spec(spec)
    s = SPHSolver(cfg, fill_blocks(spec, cfg))
    s.advance_to(t_end)
    return s.snapshot()


def test_cuda_matches_cpu_early_on():
    """Before the flow turns chaotic (first 20 ms), CUDA and CPU agree to float32 round-off
    amplified over ~100 steps: positions within 1e-4 of the particle radius scale (1e-6 m)."""
    gpu = run_on("cuda", 0.02)
    cpu = run_on("cpu", 0.02)
    np.testing.assert_allclose(gpu["position"], cpu["position"], atol=1e-6)
    np.testing.assert_allclose(gpu["density"], cpu["density"], rtol=1e-3)


def test_auto_backend_picks_cuda():
    from solver.backend import init_taichi
    assert init_taichi("auto", 0) == "cuda"
