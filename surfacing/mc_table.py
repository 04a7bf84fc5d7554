"""The marching-cubes case table, built from one rule instead of typed in.

Corner v of a cell is at offset (v & 1, v >> 1 & 1, v >> 2 & 1); bit v of a case is set when
corner v is inside (value above the iso level). Edge e = 4 * axis + m joins corner
EDGE_CORNER[e] to the corner one step along `axis` (EDGE_AXIS[e]); a vertex on an edge belongs
to the edge's lower corner and its axis, which is what makes neighbouring cells share it.

How each case is triangulated: on every face of the cell, the sign changes along the face's
four edges are joined by segments. A face with two sign changes has one segment; a face with
four (its two inside corners diagonal: the ambiguous face) has two, each cutting off one
inside corner. That choice depends only on the face's own four corners, so the two cells
sharing a face make the same segments there and the surface has no cracks. Every crossed
edge lies on two faces, so the segments close into loops; each loop is one polygon, oriented
so that its normal points from the inside corners to the outside ones and cut into a fan of
triangles. This is Lorensen & Cline's (1987) marching cubes with a fixed polarity on ambiguous
faces, not the asymptotic decider (Nielson & Hamann 1991, which looks at the face's saddle
value): either is crack-free, and the fixed rule needs no values, only signs. Nothing is
decided inside a cell (no MC33 interior test), which a closed surface does not need.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

CORNER = np.array([(v & 1, v >> 1 & 1, v >> 2 & 1) for v in range(8)])
EDGE_AXIS = np.repeat(np.arange(3), 4)
EDGE_CORNER = np.array([v for a in range(3) for v in range(8) if not v >> a & 1])


def _edge(u: int, v: int) -> int:
    """The edge joining corners u and v (which differ in one bit)."""
    a = (u ^ v).bit_length() - 1
    lo = min(u, v)
    return int(np.flatnonzero((EDGE_AXIS == a) & (EDGE_CORNER == lo))[0])


def _faces():
    """The 6 faces as their 4 corners in cyclic order."""
    out = []
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        for side in (0, 1):
            ring = [(0, 0), (1, 0), (1, 1), (0, 1)]
            out.append([side << a | x << b | y << c for x, y in ring])
    return out


def _loops(case: int) -> list[list[int]]:
    inside = [bool(case >> v & 1) for v in range(8)]
    link: dict[int, list[int]] = {}
    for ring in _faces():
        crossed = [_edge(ring[q], ring[(q + 1) % 4]) for q in range(4)
                   if inside[ring[q]] != inside[ring[(q + 1) % 4]]]
        if len(crossed) == 2:
            pairs = [tuple(crossed)]
        elif len(crossed) == 4:          # ambiguous face: cut off each inside corner
            pairs = []
            for q in range(4):
                if inside[ring[q]]:
                    pairs.append((_edge(ring[q - 1], ring[q]), _edge(ring[q], ring[(q + 1) % 4])))
        else:
            pairs = []
        for u, v in pairs:
            link.setdefault(u, []).append(v)
            link.setdefault(v, []).append(u)
    loops, seen = [], set()
    for start in sorted(link):
        if start in seen:
            continue
        loop, prev, cur = [start], None, start
        seen.add(start)
        while True:
            nxt = link[cur][0] if link[cur][0] != prev else link[cur][1]
            if nxt == start:
                break
            loop.append(nxt)
            seen.add(nxt)
            prev, cur = cur, nxt
        loops.append(_oriented(loop, inside))
    return loops


def _oriented(loop: list[int], inside: list[bool]) -> list[int]:
    """The loop in the order whose (Newell) normal points from inside to outside."""
    mid = np.array([CORNER[EDGE_CORNER[e]] + 0.5 * np.eye(3)[EDGE_AXIS[e]] for e in loop], float)
    normal = np.cross(mid, np.roll(mid, -1, axis=0)).sum(0)
    outward = np.zeros(3)
    for e in loop:
        lo, a = EDGE_CORNER[e], EDGE_AXIS[e]
        outward += (-1.0 if inside[lo | 1 << a] else 1.0) * np.eye(3)[a]
    return loop if normal @ outward > 0 else loop[::-1]


@lru_cache(maxsize=None)
def table() -> tuple[np.ndarray, np.ndarray]:
    """(triangles, count): triangles[case] holds count[case] triangles as edge triples,
    counter-clockwise seen from outside; the rest of the row is -1."""
    tris = [[(loop[0], loop[q], loop[q + 1]) for loop in _loops(c) for q in range(1, len(loop) - 1)]
            for c in range(256)]
    width = max(len(t) for t in tris)
    out = np.full((256, width, 3), -1, np.int32)
    for c, t in enumerate(tris):
        if t:
            out[c, :len(t)] = t
    return out, np.array([len(t) for t in tris], np.int32)
