"""The physics kernels of weakly compressible SPH (Müller, Charypar & Gross 2003; Tait's
equation of state after Becker & Teschner 2007). Each pass is one phase of a step, pure: its
arrays and constants come in as arguments.

  density     delta_i = sum_j W(x_ij) (+ walls), rho_i = m_i delta_i (Solenthaler & Pajarola
              2008: exact at interfaces of fluids of different rho0);
              p_i = B ((rho_i / rho0)^gamma - 1), clamped at 0, B = rho0 c^2 / gamma
  forces      a_i = -1/m_i sum_j (p_i/delta_i^2 + p_j/delta_j^2) grad W_ij        (pressure)
                    + 1/m_i sum_j mu_ij (v_j - v_i) / (delta_i delta_j) lap W_ij   (viscosity)
                    + Morris et al. 1997's viscosity in Pa s (see `morris`)
                    - sigma lap c_i n_i / |n_i| / rho_i                            (tension)
                    + g + the walls' pressure (boundary samples, kernels.ghost_tables)
  (forces end with the step length: CFL on sound + flow speed, force limit)
  advance     leapfrog: v_{n+1/2} = v_{n-1/2} + a_n (dt_{n-1/2} + dt_{n+1/2}) / 2,
              x_{n+1} = x_n + v_{n+1/2} dt_{n+1/2}; walls and colliders
Every pass of a step is gated on the controller array (clock.py), so that a GPU can run
several steps without reading anything back; k_step runs one whole step in one launch.
"""
import taichi as ti

from . import kernels as K
from .boundaries import (boundary_sums, collide_one, collider_sdf, domain_walls, hydrostatic_wall, nearest_walls,
                         table3)
from .clock import (AMAX, CAP, CFL_HS, DT, GO, HS, KICK, MIN_DT, MOVED, SOUND, UNSTABLE, VMAX, end_step,
                    gate_open, land_on_target)
from .neighbours import list_step
from .params import F_B, F_ETA, F_MASS, F_MU, F_RHO0, F_SIGMA
from .types import D1, F1, F2, F4, I1, P_H, V3, T, box_of, consts_of, ivec2, raise_max, vec3


@ti.func
def morris(eta: ti.f32, dj: ti.f32, f: ti.f32, r2: ti.f32, h: ti.f32, dv):
    """One pair's term of Morris et al. 1997's viscosity in number-density form, times
    m_i delta_i: (eta_i + eta_j) / delta_j (x_ij . grad W_ij) / (r^2 + 0.01 h^2) (v_i - v_j),
    with x_ij . grad W_ij = f r^2 (f = dW/dr / r: kernels.w_dwr), in one division."""
    return eta * f * r2 / (dj * (r2 + 0.01 * h * h)) * dv


@ti.func
def color_tension(sigma: ti.f32, n, lap: ti.f32, rho: ti.f32, h: ti.f32, threshold: ti.f32):
    """Müller et al. 2003's surface tension, -sigma lap(c) n / |n| / rho, from the color field's
    gradient n and Laplacian; only where |n| h exceeds `threshold` (at the surface)."""
    a = vec3(0.0)
    nn = n.norm()
    if sigma > 0.0 and nn * h > threshold:
        a = -sigma * lap * n / nn / rho
    return a


@ti.func
def density_pass(position: T, fluid: T, number_density: T, density: T, pressure: T, verlet: T,
                 verlet_count: T, near: T, near_count: T, lay: T, near_lay: T, rows: T, prm: T, ftab: T, ghost_t: T,
                 ghost_g: T, ctype: T, cprm: T, sdf: T, ctl: T, dkern: T):
    """Density and pressure from the Verlet list; also copies the entries now within h (and not
    coincident) into the exact list `near` that the force pass reads, without branching, in rows
    `near_lay` (SPHSolver.near_lay). `prm`: the constants (types.consts_of, box_of)."""
    h = prm[P_H]
    for i in position:
        if gate_open(ctl):
            c, box = consts_of(prm), box_of(prm)
            xi = position[i]
            s = K.w_r2(dkern, 0.0, h)                 # the particle itself
            vbase, vstep = i * lay.x, list_step(lay, rows)          # the Verlet list
            base, step = i * near_lay.x, list_step(near_lay, rows)  # `near`
            k = 0
            for m in range(verlet_count[i]):
                j = verlet[vbase + m * vstep]
                r2 = (xi - position[j]).norm_sqr()
                s += K.w_r2(dkern, r2, h)
                near[base + k * step] = j
                k += ti.select((r2 < h * h) & (r2 > 1e-18), 1, 0)
            near_count[i] = k
            # walls: the domain's six planes and the colliders, as boundary samples on the fill
            # lattice. They take the particle's own compression, so the share f of the kernel they
            # cover scales the fluid's sum up: delta = sum_fluid / (1 - f). Exact at rest and
            # under uniform (e.g. hydrostatic) compression; f is capped for particles in corners.
            wall, _g = boundary_sums(xi, c, box, ghost_t, ghost_g, ctype, cprm, sdf)   # colliders: planar
            s = s / ti.max(1.0 - wall / c.lattice, 0.1)
            f = fluid[i]
            r = ftab[f, F_MASS] * s
            number_density[i] = s
            density[i] = r
            pressure[i] = ti.max(ftab[f, F_B] * ((r / ftab[f, F_RHO0]) ** c.gamma - 1.0), 0.0)


@ti.func
def forces_pass(position: T, velocity: T, acceleration: T, fluid: T, number_density: T, density: T,
                pressure: T, near: T, near_count: T, lay: T, rows: T, prm: T, ftab: T, ghost_t: T, ghost_g: T,
                ghost_mom: T, ctype: T, cprm: T, sdf: T, stats: T, ctl: T, pkern: T,
                tension: T):
    """Accelerations (pressure, viscosity, surface tension, gravity, walls), then the step length
    from the largest speed and acceleration (kept in stats[0], stats[1]; see time_step)."""
    h = prm[P_H]
    inv_h = 1.0 / h
    if gate_open(ctl):
        stats[0] = 0.0
        stats[1] = 0.0
    for i in position:
        if gate_open(ctl):
            c, box = consts_of(prm), box_of(prm)
            xi, vi = position[i], velocity[i]
            fi = fluid[i]
            mi = ftab[fi, F_MASS]
            di = number_density[i]
            pi_ = pressure[i] / (di * di)
            a_p = vec3(0.0)
            a_v = vec3(0.0)
            a_eta = vec3(0.0)
            n = vec3(0.0)
            lap = K.lap_poly6(0.0, h) / di      # color field includes the particle itself
            base = i * lay.x
            step = list_step(lay, rows)
            # (the pressure and Müller terms multiply by 1 / h, 1 / delta_j and lap_viscosity's
            # constant, each divided once, and Morris's term divides once: kernels.w_dwr says why
            # that matters)
            visc = K.lap_viscosity(0.0, h) / (h * di)
            for m in range(near_count[i]):        # the pairs within h (see k_density)
                j = near[base + m * step]
                rv = xi - position[j]
                r2 = rv.norm_sqr()
                r = ti.sqrt(r2)
                inv_dj = 1.0 / number_density[j]
                _w, f = K.w_dwr(pkern, r2, inv_h)
                a_p -= (pi_ + pressure[j] * inv_dj * inv_dj) * f * rv
                mu = 0.5 * (ftab[fi, F_MU] + ftab[fluid[j], F_MU])
                a_v += mu * (velocity[j] - vi) * inv_dj * visc * (h - r)
                a_eta += morris(ftab[fi, F_ETA] + ftab[fluid[j], F_ETA], number_density[j], f, r2, h, vi - velocity[j])
                if ti.static(tension):
                    dj = number_density[j]
                    n += K.grad_w(K.POLY6, rv, r, h) / dj
                    lap += K.lap_poly6(r, h) / dj
            a = (c.grad_scale * a_p + a_v + a_eta / di) / mi + c.gravity
            # walls push with the particle's own pressure term only, p_i/delta_i^2 (Akinci et al.
            # 2012): boundary samples are fixed and carry no energy of their own, so this is the
            # energy-consistent force. Mirroring the pressure (2 p_i/delta_i^2) pumps energy into
            # fluid resting on a wall.
            wall = c.grad_scale * pi_ / mi * (di / c.lattice)   # samples are as compressed as the particle
            _d, wg = domain_walls(xi, box.lo, box.hi, h, ghost_t, ghost_g)
            a += wall * wg
            # the samples' hydrostatic pressure differences: -rho_i/(m_i delta_i^2) sum_b dp_b grad W
            hyd = vec3(0.0)
            da, ds = nearest_walls(xi, box.lo, box.hi, h)
            for ax in ti.static(range(3)):
                if ds[ax] != 0.0:
                    e = vec3(0.0)
                    e[ax] = ds[ax]
                    hyd += hydrostatic_wall(da[ax], e, c.gravity, ghost_mom, h)
            for k in range(ctype.shape[0]):
                phi, nk = collider_sdf(ctype[k], cprm, sdf, k, xi)
                if phi < h:
                    a += wall * table3(ghost_g, 0, ti.max(phi, 0.0), 0.0, 0.0, h) * nk
                    hyd += hydrostatic_wall(ti.max(phi, 0.0), nk, c.gravity, ghost_mom, h)
            a -= c.grad_scale * density[i] / (mi * di * di) * (di / c.lattice) * hyd
            if ti.static(tension):
                a += color_tension(ftab[fi, F_SIGMA], n, lap, density[i], h, c.threshold)
            acceleration[i] = a
            vn, an = vi.norm(), a.norm()
            raise_max(stats, 0, vn)
            raise_max(stats, 1, an)
    if gate_open(ctl):
        time_step(stats, ctl)


@ti.func
def time_step(stats: ti.template(), ctl: ti.template()):
    """The step length: CFL on sound + flow speed (CFL_HS = cfl h/2), a quarter of
    sqrt(h/2 / max acceleration), capped; landed on the target time (clock.land_on_target).
    Under MIN_DT the accelerations have blown up: UNSTABLE, and the gate closes."""
    vmax = ti.cast(stats[0], ti.f64)
    amax = ti.cast(stats[1], ti.f64)
    ctl[VMAX] = vmax
    ctl[AMAX] = amax
    dt = ctl[CFL_HS] / (ctl[SOUND] + vmax)
    if amax > 0.0:
        dt = ti.min(dt, 0.25 * ti.sqrt(ctl[HS] / amax))
    if not dt >= ctl[MIN_DT]:
        ctl[UNSTABLE] = 1.0
        ctl[DT] = dt
        ctl[GO] = 0.0
    else:
        land_on_target(ctl, ti.min(dt, ctl[CAP]))


@ti.func
def advance_pass(position: T, velocity: T, acceleration: T, ref: T, limit: ti.f32, prm: T, ctype: T, cprm: T,
                 sdf: T, ctl: T):
    """Leapfrog, v_{n+1/2} = v_{n-1/2} + KICK a_n, x_{n+1} = x_n + DT v_{n+1/2}; then the walls
    and colliders (boundaries.collide_one); MOVED if a particle is now `limit` or more from
    where the lists were built; then the step ends (clock.end_step)."""
    for i in position:
        if gate_open(ctl):
            v = velocity[i] + ti.cast(ctl[KICK], ti.f32) * acceleration[i]
            x = position[i] + ti.cast(ctl[DT], ti.f32) * v
            x, v = collide_one(x, v, box_of(prm), ctype, cprm, sdf)
            position[i] = x
            velocity[i] = v
            if (x - ref[i]).norm() >= limit:
                ctl[MOVED] = 1.0          # a plain store: every writer writes 1
    if gate_open(ctl):
        end_step(ctl)


# ------------------------------------------------------------------ the passes as kernels
# Each pass alone (one step at a time on the CPU, the density before a frame is read out, the
# timed step of bench/solver.py --phases), and k_step: a whole gated step in one launch, for the
# batches of steps a GPU runs between reads. Its loops run one after another on the device, as
# separate launches would, but the host pays one launch for them: in Taichi's launcher an array
# argument costs the host about 10 us a launch, and a GPU step of a few hundred thousand
# particles is shorter than three launches of twenty arrays each (the seventeenth session's H100
# run: the sim stage's GPU busy 26 % of the time). Not several steps a launch: unrolled, they
# compile superlinearly (on the CPU 14 s for one step, 47 s for two).
@ti.kernel
def k_density(position: V3, fluid: I1, number_density: F1, density: F1, pressure: F1,
              verlet: I1, verlet_count: I1, near: I1, near_count: I1, lay: ivec2, near_lay: ivec2,
              rows: ti.template(), prm: F1, ftab: F2, ghost_t: F4, ghost_g: F4,
              ctype: I1, cprm: F2, sdf: F1, ctl: D1, dkern: ti.template()):
    density_pass(position, fluid, number_density, density, pressure, verlet, verlet_count, near, near_count,
                 lay, near_lay, rows, prm, ftab, ghost_t, ghost_g, ctype, cprm, sdf, ctl, dkern)


@ti.kernel
def k_forces(position: V3, velocity: V3, acceleration: V3, fluid: I1, number_density: F1,
             density: F1, pressure: F1, near: I1, near_count: I1, lay: ivec2, rows: ti.template(),
             prm: F1, ftab: F2, ghost_t: F4, ghost_g: F4, ghost_mom: F2,
             ctype: I1, cprm: F2, sdf: F1, stats: F1, ctl: D1, pkern: ti.template(),
             tension: ti.template()):
    forces_pass(position, velocity, acceleration, fluid, number_density, density, pressure, near, near_count,
                lay, rows, prm, ftab, ghost_t, ghost_g, ghost_mom, ctype, cprm, sdf, stats, ctl, pkern, tension)


@ti.kernel
def k_advance(position: V3, velocity: V3, acceleration: V3, ref: V3, limit: ti.f32,
              prm: F1, ctype: I1, cprm: F2, sdf: F1, ctl: D1):
    advance_pass(position, velocity, acceleration, ref, limit, prm, ctype, cprm, sdf, ctl)


@ti.kernel
def k_step(position: V3, velocity: V3, acceleration: V3, ref: V3, fluid: I1, number_density: F1,
           density: F1, pressure: F1, verlet: I1, verlet_count: I1, near: I1, near_count: I1, lay: ivec2,
           near_lay: ivec2, rows: ti.template(), prm: F1, ftab: F2, ghost_t: F4, ghost_g: F4, ghost_mom: F2,
           ctype: I1, cprm: F2, sdf: F1, stats: F1, ctl: D1, limit: ti.f32, dkern: ti.template(),
           pkern: ti.template(), tension: ti.template()):
    """One gated step: density, forces (and the step length), advance."""
    density_pass(position, fluid, number_density, density, pressure, verlet, verlet_count, near,
                 near_count, lay, near_lay, rows, prm, ftab, ghost_t, ghost_g, ctype, cprm, sdf, ctl, dkern)
    forces_pass(position, velocity, acceleration, fluid, number_density, density, pressure, near,
                near_count, near_lay, rows, prm, ftab, ghost_t, ghost_g, ghost_mom, ctype, cprm, sdf, stats, ctl,
                pkern, tension)
    advance_pass(position, velocity, acceleration, ref, limit, prm, ctype, cprm, sdf, ctl)


@ti.kernel
def k_synced_velocity(velocity: V3, acceleration: V3, half_dt: ti.f32, out: V3):
    """Velocity at the step's time: the half-step velocity plus half a step of acceleration."""
    for i in velocity:
        out[i] = velocity[i] + half_dt * acceleration[i]
