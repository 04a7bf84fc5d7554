"""Weakly compressible SPH after Müller, Charypar & Gross 2003, with Tait's equation of state.

One step, in the order of the paper:
  1. neighbours    Verlet lists of the pairs within h + skin, rebuilt only once some particle has
                   moved skin/2 since the last build (every few steps): the particles are then
                   counting-sorted by cell (cell size (h + skin) / CELL_DIV) and the arrays
                   permuted so that each cell's particles are contiguous in memory
  2. density       number density delta_i = sum_j W(x_ij) (+ wall integral), rho_i = m_i delta_i
                   (Solenthaler & Pajarola 2008: exact at interfaces of fluids of different rho0)
                   pressure p_i = B ((rho_i / rho0)^gamma - 1), clamped at 0, B = rho0 c^2 / gamma
                   this pass reads the Verlet list and keeps the pairs now within h in a second,
                   exact list; the force pass reads only those
  3. forces        symmetric pressure  a_i -= 1/m_i sum_j (p_i/delta_i^2 + p_j/delta_j^2) grad W
                   (the pressure gradient is scaled by 1/M, M the kernel gradient's first moment on
                   the fill lattice, so that a linear pressure field is differentiated exactly)
                   viscosity           a_i += 1/m_i sum_j mu_ij (v_j - v_i)/(delta_i delta_j) lap W_visc
                   colour field        n_i = sum_j grad W / delta_j,  lap c_i = sum_j lap W / delta_j
                   surface tension     a_i -= sigma lap c_i n_i / |n_i| / rho_i   where |n_i| h > threshold
                   plus gravity and the pressure of walls (see kernels.wall_tables)
  4. time step     CFL, force and viscous limits, clamped to land on the next frame time
  5. integrate     leapfrog: v_{n+1/2} = v_{n-1/2} + a_n (dt_{n-1/2} + dt_{n+1/2}) / 2,
                   x_{n+1} = x_n + v_{n+1/2} dt_{n+1/2}
  6. collide       project out of colliders and the domain, restitution and Coulomb friction

Kernels are pure: every array and scalar comes in as an argument (Taichi ndarrays), so the same
compiled kernels serve every particle count and no field lives at module level.
"""

import math
import time
from dataclasses import dataclass, field

import numpy as np
import taichi as ti

from . import kernels as K

vec3 = ti.math.vec3
ivec3 = ti.math.ivec3
V3 = ti.types.ndarray(dtype=vec3, ndim=1)
F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
F2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
F4 = ti.types.ndarray(dtype=ti.f32, ndim=4)

SPHERE, BOX, CAPSULE, MESH = 0, 1, 2, 3
COLLIDER_TYPES = {"sphere": SPHERE, "box": BOX, "capsule": CAPSULE, "mesh": MESH}
# Fluid table columns
F_MASS, F_RHO0, F_B, F_MU, F_SIGMA = range(5)
# Collider table columns: 8 shape params, restitution, friction, sign (+1 obstacle, -1 container).
# A mesh's shape params: its distance grid's origin (3), voxel size, node counts (3) and offset
# into the flat array of all mesh grids (exact in float32 up to 2^24).
C_REST, C_FRIC, C_SIGN = 8, 9, 10
SCAN_BLOCK = 256
# Cells are (h + skin) / CELL_DIV wide; a particle's list neighbours lie within CELL_DIV cells each way. With
# CELL_DIV = 2 the 5 x 5 x 5 cells searched cover 42% less volume than 3 x 3 x 3 cells of size h,
# so fewer candidates are tested; each row of 5 cells along x is contiguous in memory.
CELL_DIV = 2
# Verlet-list skin, in units of h: lists hold pairs within h (1 + SKIN) and last until a particle
# has moved SKIN h / 2 from where they were built. Measured on the 50k dam break (bench/solver.py,
# 0.5 s): 0.15 rebuilds too often, 0.25 lists too many pairs; 0.2 was fastest.
SKIN = 0.2
# A step shorter than this fraction of the acoustic CFL step means the state has blown up. The
# three example shots at their own resolution, all frames, never went below 0.75 of it.
MIN_DT_FRACTION = 1e-3


class Unstable(RuntimeError):
    """The state has blown up mid-frame; the message says how."""


MAX_LIST_ENTRIES = 2 ** 31 - 1     # Taichi's ndarray index is int32


class TooLarge(RuntimeError):
    """The neighbour lists would pass MAX_LIST_ENTRIES."""


# ===================================================================================== config
@dataclass(frozen=True)
class SolverConfig:
    """Everything the solver needs, in SI units, derived once from the job spec."""
    particle_radius: float
    h: float                                  # kernel support radius
    gravity: tuple[float, float, float]
    domain_min: tuple[float, float, float]
    domain_max: tuple[float, float, float]
    domain_restitution: float
    domain_friction: float
    fluid_table: np.ndarray                    # (F, 5) mass, rho0, B, mu, sigma
    colliders_f: np.ndarray                    # (K, 11)
    colliders_t: np.ndarray                    # (K,) int
    collider_sdf: np.ndarray                   # mesh colliders' distance grids, flat float32
    speed_of_sound: float
    gamma: float
    cfl: float
    max_dt: float
    surface_threshold: float
    density_kernel: int = K.POLY6
    pressure_kernel: int = K.SPIKY
    lattice_density: float = 1.0               # number density of the fill lattice
    grad_scale: float = 1.0                     # 1 / lattice gradient moment (see kernels)

    @property
    def spacing(self) -> float:
        return 2.0 * self.particle_radius

    @classmethod
    def from_spec(cls, spec) -> "SolverConfig":
        r = spec.sim.particle_radius
        h = spec.smoothing_radius
        dk = K.DENSITY_KERNELS[spec.sim.kernels.density]
        pk = K.PRESSURE_KERNELS[spec.sim.kernels.pressure]
        lattice = K.lattice_number_density(dk, h, 2 * r)
        grad_scale = 1.0 / K.lattice_gradient_moment(pk, h, 2 * r, lattice)
        c = spec.sim.speed_of_sound or 10.0 * spec.expected_max_speed()
        gamma = spec.sim.gamma
        table = np.array([[f.rest_density / lattice, f.rest_density, f.rest_density * c * c / gamma,
                           f.viscosity, f.surface_tension] for f in spec.fluids], dtype=np.float32)
        cf, ct, grids = [], [], []
        offset = 0
        for ci, col in enumerate(spec.colliders):
            if col.type == "sphere":
                params = [*col.center, col.radius, 0, 0, 0, 0]
            elif col.type == "box":
                params = [*col.min, *col.max, 0, 0]
            elif col.type == "capsule":
                params = [*col.a, *col.b, col.radius, 0]
            else:
                g = mesh_collider_grid(spec, ci)
                params = [*g.origin, g.voxel, *g.phi.shape, offset]
                offset += g.phi.size
                grids.append(g.phi.ravel())
            cf.append(params + [col.restitution, col.friction, 1.0 if col.mode == "obstacle" else -1.0])
            ct.append(COLLIDER_TYPES[col.type])
        if not cf:  # Taichi ndarrays cannot be empty: one inert collider far away
            cf, ct = [[1e9, 1e9, 1e9, 1.0, 0, 0, 0, 0, 0, 0, 1.0]], [SPHERE]
        return cls(particle_radius=r, h=h, gravity=tuple(spec.sim.gravity),
                   domain_min=tuple(spec.domain.min), domain_max=tuple(spec.domain.max),
                   domain_restitution=spec.domain.restitution, domain_friction=spec.domain.friction,
                   fluid_table=table, colliders_f=np.asarray(cf, np.float32),
                   colliders_t=np.asarray(ct, np.int32),
                   collider_sdf=np.concatenate(grids or [np.zeros(1)]).astype(np.float32),
                   speed_of_sound=c, gamma=gamma,
                   cfl=spec.sim.cfl, max_dt=spec.sim.max_dt,
                   surface_threshold=spec.sim.surface_threshold, density_kernel=dk,
                   pressure_kernel=pk, lattice_density=lattice, grad_scale=grad_scale)


def mesh_collider_grid(spec, ci: int):
    """Mesh collider ci's signed distance, sampled where particles can meet it."""
    from .meshsdf import sample_sdf

    col = spec.colliders[ci]
    verts, tris = spec.collider_mesh(ci)
    lo, hi = spec.sdf_box(verts, col)
    return sample_sdf(verts, tris, lo, hi, col.voxel_size * spec.sim.particle_radius, depth=spec.sdf_pad(col))


def fill_blocks(spec, cfg: "SolverConfig | None" = None) -> dict[str, np.ndarray]:
    """Initial particles: each fluid block filled on a cubic lattice of spacing 2r, centred.

    With gravity, each block starts in hydrostatic equilibrium: the lattice is compressed along
    gravity to the Tait density rho(d) = rho0 (1 + rho0 |g| d / B)^(1/gamma) at depth d below
    the block's top. Starting at zero pressure instead, a resting column would drop until it
    is compressed and then breathe acoustically for seconds (its long acoustic modes are barely
    damped), biasing every pressure it reports.

    With cfg, lattice sites closer than one particle radius to a collider's solid side (inside
    an obstacle, outside a container) are left empty: blocks may overlap colliders.
    """
    d = 2.0 * spec.sim.particle_radius
    g = np.array(spec.sim.gravity, np.float64)
    gnorm = float(np.linalg.norm(g))
    pos, vel, fluid = [], [], []
    for fi, f in enumerate(spec.fluids):
        for b in f.blocks:
            lo, hi = np.array(b.min), np.array(b.max)
            n = np.maximum(np.floor((hi - lo) / d + 1e-6).astype(int), 1)
            start = lo + 0.5 * ((hi - lo) - (n - 1) * d)
            axes = [start[k] + d * np.arange(n[k]) for k in range(3)]
            p = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
            if cfg is not None and gnorm > 0:
                p = _hydrostatic(p, lo, hi, -g / gnorm, gnorm, cfg.fluid_table[fi], cfg.gamma)
            pos.append(p)
            vel.append(np.broadcast_to(np.array(b.velocity), p.shape))
            fluid.append(np.full(len(p), fi))
    pos = np.concatenate(pos).astype(np.float32)
    vel, fluid = np.concatenate(vel).astype(np.float32), np.concatenate(fluid).astype(np.int32)
    if cfg is not None and spec.colliders:
        free = collider_clearance(cfg, pos) >= spec.sim.particle_radius
        pos, vel, fluid = pos[free], vel[free], fluid[free]
    return {"position": pos, "velocity": vel, "acceleration": np.zeros_like(pos), "fluid": fluid,
            "id": np.arange(len(pos), dtype=np.int32)}


def collider_clearance(cfg: SolverConfig, points: np.ndarray) -> np.ndarray:
    """Each point's smallest signed distance to the colliders (negative: on the solid side)."""
    n = max(len(points), 1)
    pos = ti.Vector.ndarray(3, ti.f32, shape=n)
    pos.from_numpy(np.resize(np.asarray(points, np.float32), (n, 3)))
    out = ti.ndarray(ti.f32, shape=n)
    k_clearance(pos, *collider_arrays(cfg), out)
    return out.to_numpy()[:len(points)]


def collider_arrays(cfg: SolverConfig):
    """(types, parameter table, distance grids): the colliders as the kernels take them."""
    out = []
    for a, dtype in ((cfg.colliders_t, ti.i32), (cfg.colliders_f, ti.f32), (cfg.collider_sdf, ti.f32)):
        nd = ti.ndarray(dtype, a.shape)
        nd.from_numpy(a)
        out.append(nd)
    return tuple(out)


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


# ==================================================================================== helpers
@ti.func
def cell_of(p, origin, inv_cell: ti.f32, dims):
    c = ti.cast(ti.floor((p - origin) * inv_cell), ti.i32)
    return ti.math.clamp(c, 0, dims - 1)


@ti.func
def flat(c, dims) -> ti.i32:
    return c.x + dims.x * (c.y + dims.y * c.z)


@ti.func
def raise_max(a: ti.template(), k: ti.i32, value: ti.f32):
    """a[k] = max(a[k], value), atomically; reading first means that once the maximum is found,
    almost no thread contends for it."""
    if value > a[k]:
        ti.atomic_max(a[k], value)


@ti.func
def table_row(t: ti.template(), row: ti.i32, d: ti.f32, h: ti.f32) -> ti.f32:
    """Linear interpolation in row `row` of a table sampled on [0, h]."""
    n = t.shape[1]
    x = ti.math.clamp(d / h, 0.0, 1.0) * (n - 1)
    i = ti.min(ti.cast(ti.floor(x), ti.i32), n - 2)
    f = x - i
    return t[row, i] * (1.0 - f) + t[row, i + 1] * f


@ti.func
def hydrostatic_wall(a: ti.f32, n, g, mom: ti.template(), h: ti.f32):
    """sum_b (g . x_bi) grad W_ib over the samples beyond a plane wall at distance a with
    inward normal n: the pressure difference a hydrostatic wall adds (Adami et al. 2012)."""
    gn = g.dot(n)
    return table_row(mom, 0, a, h) * gn * n + table_row(mom, 1, a, h) * (g - gn * n)


@ti.func
def table3(t: ti.template(), kind: ti.i32, a: ti.f32, b: ti.f32, c: ti.f32, h: ti.f32) -> ti.f32:
    """Trilinear interpolation in ghost table `kind` (0 H, 1 Q, 2 O) sampled on [0, h]^3."""
    n = t.shape[1]
    u = ti.math.clamp(vec3(a, b, c) / h, 0.0, 1.0) * (n - 1)
    i = ti.min(ti.cast(ti.floor(u), ti.i32), n - 2)
    f = u - i
    out = 0.0
    for dx, dy, dz in ti.static(ti.ndrange(2, 2, 2)):
        wgt = (f.x if dx else 1.0 - f.x) * (f.y if dy else 1.0 - f.y) * (f.z if dz else 1.0 - f.z)
        out += wgt * t[kind, i.x + dx, i.y + dy, i.z + dz]
    return out


@ti.func
def nearest_walls(x, dmin, dmax, h: ti.f32):
    """Per axis, the distance a (h if none is within h) to the nearer box wall and the sign s of
    its inward normal (+1 low wall, -1 high wall, 0 none)."""
    a = vec3(h)
    s = vec3(0.0)
    for ax in ti.static(range(3)):
        lo = x[ax] - dmin[ax]
        hi = dmax[ax] - x[ax]
        if lo <= hi and lo < h:
            a[ax], s[ax] = ti.max(lo, 0.0), 1.0
        elif hi < lo and hi < h:
            a[ax], s[ax] = ti.max(hi, 0.0), -1.0
    return a, s


@ti.func
def domain_walls(x, dmin, dmax, h: ti.f32, T: ti.template(), G: ti.template()):
    """Missing number density, and missing grad-W sum (pointing into the fluid), near the box
    walls; exact at edges and corners by inclusion-exclusion (see kernels.ghost_tables)."""
    a, s = nearest_walls(x, dmin, dmax, h)
    dens = 0.0
    grad = vec3(0.0)
    if s.norm_sqr() > 0:
        dens = (table3(T, 0, a.x, 0.0, 0.0, h) + table3(T, 0, a.y, 0.0, 0.0, h) + table3(T, 0, a.z, 0.0, 0.0, h)
                - table3(T, 1, a.x, a.y, 0.0, h) - table3(T, 1, a.x, a.z, 0.0, h) - table3(T, 1, a.y, a.z, 0.0, h)
                + table3(T, 2, a.x, a.y, a.z, h))
        grad = s * vec3(
            table3(G, 0, a.x, 0.0, 0.0, h) - table3(G, 1, a.x, a.y, 0.0, h)
            - table3(G, 1, a.x, a.z, 0.0, h) + table3(G, 2, a.x, a.y, a.z, h),
            table3(G, 0, a.y, 0.0, 0.0, h) - table3(G, 1, a.y, a.x, 0.0, h)
            - table3(G, 1, a.y, a.z, 0.0, h) + table3(G, 2, a.y, a.x, a.z, h),
            table3(G, 0, a.z, 0.0, 0.0, h) - table3(G, 1, a.z, a.x, 0.0, h)
            - table3(G, 1, a.z, a.y, 0.0, h) + table3(G, 2, a.z, a.x, a.y, h))
    return dens, grad


@ti.func
def mesh_sdf(prm: ti.template(), sdf: ti.template(), k: ti.i32, p):
    """Trilinear signed distance of mesh collider k, and the normalised gradient of that
    trilinear field. Beyond the grid, the distance to the grid's box is added to the value at
    the nearest grid point (the grid reaches a kernel radius past the mesh, so this is far)."""
    origin = vec3(prm[k, 0], prm[k, 1], prm[k, 2])
    inv = 1.0 / prm[k, 3]
    dims = ivec3(ti.cast(prm[k, 4], ti.i32), ti.cast(prm[k, 5], ti.i32), ti.cast(prm[k, 6], ti.i32))
    base = ti.cast(prm[k, 7], ti.i32)
    g = (p - origin) * inv
    gc = ti.math.clamp(g, 0.0, ti.cast(dims - 1, ti.f32))
    i = ti.min(ti.cast(ti.floor(gc), ti.i32), dims - 2)
    f = gc - ti.cast(i, ti.f32)
    phi = 0.0
    grad = vec3(0.0)
    for dx, dy, dz in ti.static(ti.ndrange(2, 2, 2)):
        v = sdf[base + (i.x + dx) * dims.y * dims.z + (i.y + dy) * dims.z + i.z + dz]
        wx = f.x if dx else 1.0 - f.x
        wy = f.y if dy else 1.0 - f.y
        wz = f.z if dz else 1.0 - f.z
        phi += wx * wy * wz * v
        grad += v * vec3((1.0 if dx else -1.0) * wy * wz, (1.0 if dy else -1.0) * wx * wz,
                         (1.0 if dz else -1.0) * wx * wy)
    n = vec3(0.0, 1.0, 0.0)
    outside = (g - gc) / inv
    off = outside.norm()
    if off > 0.0:
        phi += off
        n = outside / off
    elif grad.norm_sqr() > 1e-12:
        n = grad.normalized()
    return phi, n


@ti.func
def collider_sdf(kind: ti.i32, prm: ti.template(), sdf: ti.template(), k: ti.i32, p):
    """Signed distance (positive outside the solid) and outward unit normal of collider k."""
    phi = 0.0
    n = vec3(0.0, 1.0, 0.0)
    if kind == SPHERE:
        c = vec3(prm[k, 0], prm[k, 1], prm[k, 2])
        d = p - c
        L = d.norm()
        phi = L - prm[k, 3]
        if L > 1e-9:
            n = d / L
    elif kind == BOX:
        lo = vec3(prm[k, 0], prm[k, 1], prm[k, 2])
        hi = vec3(prm[k, 3], prm[k, 4], prm[k, 5])
        c = 0.5 * (lo + hi)
        half = 0.5 * (hi - lo)
        d = p - c
        q = ti.abs(d) - half
        outside = ti.max(q, 0.0)
        L = outside.norm()
        if L > 0.0:
            phi = L
            n = outside * ti.math.sign(d) / L
        else:
            # inside: nearest face
            phi = ti.max(q.x, ti.max(q.y, q.z))
            axis = 0
            if q.y >= q.x and q.y >= q.z:
                axis = 1
            elif q.z >= q.x and q.z >= q.y:
                axis = 2
            n = vec3(0.0)
            n[axis] = 1.0 if d[axis] >= 0 else -1.0
    elif kind == MESH:
        phi, n = mesh_sdf(prm, sdf, k, p)
    else:  # capsule: segment a-b with radius
        a = vec3(prm[k, 0], prm[k, 1], prm[k, 2])
        b = vec3(prm[k, 3], prm[k, 4], prm[k, 5])
        ab = b - a
        t = ti.math.clamp((p - a).dot(ab) / ti.max(ab.dot(ab), 1e-12), 0.0, 1.0)
        d = p - (a + t * ab)
        L = d.norm()
        phi = L - prm[k, 6]
        if L > 1e-9:
            n = d / L
    s = prm[k, C_SIGN]   # containers keep particles inside: flip the field
    return phi * s, n * s


# ===================================================================================== kernels
@ti.kernel
def k_clearance(pos: V3, ctype: I1, cprm: F2, sdf: F1, out: F1):
    for i in pos:
        best = 1e30
        for k in range(ctype.shape[0]):
            phi, _n = collider_sdf(ctype[k], cprm, sdf, k, pos[i])
            best = ti.min(best, phi)
        out[i] = best


@ti.kernel
def k_fill_i(a: I1, value: ti.i32):
    for i in a:
        a[i] = value


@ti.kernel
def k_count(pos: V3, cell: I1, count: I1, origin: vec3, inv_cell: ti.f32, dims: ivec3):
    for i in pos:
        c = flat(cell_of(pos[i], origin, inv_cell, dims), dims)
        cell[i] = c
        ti.atomic_add(count[c], 1)


@ti.kernel
def k_scan_blocks(count: I1, start: I1, block_sum: I1, n: ti.i32):
    """Exclusive scan inside blocks of SCAN_BLOCK cells, blocks in parallel."""
    for b in range((n + SCAN_BLOCK - 1) // SCAN_BLOCK):
        s = 0
        for k in range(SCAN_BLOCK):
            c = b * SCAN_BLOCK + k
            if c < n:
                start[c] = s
                s += count[c]
        block_sum[b] = s


@ti.kernel
def k_scan_sums(block_sum: I1, nb: ti.i32):
    """Exclusive scan of the block totals (a few hundred values: one thread)."""
    ti.loop_config(serialize=True)
    s = 0
    for b in range(nb):
        v = block_sum[b]
        block_sum[b] = s
        s += v


@ti.kernel
def k_scan_add(start: I1, block_sum: I1, n: ti.i32):
    for c in range(n):
        start[c] += block_sum[c // SCAN_BLOCK]


@ti.kernel
def k_scatter(cell: I1, start: I1, fill: I1, order: I1):
    for i in cell:
        c = cell[i]
        slot = start[c] + ti.atomic_add(fill[c], 1)
        order[slot] = i


@ti.kernel
def k_gather(order: I1, pos: V3, ref: V3, vel: V3, acc: V3, fluid: I1, pid: I1,
             pos_o: V3, ref_o: V3, vel_o: V3, acc_o: V3, fluid_o: I1, pid_o: I1):
    for s in order:
        i = order[s]
        pos_o[s] = pos[i]
        ref_o[s] = ref[i]
        vel_o[s] = vel[i]
        acc_o[s] = acc[i]
        fluid_o[s] = fluid[i]
        pid_o[s] = pid[i]


@ti.kernel
def k_neighbours(ref: V3, nbr: I1, nbn: I1, cap: ti.i32, reach: ti.f32,
                 start: I1, count: I1, origin: vec3, inv_cell: ti.f32, dims: ivec3, stats: F1):
    """Verlet lists: every j != i within `reach` (= h + skin) of i, at the reference positions,
    in grid order, at nbr[i * cap ...]. A particle with more than `cap` raises stats[2] to its
    count, and the lists are built again larger. The candidate loop has no branch: in a
    disordered fluid, whether a candidate is a neighbour is a coin toss that a branch
    predictor keeps losing."""
    for i in ref:
        xi = ref[i]
        ci = cell_of(xi, origin, inv_cell, dims)
        m = 0
        base = i * cap
        for dz, dy in ti.ndrange((-CELL_DIV, CELL_DIV + 1), (-CELL_DIV, CELL_DIV + 1)):
            cy, cz = ci.y + dy, ci.z + dz
            if 0 <= cy < dims.y and 0 <= cz < dims.z:
                # the cells of a row along x are contiguous: one loop over their particles
                x0 = ti.max(ci.x - CELL_DIV, 0)
                x1 = ti.min(ci.x + CELL_DIV, dims.x - 1)
                c0 = flat(ivec3(x0, cy, cz), dims)
                c1 = flat(ivec3(x1, cy, cz), dims)
                for j in range(start[c0], start[c1] + count[c1]):
                    r2 = (xi - ref[j]).norm_sqr()
                    nbr[base + ti.min(m, cap - 1)] = j
                    m += ti.select((r2 < reach * reach) & (j != i), 1, 0)
        nbn[i] = ti.min(m, cap)
        if m > cap:
            ti.atomic_max(stats[2], ti.cast(m, ti.f32))


@ti.kernel
def k_max_displacement(pos: V3, ref: V3, out: F1):
    for i in pos:
        raise_max(out, 0, (pos[i] - ref[i]).norm())


@ti.kernel
def k_density(pos: V3, fluid: I1, delta: F1, rho: F1, prs: F1, nbr: I1, nbn: I1, cap: ti.i32,
              near: I1, nearn: I1, h: ti.f32, ftab: F2, gamma: ti.f32, oct_t: F4, oct_g: F4,
              lattice: ti.f32, dmin: vec3, dmax: vec3, ctype: I1, cprm: F2, sdf: F1, dkern: ti.template()):
    """Density and pressure from the Verlet list; also copies the entries now within h (and not
    coincident) into the exact list `near` that the force pass reads, without branching."""
    for i in pos:
        xi = pos[i]
        s = K.w_r2(dkern, 0.0, h)                 # the particle itself
        base = i * cap
        k = 0
        for m in range(nbn[i]):
            j = nbr[base + m]
            r2 = (xi - pos[j]).norm_sqr()
            s += K.w_r2(dkern, r2, h)
            near[base + k] = j
            k += ti.select((r2 < h * h) & (r2 > 1e-18), 1, 0)
        nearn[i] = k
        # walls: the domain's six planes and the colliders, as boundary samples on the fill
        # lattice. They take the particle's own compression, so the share f of the kernel they
        # cover scales the fluid's sum up: delta = sum_fluid / (1 - f). Exact at rest and
        # under uniform (e.g. hydrostatic) compression; f is capped for particles in corners.
        wall, _g = domain_walls(xi, dmin, dmax, h, oct_t, oct_g)
        for c in range(ctype.shape[0]):
            phi, _n = collider_sdf(ctype[c], cprm, sdf, c, xi)
            if phi < h:
                wall += table3(oct_t, 0, ti.max(phi, 0.0), 0.0, 0.0, h)   # planar approximation
        s = s / ti.max(1.0 - wall / lattice, 0.1)
        f = fluid[i]
        r = ftab[f, F_MASS] * s
        delta[i] = s
        rho[i] = r
        prs[i] = ti.max(ftab[f, F_B] * ((r / ftab[f, F_RHO0]) ** gamma - 1.0), 0.0)


@ti.kernel
def k_forces(pos: V3, vel: V3, acc: V3, fluid: I1, delta: F1, rho: F1, prs: F1,
             near: I1, nearn: I1, cap: ti.i32,
             h: ti.f32, ftab: F2, gravity: vec3, oct_t: F4, oct_g: F4, mom: F2, lattice: ti.f32,
             grad_scale: ti.f32, threshold: ti.f32,
             dmin: vec3, dmax: vec3, ctype: I1, cprm: F2, sdf: F1, stats: F1, pkern: ti.template(),
             tension: ti.template()):
    for i in pos:
        xi, vi = pos[i], vel[i]
        fi = fluid[i]
        mi = ftab[fi, F_MASS]
        di = delta[i]
        pi_ = prs[i] / (di * di)
        a_p = vec3(0.0)
        a_v = vec3(0.0)
        n = vec3(0.0)
        lap = K.lap_poly6(0.0, h) / di      # colour field includes the particle itself
        base = i * cap
        for m in range(nearn[i]):        # the pairs within h (see k_density)
            j = near[base + m]
            rv = xi - pos[j]
            r = ti.sqrt(rv.norm_sqr())
            dj = delta[j]
            a_p -= (pi_ + prs[j] / (dj * dj)) * K.grad_w(pkern, rv, r, h)
            mu = 0.5 * (ftab[fi, F_MU] + ftab[fluid[j], F_MU])
            a_v += mu * (vel[j] - vi) / (di * dj) * K.lap_viscosity(r, h)
            if ti.static(tension):
                n += K.grad_w(K.POLY6, rv, r, h) / dj
                lap += K.lap_poly6(r, h) / dj
        a = (grad_scale * a_p + a_v) / mi + gravity
        # walls push with the particle's own pressure term only, p_i/delta_i^2 (Akinci et al.
        # 2012): boundary samples are fixed and carry no energy of their own, so this is the
        # energy-consistent force. Mirroring the pressure (2 p_i/delta_i^2) pumps energy into
        # fluid resting on a wall.
        wall = grad_scale * pi_ / mi * (di / lattice)   # samples are as compressed as the particle
        _d, wg = domain_walls(xi, dmin, dmax, h, oct_t, oct_g)
        a += wall * wg
        # the samples' hydrostatic pressure differences: -rho_i/(m_i delta_i^2) sum_b dp_b grad W
        hyd = vec3(0.0)
        da, ds = nearest_walls(xi, dmin, dmax, h)
        for ax in ti.static(range(3)):
            if ds[ax] != 0.0:
                e = vec3(0.0)
                e[ax] = ds[ax]
                hyd += hydrostatic_wall(da[ax], e, gravity, mom, h)
        for k in range(ctype.shape[0]):
            phi, nk = collider_sdf(ctype[k], cprm, sdf, k, xi)
            if phi < h:
                a += wall * table3(oct_g, 0, ti.max(phi, 0.0), 0.0, 0.0, h) * nk
                hyd += hydrostatic_wall(ti.max(phi, 0.0), nk, gravity, mom, h)
        a -= grad_scale * rho[i] / (mi * di * di) * (di / lattice) * hyd
        if ti.static(tension):
            sigma = ftab[fi, F_SIGMA]
            nn = n.norm()
            if sigma > 0.0 and nn * h > threshold:
                a -= sigma * lap * n / nn / rho[i]
        acc[i] = a
        vn, an = vi.norm(), a.norm()
        raise_max(stats, 0, vn)
        raise_max(stats, 1, an)


@ti.kernel
def k_integrate(pos: V3, vel: V3, acc: V3, kick: ti.f32, dt: ti.f32, keep: ti.f32,
                dmin: vec3, dmax: vec3, rest: ti.f32, fric: ti.f32, ctype: I1, cprm: F2, sdf: F1):
    for i in pos:
        v = vel[i] + kick * acc[i]
        x = pos[i] + dt * v
        # colliders: project to the surface (plus `keep`), reflect the normal velocity with
        # restitution, and apply Coulomb friction to the tangential part
        for k in range(ctype.shape[0]):
            phi, n = collider_sdf(ctype[k], cprm, sdf, k, x)
            if phi < keep:
                x += (keep - phi) * n
                vn = v.dot(n)
                if vn < 0.0:
                    vt = v - vn * n
                    vtn = vt.norm()
                    scale = 0.0
                    if vtn > 1e-12:
                        scale = ti.max(0.0, 1.0 - cprm[k, C_FRIC] * (1.0 + cprm[k, C_REST]) * ti.abs(vn) / vtn)
                    v = vt * scale - cprm[k, C_REST] * vn * n
        # the domain box, the same way
        for ax in ti.static(range(3)):
            lo = dmin[ax] + keep
            hi = dmax[ax] - keep
            hit = 0.0
            if x[ax] < lo:
                x[ax] = lo
                hit = -1.0
            elif x[ax] > hi:
                x[ax] = hi
                hit = 1.0
            if hit != 0.0 and v[ax] * hit > 0.0:
                vn = v[ax]
                vt = v
                vt[ax] = 0.0
                vtn = vt.norm()
                scale = 0.0
                if vtn > 1e-12:
                    scale = ti.max(0.0, 1.0 - fric * (1.0 + rest) * ti.abs(vn) / vtn)
                v = vt * scale
                v[ax] = -rest * vn
        pos[i] = x
        vel[i] = v


@ti.kernel
def k_synced_velocity(vel: V3, acc: V3, half_dt: ti.f32, out: V3):
    """Velocity at the step's time: the half-step velocity plus half a step of acceleration."""
    for i in vel:
        out[i] = vel[i] + half_dt * acc[i]


# ====================================================================================== solver
@dataclass
class PhaseTimer:
    """Wall time per step phase (synchronised), for logs and benchmarks."""
    totals: dict[str, float] = field(default_factory=dict)

    def add(self, name: str, seconds: float) -> None:
        self.totals[name] = self.totals.get(name, 0.0) + seconds


class SPHSolver:
    """One data-oriented solver: struct-of-arrays particle state and its step.

    State (Taichi ndarrays, N particles, kept sorted by grid cell):
      pos     (N,3) position x_n, m
      vel     (N,3) half-step velocity v_{n-1/2}, m/s
      acc     (N,3) last acceleration a_{n-1}, m/s^2 (for synchronised output velocity)
      fluid   (N,)  fluid index into the fluid table
      pid     (N,)  particle id, stable over the shot
      delta   (N,)  number density sum_j W, 1/m^3
      rho     (N,)  density m_i delta_i, kg/m^3
      prs     (N,)  pressure (Tait), Pa
      ref     (N,3) positions when the neighbour lists were last built
    Controller state: time t, step count, dt_prev (dt_{n-1/2}).

    Neighbour lists (Verlet lists) hold every pair within h + skin at the reference positions.
    They stay complete while no particle has moved skin/2 from its reference position, so they
    (and the sort by cell) are rebuilt only when one has: about every few steps instead of
    every step. The lists are a function of the reference positions, which checkpoints keep,
    so a resumed run rebuilds exactly the lists it had.
    """

    def __init__(self, cfg: SolverConfig, state: dict[str, np.ndarray], time_s: float = 0.0,
                 step: int = 0, dt_prev: float = 0.0):
        self.cfg = cfg
        n = len(state["position"])
        self.n = n
        self.time = float(time_s)
        self.steps = int(step)
        self.dt_prev = float(dt_prev)
        self.timer = PhaseTimer()
        h = cfg.h
        self.h = h
        self.origin = vec3(*cfg.domain_min)
        size = np.array(cfg.domain_max) - np.array(cfg.domain_min)
        self.skin = SKIN * h
        cell = (h + self.skin) / CELL_DIV         # the lists reach h + skin
        dims = np.maximum(np.ceil(size / cell).astype(int), 1)
        self.dims = ivec3(*map(int, dims))
        self.n_cells = int(np.prod(dims))
        self.inv_cell = 1.0 / cell

        def v3():
            return ti.Vector.ndarray(3, ti.f32, shape=n)

        self.pos, self.vel, self.acc, self.ref = v3(), v3(), v3(), v3()
        self.pos_b, self.vel_b, self.acc_b, self.ref_b = v3(), v3(), v3(), v3()
        self.fluid, self.pid = ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, n)
        self.fluid_b, self.pid_b = ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, n)
        self.delta, self.rho, self.prs = (ti.ndarray(ti.f32, n) for _ in range(3))
        self.cell, self.order = ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, n)
        self.vout = v3()
        self.count = ti.ndarray(ti.i32, self.n_cells)
        self.start = ti.ndarray(ti.i32, self.n_cells)
        self.fill = ti.ndarray(ti.i32, self.n_cells)
        self.block_sum = ti.ndarray(ti.i32, (self.n_cells + SCAN_BLOCK - 1) // SCAN_BLOCK)
        self.stats = ti.ndarray(ti.f32, 3)    # max speed, max acceleration, list overflow
        self.moved = ti.ndarray(ti.f32, 1)    # largest distance from the reference positions
        # neighbour lists: room for 1.5x the fill lattice's pairs within h + skin, grown on overflow
        self.nb_cap = 0
        self._grow_neighbours(int(1.5 * 4.0 / 3.0 * math.pi * ((h + self.skin) / cfg.spacing) ** 3) + 8)
        self.lists_built = 0

        self.ftab = ti.ndarray(ti.f32, cfg.fluid_table.shape)
        self.ftab.from_numpy(cfg.fluid_table)
        self.ctype, self.cprm, self.sdf = collider_arrays(cfg)
        ot, og = K.ghost_tables(cfg.density_kernel, cfg.pressure_kernel, h, cfg.particle_radius)
        self.oct_t = ti.ndarray(ti.f32, ot.shape)
        self.oct_t.from_numpy(ot)
        self.oct_g = ti.ndarray(ti.f32, og.shape)
        self.oct_g.from_numpy(og)
        mom = K.ghost_moment_tables(cfg.pressure_kernel, h, cfg.particle_radius)
        self.mom = ti.ndarray(ti.f32, mom.shape)
        self.mom.from_numpy(mom)
        self.pos.from_numpy(state["position"].astype(np.float32))
        self.vel.from_numpy(state["velocity"].astype(np.float32))
        self.acc.from_numpy(state.get("acceleration", np.zeros((n, 3), np.float32)).astype(np.float32))
        self.fluid.from_numpy(state["fluid"].astype(np.int32))
        self.pid.from_numpy(state["id"].astype(np.int32))
        # a checkpoint's reference positions give back its lists; without them, build afresh
        self._lists_from_ref = "position_ref" in state
        if self._lists_from_ref:
            self.ref.from_numpy(state["position_ref"].astype(np.float32))
        self._lists_valid = False
        self.dmin, self.dmax = vec3(*cfg.domain_min), vec3(*cfg.domain_max)
        self.keep = 0.5 * cfg.particle_radius          # centres stay this far from any wall
        nu_max = float(np.max(cfg.fluid_table[:, F_MU] / cfg.fluid_table[:, F_RHO0]))
        self.dt_visc = 0.125 * (0.5 * h) ** 2 / nu_max if nu_max > 0 else math.inf
        self.vmax = 0.0
        self.amax = 0.0
        self.tension = bool((cfg.fluid_table[:, F_SIGMA] > 0).any())   # compile the colour field in?

    # ----------------------------------------------------------------------------- phases
    def build_lists(self) -> None:
        """Sort the particles by the cell of their reference position (a counting sort: count,
        scan, scatter, gather) and list the pairs within h + skin there."""
        k_fill_i(self.count, 0)
        k_fill_i(self.fill, 0)
        k_count(self.ref, self.cell, self.count, self.origin, self.inv_cell, self.dims)
        k_scan_blocks(self.count, self.start, self.block_sum, self.n_cells)
        k_scan_sums(self.block_sum, self.block_sum.shape[0])
        k_scan_add(self.start, self.block_sum, self.n_cells)
        k_scatter(self.cell, self.start, self.fill, self.order)
        k_gather(self.order, self.pos, self.ref, self.vel, self.acc, self.fluid, self.pid,
                 self.pos_b, self.ref_b, self.vel_b, self.acc_b, self.fluid_b, self.pid_b)
        self.pos, self.pos_b = self.pos_b, self.pos
        self.ref, self.ref_b = self.ref_b, self.ref
        self.vel, self.vel_b = self.vel_b, self.vel
        self.acc, self.acc_b = self.acc_b, self.acc
        self.fluid, self.fluid_b = self.fluid_b, self.fluid
        self.pid, self.pid_b = self.pid_b, self.pid
        while True:
            self.stats.fill(0.0)
            k_neighbours(self.ref, self.nbr, self.nbn, self.nb_cap, self.h + self.skin, self.start,
                         self.count, self.origin, self.inv_cell, self.dims, self.stats)
            most = float(self.stats.to_numpy()[2])
            if most <= self.nb_cap:
                break
            self._grow_neighbours(int(1.25 * most) + 8)
        self.lists_built += 1

    def update_lists(self) -> None:
        """Rebuild the neighbour lists if a particle moved skin/2 from its reference position
        (two such particles may then be within h but not listed)."""
        if self._lists_valid:
            self.moved.fill(0.0)
            k_max_displacement(self.pos, self.ref, self.moved)
            if 2.0 * float(self.moved.to_numpy()[0]) < self.skin:
                return
        if not self._lists_from_ref:
            self.ref.copy_from(self.pos)
        self._lists_from_ref = False
        self.build_lists()
        self._lists_valid = True

    def _grow_neighbours(self, cap: int) -> None:
        cap = -(-cap // 8) * 8
        if self.n * cap > MAX_LIST_ENTRIES:
            raise TooLarge(f"{self.n:,} particles with up to {cap} neighbours each need neighbour lists "
                           f"of {self.n * cap:,} entries, over the limit of {MAX_LIST_ENTRIES:,}; use "
                           f"fewer particles (a larger sim.particle_radius or smaller fluid blocks)")
        self.nb_cap = cap
        self.nbr = ti.ndarray(ti.i32, max(self.n * cap, 1))     # within h + skin at `ref`
        self.nbn = ti.ndarray(ti.i32, self.n)
        self.near = ti.ndarray(ti.i32, max(self.n * cap, 1))    # within h now (a subset)
        self.nearn = ti.ndarray(ti.i32, self.n)

    def density(self) -> None:
        cfg = self.cfg
        k_density(self.pos, self.fluid, self.delta, self.rho, self.prs, self.nbr, self.nbn, self.nb_cap,
                  self.near, self.nearn, self.h, self.ftab, cfg.gamma,
                  self.oct_t, self.oct_g, cfg.lattice_density, self.dmin, self.dmax, self.ctype, self.cprm, self.sdf,
                  cfg.density_kernel)

    def forces(self) -> None:
        """Accelerations and the step's maxima."""
        cfg = self.cfg
        self.stats.fill(0.0)
        k_forces(self.pos, self.vel, self.acc, self.fluid, self.delta, self.rho, self.prs,
                 self.near, self.nearn, self.nb_cap, self.h, self.ftab,
                 vec3(*cfg.gravity), self.oct_t, self.oct_g, self.mom, cfg.lattice_density, cfg.grad_scale,
                 cfg.surface_threshold, self.dmin, self.dmax,
                 self.ctype, self.cprm, self.sdf, self.stats, cfg.pressure_kernel, self.tension)
        s = self.stats.to_numpy()
        self.vmax, self.amax = float(s[0]), float(s[1])

    def stable_dt(self) -> float:
        """CFL (sound + flow speed), force and viscous limits, capped by max_dt.

        Raises Unstable when the step falls below MIN_DT_FRACTION of the acoustic CFL step: the
        accelerations have blown up, and stepping on either crawls (every particle pushed into
        one corner ran for over ten minutes on one frame) or flings particles apart."""
        cfg, hs = self.cfg, 0.5 * self.h
        acoustic = cfg.cfl * hs / cfg.speed_of_sound
        dt = cfg.cfl * hs / (cfg.speed_of_sound + self.vmax)
        if self.amax > 0:
            dt = min(dt, 0.25 * math.sqrt(hs / self.amax))
        if not dt >= MIN_DT_FRACTION * acoustic:
            raise Unstable(f"the time step fell to {dt:.3g} s (max acceleration {self.amax:.3g} m/s^2, "
                           f"max speed {self.vmax:.3g} m/s)")
        return min(dt, self.dt_visc, cfg.max_dt)

    def integrate(self, dt: float) -> None:
        cfg = self.cfg
        kick = 0.5 * (self.dt_prev + dt)
        k_integrate(self.pos, self.vel, self.acc, kick, dt, self.keep, self.dmin, self.dmax,
                    cfg.domain_restitution, cfg.domain_friction, self.ctype, self.cprm, self.sdf)
        self.dt_prev = dt
        self.time += dt
        self.steps += 1

    # ------------------------------------------------------------------------------- step
    def step(self, t_target: float | None = None, timed: bool = False) -> float:
        """One substep; never steps past t_target. Returns dt."""
        phases = (("neighbours", self.update_lists), ("density", self.density), ("forces", self.forces))
        for name, fn in phases:
            if timed:
                ti.sync()
                t0 = time.perf_counter()
                fn()
                ti.sync()
                self.timer.add(name, time.perf_counter() - t0)
            else:
                fn()
        dt = self.stable_dt()
        if t_target is not None:
            remaining = t_target - self.time
            if remaining <= dt * 1.0001:
                dt = remaining
            elif remaining < 2 * dt:       # split the last two steps evenly, no sliver step
                dt = 0.5 * remaining
        t0 = time.perf_counter()
        self.integrate(dt)
        if timed:
            ti.sync()
            self.timer.add("integrate", time.perf_counter() - t0)
        return dt

    def advance_to(self, t_target: float, should_stop=None) -> bool:
        """Step until t_target. Returns False if should_stop() asked to stop early."""
        while self.time < t_target - 1e-9:
            self.step(t_target)
            if should_stop is not None and should_stop():
                return self.time >= t_target - 1e-9
        self.time = max(self.time, t_target) if abs(self.time - t_target) < 1e-9 else self.time
        return True

    # --------------------------------------------------------------------------- read out
    def refresh_fields(self) -> None:
        """Density and pressure for the current positions (after the last integrate)."""
        self.update_lists()
        self.density()

    def snapshot(self) -> dict[str, np.ndarray]:
        """Frame data at the current time, ordered by particle id."""
        self.refresh_fields()
        k_synced_velocity(self.vel, self.acc, 0.5 * self.dt_prev, self.vout)
        pid = self.pid.to_numpy()
        order = np.argsort(pid, kind="stable")
        return {"position": self.pos.to_numpy()[order], "velocity": self.vout.to_numpy()[order],
                "density": self.rho.to_numpy()[order], "pressure": self.prs.to_numpy()[order],
                "id": pid[order], "fluid": self.fluid.to_numpy()[order]}

    def state(self) -> dict[str, np.ndarray]:
        """Full state in the solver's own order, for bit-exact checkpoints."""
        out = {"position": self.pos.to_numpy(), "velocity": self.vel.to_numpy(),
               "acceleration": self.acc.to_numpy(), "fluid": self.fluid.to_numpy(),
               "id": self.pid.to_numpy()}
        if self._lists_valid or self._lists_from_ref:
            out["position_ref"] = self.ref.to_numpy()
        return out

    def controller(self) -> dict[str, float]:
        return {"time": self.time, "step": self.steps, "dt_prev": self.dt_prev}
