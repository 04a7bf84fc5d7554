"""The block-sparse grid the surfacer works on, and its errors.

Node (i, j, k) of the global grid sits at world position cell * (i, j, k). Nodes are grouped
in blocks of B^3 (one OpenVDB leaf node each); only the blocks that particle supports reach
exist.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .mc_table import CORNER


class SurfacingError(ValueError):
    """Base of every error the surfacer raises on purpose."""


B = 8                   # nodes per block edge of the sparse grid: one OpenVDB leaf node


class GridTooLarge(SurfacingError):
    """The particles are spread too far for the block index at this cell size."""


@dataclass
class Field:
    """The color and velocity fields on a block-sparse grid (see surfacing/splat.py).

    Block n holds nodes blocks[n] * 8 + (0..7)^3 of the global grid, node (i, j, k) at world
    position cell * (i, j, k). `color` covers every block; `velocity` only the blocks
    velocity_ids (the band the iso surface passes through). Both arrays end with one all-zero
    block, the stand-in for blocks that are missing (or outside the band)."""
    color: np.ndarray                # (nb + 1, 8, 8, 8) float32
    blocks: np.ndarray                # (nb, 3) int64 block coordinates
    lookup: np.ndarray                # int32 block ids over the blocks' bounding box, -1 = none
    base_block: np.ndarray            # (3,) block coordinates of lookup[0, 0, 0]
    cell: float
    velocity: np.ndarray | None = None        # (len(velocity_ids) + 1, 8, 8, 8, 3) float32, m/s
    velocity_ids: np.ndarray | None = None    # the block ids that carry velocity

    @property
    def n_blocks(self) -> int:
        return len(self.blocks)

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

    def crossing_blocks(self, iso: float) -> tuple[np.ndarray, np.ndarray]:
        """(ids, upper): the blocks owning a grid cell with corners on both sides of `iso`, and
        the (7, len(ids)) ids of their upper neighbours in _UPPER's order, whose first node
        layers those cells reach (nb where missing)."""
        nb = self.n_blocks
        flat = self.color[:nb].reshape(nb, -1)
        above = np.r_[flat.max(1) > iso, False]          # the zero block: all below
        below = np.r_[flat.min(1) <= iso, True]
        nbrs = np.stack([self.neighbour(o) for o in _UPPER])
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
