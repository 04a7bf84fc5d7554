#!/usr/bin/env bash
# Every GPU test and benchmark in one call, for a lent GPU machine (see bench/RESULTS.md).
#
#   bash bench/gpu.sh                 # from the repository root, with .venv set up
#
# The device machine cannot reach PyPI: carry .venv (built here on the same architecture)
# or a .whl folder; if .whl exists its wheels are installed into /tmp/site first.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PY=.venv/bin/python
if [ -d .whl ] && ! $PY -c "import taichi" 2>/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site
  PY=python3
fi
export PYTHONUNBUFFERED=1 ENABLE_TAICHI_HEADER_PRINT=0
echo "# $(date -u +%Y-%m-%dT%H:%MZ) $(nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || echo 'no nvidia-smi')"
echo "## GPU tests"
$PY -m pytest -q -m gpu tests 2>&1 | tail -n 15
echo "## solver: particle-steps per second on CUDA"
for solver in wcsph dfsph; do
  for n in 50000 1000000 4000000; do
    $PY bench/solver.py --only sphshot --solver "$solver" --backend cuda --particles "$n" \
      --radius "$(python3 -c "print(0.006*(50000/$n)**(1/3))")" --stop-at 0.02 2>&1 | grep -E "^(sphshot|#)"
  done
done
echo "## DFSPH: simulated seconds per wall second, 1M-particle dam break (target: 1 s in 10 s)"
$PY bench/solver.py --only sphshot --solver dfsph --backend cuda --particles 1000000 \
  --radius "$(python3 -c "print(0.006*(50000/1000000)**(1/3))")" --stop-at 0.25 2>&1 | grep -E "^(sphshot|#)"
echo "## surfacing (sphshot side, Taichi on CUDA)"
$PY - <<'PY'
import time, numpy as np
from solver.backend import init_taichi
print("backend", init_taichi("cuda", 0))
from surfacing.reconstruct import color_field, marching_cubes
rng = np.random.default_rng(0)
for n in (50_000, 500_000):
    side = round(n ** (1 / 3)); ax = np.arange(side) * 0.02
    P = (np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3) + rng.uniform(-0.003, 0.003, (side ** 3, 3))).astype(np.float32)
    vel = np.zeros_like(P); vol = np.full(len(P), 0.02 ** 3, np.float32)
    marching_cubes(color_field(P[:2000], vel[:2000], vol[:2000], 0.0075, 0.04), 0.6)   # compile both
    t = time.perf_counter(); f = color_field(P, vel, vol, 0.0075, 0.04); t1 = time.perf_counter(); m = marching_cubes(f, 0.6); t2 = time.perf_counter()
    print(f"surface n={len(P)} splat_s={t1 - t:.3f} marching_cubes_s={t2 - t1:.3f} tris={len(m.faces)}")
PY
echo "## render: EGL on the GPU"
$PY - <<'PY'
import os, time
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
import pyvista as pv
pl = pv.Plotter(off_screen=True, window_size=(1280, 720)); pl.add_mesh(pv.Sphere(theta_resolution=400, phi_resolution=400), pbr=True)
pl.enable_anti_aliasing("ssaa"); pl.screenshot(return_img=True)
t = time.perf_counter(); [pl.screenshot(return_img=True) for _ in range(20)]
info = pl.ren_win.ReportCapabilities().splitlines()
print("render", [l for l in info if "OpenGL renderer string" in l], f"{(time.perf_counter() - t) / 20 * 1000:.1f} ms/frame at 1280x720 SSAA")
PY
