"""Sums over all particles that come out the same on every run and backend."""
import numpy as np
import taichi as ti

from .types import F1

CHUNK = 1024            # particles a thread sums, in order


@ti.kernel
def k_chunk_sums(a: F1, partial: F1):
    """partial[c]: the sum of a over chunk c of CHUNK particles, in order. The host adds the
    partial sums in float64. (One sum by every thread was an atomic each, and on a GPU took most
    of DFSPH's solve time: 1.5 ms a sweep at 1M particles.)"""
    n = a.shape[0]
    for c in partial:
        s = 0.0
        for k in range(CHUNK):
            i = c * CHUNK + k
            if i < n:
                s += a[i]
        partial[c] = s


class Summer:
    """total(a): the sum of an (n,) float32 ndarray, in float64 on the host."""

    def __init__(self, n: int):
        self.partial = ti.ndarray(ti.f32, (n + CHUNK - 1) // CHUNK)

    def total(self, a) -> float:
        k_chunk_sums(a, self.partial)
        return float(self.partial.to_numpy().sum(dtype=np.float64))
