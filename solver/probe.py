"""One small kernel that asks a device for what the solver's and surfacer's kernels need
besides float32 (solver.backend runs it on a Vulkan device before taking it)."""
import taichi as ti

from .types import D1

L1 = ti.types.ndarray(dtype=ti.i64, ndim=1)


@ti.kernel
def k_probe(f: D1, k: L1):
    """float64 atomics and arithmetic (the step's clock, clock.py) and int64 atomics (the
    surfacer's fixed-point sums): f[0] = 1.5, k[0] = 6 << 33."""
    for i in range(4):
        ti.atomic_max(f[0], ti.cast(i, ti.f64) * 0.5)
        ti.atomic_add(k[0], ti.cast(i, ti.i64) << 33)
