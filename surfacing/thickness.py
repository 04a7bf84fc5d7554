"""How much water a view ray crosses behind a point of the surface.

From each point, along its ray away from the eye, to where the ray next leaves the water: the
zero crossing of a level set (negative inside), found by sphere tracing. The level set's
narrow band gives the distance to the surface near it; deeper inside, its background value is a
lower bound, so every step is safe. Beer-Lambert absorption over this length is the water's
depth tint: a thin sheet stays clear, a deep pool takes the water's color, and a stone under the
surface is seen through exactly the water above it (the level set ends at colliders).
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
