"""Color-field splatting in Taichi: particles -> the nodes of a block-sparse grid near them.

c(x) = sum_j V_j W(x - x_j) with V_j the particle's volume (the caller's: the surface stage gives
m_j / max(rho_j, rho0_j), reconstruct.particle_volumes), and the velocity field
u(x) = sum_j V_j v_j W(x - x_j) / c(x).

Storage: blocks of 8^3 nodes (one OpenVDB leaf each), allocated only where some particle's
support reaches, plus one node of padding (so that every grid cell with a non-zero corner has
all eight corners in allocated blocks, which marching cubes relies on). Node (i, j, k) sits at
world position cell * (i, j, k); block n holds the nodes blocks[n] * 8 + (0..7)^3.

Scatter without atomics: particles are binned into cubes of edge 2h and the cubes are split
into 8 phases by the parity of their coordinates. Two cubes of one phase are at least 2h apart,
so their particles' supports never share a node: every phase runs in parallel over its cubes,
each cube's particles one after another, with plain (non-atomic) adds. The sum is therefore the
same on every run and with any number of threads (the order of adds is fixed).

Everything stays on the device from the particles' upload to the field (surfacing/device.py):
the particles are counting-sorted by cube there (each cube's run then sorted by particle
index, so the order of adds is the input order, as a stable sort gives), and the color and
velocity are device arrays the marching cubes reads in place.

On a GPU the phases leave too few threads (a few thousand cubes, each a long serial loop:
0.45 s at 4M particles on an H200), so there every particle's node planes run in parallel and
add with 64-bit integer atomics in fixed point (FIXED): integer sums do not depend on the
order of the adds, so the field is again the same on every run; it agrees with the phased
float sums to float32 round-off (tests/test_surfacing.py). CUDA only: 64-bit atomics are not
sure to exist on Vulkan or Metal devices, which keep the phased scatter.
"""
import math

import numpy as np
import taichi as ti

from solver import kernels as K
from solver.neighbours import k_scatter
from solver.types import F1, I1, V3, ivec3, vec3

from . import anisotropy as A, device as D
from .device import I3, I64, R8
from .grid import B, GridTooLarge

B2, B3 = B * B, B * B * B
MAX_LOOKUP = 1 << 28           # block-index entries (1 GiB of int32); beyond this, refuse
# fixed-point scale of the GPU scatter's 64-bit integer sums: each term keeps float32's relative
# precision (it is rounded to 2^-40 after being computed in float32), the sum is exact, and the
# range is 8e6 (color about 1 in the bulk; momentum = color x speed in m/s)
FIXED = float(2 ** 40)



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
def k_splat(pos: V3, vel: V3, vol: F1, start: I1, count: I1, touches: I1, key0: ti.i32, key1: ti.i32, origin: vec3,
            cell: ti.f32, h: ti.f32, target: I3, out: R8, sigma: ti.f32, shape: A.R7, kind: ti.template(),
            velocity_pass: ti.template(), anisotropic: ti.template()):
    """Each particle adds into the nodes of its support, slab by slab and a block row (8 nodes
    along z, one vector) at a time: for each node plane i the sphere cuts, the block rows of
    the square around the plane's disc whose nearest node lies inside the sphere. The 8 weights
    of a row are one vector expression (kernels.shape, branch-free: 0 outside the sphere), and
    the row is one vector load and store, which LLVM compiles to SIMD instructions; this was
    0.58 s against 1.08 s for a node-by-node loop reading W from a table at 500k particles.

    target[block] is the slot each block's rows go to, -1 to skip the block. Row r (= i * 8 + j
    within the block) of slot b is out[b * 64 + r] in the color pass, which adds V_j W; the
    velocity pass adds V_j W v_j, component a into out[(b * 3 + a) * 64 + r], from the particles
    with touches[p] only. The outer loop runs over one phase's cubes (keys key0 to key1) in
    parallel; see the module docstring. Plain loads and stores,
    not `+=` (which Taichi compiles to an atomic add). Node indices are never negative, so
    `>> 3` and `& 7` are the block and the node within it. Distances are in units of h.
    `anisotropic`: the kernel of particle p is W(|A_p d|) (shape[p]: surfacing/anisotropy.py),
    inside the isotropic sphere, so the sphere's pruning still holds."""
    nx, ny, nz = target.shape[0] * B, target.shape[1] * B, target.shape[2] * B
    inv = 1.0 / cell
    ih = 1.0 / h
    step = cell * ih                                    # node spacing in units of h
    lanes = ti.Vector([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]) * step
    for c in range(key0, key1):
        for p in range(start[c], start[c] + count[c]):
            if ti.static(velocity_pass):
                if touches[p] == 0:
                    continue
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
                                    q = txz + y * y
                                    if ti.static(anisotropic):
                                        q = A.quad(shape, p, dx, y, z)
                                    w = K.shape(kind, q)
                                    row = (i & 7) * B + (j & 7)
                                    if ti.static(velocity_pass):    # no races: see above
                                        for a in ti.static(range(3)):
                                            n = (b * 3 + a) * B2 + row
                                            out[n] = out[n] + w * vv[a]
                                    else:
                                        n = b * B2 + row
                                        out[n] = out[n] + w * vp


@ti.kernel
def k_splat_atomic(pos: V3, vel: V3, vol: F1, touches: I1, slabs: ti.i32, origin: vec3, cell: ti.f32, h: ti.f32,
                   target: I3, acc: I64, scale: ti.f32, shape: A.R7, kind: ti.template(), velocity_pass: ti.template(),
                   anisotropic: ti.template()):
    """The GPU scatter: one thread per particle and node plane of its support (`slabs` planes
    at most), adding round(scale V_j W) -- times v_j in the velocity pass -- into the integer
    sums `acc` with atomics (node n of slot b at b * 512 + n; component a of the momentum at
    (b * 3 + a) * 512 + n: the layout of k_splat's rows). `scale` includes sigma."""
    nx, ny, nz = target.shape[0] * B, target.shape[1] * B, target.shape[2] * B
    inv = 1.0 / cell
    ih = 1.0 / h
    for p, s in ti.ndrange(pos.shape[0], slabs):
        skip = False
        if ti.static(velocity_pass):
            skip = touches[p] == 0
        x = pos[p]
        g = (x - origin) * inv
        i0, i1 = _span(g.x, h * inv, nx)
        i = i0 + s
        if not skip and i <= i1:
            dx = (origin.x + cell * i - x.x) * ih
            rem_x = 1.0 - dx * dx
            if rem_x > 0.0:
                half = ti.sqrt(rem_x) * h * inv
                j0, j1 = _span(g.y, half, ny)
                k0, k1 = _span(g.z, half, nz)
                vp = vol[p] * scale
                vv = vp * vel[p]
                for j in range(j0, j1 + 1):
                    dy = (origin.y + cell * j - x.y) * ih
                    rem = rem_x - dy * dy
                    if rem > 0.0:
                        for k in range(k0, k1 + 1):
                            dz = (origin.z + cell * k - x.z) * ih
                            q = dx * dx + dy * dy + dz * dz
                            if ti.static(anisotropic):
                                q = A.quad(shape, p, dx, dy, dz)
                            b = target[i >> 3, j >> 3, k >> 3]
                            if q < 1.0 and b >= 0:
                                w = K.shape(kind, q)
                                node = ((i & 7) * B + (j & 7)) * B + (k & 7)
                                if ti.static(velocity_pass):
                                    for a in ti.static(range(3)):
                                        ti.atomic_add(acc[(b * 3 + a) * B3 + node], ti.cast(ti.round(w * vv[a]), ti.i64))
                                else:
                                    ti.atomic_add(acc[b * B3 + node], ti.cast(ti.round(w * vp), ti.i64))


@ti.kernel
def k_fixed_to_rows(acc: I64, inv_scale: ti.f64, rows: R8):
    for r in rows:
        v = ti.Vector([0.0] * B)
        for q in ti.static(range(B)):
            v[q] = ti.cast(ti.cast(acc[r * B + q], ti.f64) * inv_scale, ti.f32)
        rows[r] = v


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
    """(base_block, shape, origin, top) of the block array over the particles' supports: the
    block coordinates of its first block, its shape in blocks, the world position of its first
    node, and the particles' upper bounds. Bounds are taken a column at a time (numpy's min over
    axis 0 of an (N, 3) array is 25 times slower)."""
    reach = support / cell + 2.0                    # the support, the padding node, round-off
    cols = [positions[:, a] for a in range(3)]
    bottom = np.array([c.min() for c in cols], np.float64)
    top = np.array([c.max() for c in cols], np.float64)
    lo = np.floor(bottom / cell - reach).astype(np.int64)
    hi = np.ceil(top / cell + reach).astype(np.int64)
    base_block = lo // B
    shape = tuple(int(v) for v in hi // B - base_block + 1)
    if math.prod(shape) > MAX_LOOKUP:
        raise GridTooLarge(f"the particles span {shape} blocks of {B}^3 cells; increase "
                           f"surface.cell_size or remove stray particles")
    return base_block, shape, (base_block * B * cell).astype(np.float32), top


@ti.kernel
def k_cube_keys(pos: V3, origin: vec3, inv: ti.f32, dims: ivec3, half: ivec3, key: I1, count: I1):
    """key[p]: particle p's cube of edge 2h, numbered phase by phase (the phase is the parity
    of the cube's coordinates; see the module docstring); count[key] += 1."""
    per_phase = half.x * half.y * half.z
    for p in pos:
        c = ti.math.clamp(ti.cast(ti.floor((pos[p] - origin) * inv), ti.i32), 0, dims - 1)
        phase = (c.x & 1) * 4 + (c.y & 1) * 2 + (c.z & 1)
        k = phase * per_phase + ((c.x >> 1) * half.y + (c.y >> 1)) * half.z + (c.z >> 1)
        key[p] = k
        ti.atomic_add(count[k], 1)


@ti.kernel
def k_take_v3(order: I1, src: V3, dst: V3):
    for s in order:
        dst[s] = src[order[s]]


@ti.kernel
def k_take_i1(order: I1, src: I1, dst: I1):
    for s in order:
        dst[s] = src[order[s]]


@ti.kernel
def k_take_f1(order: I1, src: F1, dst: F1):
    for s in order:
        dst[s] = src[order[s]]


@ti.kernel
def k_target(lookup: I3, slot: I1, target: I3):
    """target[block] = slot[lookup[block]], -1 where no block."""
    for i, j, k in lookup:
        b = lookup[i, j, k]
        target[i, j, k] = slot[b] if b >= 0 else -1


@ti.kernel
def k_divide(momentum: R8, rows: R8, ids: I1, out: V3):
    """out[b * 512 + node] = momentum / color at the node of block ids[b] (0 where the color is
    at most 1e-6): the velocity field, node-major vectors."""
    for b, r in ti.ndrange(ids.shape[0], B2):
        c = rows[ids[b] * B2 + r]
        for a in ti.static(range(3)):
            m = momentum[(b * 3 + a) * B2 + r]
            for q in ti.static(range(B)):
                out[(b * B2 + r) * B + q][a] = m[q] / c[q] if c[q] > 1e-6 else 0.0


def sort_by_cube(positions, origin: np.ndarray, top: np.ndarray, support: float):
    """(order, start, count, per_phase): the particles counting-sorted by cube of edge 2h on
    the device; cube keys run phase by phase, per_phase cubes each; start/count per key."""
    n = positions.shape[0]
    edge = 2.0 * support
    dims = [int(v) + 1 for v in np.floor((top - origin) / edge)]
    half = [(d + 1) // 2 for d in dims]
    per_phase = math.prod(half)
    key = D.empty(ti.i32, n)
    count = D.zeros(ti.i32, 8 * per_phase)
    k_cube_keys(positions, vec3(*map(float, origin)), 1.0 / edge, ivec3(*dims), ivec3(*half),
                key, count)
    return (*_order_by_key(key, count), per_phase)


def _order_by_key(key, count):
    """(order, start): the counting sort of particles by `key` (count: particles per key),
    each key's run in increasing particle index (so that sums over it add in the same order on
    every run and backend)."""
    keys = count.shape[0]
    start, _ = D.exclusive_scan(count, keys)
    order = D.empty(ti.i32, key.shape[0])
    k_scatter(key, start, count, D.zeros(ti.i32, keys), order)      # the neighbour sort's, with keys for cells
    return order, start, count


@ti.kernel
def k_cell_keys(pos: V3, origin: vec3, inv: ti.f32, dims: ivec3, key: I1, count: I1):
    """key[p]: particle p's cell, numbered x, then y, then z (a row along z is contiguous)."""
    for p in pos:
        c = ti.math.clamp(ti.cast(ti.floor((pos[p] - origin) * inv), ti.i32), 0, dims - 1)
        k = (c.x * dims.y + c.y) * dims.z + c.z
        key[p] = k
        ti.atomic_add(count[k], 1)


def sort_by_cell(positions, origin: np.ndarray, top: np.ndarray, edge: float):
    """(order, start, count, dims): the particles counting-sorted by cells of `edge` numbered
    row by row (_order_by_key)."""
    dims = [int(v) + 1 for v in np.floor((top - origin) / edge)]
    key, count = D.empty(ti.i32, positions.shape[0]), D.zeros(ti.i32, math.prod(dims))
    k_cell_keys(positions, vec3(*map(float, origin)), 1.0 / edge, ivec3(*dims), key, count)
    return (*_order_by_key(key, count), dims)


def mark_blocks(pos, base_block: np.ndarray, shape: tuple, origin: np.ndarray, cell: float, support: float):
    """(lookup, blocks): the blocks the particles' supports reach. lookup: int32 array of
    `shape`, block id or -1; blocks: (nb, 3) block coordinates in lookup order (x, y, z
    lexicographic)."""
    used = D.zeros(ti.i32, shape)
    k_mark(pos, vec3(*map(float, origin)), float(cell), float(support), used)
    used = D.host(used).astype(bool)
    lookup = np.full(shape, -1, np.int32)
    lookup[used] = np.arange(int(used.sum()), dtype=np.int32)
    return lookup, np.argwhere(used) + base_block


class Splat:
    """Particles sorted on the device for the phased scatter onto the blocks their supports
    reach.

    color() is the color field on every block (a device array of rows); velocity(v, ids, rows)
    the velocity field on the blocks `ids` only, from the particles that reach them."""

    def __init__(self, positions: np.ndarray, volumes: np.ndarray, cell: float, support: float,
                 kernel: str = "cubic", method: str = "auto", anisotropic: bool = False, spray_below: int = 0,
                 center_smoothing: float = 0.0, center_inflation: float = 0.0):
        """method: "phased", "atomic" or "auto" (atomic on CUDA, else phased). anisotropic: Yu
        & Turk's kernels (surfacing/anisotropy.py), centres smoothed by `center_smoothing`
        (their lambda), then pushed back out by `center_inflation` (Taubin's mu, as a positive
        number; anisotropy.k_inflate) where both are set. spray_below: particles with fewer
        neighbours than this within anisotropy.RADIUS supports (itself counted) are spray, left
        out of the field (self.spray: their mask, in input order)."""
        self.center_smoothing = float(center_smoothing)
        self.center_inflation = float(center_inflation)
        self.cell, self.support = float(cell), float(support)
        self.atomic = D.on_cuda() if method == "auto" else method == "atomic"
        self.anisotropic = bool(anisotropic)
        self.kind = K.DENSITY_KERNELS[kernel]
        self.sigma = K.sigma(self.kind, self.support)
        self.base_block, shape, self.origin, top = grid_frame(positions, cell, support)
        self.n = len(positions)
        self.spray = np.zeros(self.n, bool)
        raw, vol = D.vec3s(positions), D.upload(np.asarray(volumes), ti.f32)
        self.shape = D.zeros(ti.f32, 1, A.COLUMNS)            # (not read by the isotropic splat)
        self.order = None
        if self.anisotropic or spray_below > 0:
            raw, vol = self._anisotropy(raw, vol, top, spray_below)
        if not self.atomic:                 # (the atomic scatter takes any order)
            order, self.start, self.count, self.per_phase = sort_by_cube(raw, self.origin, top, support)
            raw, vol = self._take(order, raw, vol)
        self.pos, self.vol = raw, vol
        self.lookup, self.blocks = mark_blocks(self.pos, self.base_block, shape, self.origin, cell, support)
        self.lookup_dev = D.upload(self.lookup)

    def _take(self, order, pos, vol):
        """(pos, vol) in `order` (and the anisotropy table, if any); self.order, the order into
        the input, follows."""
        out_pos, out_vol = D.empty(ti.f32, self.n, 3), D.empty(ti.f32, self.n)
        k_take_v3(order, pos, out_pos)
        k_take_f1(order, vol, out_vol)
        if self.anisotropic and self.order is not None:     # (the table is made after the first sort)
            rows = D.empty(ti.f32, self.n, A.COLUMNS)
            A.k_take_rows(order, self.shape, rows)
            self.shape = rows
        if self.order is None:
            self.order = order
        else:                               # composed with the sort before it
            both = D.empty(ti.i32, self.n)
            k_take_i1(order, self.order, both)
            self.order = both
        return out_pos, out_vol

    def _anisotropy(self, raw, vol, top, spray_below: int):
        """Sort by cell, then per particle its neighbour count (spray), and with `anisotropic`
        its smoothed centre and kernel (surfacing/anisotropy.py). Returns (positions, volumes)
        in the sorted order, the centres for positions where anisotropic. The neighbour search
        sorts by cells of edge h numbered row by row (sort_by_cell): a row of cells along z is
        one run of particles. At 500k particles k_anisotropy takes 0.84 s on 2 cores (over the
        scatter's 2h cubes, numbered phase by phase, 1.45 s; cells of edge h numbered that way,
        2.56 s; cells of 2h or 2h/3 row by row, 0.85 and 1.12 s)."""
        edge = self.support
        order, start, count, dims = sort_by_cell(raw, self.origin, top, edge)
        pos, vol = self._take(order, raw, vol)
        center, table = D.empty(ti.f32, self.n, 3), D.empty(ti.f32, self.n, A.COLUMNS)
        neighbours = D.empty(ti.i32, self.n)
        A.k_anisotropy(pos, start, count, vec3(*map(float, self.origin)), edge, ivec3(*dims),
                       A.RADIUS * self.support, self.center_smoothing, center, table, neighbours,
                       self.anisotropic and self.center_smoothing > 0)
        if self.anisotropic and self.center_smoothing > 0 and self.center_inflation > 0:
            inflated = D.empty(ti.f32, self.n, 3)
            A.k_inflate(pos, center, start, count, vec3(*map(float, self.origin)), edge, ivec3(*dims),
                        self.support, self.center_inflation, inflated)
            center = inflated
        A.k_weigh(vol, table, neighbours, spray_below, self.anisotropic)
        if spray_below > 0:
            few = D.host(neighbours) < spray_below
            self.spray[D.host(self.order)[few]] = True
        if not self.anisotropic:
            return pos, vol
        self.shape = table
        return center, vol

    @property
    def n_blocks(self) -> int:
        return len(self.blocks)

    def color(self):
        """(nb + 1) * 64 rows of 8 nodes (a device array); the last block stays zero (the
        stand-in for missing ones)."""
        rows = D.zeros(ti.f32, (self.n_blocks + 1) * B2, B)
        self._scatter(None, self.pos, self.lookup_dev, rows, False)
        return rows

    def velocity(self, velocities: np.ndarray, ids: np.ndarray, rows):
        """The velocity field on the blocks `ids` (zero where the color is at most 1e-6), on
        the device: (len(ids) + 1) * 512 vectors, node-major (block b's node n at b * 512 + n);
        `rows`: the color (color()'s device array)."""
        nv = len(ids)
        slot = np.full(self.n_blocks + 1, -1, np.int32)
        slot[ids] = np.arange(nv, dtype=np.int32)
        target = D.empty(ti.i32, self.lookup.shape)
        k_target(self.lookup_dev, D.upload(slot), target)
        touches = D.empty(ti.i32, self.n)
        k_touches(self.pos, vec3(*map(float, self.origin)), self.cell, self.support, target, touches)
        momentum = D.zeros(ti.f32, (nv + 1) * 3 * B2, B)
        vel = D.vec3s(velocities)
        if self.order is not None:
            sorted_vel = D.empty(ti.f32, self.n, 3)
            k_take_v3(self.order, vel, sorted_vel)
            vel = sorted_vel
        self._scatter(touches, vel, target, momentum, True)
        out = D.zeros(ti.f32, (nv + 1) * B3, 3)
        if nv:
            k_divide(momentum, rows, D.upload(np.asarray(ids, np.int32)), out)
        return out

    def _scatter(self, touches, vel, target, out, velocity_pass: bool) -> None:
        """Add the particles (those with `touches`, if given) into `out`: the color, or the
        momentum; one launch per phase."""
        if touches is None:
            touches = D.zeros(ti.i32, 1)      # not read by the color pass
        if self.atomic:
            scale = FIXED
            acc = D.zeros(ti.i64, out.shape[0] * B)
            slabs = int(math.floor(2.0 * self.support / self.cell)) + 2
            k_splat_atomic(self.pos, vel, self.vol, touches, slabs, vec3(*map(float, self.origin)), self.cell,
                           self.support, target, acc, self.sigma * scale, self.shape, self.kind, velocity_pass,
                           self.anisotropic)
            k_fixed_to_rows(acc, 1.0 / scale, out)
            return
        for ph in range(8):
            k_splat(self.pos, vel, self.vol, self.start, self.count, touches, ph * self.per_phase,
                    (ph + 1) * self.per_phase, vec3(*map(float, self.origin)), self.cell, self.support, target,
                    out, self.sigma, self.shape, self.kind, velocity_pass, self.anisotropic)
