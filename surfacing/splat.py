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


@ti.kernel
def k_splat(pos: V3, vel: V3, vol: F1, origin: vec3, cell: ti.f32, h: ti.f32,
            colour: G3, momentum: G3V, kern: ti.template()):
    nx, ny, nz = colour.shape
    reach = ti.cast(ti.ceil(h / cell), ti.i32)
    for p in pos:
        x = pos[p]
        base = ti.cast(ti.round((x - origin) / cell), ti.i32)
        for di, dj, dk in ti.ndrange((-reach, reach + 1), (-reach, reach + 1), (-reach, reach + 1)):
            i, j, k = base.x + di, base.y + dj, base.z + dk
            if 0 <= i < nx and 0 <= j < ny and 0 <= k < nz:
                node = origin + cell * vec3(i, j, k)
                wgt = vol[p] * K.w(kern, (node - x).norm(), h)
                if wgt > 0.0:
                    ti.atomic_add(colour[i, j, k], wgt)
                    ti.atomic_add(momentum[i, j, k], wgt * vel[p])


def splat(positions: np.ndarray, velocities: np.ndarray, volumes: np.ndarray, origin: np.ndarray,
          shape: tuple[int, int, int], cell: float, support: float, kernel: int = K.CUBIC):
    """Return (colour, velocity) node arrays of `shape`, node (i,j,k) at origin + cell*(i,j,k)."""
    n = len(positions)
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
