"""Sums over all particles that come out the same on every run and backend."""
import numpy as np
import taichi as ti

from .types import F1, F2

CHUNK = 1024            # particles a thread sums, in order
GROUP = 64              # chunk sums a thread adds in float64, in order, before the last serial sum


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
def chunk_sum(a: ti.template(), c: ti.i32) -> ti.f32:
    """The sum of a over chunk c (particles c CHUNK .. c CHUNK + CHUNK - 1), in order."""
    n = a.shape[0]
    s = 0.0
    for k in range(CHUNK):
        i = c * CHUNK + k
        if i < n:
            s += a[i]
    return s


@ti.func
def chunk_sums_pass(a: ti.template(), partial: ti.template(), go: ti.template()):
    """k_chunk_sums' loop; with a gate `go` (not None), only while go[0] (a solve's DONE) is 0."""
    for c in partial:
        if sweep_open(go):
            partial[c] = chunk_sum(a, c)


@ti.kernel
def k_chunk_sums2(a: F1, b: F1, partial: F2):
    """partial[0, c], partial[1, c]: k_chunk_sums of a and of b, in one launch."""
    for c in range(partial.shape[1]):
        partial[0, c] = chunk_sum(a, c)
        partial[1, c] = chunk_sum(b, c)


@ti.func
def total_pass(partial: ti.template(), groups: ti.template(), go: ti.template()):
    """The chunk sums' total in float64 on the device, in ordered_total's order: groups[g] the
    sum of chunk sums g GROUP .. g GROUP + GROUP - 1 (in parallel over the groups), then the
    groups in order on one thread, returned. (One thread over all the chunk sums waits on each
    load in turn: about 0.2 ms a sum at 1M particles on a GPU.)"""
    parts = partial.shape[0]
    for g in groups:
        if sweep_open(go):
            s = ti.cast(0.0, ti.f64)
            for k in range(GROUP):
                c = g * GROUP + k
                if c < parts:
                    s += ti.cast(partial[c], ti.f64)
            groups[g] = s
    total = ti.cast(0.0, ti.f64)
    if sweep_open(go):
        for g in range(groups.shape[0]):
            total += groups[g]
    return total


def ordered_total(partial: np.ndarray) -> float:
    """The float32 chunk sums' total in float64 in total_pass's order: within each group of
    GROUP in order, then the groups in order (so the host and the device decide alike)."""
    p = np.zeros(-(-len(partial) // GROUP) * GROUP, np.float64)
    p[:len(partial)] = partial
    rows = p.reshape(-1, GROUP)
    groups = np.zeros(len(rows))
    for k in range(GROUP):
        groups += rows[:, k]
    return float(np.cumsum(groups)[-1])


class Summer:
    """total(a): the sum of an (n,) float32 ndarray, in float64 on the host; totals(a, b): two
    sums for one read-back (on a GPU each read-back waits for the device)."""

    def __init__(self, n: int):
        self.partial = ti.ndarray(ti.f32, (n + CHUNK - 1) // CHUNK)
        self.groups = ti.ndarray(ti.f64, -(-self.partial.shape[0] // GROUP))    # total_pass's
        self.partial2 = None

    def total(self, a) -> float:
        k_chunk_sums(a, self.partial)
        return ordered_total(self.partial.to_numpy())

    def totals(self, a, b) -> tuple[float, float]:
        if self.partial2 is None:
            self.partial2 = ti.ndarray(ti.f32, (2, self.partial.shape[0]))
        k_chunk_sums2(a, b, self.partial2)
        p = self.partial2.to_numpy()
        return ordered_total(p[0]), ordered_total(p[1])
