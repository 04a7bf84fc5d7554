"""Sums over all particles that come out the same on every run and backend."""
import numpy as np
import taichi as ti

from .types import F1, F2

CHUNK = 1024            # particles a thread sums, in order


@ti.kernel
def k_chunk_sums(a: F1, partial: F1):
    """partial[c]: the sum of a over chunk c of CHUNK particles, in order. The host adds the
    partial sums in float64. (One sum by every thread was an atomic each, and on a GPU took most
    of DFSPH's solve time: 1.5 ms a sweep at 1M particles.)"""
    chunk_sums_pass(a, partial, None)


@ti.func
def sweep_open(go: ti.template()) -> bool:
    """No gate (None), or a solve's gate whose DONE (go[0]) is 0 (dfsph.k_sweeps)."""
    result = True
    if ti.static(not isinstance(go, type(None))):
        result = go[0] < 0.5
    return result


@ti.func
def chunk_sums_pass(a: ti.template(), partial: ti.template(), go: ti.template()):
    """k_chunk_sums' loop; with a gate `go` (not None), only while go[0] (a solve's DONE) is 0."""
    n = a.shape[0]
    for c in partial:
        if sweep_open(go):
            s = 0.0
            for k in range(CHUNK):
                i = c * CHUNK + k
                if i < n:
                    s += a[i]
            partial[c] = s


@ti.kernel
def k_chunk_sums2(a: F1, b: F1, partial: F2):
    """partial[0, c], partial[1, c]: k_chunk_sums of a and of b, in one pass."""
    n = a.shape[0]
    for c in range(partial.shape[1]):
        s, t = 0.0, 0.0
        for k in range(CHUNK):
            i = c * CHUNK + k
            if i < n:
                s += a[i]
                t += b[i]
        partial[0, c] = s
        partial[1, c] = t


class Summer:
    """total(a): the sum of an (n,) float32 ndarray, in float64 on the host; totals(a, b): two
    sums for one read-back (on a GPU each read-back waits for the device)."""

    def __init__(self, n: int):
        self.partial = ti.ndarray(ti.f32, (n + CHUNK - 1) // CHUNK)
        self.partial2 = None

    def total(self, a) -> float:
        k_chunk_sums(a, self.partial)
        return float(np.cumsum(self.partial.to_numpy(), dtype=np.float64)[-1])      # in order, as k_sweeps

    def totals(self, a, b) -> tuple[float, float]:
        if self.partial2 is None:
            self.partial2 = ti.ndarray(ti.f32, (2, self.partial.shape[0]))
        k_chunk_sums2(a, b, self.partial2)
        s = self.partial2.to_numpy().sum(axis=1, dtype=np.float64)
        return float(s[0]), float(s[1])
