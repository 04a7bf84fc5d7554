"""A triangle mesh with per-vertex normals and velocities: what the surfacer returns."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Mesh:
    points: np.ndarray        # (V, 3) float32, world
    faces: np.ndarray         # (F, 3) int32, outward-facing (counter-clockwise seen from outside)
    normals: np.ndarray       # (V, 3) float32, outward unit
    velocity: np.ndarray      # (V, 3) float32, m/s

    @classmethod
    def empty(cls) -> "Mesh":
        z = np.zeros((0, 3), np.float32)
        return cls(z, np.zeros((0, 3), np.int32), z, z)
