"""The initial particles: fluid blocks filled on the lattice of solver.lattice, one particle per (2r)^3."""
from __future__ import annotations

from typing import Iterable

import numpy as np

from .boundaries import collider_clearance
from .errors import NoParticles
from .lattice import Domain, block_sites
from .params import F_B, F_RHO0, Block, SolverParams


def fill_blocks(params: SolverParams, blocks: Iterable[Block] | None = None, settle: bool = True,
                compressible: bool = False) -> dict[str, np.ndarray]:
    """Initial particles: each block filled on `params.lattice` (solver.lattice: the sites of one
    face-centred cubic lattice shared by all blocks, or a cubic lattice of spacing 2r centred in
    each block), one particle per (2r)^3.

    With `settle` (what a shot uses), lattice sites closer than one particle radius to a
    collider's solid side (inside an obstacle, outside a container) are left empty: blocks may
    overlap colliders. With `settle` and `compressible` (weakly compressible SPH), and with
    gravity, each block also starts in hydrostatic equilibrium: the lattice is compressed along
    gravity to the Tait density rho(d) = rho0 (1 + rho0 |g| d / B)^(1/gamma) at depth d below
    the block's top. Starting at zero pressure instead, a resting column would drop until it is
    compressed and then breathe acoustically for seconds (its long acoustic modes are barely
    damped), biasing every pressure it reports. An incompressible solver (DFSPH) starts from the
    lattice, which is at rest density. Tests of other properties start from the plain lattice
    (settle=False).

    Raises NoParticles when nothing is left.
    """
    d = params.spacing
    g = np.array(params.gravity, np.float64)
    gnorm = float(np.linalg.norm(g))
    blocks = list(params.blocks if blocks is None else blocks)
    own = tuple(blocks) == params.blocks
    if params.lattice == "fcc" and not own:
        raise ValueError("an fcc fill fills the blocks its lattice was fitted to: pass params.blocks")
    domain = params.fill_domain if own else Domain(     # cubic: any blocks
        params.domain_min, params.domain_max, params.open_faces, d, params.lattice, [(b.min, b.max) for b in blocks])
    position, velocity, fluid = [], [], []
    for bi, b in enumerate(blocks):
        lo, hi = np.array(b.min), np.array(b.max)
        p = block_sites(domain, bi)
        if settle and compressible and gnorm > 0:
            p = _hydrostatic(p, lo, hi, -g / gnorm, gnorm, params.fluid_table[b.fluid], params.gamma)
        position.append(p)
        velocity.append(np.broadcast_to(np.array(b.velocity), p.shape))
        fluid.append(np.full(len(p), b.fluid))
    if not position:
        raise NoParticles("expected at least one fluid block, got none")
    position = np.concatenate(position).astype(np.float32)
    velocity, fluid = np.concatenate(velocity).astype(np.float32), np.concatenate(fluid).astype(np.int32)
    if settle and params.colliders:
        free = collider_clearance(params, position) >= params.particle_radius
        position, velocity, fluid = position[free], velocity[free], fluid[free]
    if len(position) == 0:
        raise NoParticles("expected at least one particle, got 0: every fluid block lies inside a collider")
    return {"position": position, "velocity": velocity, "acceleration": np.zeros_like(position),
            "fluid": fluid, "id": np.arange(len(position), dtype=np.int32)}


def _hydrostatic(p, lo, hi, up, g, fluid_row, gamma):
    """Compress a block's particles along `up` so each layer has its hydrostatic density."""
    rho0, B = float(fluid_row[F_RHO0]), float(fluid_row[F_B])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    top, bottom = (corners @ up).max(), (corners @ up).min()
    height = np.linspace(0.0, top - bottom, 513)                      # above the block's bottom
    ratio = (1.0 + rho0 * g * (top - bottom - height) / B) ** (-1.0 / gamma)   # rho0 / rho
    squeezed = np.concatenate([[0.0], np.cumsum(0.5 * (ratio[1:] + ratio[:-1]) * np.diff(height))])
    s = p @ up - bottom
    return p + np.outer(np.interp(s, height, squeezed) - s, up)
