"""Arrays on the compute device for the surfacer, and an exclusive scan in Taichi.

The surfacer keeps a frame's arrays where its kernels run, from the particles' upload to the
mesh's read-back. On a GPU they are Taichi ndarrays: a numpy array passed to a kernel is copied
to the device and back at every launch, which there cost more than the kernels themselves. On
the CPU they are numpy arrays, which Taichi reads and writes in place (Taichi's own CPU
ndarrays cost 20-30 ms each to allocate once earlier ones had been freed: 1.4 s a frame).
Vectors: a numpy array's last axis, a Taichi ndarray's element type.
"""

import numpy as np
import taichi as ti

from solver.backend import current_arch
from solver.neighbours import exclusive_scan as exclusive_scan_into
from solver.types import I1

# kernel argument types the surfacer adds to the solver's (solver/types.py)
I2 = ti.types.ndarray(dtype=ti.i32, ndim=2)
I3 = ti.types.ndarray(dtype=ti.i32, ndim=3)
I64 = ti.types.ndarray(dtype=ti.i64, ndim=1)
U2 = ti.types.ndarray(dtype=ti.u8, ndim=2)
R8 = ti.types.ndarray(dtype=ti.types.vector(8, ti.f32), ndim=1)     # rows of 8 grid nodes along z


_NP = {ti.i32: np.int32, ti.i64: np.int64, ti.f32: np.float32, ti.u8: np.uint8}


def on_cpu() -> bool:
    """Whether Taichi runs on the CPU (else a GPU: CUDA, Vulkan or Metal)."""
    return current_arch() == "cpu"


def on_cuda() -> bool:
    return current_arch() == "cuda"


def _shape(shape) -> tuple:
    return tuple(max(int(s), 1) for s in (shape if isinstance(shape, tuple) else (shape,)))


def empty(dtype, shape, vec: int = 0):
    """An array of `shape` (at least one element along each axis) of `dtype`, or of vectors of
    `vec` of them, on the device."""
    shape = _shape(shape)
    if on_cpu():
        return np.empty(shape + ((vec,) if vec else ()), _NP[dtype])
    return ti.Vector.ndarray(vec, dtype, shape=shape) if vec else ti.ndarray(dtype, shape=shape)


def zeros(dtype, shape, vec: int = 0):
    shape = _shape(shape)
    if on_cpu():
        return np.zeros(shape + ((vec,) if vec else ()), _NP[dtype])
    out = empty(dtype, shape, vec)
    out.fill(0)
    return out


def upload(a: np.ndarray, dtype=ti.i32, vec: int = 0):
    """A numpy array (its last axis the vectors if `vec`) as a device array of `dtype`."""
    a = np.ascontiguousarray(a, _NP[dtype])
    if a.size == 0:
        return zeros(dtype, a.shape[:-1] if vec else a.shape, vec)
    if on_cpu():
        return a
    out = empty(dtype, a.shape[:-1] if vec else a.shape, vec)
    out.from_numpy(a)
    return out


def vec3s(a: np.ndarray):
    """(N, 3) numpy -> N float32 vectors on the device."""
    return upload(np.asarray(a).reshape(-1, 3), ti.f32, 3)


def host(a) -> np.ndarray:
    """A device array as numpy (the array itself on the CPU)."""
    return a if isinstance(a, np.ndarray) else a.to_numpy()


def exclusive_scan(count, n: int):
    """(start, total): start[i] = count[0] + ... + count[i - 1] for the first n entries, as a
    device array, and the sum of all n (solver/neighbours.py's scan)."""
    start = empty(ti.i32, n)
    exclusive_scan_into(count, start, n, lambda level, size: empty(ti.i32, size))
    total = 0 if n == 0 else int(start[n - 1]) + int(count[n - 1])
    return start, total


@ti.kernel
def k_block_sides(color: R8, nb: ti.i32, iso: ti.f32, above: I1, below: I1):
    """above[b]: some node of block b is above iso; below[b]: some node is at or below it."""
    for b in range(nb):
        hi, lo = -1e30, 1e30
        for r in range(64):
            row = color[b * 64 + r]
            hi = ti.max(hi, row.max())
            lo = ti.min(lo, row.min())
        above[b] = 1 if hi > iso else 0
        below[b] = 1 if lo <= iso else 0


def block_sides(rows, nb: int, iso: float):
    """(above, below) bool arrays of the nb blocks (see k_block_sides)."""
    above, below = empty(ti.i32, nb), empty(ti.i32, nb)
    if nb:
        k_block_sides(rows, nb, iso, above, below)
    return host(above)[:nb].astype(bool), host(below)[:nb].astype(bool)
