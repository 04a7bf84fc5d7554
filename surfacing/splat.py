"""Colour-field splatting in Taichi: particles -> the nodes of a block-sparse grid near them.

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

from .reconstruct import B, GridTooLarge

B3 = B * B * B
MAX_LOOKUP = 1 << 28           # block-index entries (1 GiB of int32); beyond this, refuse
TABLE_INTERVALS = 8192         # the kernel table: 32 KiB, in L1 cache

vec3 = ti.math.vec3
V3 = ti.types.ndarray(dtype=vec3, ndim=1)
F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
I3 = ti.types.ndarray(dtype=ti.i32, ndim=3)


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
            target: I3, colour: F1, momentum: V3, table: F1, velocity_pass: ti.template()):
    """Each particle adds into the nodes of its support, slab by slab: for each node plane i
    the sphere cuts, the square of nodes around the plane's disc (4/pi of the disc's nodes),
    whose rows all have the same length and block split, so the loops are branch-predictable
    and need one square root per slab instead of one per row. Nodes outside the sphere read
    W = 0 from the table's end (so the sum is the same as over the sphere alone); this was
    0.78 s against 1.25 s for row-exact spans at 500k particles.

    target[block] is the slot each block's nodes go to, -1 to skip the block; node n of slot b
    is entry b * 512 + n of the flat `colour` / `momentum`. The colour pass adds V_j W into
    `colour`, the velocity pass V_j W v_j into `momentum`, W read from `table` (see
    kernel_table) at t = r^2 in table intervals. The outer loop runs over one phase's cubes in
    parallel; see the module docstring. Plain loads and stores, not `+=` (which Taichi
    compiles to an atomic add). Node indices are never negative, so `>> 3` and `& 7` are the
    block and the node within it."""
    nx, ny, nz = target.shape[0] * B, target.shape[1] * B, target.shape[2] * B
    n_tab = table.shape[0] - 2
    per_r2 = n_tab / (h * h)                            # table intervals per unit of r^2
    sq = ti.sqrt(per_r2)                                # lengths scaled so that t = |d|^2
    inv = 1.0 / cell
    step = cell * sq
    for c in first:
        for p in range(first[c], last[c]):
            x = pos[p]
            vp = vol[p]
            vv = vp * vel[p]
            g = (x - origin) * inv                      # the particle in node units
            i0, i1 = _span(g.x, h * inv, nx)
            for i in range(i0, i1 + 1):
                dx = origin.x + cell * i - x.x
                rem_x = h * h - dx * dx
                if rem_x > 0.0:
                    half = ti.sqrt(rem_x) * inv         # the disc's radius in node units
                    j0, j1 = _span(g.y, half, ny)
                    k0, k1 = _span(g.z, half, nz)
                    tx = dx * dx * per_r2
                    y0 = (origin.y + cell * j0 - x.y) * sq
                    z0 = (origin.z + cell * k0 - x.z) * sq
                    k = k0
                    while k <= k1:                      # the slab's blocks along k
                        kb = k >> 3
                        k_end = ti.min(k1, kb * B + B - 1)
                        zk = z0 + step * (k - k0)
                        for j in range(j0, j1 + 1):
                            b = target[i >> 3, j >> 3, kb]
                            if b >= 0:
                                y = y0 + step * (j - j0)
                                txy = tx + y * y
                                base = b * B3 + ((i & 7) * B + (j & 7)) * B - kb * B
                                z = zk      # a running sum over at most 8 nodes (one block)
                                for n in range(k, k_end + 1):
                                    t = txy + z * z
                                    z += step
                                    e = ti.min(ti.cast(t, ti.i32), n_tab)   # past the rim: 0
                                    w0 = table[e]
                                    wgt = w0 + (t - e) * (table[e + 1] - w0)
                                    if ti.static(velocity_pass):    # no races: see above
                                        momentum[base + n] = momentum[base + n] + wgt * vv
                                    else:
                                        colour[base + n] = colour[base + n] + wgt * vp
                        k = k_end + 1


def kernel_table(kind: int, h: float, intervals: int = TABLE_INTERVALS) -> np.ndarray:
    """W(r) at r^2 = h^2 (0, 1, ..., intervals) / intervals, then one more 0: the splat reads W
    by linear interpolation in r^2, with no square root and no branch per node. The error is
    largest near r = 0, where W as a function of s = r^2 / h^2 has an s^1.5 term, c s^1.5 W(0)
    (c = 6 for the cubic spline, 20 for Wendland C2, 0 for poly6): at most (4/27) c
    intervals^-1.5 W(0) there, 1.2e-6 W(0) (cubic) and 4.0e-6 W(0) (Wendland) at 8192
    intervals; tests/test_surfacing.py checks 5e-6 for every kernel."""
    r2 = np.linspace(0.0, 1.0, intervals + 1) * (h * h)
    w = K.w_np(kind, np.sqrt(r2), h)
    w[-1] = 0.0                                       # W(h) = 0 exactly, whatever the round-off
    return np.r_[w, 0.0].astype(np.float32)


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


def allocate(positions: np.ndarray, cell: float, support: float):
    """The blocks the particles' supports reach: (lookup, base_block, blocks, origin).

    lookup: int32 array over the blocks' bounding box, block id or -1; base_block: the block
    coordinates of lookup[0, 0, 0]; blocks: (nb, 3) block coordinates in lookup order (x, y, z
    lexicographic); origin: world position of node base_block * 8."""
    reach = support / cell + 2.0                    # the support, the padding node, round-off
    lo = np.floor(positions.min(0).astype(np.float64) / cell - reach).astype(np.int64)
    hi = np.ceil(positions.max(0).astype(np.float64) / cell + reach).astype(np.int64)
    base_block = lo // B
    shape = tuple(int(v) for v in hi // B - base_block + 1)
    if math.prod(shape) > MAX_LOOKUP:
        raise GridTooLarge(f"the particles span {shape} blocks of {B}^3 cells; increase "
                           f"surface.cell_size or remove stray particles")
    origin = (base_block * B * cell).astype(np.float32)
    used = ti.ndarray(ti.i32, shape=shape)
    used.fill(0)
    k_mark(_vec3_ndarray(positions), vec3(*map(float, origin)), float(cell), float(support), used)
    used = used.to_numpy().astype(bool)
    lookup = np.full(shape, -1, np.int32)
    lookup[used] = np.arange(int(used.sum()), dtype=np.int32)
    blocks = np.argwhere(used) + base_block
    return lookup, base_block, blocks, origin


class Splat:
    """Particles sorted for the phased scatter onto the blocks their supports reach.

    colour() is the colour field on every block; velocity(v, ids, colour) the velocity field
    on the blocks `ids` only, from the particles that reach them."""

    def __init__(self, positions: np.ndarray, volumes: np.ndarray, cell: float, support: float,
                 kernel: str = "cubic"):
        self.lookup, self.base_block, self.blocks, self.origin = allocate(positions, cell, support)
        self.cell, self.support = float(cell), float(support)
        self.table = kernel_table(K.DENSITY_KERNELS[kernel], self.support)
        # particles into cubes of edge 2h, ordered by phase, then cube (the order inside a
        # cube made no difference to the splat's speed; a stable sort keeps it fixed)
        cube = np.floor((positions.astype(np.float64) - self.origin) / (2 * support)).astype(np.int64)
        cdims = cube.max(0) + 1
        phase = (cube[:, 0] & 1) * 4 + (cube[:, 1] & 1) * 2 + (cube[:, 2] & 1)
        cube_id = (cube[:, 0] * cdims[1] + cube[:, 1]) * cdims[2] + cube[:, 2]
        self.order = np.argsort(phase * int(np.prod(cdims)) + cube_id, kind="stable")
        self.cube_id, self.phase = cube_id[self.order], phase[self.order]
        self.pos = _vec3_ndarray(positions[self.order])
        self.vol = ti.ndarray(ti.f32, shape=len(self.order))
        self.vol.from_numpy(np.ascontiguousarray(volumes[self.order], np.float32))

    @property
    def n_blocks(self) -> int:
        return len(self.blocks)

    def colour(self) -> np.ndarray:
        """(nb + 1, 8, 8, 8) float32; the last block stays zero (the stand-in for missing ones)."""
        colour = np.zeros((self.n_blocks + 1, B3), np.float32)
        self._scatter(np.ones(len(self.order), bool), self.pos, self.lookup, colour, None)
        return colour.reshape(-1, B, B, B)

    def velocity(self, velocities: np.ndarray, ids: np.ndarray, colour: np.ndarray) -> np.ndarray:
        """(len(ids) + 1, 8, 8, 8, 3) float32 on the blocks `ids` (zero where colour <= 1e-6)."""
        slot = np.full(self.n_blocks + 1, -1, np.int32)
        slot[ids] = np.arange(len(ids), dtype=np.int32)
        target = np.where(self.lookup >= 0, slot[self.lookup], -1).astype(np.int32)
        touches = np.zeros(len(self.order), np.int32)
        k_touches(self.pos, vec3(*map(float, self.origin)), self.cell, self.support, target, touches)
        momentum = np.zeros((len(ids) + 1, B3, 3), np.float32)
        vel = _vec3_ndarray(velocities[self.order])
        self._scatter(touches.astype(bool), vel, target, None, momentum)
        u = momentum.reshape(-1, B, B, B, 3)
        c = np.concatenate([colour[ids], np.zeros((1, B, B, B), np.float32)])[..., None]
        np.divide(u, c, out=u, where=c > 1e-6)
        u[np.broadcast_to(c <= 1e-6, u.shape)] = 0.0
        return u

    def _scatter(self, use: np.ndarray, vel, target: np.ndarray, colour, momentum) -> None:
        """Add the particles `use` (in sorted order) into colour, or into momentum if given."""
        velocity_pass = momentum is not None
        dummy1, dummy3 = np.zeros(1, np.float32), np.zeros((1, 3), np.float32)
        idx = np.flatnonzero(use)
        if len(idx) == 0:
            return
        # each cube's taking part particles as one index range into the sorted arrays (particles
        # in between that reach no target block add nothing)
        cube_id, phase = self.cube_id[idx], self.phase[idx]
        starts = np.flatnonzero(np.r_[True, cube_id[1:] != cube_id[:-1]])
        ends = np.r_[starts[1:], len(idx)]
        first_all, last_all = idx[starts], idx[ends - 1] + 1
        for ph in range(8):
            sel = phase[starts] == ph
            if not sel.any():
                continue
            k_splat(self.pos, vel, self.vol, first_all[sel].astype(np.int32), last_all[sel].astype(np.int32),
                    vec3(*map(float, self.origin)), self.cell, self.support, target,
                    dummy1 if velocity_pass else colour.reshape(-1),
                    momentum.reshape(-1, 3) if velocity_pass else dummy3,
                    self.table, velocity_pass)


def _vec3_ndarray(a: np.ndarray):
    out = ti.Vector.ndarray(3, ti.f32, shape=len(a))
    out.from_numpy(np.ascontiguousarray(a, np.float32))
    return out
