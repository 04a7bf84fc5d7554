"""How much water lies along a line: behind a point of the surface along a view ray
(ray_thickness), or straight above a point (water_above).

ray_thickness: from each point, along its ray away from the eye, to where the ray next leaves
the water: the zero crossing of a level set (negative inside), found by sphere tracing. The level
set's narrow band gives the distance to the surface near it; deeper inside, its background value
is a lower bound, so every step is safe. Beer-Lambert absorption over this length is the water's
depth tint: a thin sheet stays clear, a deep pool takes the water's color, and a stone under the
surface is seen through exactly the water above it (the level set ends at colliders).

water_above: every layer of water over a point (y is up, as in the render), which the light that
reaches a collider under the water has come through.
"""
from __future__ import annotations

import numpy as np


def sample(sdf: np.ndarray, index_min, cell: float, p: np.ndarray, outside: float) -> np.ndarray:
    """Trilinear samples of a dense grid whose sample (i, j, k) lies at cell * (index_min + (i, j,
    k)); `outside` beyond it (SciPy's map_coordinates: 3x the speed of eight NumPy gathers)."""
    from scipy.ndimage import map_coordinates

    g = (np.asarray(p, np.float64) / cell - np.asarray(index_min, np.float64)).T
    return map_coordinates(sdf, g, output=np.float64, order=1, mode="constant", cval=outside, prefilter=False)


def ray_thickness(sdf: np.ndarray, index_min, cell: float, points: np.ndarray, directions: np.ndarray,
                  max_length: float, min_step: float = 0.0) -> np.ndarray:
    """Length of water along each ray (unit `directions`) from `points` on the surface, up to
    `max_length`: from where the ray enters (found in quarter-cell steps, within two cells of
    its start: a ray at a grazing angle is still at the surface after the first) to where it
    leaves (within half a cell, or `min_step` if that is longer: the caller's tolerance, which
    bounds the steps through deep water)."""
    points = np.asarray(points, np.float64)
    directions = np.asarray(directions, np.float64)
    outside = float(np.abs(sdf).max()) if sdf.size else 1.0
    length = np.zeros(len(points))
    entry = np.full(len(points), np.nan)
    live = np.arange(len(points))
    while live.size:
        phi = sample(sdf, index_min, cell, points[live] + length[live, None] * directions[live], outside)
        inside = phi < 0
        entered = ~np.isnan(entry[live])
        entry[live[inside & ~entered]] = length[live[inside & ~entered]]
        going = np.where(entered, inside, inside | (length[live] < 2 * cell)) & (length[live] < max_length)
        step = np.where(inside, np.maximum(-phi, max(0.5 * cell, min_step)), 0.25 * cell)
        live, step = live[going], step[going]
        length[live] += step
    return np.where(np.isnan(entry), 0.0, np.minimum(length, max_length) - np.nan_to_num(entry))


def water_above(sdf: np.ndarray, index_min, cell: float, points: np.ndarray) -> np.ndarray:
    """Length of water straight above each point (along +y, to the top of the grid), however
    many layers of it there are: the level set's occupancy clip(1/2 - phi / cell, 0, 1) (the
    surface placed within its cell) summed up each column of samples from the top, and
    interpolated trilinearly at the points, so that it changes smoothly as a point moves (no
    steps at the cells); zero beyond the grid's columns and above its top, and below its bottom
    the whole column. Only the columns over the points' bounding box are summed."""
    points = np.array(points, np.float64)
    if len(points) == 0 or sdf.size == 0:
        return np.zeros(len(points))
    points[:, 1] = np.maximum(points[:, 1], cell * index_min[1])     # below the grid: its whole column
    g = points / cell - np.asarray(index_min, np.float64)
    lo = np.maximum(np.floor(g.min(axis=0)).astype(int) - 1, 0)
    hi = np.minimum(np.floor(g.max(axis=0)).astype(int) + 2, np.array(sdf.shape) - 1)
    if (hi < lo).any():
        return np.zeros(len(points))
    block = sdf[lo[0]:hi[0] + 1, lo[1]:, lo[2]:hi[2] + 1]
    above = np.empty(block.shape, np.float32)
    for x0 in range(0, block.shape[0], 32):      # a slab at a time: one block-sized array in all
        occupied = block[x0:x0 + 32] * np.float32(-1.0 / cell)
        occupied += np.float32(0.5)
        np.clip(occupied, 0.0, 1.0, out=occupied)
        # each column's total less what lies below and at sample j, then half of sample j: the
        # water from j's own height up
        slab = np.cumsum(occupied, axis=1, dtype=np.float32, out=above[x0:x0 + 32])
        np.subtract(slab[:, -1:, :], slab, out=slab)
        occupied *= np.float32(0.5)
        slab += occupied
    above *= np.float32(cell)
    return sample(above, np.asarray(index_min) + lo, cell, points, 0.0)
