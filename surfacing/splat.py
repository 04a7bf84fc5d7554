"""Color-field splatting in Taichi: particles -> the nodes of a block-sparse grid near them.

c(x) = sum_j V_j W(x - x_j) with V_j = m_j / rho_j (the particle's volume, from the sim cache),
and the velocity field u(x) = sum_j V_j v_j W(x - x_j) / c(x).

Storage: blocks of 8^3 nodes (one OpenVDB leaf each), allocated only where some particle's
support reaches, plus one node of padding (so that every grid cell with a non-zero corner has
all eight corners in allocated blocks, which marching cubes relies on). Node (i, j, k) sits at
world position cell * (i, j, k); block n holds the nodes blocks[n] * 8 + (0..7)^3.

Scatter without atomics: particles are binned into cubes of edge 2h and the cubes are split
into 8 phases by the parity of their coordinates. Two cubes of one phase are at least 2h apart,
so their particles' supports never share a node: every phase runs in parallel over its cubes,
each cube's particles one after another, with plain (non-atomic) adds. The sum is therefore the
same on every run and with any number of threads (the order of adds is fixed).
"""
import math

import numpy as np
import taichi as ti

from solver import kernels as K

from .grid import B, GridTooLarge

B2, B3 = B * B, B * B * B
MAX_LOOKUP = 1 << 28           # block-index entries (1 GiB of int32); beyond this, refuse

vec3 = ti.math.vec3
V3 = ti.types.ndarray(dtype=vec3, ndim=1)
F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
I3 = ti.types.ndarray(dtype=ti.i32, ndim=3)
R8 = ti.types.ndarray(dtype=ti.types.vector(B, ti.f32), ndim=1)     # rows of 8 nodes along z


@ti.func
def _span(g: ti.f32, reach: ti.f32, n: ti.i32):
    """First and last node index within `reach` (node units) of `g`, clipped to [0, n)."""
    return ti.max(ti.cast(ti.ceil(g - reach), ti.i32), 0), ti.min(ti.cast(ti.floor(g + reach), ti.i32), n - 1)


@ti.func
def _blocks_within(g, reach: ti.f32, shape):
    """The block index ranges ((x0, x1), (y0, y1), (z0, z1)), ends exclusive, of the nodes
    within `reach` (node units, per axis) of `g`, for a block array of `shape`."""
    lo_x, hi_x = _span(g.x, reach, shape[0] * B)
    lo_y, hi_y = _span(g.y, reach, shape[1] * B)
    lo_z, hi_z = _span(g.z, reach, shape[2] * B)
    return (lo_x // B, hi_x // B + 1), (lo_y // B, hi_y // B + 1), (lo_z // B, hi_z // B + 1)


@ti.kernel
def k_mark(pos: V3, origin: vec3, cell: ti.f32, h: ti.f32, used: I3):
    """used[block] = 1 for every block within one node of some particle's support cube."""
    for p in pos:
        rx, ry, rz = _blocks_within((pos[p] - origin) / cell, h / cell + 1.0, used.shape)
        for bi, bj, bk in ti.ndrange(rx, ry, rz):
            used[bi, bj, bk] = 1


@ti.kernel
def k_splat(pos: V3, vel: V3, vol: F1, first: I1, last: I1, origin: vec3, cell: ti.f32, h: ti.f32,
            target: I3, out: R8, sigma: ti.f32, kind: ti.template(), velocity_pass: ti.template()):
    """Each particle adds into the nodes of its support, slab by slab and a block row (8 nodes
    along z, one vector) at a time: for each node plane i the sphere cuts, the block rows of
    the square around the plane's disc whose nearest node lies inside the sphere. The 8 weights
    of a row are one vector expression (kernels.shape, branch-free: 0 outside the sphere), and
    the row is one vector load and store, which LLVM compiles to SIMD instructions; this was
    0.58 s against 1.08 s for a node-by-node loop reading W from a table at 500k particles.

    target[block] is the slot each block's rows go to, -1 to skip the block. Row r (= i * 8 + j
    within the block) of slot b is out[b * 64 + r] in the color pass, which adds V_j W; the
    velocity pass adds V_j W v_j, component a into out[(b * 3 + a) * 64 + r]. The outer loop
    runs over one phase's cubes in parallel; see the module docstring. Plain loads and stores,
    not `+=` (which Taichi compiles to an atomic add). Node indices are never negative, so
    `>> 3` and `& 7` are the block and the node within it. Distances are in units of h."""
    nx, ny, nz = target.shape[0] * B, target.shape[1] * B, target.shape[2] * B
    inv = 1.0 / cell
    ih = 1.0 / h
    step = cell * ih                                    # node spacing in units of h
    lanes = ti.Vector([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]) * step
    for c in first:
        for p in range(first[c], last[c]):
            x = pos[p]
            vp = vol[p] * sigma
            vv = vp * vel[p]
            g = (x - origin) * inv                      # the particle in node units
            i0, i1 = _span(g.x, h * inv, nx)
            for i in range(i0, i1 + 1):
                dx = (origin.x + cell * i - x.x) * ih
                rem_x = 1.0 - dx * dx
                if rem_x > 0.0:
                    half = ti.sqrt(rem_x) * h * inv     # the disc's radius in node units
                    j0, j1 = _span(g.y, half, ny)
                    k0, k1 = _span(g.z, half, nz)
                    y0 = (origin.y + cell * j0 - x.y) * ih
                    for kb in range(k0 >> 3, (k1 >> 3) + 1):
                        z_lo = (origin.z + cell * (kb * B) - x.z) * ih
                        z = z_lo + lanes
                        txz = dx * dx + z * z
                        gap = ti.max(ti.max(z_lo, -(z_lo + 7.0 * step)), 0.0)   # to the row's span
                        rem = rem_x - gap * gap
                        for j in range(j0, j1 + 1):
                            y = y0 + step * (j - j0)
                            if y * y < rem:
                                b = target[i >> 3, j >> 3, kb]
                                if b >= 0:
                                    w = K.shape(kind, txz + y * y)
                                    row = (i & 7) * B + (j & 7)
                                    if ti.static(velocity_pass):    # no races: see above
                                        for a in ti.static(range(3)):
                                            n = (b * 3 + a) * B2 + row
                                            out[n] = out[n] + w * vv[a]
                                    else:
                                        n = b * B2 + row
                                        out[n] = out[n] + w * vp


@ti.kernel
def k_touches(pos: V3, origin: vec3, cell: ti.f32, h: ti.f32, target: I3, touches: I1):
    """touches[p] = 1 where particle p's support cube reaches a block with target >= 0."""
    for p in pos:
        rx, ry, rz = _blocks_within((pos[p] - origin) / cell, h / cell, target.shape)
        hit = 0
        for bi, bj, bk in ti.ndrange(rx, ry, rz):
            if target[bi, bj, bk] >= 0:
                hit = 1
        touches[p] = hit


def grid_frame(positions: np.ndarray, cell: float, support: float):
    """(base_block, shape, origin) of the block array over the particles' supports: the block
    coordinates of its first block, its shape in blocks, and the world position of its first
    node. Bounds are taken a column at a time (numpy's min over axis 0 of an (N, 3) array is
    25 times slower)."""
    reach = support / cell + 2.0                    # the support, the padding node, round-off
    cols = [positions[:, a] for a in range(3)]
    lo = np.floor(np.array([c.min() for c in cols], np.float64) / cell - reach).astype(np.int64)
    hi = np.ceil(np.array([c.max() for c in cols], np.float64) / cell + reach).astype(np.int64)
    base_block = lo // B
    shape = tuple(int(v) for v in hi // B - base_block + 1)
    if math.prod(shape) > MAX_LOOKUP:
        raise GridTooLarge(f"the particles span {shape} blocks of {B}^3 cells; increase "
                           f"surface.cell_size or remove stray particles")
    return base_block, shape, (base_block * B * cell).astype(np.float32)


def phase_order(positions: np.ndarray, origin: np.ndarray, support: float):
    """(order, cube_id, phase): the particles into cubes of edge 2h, ordered by phase, then
    cube (the order inside a cube made no difference to the splat's speed; a stable sort keeps
    it fixed); cube_id and phase in that order."""
    cube = [np.floor((positions[:, a].astype(np.float64) - origin[a]) / (2 * support)).astype(np.int64)
            for a in range(3)]
    dims = [int(c.max()) + 1 for c in cube]
    phase = (cube[0] & 1) * 4 + (cube[1] & 1) * 2 + (cube[2] & 1)
    cube_id = (cube[0] * dims[1] + cube[1]) * dims[2] + cube[2]
    order = np.argsort(phase * math.prod(dims) + cube_id, kind="stable")
    return order, cube_id[order], phase[order]


def mark_blocks(pos, base_block: np.ndarray, shape: tuple, origin: np.ndarray, cell: float, support: float):
    """(lookup, blocks): the blocks the particles' supports reach. lookup: int32 array of
    `shape`, block id or -1; blocks: (nb, 3) block coordinates in lookup order (x, y, z
    lexicographic)."""
    used = ti.ndarray(ti.i32, shape=shape)
    used.fill(0)
    k_mark(pos, vec3(*map(float, origin)), float(cell), float(support), used)
    used = used.to_numpy().astype(bool)
    lookup = np.full(shape, -1, np.int32)
    lookup[used] = np.arange(int(used.sum()), dtype=np.int32)
    return lookup, np.argwhere(used) + base_block


class Splat:
    """Particles sorted for the phased scatter onto the blocks their supports reach.

    color() is the color field on every block; velocity(v, ids, color) the velocity field
    on the blocks `ids` only, from the particles that reach them."""

    def __init__(self, positions: np.ndarray, volumes: np.ndarray, cell: float, support: float,
                 kernel: str = "cubic"):
        self.cell, self.support = float(cell), float(support)
        self.kind = K.DENSITY_KERNELS[kernel]
        self.sigma = K.sigma(self.kind, self.support)
        self.base_block, shape, self.origin = grid_frame(positions, cell, support)
        self.order, self.cube_id, self.phase = phase_order(positions, self.origin, support)
        # np.take, not positions[order]: 4 ms against 20 ms at 500k particles
        self.pos = _vec3_ndarray(np.take(positions, self.order, axis=0))
        self.vol = ti.ndarray(ti.f32, shape=len(self.order))
        self.vol.from_numpy(np.ascontiguousarray(np.take(volumes, self.order), np.float32))
        self.lookup, self.blocks = mark_blocks(self.pos, self.base_block, shape, self.origin, cell, support)

    @property
    def n_blocks(self) -> int:
        return len(self.blocks)

    def color(self) -> np.ndarray:
        """(nb + 1, 8, 8, 8) float32; the last block stays zero (the stand-in for missing ones)."""
        color = np.zeros((self.n_blocks + 1, B3), np.float32)
        self._scatter(np.ones(len(self.order), bool), self.pos, self.lookup, color, False)
        return color.reshape(-1, B, B, B)

    def velocity(self, velocities: np.ndarray, ids: np.ndarray, color: np.ndarray) -> np.ndarray:
        """(len(ids) + 1, 8, 8, 8, 3) float32 on the blocks `ids` (zero where color <= 1e-6): a
        view of component-major blocks, the layout the scatter writes."""
        slot = np.full(self.n_blocks + 1, -1, np.int32)
        slot[ids] = np.arange(len(ids), dtype=np.int32)
        target = np.where(self.lookup >= 0, slot[self.lookup], -1).astype(np.int32)
        touches = np.zeros(len(self.order), np.int32)
        k_touches(self.pos, vec3(*map(float, self.origin)), self.cell, self.support, target, touches)
        momentum = np.zeros((len(ids) + 1, 3 * B3), np.float32)
        vel = _vec3_ndarray(np.take(velocities, self.order, axis=0))
        self._scatter(touches.astype(bool), vel, target, momentum, True)
        u = momentum.reshape(-1, 3, B, B, B)
        c = np.concatenate([color[ids], np.zeros((1, B, B, B), np.float32)])[:, None]
        np.divide(u, c, out=u, where=c > 1e-6)
        u[np.broadcast_to(c <= 1e-6, u.shape)] = 0.0
        return np.moveaxis(u, 1, -1)

    def _scatter(self, use: np.ndarray, vel, target: np.ndarray, out: np.ndarray, velocity_pass: bool) -> None:
        """Add the particles `use` (in sorted order) into `out`: the color, or the momentum."""
        idx = np.flatnonzero(use)
        if len(idx) == 0:
            return
        # each cube's taking part particles as one index range into the sorted arrays (particles
        # in between that reach no target block add nothing)
        cube_id, phase = self.cube_id[idx], self.phase[idx]
        starts = np.flatnonzero(np.r_[True, cube_id[1:] != cube_id[:-1]])
        ends = np.r_[starts[1:], len(idx)]
        first_all, last_all = idx[starts], idx[ends - 1] + 1
        rows = out.reshape(-1, B)
        for ph in range(8):
            sel = phase[starts] == ph
            if not sel.any():
                continue
            k_splat(self.pos, vel, self.vol, first_all[sel].astype(np.int32), last_all[sel].astype(np.int32),
                    vec3(*map(float, self.origin)), self.cell, self.support, target, rows, self.sigma,
                    self.kind, velocity_pass)


def _vec3_ndarray(a: np.ndarray):
    out = ti.Vector.ndarray(3, ti.f32, shape=len(a))
    out.from_numpy(np.ascontiguousarray(a, np.float32))
    return out
