"""Colour-field splatting in Taichi: particles -> grid nodes near them.

c(x) = sum_j V_j W(x - x_j) with V_j = m_j / rho_j (the particle's volume, from the sim cache),
and the velocity field u(x) = sum_j V_j v_j W(x - x_j) / c(x). Only grid nodes within the
kernel support of some particle are touched (each particle visits its own neighbourhood), so the
work is proportional to particles x nodes-per-support, not to the grid's volume.
"""
import numpy as np
import taichi as ti

from solver import kernels as K

vec3 = ti.math.vec3
V3 = ti.types.ndarray(dtype=vec3, ndim=1)
F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
G3 = ti.types.ndarray(dtype=ti.f32, ndim=3)
G3V = ti.types.ndarray(dtype=vec3, ndim=3)


@ti.func
def _span(g: ti.f32, reach: ti.f32, n: ti.i32):
    """First and last node index within `reach` (node units) of `g`, clipped to [0, n)."""
    return ti.max(ti.cast(ti.ceil(g - reach), ti.i32), 0), ti.min(ti.cast(ti.floor(g + reach), ti.i32), n - 1)


@ti.kernel
def k_splat(pos: V3, vel: V3, vol: F1, origin: vec3, cell: ti.f32, h: ti.f32,
            colour: G3, momentum: G3V, kern: ti.template()):
    """Each particle adds into the nodes inside its support sphere. The loops run over the
    sphere, row by row (the k range of each (i, j) column from the remaining radius), not over
    its bounding cube, which would be 3.5x the iterations for nothing."""
    nx, ny, nz = colour.shape
    for p in pos:
        x = pos[p]
        g = (x - origin) / cell                     # the particle in node units
        i0, i1 = _span(g.x, h / cell, nx)
        for i in range(i0, i1 + 1):
            dx = origin.x + cell * i - x.x
            rem_x = h * h - dx * dx
            if rem_x > 0.0:
                j0, j1 = _span(g.y, ti.sqrt(rem_x) / cell, ny)
                for j in range(j0, j1 + 1):
                    dy = origin.y + cell * j - x.y
                    rem = rem_x - dy * dy
                    if rem > 0.0:
                        k0, k1 = _span(g.z, ti.sqrt(rem) / cell, nz)
                        for k in range(k0, k1 + 1):
                            dz = origin.z + cell * k - x.z
                            r2 = dx * dx + dy * dy + dz * dz
                            if r2 < h * h:              # round-off at the sphere's rim
                                wgt = vol[p] * K.w(kern, ti.sqrt(r2), h)
                                ti.atomic_add(colour[i, j, k], wgt)
                                ti.atomic_add(momentum[i, j, k], wgt * vel[p])


def splat(positions: np.ndarray, velocities: np.ndarray, volumes: np.ndarray, origin: np.ndarray,
          shape: tuple[int, int, int], cell: float, support: float, kernel: int = K.CUBIC):
    """Return (colour, velocity) node arrays of `shape`, node (i,j,k) at origin + cell*(i,j,k)."""
    n = len(positions)
    # particles in grid order, so that consecutive particles add into the same cache lines
    key = np.floor((positions - origin) / support).astype(np.int64)
    order = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
    positions, velocities, volumes = positions[order], velocities[order], volumes[order]
    pos = ti.Vector.ndarray(3, ti.f32, shape=n)
    vel = ti.Vector.ndarray(3, ti.f32, shape=n)
    vol = ti.ndarray(ti.f32, shape=n)
    pos.from_numpy(positions.astype(np.float32))
    vel.from_numpy(velocities.astype(np.float32))
    vol.from_numpy(volumes.astype(np.float32))
    colour = ti.ndarray(ti.f32, shape=shape)
    momentum = ti.Vector.ndarray(3, ti.f32, shape=shape)
    colour.fill(0.0)
    momentum.fill(0.0)
    k_splat(pos, vel, vol, vec3(*map(float, origin)), float(cell), float(support), colour, momentum, kernel)
    c = colour.to_numpy()
    u = momentum.to_numpy()
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(c[..., None] > 1e-6, u / c[..., None], 0.0).astype(np.float32)
    return c, u
