"""Step limits that need no device: imported by the solvers and by the pipeline's estimate."""
from __future__ import annotations

import math

import numpy as np


def explicit_viscous_limit(h: float, nu) -> float:
    """The longest stable explicit step for kinematic viscosities nu (m^2/s): (h / 2)^2 / (8 nu)
    for the largest (inf without viscosity)."""
    nu_max = float(np.max(nu))
    return 0.125 * (0.5 * h) ** 2 / nu_max if nu_max > 0 else math.inf
