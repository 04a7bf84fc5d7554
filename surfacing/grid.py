"""The block-sparse grid the surfacer works on, and its errors.

Node (i, j, k) of the global grid sits at world position cell * (i, j, k). Nodes are grouped
in blocks of B^3 (one OpenVDB leaf node each); only the blocks that particle supports reach
exist.
"""
from __future__ import annotations

import numpy as np

from .mc_table import CORNER


class SurfacingError(ValueError):
    """Base of every error the surfacer raises on purpose."""


B = 8                   # nodes per block edge of the sparse grid: one OpenVDB leaf node


class GridTooLarge(SurfacingError):
    """The particles are spread too far for the block index at this cell size."""


class Field:
    """The color and velocity fields on a block-sparse grid (see surfacing/splat.py).

    Block n holds nodes blocks[n] * 8 + (0..7)^3 of the global grid, node (i, j, k) at world
    position cell * (i, j, k). `color` covers every block; `velocity` only the blocks
    velocity_ids (the band the iso surface passes through). Both arrays end with one all-zero
    block, the stand-in for blocks that are missing (or outside the band).

    The color lives where it was made: `rows` is the device array the splat wrote (rows of 8
    nodes along z, block-major) and `color` the numpy copy, fetched once when first asked for
    (the VDB grids); a Field made from numpy uploads `rows` when a kernel first needs it."""

    def __init__(self, color, blocks: np.ndarray, lookup: np.ndarray, base_block: np.ndarray, cell: float,
                 velocity: np.ndarray | None = None, velocity_ids: np.ndarray | None = None,
                 velocity_rows=None):
        if isinstance(color, np.ndarray) and color.ndim == 4:      # (nb + 1, 8, 8, 8)
            self._color, self._rows = np.ascontiguousarray(color, np.float32), None
        else:                                                       # rows on the device
            self._color, self._rows = None, color
        self.blocks = blocks                    # (nb, 3) int64 block coordinates
        self.lookup = lookup                    # int32 block ids over the blocks' bounding box, -1 = none
        self.base_block = base_block            # (3,) block coordinates of lookup[0, 0, 0]
        self.cell = cell
        self._velocity = velocity               # see the velocity property
        self.velocity_ids = velocity_ids        # the block ids that carry velocity
        self.velocity_rows = velocity_rows      # the velocity on the device: node-major vectors
        self._upper = None
        self.spray = None                       # mask of the particles left out as spray (input order)
        self.edge_power = 1.0                   # marching cubes interpolates color^edge_power (surfacing/mc.py)

    @property
    def n_blocks(self) -> int:
        return len(self.blocks)

    @property
    def color(self) -> np.ndarray:
        """(nb + 1, 8, 8, 8) float32."""
        if self._color is None:
            from .device import host
            self._color = host(self._rows).reshape(-1, B, B, B)
        return self._color

    @property
    def velocity(self) -> np.ndarray | None:
        """(len(velocity_ids) + 1, 8, 8, 8, 3) float32, m/s, or None; fetched from the device
        when first asked for."""
        if self._velocity is None and self.velocity_rows is not None:
            from .device import host
            self._velocity = host(self.velocity_rows).reshape(-1, B, B, B, 3)
        return self._velocity

    @property
    def rows(self):
        """The color on the device: (nb + 1) * 64 rows of 8 float32."""
        if self._rows is None:
            import taichi as ti

            from .device import upload
            self._rows = upload(self._color.reshape(-1, B), ti.f32, B)
        return self._rows

    @property
    def velocity_slot(self) -> np.ndarray:
        """(nb + 1,): where each block's velocity is in `velocity` (the zero block if nowhere)."""
        slot = np.full(self.n_blocks + 1, len(self.velocity_ids), np.int64)
        slot[self.velocity_ids] = np.arange(len(self.velocity_ids))
        return slot

    def neighbour(self, offset, ids=None) -> np.ndarray:
        """Id of each block's (or of blocks `ids`') neighbour at block offset (dx, dy, dz); nb
        (the zero block) if none."""
        blocks = self.blocks if ids is None else self.blocks[ids]
        return self.block_of((blocks + np.asarray(offset)) * B)

    def block_of(self, nodes: np.ndarray) -> np.ndarray:
        """Block id of integer global node indices (N, 3); nb (the zero block) where missing."""
        b = nodes // B - self.base_block
        inside = ((b >= 0) & (b < self.lookup.shape)).all(1)
        ids = np.full(len(nodes), self.n_blocks, np.int64)
        ids[inside] = self.lookup[b[inside, 0], b[inside, 1], b[inside, 2]]
        ids[ids < 0] = self.n_blocks
        return ids

    @property
    def upper(self) -> np.ndarray:
        """(nb + 1, 8) int32: each block's id, then its upper neighbours in _UPPER's order (nb
        where missing; the zero block's row is all nb)."""
        if self._upper is None:
            nb = self.n_blocks
            up = np.full((nb + 1, 8), nb, np.int32)
            up[:nb, 0] = np.arange(nb)
            for col, o in enumerate(_UPPER, 1):
                up[:nb, col] = self.neighbour(o)
            self._upper = up
        return self._upper

    def crossing_blocks(self, iso: float) -> tuple[np.ndarray, np.ndarray]:
        """(ids, upper): the blocks owning a grid cell with corners on both sides of `iso`, and
        the (7, len(ids)) ids of their upper neighbours in _UPPER's order, whose first node
        layers those cells reach (nb where missing). Per-block extremes on the device."""
        from .device import block_sides
        nb = self.n_blocks
        above, below = block_sides(self.rows, nb, iso)
        above, below = np.r_[above, False], np.r_[below, True]     # the zero block: all below
        nbrs = self.upper[:nb, 1:].T
        crosses = (above[:nb] | above[nbrs].any(0)) & (below[:nb] | below[nbrs].any(0))
        ids = np.flatnonzero(crosses)
        return ids, nbrs[:, ids]

    def dense(self):
        """(array, index0): the color as one dense array over the blocks' bounding box (tests)."""
        lo, hi = self.blocks.min(0), self.blocks.max(0) + 1
        out = np.zeros(tuple((hi - lo) * B), np.float32)
        for n, b in enumerate(self.blocks - lo):
            out[b[0] * B:(b[0] + 1) * B, b[1] * B:(b[1] + 1) * B, b[2] * B:(b[2] + 1) * B] = self.color[n]
        return out, lo * B


# the 7 blocks (besides the block itself) whose nodes the cells of a block touch, at the block
# offsets of a cell's corners 1 to 7: the columns surfacing/mc.py expects
_UPPER = [tuple(int(v) for v in c) for c in CORNER[1:]]
