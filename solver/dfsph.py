"""Divergence-free SPH (Bender & Koschier 2015, 2017), in the number-density form of
Solenthaler & Pajarola 2008 so that fluids of different rest density share one constraint.

Every particle i has mass m_i = rho0_i / delta0 (delta0: the fill lattice's number density), so
rho_i / rho0_i = delta_i / delta0 whatever its fluid, and incompressibility is delta_i = delta0
for all. A pressure-like kappa_i (= p_i / delta_i^2) changes velocities by

    v_i -= dt / m_i [ sum_j (kappa_i + kappa_j) grad W_ij + kappa_i sum_b grad W_ib ]      (1)

which conserves momentum between fluid particles. The box's walls are mirrors: the sums over j
take in the images of i and of its neighbours in each wall within h (in two or three walls at an
edge or a corner), as fluid, with their velocities mirrored and their own kappa (ghost
particles, as Colagrossi & Landrini 2003). So the layer along a wall is held by its mirror image
as the bulk is held by its neighbours: a sparse layer reads sparse. (Tabulated samples beyond
the walls read a full lattice whatever the layer held: it sank to half a radius from the wall
as a sparse layer, and the squeezed-out particles rose up the walls.) Colliders' boundary
samples b push with the particle's own kappa (Akinci et al. 2012). With the DFSPH factor

    alpha_i = 1 / ( |sum_j grad W_ij + sum_b grad W_ib|^2 / m_i + sum_j |grad W_ij|^2 / m_j )

one Jacobi sweep of (1) with kappa_i = alpha_i (delta*_i - delta0) / dt^2 removes particle i's
predicted compression delta*_i - delta0, and kappa_i = alpha_i (D delta_i / Dt) / dt its
compressing divergence.

Near a wall the images make that factor a lumped one: it counts each image as a neighbour of its
own, where a push on i also moves i's own images (they carry kappa_i, so i's push is P_i = sum_j
grad W_ij + sum_b grad W_ib + S_i, S_i the gradients of i's own images, counted once more) and a
push on neighbour j moves j's images with it. The exact inverse of a sweep's diagonal is

    1 / alpha_i = |P_i|^2 / m_i + sum_j |grad W_ij + sum_s M_s grad W_ij^s|^2 / m_j

(M_s: the mirror in the walls s; grad W_ij^s: towards j's image in them). Particles with fewer
than MIN_DIVERGENCE_NEIGHBOURS take it: there the lumped factor read up to twice the exact (a
resting box's top corners), and a sheet sliding into an edge of two walls at 1.6 m/s threw
particles up the edge at 9.4 m/s (SPlisHSPlasH's DFSPH: 3.3; with the exact factor 6.1). The
bulk keeps the lumped one, 1.28 times the exact at the median particle along a wall: that
over-relaxation measured quieter resting water (bench/RESULTS.md, thirty-eighth session).

One step (Bender & Koschier 2017, Algorithm 1):

  1. neighbours, number density, alpha
  2. divergence solve: D delta / Dt = sum_j v_ij . grad W_ij + v_i . sum_b grad W_ib -> 0
     where it compresses, and where it expands once the fluid there has thinned under its
     target (at half weight: LOOSE), until its mean times dt / delta0 is under
     max_divergence_error
  3. non-pressure accelerations (gravity, viscosity, surface tension)
  4. time step: CFL on the particles' speeds (no speed of sound): on how fast neighbours close
     in, dt = cfl r / v_close, never shorter than on the speed alone, cfl r / max |v + a dt|;
     the particles fast enough to outrun their neighbourhood searched to 2h; capped by max_dt
     (DFSPHSolver.stable_dt)
  5. v* = v + dt a; a viscosity in Pa s is taken implicitly where the step is beyond its
     explicit limit (solver.viscosity)
  6. density solve: delta* = delta + dt D delta / Dt -> delta0 where compressed (at a free
     surface, towards the particle's own target: SURFACE_FROM), until the mean relative
     compression is under max_density_error (Chebyshev-accelerated in steps longer than the
     speed CFL's: CHEBYSHEV_RHO)
  7. drift x += dt v*, collide
Both solves start from the previous step's kappa (warm start): its push (1) is summed by the
pass over the pairs just before the solve (step 1's for step 2, step 3's for step 6), and the
solve's first launch only scales it. A particle's reported pressure is both solves' kappa times
delta^2.
"""
import math

import numpy as np
import taichi as ti

from . import kernels as K
from .boundaries import (boundary_sums, collider_sdf, mirror_walls, nearest_walls, reflect, reflect_velocity,
                         wall_viscosity)
from .errors import Unstable
from .neighbours import cell_of, flat, k_follow, list_step
from .params import F_ETA, F_INV_MASS, F_MASS, F_MU, F_RHO0, F_SIGMA, F_XSPH, NO_SLIP_ROWS, SolverParams
from .sph import NOT_FINITE, SPHSolver
from .stability import explicit_viscous_limit
from .sums import Summer, chunk_sums_pass, sweep_open, total_pass
from .types import D1, F1, F2, F4, I1, IV2, P_H, V3, V4, T, box_of, consts_of, ivec2, ivec3, raise_max, vec3, vec4
from .viscosity import ImplicitViscosity
from .wcsph import color_tension, morris

# A particle with fewer neighbours than this is at a free surface and takes no part in the
# divergence solve (its neighbourhood is too thin to tell expansion from splashing apart);
# SPlisHSPlasH uses 20 for a 3D kernel of h = 4 r, whose full neighbourhood holds about 30.
MIN_DIVERGENCE_NEIGHBOURS = 20
# Fewest sweeps of each solve. SPlisHSPlasH takes 2 for the density solve (its `minIterations`)
# and 1 for the divergence solve; 1 was tried for ours and was 4 % faster on bench/solver.py, but
# left a resting column and a sinking blob measurably less settled (tests/test_dfsph.py's
# stays_put and sinks, just past their bounds)
MIN_DENSITY_ITERATIONS, MIN_DIVERGENCE_ITERATIONS = 2, 2
# Share of the last step's kappa a solve starts from. The whole of it overshoots where the flow
# has changed (a particle that left the bulk still gets pushed; measured: the whole density
# kappa blew a resting column up within 2 s); SPlisHSPlasH takes half.
WARM_START = 0.5
# Chebyshev's semi-iterative acceleration of the density solve's Jacobi sweeps (Wang 2015, "A
# Chebyshev semi-iterative approach for accelerating projective and position-based dynamics"):
# from sweep CHEBYSHEV_FROM on, sweep k+1 lands at omega_{k+1} (x^_{k+1} - x_{k-1}) + x_{k-1}, x^
# the plain sweep's result (velocities and kappa total alike), with omega_S = 2 / (2 - rho^2) and
# omega_{k+1} = 4 / (4 - rho^2 omega_k); rho stands for the Jacobi iteration's spectral radius.
# On bench/solver.py's dam break with the closing-speed step (stable_dt) 0.9 took the density
# solve from 14.8 to 6.8 sweeps a step at the same bound, 0.95 to 5.0; 0.98 to 3.9, but the
# divergence solve after it rose from 3.3 to 4.4 sweeps (bench/RESULTS.md, forty-ninth and
# fiftieth sessions). 0.9, not 0.95: the example's mesh volume peaked at +1.65 % of its first
# frame's with 0.9 and at +2.01 % with 0.95 (issue 18's bound: 2 %), for 3 % more time on the
# bench. The sweep that ends a solve is a plain one, so the error the stop reads is
# never extrapolated past. It runs only in steps that the closing-speed CFL made longer than the
# speed CFL's (DFSPHSolver.accelerated): the extrapolation overshoots the one-sided solve (kappa
# only where compressed) into expansion that no later sweep pulls back, and water at rest, whose
# step the speed floor sets, gets noisier (the oil-on-water layers of tests/test_dfsph.py: 26.9
# mm/s rms against 3.6 when every solve was accelerated). The divergence solve is not
# accelerated: it takes 2-3 sweeps a step, and 0.9 on it changed nothing.
CHEBYSHEV_RHO = {0: 0.0, 1: 0.9}      # DIVERGENCE, DENSITY
CHEBYSHEV_FROM = 2
# A particle at a free surface misses the fluid beyond it: on the fill lattice's flat top its
# number density reads 0.78 delta0 (cubic spline, h = 4 r). Pushing only where delta > delta0,
# DFSPH let the top layers sink into the ones below until their sums read delta0 (a settled pool
# lost 1.9 % of its volume, its top layer packed 1.25 layers' worth of particles). Each particle
# has its own target instead, delta0 (1 - D): D is the share its neighbourhood misses, judged
# from how one-sided it is, g = |sum_j grad W_ij| h / delta0 (walls' images and colliders
# included): 0 up to SURFACE_FROM (the bulk of a settled pool reads 0.07, its 99th percentile
# 0.33), rising linearly to the fill's top layer's own (g, D) (params.surface_deficit, on the
# planes the fill lays: 1.14, 0.22), at most SURFACE_MOST. Squeezing the top layer raises its
# sum faster than its g, so the target resists from the first hundredth of a radius. The push
# towards a target under delta0 is capped at SURFACE_PUSH of delta0: a film's tip meeting a wall
# reads one-sided like a flat top but with far fewer neighbours, and uncapped it was flung out
# at 8 m/s (bench/RESULTS.md, twenty-eighth session).
SURFACE_FROM, SURFACE_MOST, SURFACE_PUSH = 0.35, 0.35, 0.02
# Where the flow expands, the divergence solve pulls it back too, once the number density has
# fallen LOOSE under the particle's target and it has PULL_BACK_NEIGHBOURS: the expanding rate's
# kappa is negative there, at EXPANSION_WEIGHT (the bulk of an incompressible fluid no more
# expands than it compresses; a one-sided solve let a splash's churned bulk stay aerated, and the
# surface mesh closed over the gaps). At 0.75 the example blew up in frame 17, and without the
# LOOSE gate in frame 2 (tension at rest density is the tensile instability's way in); at half
# weight the core of an expanding ball stops 1.5-2 % under rest. The target already says what a
# one-sided neighbourhood misses, so the pull reaches thinner neighbourhoods than the compression
# side's MIN_DIVERGENCE_NEIGHBOURS: with 20 for both, a sheet two to four particles thick (the
# surge behind Martin & Moyce's front, bench/RESULTS.md's twenty-ninth session) was pushed towards
# its surface targets and never pulled back: by t sqrt(g / a) = 5.25 it stood 1.9-2.0 times its
# water's depth (median number density 0.76-0.77 of rest); with 12, 1.2 times (0.94).
LOOSE, EXPANSION_WEIGHT, PULL_BACK_NEIGHBOURS = 0.005, 0.5, 12
MUELLER, AKINCI = 1, 2          # surface tension models
# Which viscosity terms k_nonpressure sums (a bit set, compiled in: a shot's fluids without
# Müller's mu, Morris's eta or XSPH skip that term's work per pair: on the example, water with
# eta and XSPH but no mu, the pass's fastest run went from 2.0 to 1.6 ms)
MU_TERM, ETA_TERM, XSPH_TERM = 1, 2, 4
# The CFL speed is at least this share of the shot's expected largest speed V = sqrt(2 g H).
# A resting column of height H took the steps of max_dt and blew up within a few steps above
# dt = 2.8 r / V (tried: 0.4 m at r = 2.5 mm above 2.5-3 ms, at r = 5 mm above 4.2-6 ms;
# 0.2 m at r = 5 mm above 6-8 ms): the step the density solve can hold a column with scales
# with r / sqrt(g H), the time a gravity wave takes to cross a particle. With cfl = 0.4 a
# floor of V / 4 caps the step at 1.6 r / V, 0.57 of that limit.
SPEED_FLOOR = 0.25


@ti.kernel
def k_density_factor(position: V3, fluid: I1, number_density: F1, density: F1, alpha: F1, target: F1,
                     wall_grad: V3, verlet: I1, verlet_count: I1, near: I1, near_count: I1, gfac: F1, lay: ivec2,
                     near_lay: ivec2, rows: ti.template(), img: I1, img_g: V3, img_span: IV2, img_top: I1, prm: F1,
                     ftab: F2, ghost_t: F4, ghost_g: F4, visc_t: F2, wall_visc: F1, ctype: I1, cprm: F2, sdf: F1,
                     surface_g: ti.f32, surface_d: ti.f32, warm_kappa: F1, warm_push: V3, kern: ti.template()):
    """Number density delta_i = sum_j W_ij + sum_b W_ib, density m_i delta_i and the factor
    alpha_i (a sweep's exact diagonal where the neighbourhood is sparse: module docstring), and
    the particle's target number density delta0 (1 - D_i) (SURFACE_FROM: D_i from how one-sided
    its neighbourhood is, reaching surface_d at the lattice top's one-sidedness surface_g);
    copies the Verlet entries now within h into `near`, as the WCSPH density pass, in rows
    `near_lay` (on the CPU no wider than the longest list: SPHSolver.build_lists; on a GPU `near`
    is `verlet` itself, filtered in place), and beside each entry the pair's dW/dr / r (`gfac`),
    so that the solves' sweeps, at these same positions, take grad W_ij = gfac x_ij without a
    square root or the kernel's pieces. wall_visc[i]: the no-slip weight 2 eta_i S_i /
    (delta_i delta0) of the walls near i (boundaries.wall_viscosity). `prm`: the constants
    (types.consts_of, box_of).

    The walls' images j' of i and its neighbours within h are listed for the sweeps as the
    neighbours are: `img` holds image_entry(j, sub) (sub: the walls' bit set), `img_g` grad
    W_ij', and img_span[i] = (start, count) particle i's entries. A particle with a wall near counts its
    images first and reserves as many entries at the pool's top (`img_top`, atomically); where the
    pool is too small img_top ends past its size, and the host grows it and runs this again.

    warm_push[i]: the push sum_j (k_i + k_j) grad W_ij + k_i grad W_ib (images included) of
    k = warm_kappa, the divergence solve's last total, which that solve's warm start applies
    (warm_start_pass): summed here, where every pair's gradient is at hand, and not in a pass of
    its own."""
    h = prm[P_H]
    inv_h = 1.0 / h
    img_top[0] = 0
    cap = img.shape[0]
    for i in position:
        c, box = consts_of(prm), box_of(prm)
        xi = position[i]
        s = K.w_r2(kern, 0.0, h)
        grad_sum = vec3(0.0)
        sq = 0.0
        ki = warm_kappa[i]
        push = vec3(0.0)
        vbase, vstep = i * lay.x, list_step(lay, rows)          # the Verlet list
        base, step = i * near_lay.x, list_step(near_lay, rows)  # `near` and `gfac`
        k = 0
        for m in range(verlet_count[i]):
            j = verlet[vbase + m * vstep]
            rv = xi - position[j]
            r2 = rv.norm_sqr()
            inside = (r2 < h * h) & (r2 > 1e-18)
            slot = base + k * step
            near[slot] = j
            k += ti.select(inside, 1, 0)
            if inside:
                w, f = K.w_dwr(kern, r2, inv_h)
                s += w
                gfac[slot] = f
                g = f * rv
                grad_sum += g
                push += (ki + warm_kappa[j]) * g
                sq += g.norm_sqr() * ftab[fluid[j], F_INV_MASS]
        near_count[i] = k
        # the box walls: images of i and its neighbours mirrored in the walls within h (and in
        # both or all three at an edge or corner), as fluid with their velocities mirrored
        s_m = 0.0
        mask, planes = mirror_walls(xi, box, h)
        start, q = 0, 0
        if mask != 0:
            reserve = 0
            for sub in range(1, 8):
                if (sub & mask) == sub:
                    for m in range(-1, k):
                        j = i if m < 0 else near[base + m * step]
                        r2 = (xi - reflect(position[j], sub, planes)).norm_sqr()
                        reserve += ti.select((r2 < h * h) & (r2 > 1e-18), 1, 0)
            start = ti.atomic_add(img_top[0], reserve)
            end = ti.min(start + reserve, cap)
            for sub in range(1, 8):
                if (sub & mask) == sub:
                    for m in range(-1, k):
                        j = i if m < 0 else near[base + m * step]
                        rv = xi - reflect(position[j], sub, planes)
                        r2 = rv.norm_sqr()
                        if (r2 < h * h) & (r2 > 1e-18):
                            w, f = K.w_dwr(kern, r2, inv_h)
                            s_m += w
                            g = f * rv
                            grad_sum += g
                            push += (ki + warm_kappa[j]) * g
                            sq += g.norm_sqr() * ftab[fluid[j], F_INV_MASS]
                            if start + q < end:
                                img[start + q] = image_entry(j, sub)
                                img_g[start + q] = g
                                q += 1
        img_span[i] = ivec2(start, q)
        # where the neighbourhood is sparse, the factor is a sweep's exact diagonal (module
        # docstring): i's own images, and each neighbour's gradient with its images' mirrored back
        sparse = (k < MIN_DIVERGENCE_NEIGHBOURS) & (mask != 0)
        own = vec3(0.0)
        sq_exact = 0.0
        if sparse:
            for m in range(-1, k):
                j = i if m < 0 else near[base + m * step]
                back = vec3(0.0)
                if m >= 0:
                    back = gfac[base + m * step] * (xi - position[j])
                for sub in range(1, 8):
                    if (sub & mask) == sub:
                        rv = xi - reflect(position[j], sub, planes)
                        r2 = rv.norm_sqr()
                        if (r2 < h * h) & (r2 > 1e-18):
                            _w, f = K.w_dwr(kern, r2, inv_h)
                            g = f * rv
                            if m < 0:
                                own += g
                            else:
                                back += reflect_velocity(g, sub)
                if m >= 0:
                    sq_exact += back.norm_sqr() * ftab[fluid[j], F_INV_MASS]
        # colliders from their tables, added: the images cover the space beyond the walls that
        # the fluid mirrors into, which never lies beyond a collider's face too
        wd, wg = boundary_sums(xi, c, box, ghost_t, ghost_g, ctype, cprm, sdf, False)
        s += s_m + wd
        mi = ftab[fluid[i], F_MASS]
        number_density[i] = s
        density[i] = mi * s
        wall_grad[i] = wg
        warm_push[i] = push + ki * wg
        grad = grad_sum + wg
        beta = grad.norm_sqr() / mi + sq
        if sparse:
            beta = (grad + own).norm_sqr() / mi + sq_exact
        g = grad.norm() * h / c.lattice
        d = surface_d * ti.max(g - SURFACE_FROM, 0.0) / (surface_g - SURFACE_FROM)
        target[i] = c.lattice * (1.0 - ti.min(d, SURFACE_MOST))
        eta = ftab[fluid[i], F_ETA]
        wv = 0.0
        if eta > 0.0:
            wv = 2.0 * eta * wall_viscosity(xi, c, box, visc_t, ctype, cprm, sdf) / (s * c.lattice)
        wall_visc[i] = wv
        alpha[i] = ti.select(beta > 0.0, 1.0 / ti.max(beta, 1e-30), 0.0)


@ti.func
def image_entry(j, sub):
    """An entry of the walls' image list: neighbour j mirrored in the walls of bit set sub."""
    return j * 8 + sub


@ti.func
def image_of(e):
    """(j, sub) of an image_entry."""
    return e >> 3, e & 7


@ti.func
def image_terms(out, i, img: ti.template(), img_g: ti.template(), img_span: ti.template(), field: ti.template(),
                ki: ti.f32, rate: ti.template(), packed: ti.template() = False):
    """out plus the terms of the walls' images j' of i and its neighbours (k_density_factor's
    list): with `rate`, sum_j' (v_i - M v_j) . grad W_ij' (`field` the sweeps' velocities, v4);
    else sum_j' (kappa_i + kappa_j) grad W_ij' (`field` kappa, ki = kappa_i; `packed`: the
    sweeps' xk, kappa in w)."""
    span = img_span[i]
    for q in range(span.x, span.x + span.y):
        j, sub = image_of(img[q])
        if ti.static(rate):
            out += (field[i].xyz - reflect_velocity(field[j].xyz, sub)).dot(img_g[q])
        elif ti.static(packed):
            out += (ki + field[j].w) * img_g[q]
        else:
            out += (ki + field[j]) * img_g[q]
    return out


# The sweeps' passes read a neighbour's position with its kappa (xk: x, y, z, kappa) and its velocity
# (v4: vx, vy, vz, 0) as one 16-byte load each: DFSPHSolver packs them at a solve's warm start and
# unpacks the velocities after it. Against three-float arrays (position, velocity) and kappa apart,
# on bench/solver.py's dam break at 0.15 s (2-core AMD EPYC, no AVX-512, minima of 30 launches):
# the kappa pass 1.66-1.76 ms against 1.88-1.97, the apply pass 1.44-1.49 against 1.68-1.75
# (bench/RESULTS.md, forty-fourth session).
# The sweeps' passes sum a particle's pairs alternately into two sums, added at the end: one sum's
# adds wait on each other (each a float add's latency), two overlap. On bench/solver.py's dam break
# at 0.15 s (2-core AMD EPYC, the two versions timed alternately in one process, 150 launches
# each): the apply pass 11 % faster, the kappa pass 5 %; four sums, or two in the
# non-pressure pass, were slower (bench/RESULTS.md, forty-first session).
@ti.func
def density_rate(i, v4: ti.template(), xk: ti.template(), near: ti.template(),
                 near_count: ti.template(), gfac: ti.template(), lay: ivec2, rows: ti.template(),
                 wall_grad: ti.template(), img: ti.template(), img_g: ti.template(), img_span: ti.template()):
    """D delta_i / Dt = sum_j (v_i - v_j) . grad W_ij + v_i . sum_b grad W_ib (samples at rest),
    with the walls' images j' of i and its neighbours (velocities mirrored); the pairs summed
    alternately into two sums (see above)."""
    xi, vi = xk[i].xyz, v4[i].xyz
    rate = vi.dot(wall_grad[i])
    base = i * lay.x
    step = list_step(lay, rows)
    n = near_count[i]
    r0, r1 = 0.0, 0.0
    for q in range(n // 2):
        e = base + 2 * q * step
        r0 += rate_term(xi, vi, e, near, xk, v4, gfac)
        r1 += rate_term(xi, vi, e + step, near, xk, v4, gfac)
    if n % 2 == 1:
        rate += rate_term(xi, vi, base + (n - 1) * step, near, xk, v4, gfac)
    return image_terms(rate + (r0 + r1), i, img, img_g, img_span, v4, 0.0, True)


@ti.func
def rate_term(xi, vi, e, near: ti.template(), xk: ti.template(), v4: ti.template(), gfac: ti.template()):
    """(v_i - v_j) . grad W_ij for the neighbour list's entry e."""
    j = near[e]
    return (vi - v4[j].xyz).dot(gfac[e] * (xi - xk[j].xyz))


@ti.func
def push_term(xi, ki, e, near: ti.template(), xk: ti.template(), gfac: ti.template()):
    """(kappa_i + kappa_j) grad W_ij for the neighbour list's entry e."""
    xj = xk[near[e]]
    return (ki + xj.w) * gfac[e] * (xi - xj.xyz)


@ti.func
def divergence_kappa_pass(xk: T, v4: T, number_density: T, target: T, near: T, near_count: T, gfac: T, lay: T,
                          rows: T, img: T, img_g: T, img_span: T, alpha: T, wall_grad: T, residual: T, dt: ti.f32,
                          go: T):
    """kappa_i = alpha_i max(D delta_i / Dt, 0) / dt for particles with a full neighbourhood
    (MIN_DIVERGENCE_NEIGHBOURS), and EXPANSION_WEIGHT alpha_i (D delta_i / Dt) / dt where those
    with PULL_BACK_NEIGHBOURS whose number density fell LOOSE under their target expand (a
    negative kappa), into xk[i].w; residual[i] the rate each compresses or expands at that the
    sweep acts on."""
    for i in xk:
        if sweep_open(go):
            rate = density_rate(i, v4, xk, near, near_count, gfac, lay, rows, wall_grad, img, img_g, img_span)
            loose = number_density[i] < (1.0 - LOOSE) * target[i]
            compressing = (rate > 0.0) & (near_count[i] >= MIN_DIVERGENCE_NEIGHBOURS)
            thinned = loose & (rate < 0.0) & (near_count[i] >= PULL_BACK_NEIGHBOURS)
            rate = ti.select(compressing | thinned, rate, 0.0)
            xk[i].w = alpha[i] * rate / dt * ti.select(rate < 0.0, EXPANSION_WEIGHT, 1.0)
            residual[i] = ti.abs(rate)


@ti.func
def density_kappa_pass(xk: T, v4: T, number_density: T, target: T, near: T, near_count: T, gfac: T, lay: T,
                       rows: T, img: T, img_g: T, img_span: T, alpha: T, wall_grad: T, residual: T, dt: ti.f32,
                       prm: T, go: T):
    """kappa_i = alpha_i e / dt^2 with delta* = delta + dt D delta / Dt and the compression
    e = max(delta*_i - delta0, min(delta*_i - target_i, SURFACE_PUSH delta0), 0): over rest
    density as before, or over the particle's own target where its neighbourhood is one-sided
    (at most SURFACE_PUSH there), into xk[i].w; residual[i] = e."""
    for i in xk:
        if sweep_open(go):
            c = consts_of(prm)
            rate = density_rate(i, v4, xk, near, near_count, gfac, lay, rows, wall_grad, img, img_g, img_span)
            predicted = number_density[i] + dt * rate
            excess = ti.max(predicted - c.lattice, ti.min(predicted - target[i], SURFACE_PUSH * c.lattice), 0.0)
            xk[i].w = alpha[i] * excess / (dt * dt)
            residual[i] = excess


@ti.func
def apply_pass(xk: T, v4: T, fluid: T, near: T, near_count: T, gfac: T, lay: T, rows: T, img: T, img_g: T,
               img_span: T, total: T, wall_grad: T, dt: ti.f32, ftab: T, go: T, delta: T, omega: ti.f32):
    """Equation (1) with this sweep's kappa (xk's w); total += kappa (the step's pressure, and
    the next step's warm start). The walls' images j' carry kappa_j. The pairs are summed
    alternately into two sums, as density_rate's. With Chebyshev's acceleration (CHEBYSHEV_RHO)
    the sweep's change u = (velocity change, kappa) becomes omega u + (omega - 1) delta_i,
    delta_i the last sweep's change (x_{k+1} - x_k, so that x_{k-1} need not be kept)."""
    for i in xk:
        if sweep_open(go):
            xi = xk[i].xyz
            ki = xk[i].w
            push = ki * wall_grad[i]
            base = i * lay.x
            step = list_step(lay, rows)
            n = near_count[i]
            p0, p1 = vec3(0.0), vec3(0.0)
            for q in range(n // 2):
                e = base + 2 * q * step
                p0 += push_term(xi, ki, e, near, xk, gfac)
                p1 += push_term(xi, ki, e + step, near, xk, gfac)
            if n % 2 == 1:
                push += push_term(xi, ki, base + (n - 1) * step, near, xk, gfac)
            push = image_terms(push + (p0 + p1), i, img, img_g, img_span, xk, ki, False, True)
            u = vec4(-dt / ftab[fluid[i], F_MASS] * push, ki)
            if ti.static(not isinstance(delta, type(None))):
                if omega > 0.0:
                    u = omega * u + (omega - 1.0) * delta[i]
                delta[i] = u
            v4[i] = vec4(v4[i].xyz + u.xyz, 0.0)
            total[i] += u.w


@ti.func
def warm_start_pass(position: T, velocity: T, xk: T, v4: T, fluid: T, total: T, warm_push: T, dt: ti.f32,
                    warm: ti.f32, ftab: T, delta: T):
    """The warm start (Bender & Koschier 2017, Algorithms 2 and 3): equation (1) with kappa =
    warm times the last solve's total, and total *= warm. A push is linear in kappa, so this is
    warm times the push of the total, which the neighbour pass before the solve summed
    (warm_push: k_density_factor's for the divergence solve, k_nonpressure's for the density
    solve); a pass over the pairs of its own cost about as much as a sweep's apply pass. The
    velocities go to the sweeps' v4, the positions to their xk (unpacked: k_unpack)."""
    for i in total:
        v4[i] = vec4(velocity[i] - dt * warm / ftab[fluid[i], F_MASS] * warm_push[i], 0.0)
        xk[i] = vec4(position[i], 0.0)
        total[i] *= warm
        if ti.static(not isinstance(delta, type(None))):
            delta[i] = vec4(0.0)


@ti.kernel
def k_warm_start(position: V3, velocity: V3, xk: V4, v4: V4, fluid: I1, total: F1, warm_push: V3, dt: ti.f32,
                 warm: ti.f32, ftab: F2, delta: V4, chebyshev: ti.template()):
    if ti.static(chebyshev):
        warm_start_pass(position, velocity, xk, v4, fluid, total, warm_push, dt, warm, ftab, delta)
    else:
        warm_start_pass(position, velocity, xk, v4, fluid, total, warm_push, dt, warm, ftab, None)


@ti.kernel
def k_unpack(v4: V4, velocity: V3):
    """A solve's velocities back from the sweeps' v4."""
    for i in velocity:
        velocity[i] = v4[i].xyz


@ti.kernel
def k_divergence_kappa(xk: V4, v4: V4, number_density: F1, target: F1, near: I1, near_count: I1, gfac: F1,
                       lay: ivec2, rows: ti.template(), img: I1, img_g: V3, img_span: IV2, alpha: F1, wall_grad: V3,
                       residual: F1, dt: ti.f32):
    divergence_kappa_pass(xk, v4, number_density, target, near, near_count, gfac, lay, rows, img, img_g, img_span,
                          alpha, wall_grad, residual, dt, None)


@ti.kernel
def k_density_kappa(xk: V4, v4: V4, number_density: F1, target: F1, near: I1, near_count: I1, gfac: F1,
                    lay: ivec2, rows: ti.template(), img: I1, img_g: V3, img_span: IV2, alpha: F1, wall_grad: V3,
                    residual: F1, dt: ti.f32, prm: F1):
    density_kappa_pass(xk, v4, number_density, target, near, near_count, gfac, lay, rows, img, img_g, img_span,
                       alpha, wall_grad, residual, dt, prm, None)


@ti.kernel
def k_apply_kappa(xk: V4, v4: V4, fluid: I1, near: I1, near_count: I1, gfac: F1, lay: ivec2, rows: ti.template(),
                  img: I1, img_g: V3, img_span: IV2, total: F1, wall_grad: V3, dt: ti.f32, ftab: F2, delta: V4,
                  omega: ti.f32, chebyshev: ti.template()):
    if ti.static(chebyshev):
        apply_pass(xk, v4, fluid, near, near_count, gfac, lay, rows, img, img_g, img_span, total, wall_grad, dt, ftab,
                   None, delta, omega)
    else:
        apply_pass(xk, v4, fluid, near, near_count, gfac, lay, rows, img, img_g, img_span, total, wall_grad, dt, ftab,
                   None, None, 1.0)


@ti.kernel
def k_scale(a: F1, factor: ti.f32):
    for i in a:
        a[i] *= factor


# ------------------------------------------------------------- a solve's sweeps, gated on the device
# On a GPU the host does not read each sweep's error: k_sweeps runs a sweep and decides on the
# device whether the solve is done (the controller `go`: DONE, ITER, ERR), the host launches as
# many as the last solve took and reads once, and sweeps launched after DONE do nothing. Each
# launch is one kernel where a sweep was three launches and a read (see wcsph.k_step for why
# launches cost). The mean error is the chunk sums' total (sums.total_pass, in the order the
# host's Summer.total adds them) over `norm` = n delta0.
DONE, ITER, ERR = 0, 1, 2
DIVERGENCE, DENSITY = 0, 1


@ti.kernel
def k_sweeps(position: V3, velocity: V3, xk: V4, v4: V4, fluid: I1, number_density: F1, target: F1, near: I1,
             near_count: I1, gfac: F1, lay: ivec2, rows: ti.template(), img: I1, img_g: V3, img_span: IV2, alpha: F1,
             wall_grad: V3, total: F1, warm_push: V3, residual: F1, partial: F1, groups: D1, dt: ti.f32, warm: ti.f32,
             prm: F1, ftab: F2, go: D1, bound: ti.f64, norm: ti.f64, min_iterations: ti.i32, max_iterations: ti.i32,
             delta: V4, omegas: F1, solve: ti.template(), warm_start: ti.template(), count: ti.template()):
    """warm_start: first the warm start (total *= warm and applied: warm_start_pass; the
    controller reset); then `count` sweeps, each unless done as Bender & Koschier 2017's Algorithms 2 and 3
    (and SPlisHSPlasH) take it: this kappa and the mean error it removes, then kappa applied
    (total += kappa), one more iteration. Done once that error is within `bound` after
    min_iterations sweeps, or after max_iterations: the last kappa is applied, not computed to be
    thrown away. (The sweeps of one launch are its passes in a row: a launch costs the 2-core CPU's
    host about 0.25 ms however little its passes do.) With Chebyshev's acceleration (CHEBYSHEV_RHO
    of the solve), `omegas` the weight of each sweep (chebyshev_weights) but the last."""
    chebyshev = ti.static(CHEBYSHEV_RHO[solve] > 0.0)
    if ti.static(warm_start):
        go[DONE], go[ITER], go[ERR] = 0.0, 0.0, 0.0
        if ti.static(chebyshev):
            warm_start_pass(position, velocity, xk, v4, fluid, total, warm_push, dt, warm, ftab, delta)
        else:
            warm_start_pass(position, velocity, xk, v4, fluid, total, warm_push, dt, warm, ftab, None)
    for _sweep in ti.static(range(count)):
        if ti.static(solve == DIVERGENCE):
            divergence_kappa_pass(xk, v4, number_density, target, near, near_count, gfac, lay, rows, img, img_g,
                                  img_span, alpha, wall_grad, residual, dt, go)
        else:
            density_kappa_pass(xk, v4, number_density, target, near, near_count, gfac, lay, rows, img, img_g,
                               img_span, alpha, wall_grad, residual, dt, prm, go)
        chunk_sums_pass(residual, partial, go)
        s = total_pass(partial, groups, go)
        if ti.static(chebyshev):
            omega = 0.0
            k = ti.cast(go[ITER], ti.i32)
            if not last_sweep(s / norm, bound, k, min_iterations, max_iterations):
                omega = omegas[ti.min(k, omegas.shape[0] - 1)]
            apply_pass(xk, v4, fluid, near, near_count, gfac, lay, rows, img, img_g, img_span, total, wall_grad, dt,
                       ftab, go, delta, omega)
        else:
            apply_pass(xk, v4, fluid, near, near_count, gfac, lay, rows, img, img_g, img_span, total, wall_grad, dt,
                       ftab, go, None, 1.0)
        if go[DONE] < 0.5:
            go[ITER] += 1.0
            go[ERR] = s / norm
            if last_sweep(go[ERR], bound, ti.cast(go[ITER], ti.i32) - 1, min_iterations, max_iterations):
                go[DONE] = 1.0


@ti.func
def last_sweep(err, bound, k, min_iterations, max_iterations) -> bool:
    """Whether sweep k (from 0), whose kappa removes the mean error err, ends its solve."""
    return (err <= bound and k + 1 >= min_iterations) or k + 1 >= max_iterations


def chebyshev_weights(rho: float, count: int) -> np.ndarray:
    """omega_k for sweeps k = 0 .. count - 1 (CHEBYSHEV_RHO's recurrence; 1 before
    CHEBYSHEV_FROM), as float32: the host's loop and the device's sweeps apply the same."""
    out = np.ones(count, np.float64)
    for k in range(CHEBYSHEV_FROM, count):
        out[k] = 2.0 / (2.0 - rho * rho) if k == CHEBYSHEV_FROM else 4.0 / (4.0 - rho * rho * out[k - 1])
    return out.astype(np.float32)


@ti.kernel
def k_nonpressure(position: V3, velocity: V3, acceleration: V3, fluid: I1, number_density: F1, density: F1,
                  near: I1, near_count: I1, gfac: F1, lay: ivec2, rows: ti.template(), img: I1, img_g: V3,
                  img_span: IV2, prm: F1, ftab: F2, stats: F1, dt_guess: ti.f32, normal: V3, viscous: V3,
                  wall_visc: F1, wall_grad: V3, warm_kappa: F1, warm_push: V3, ctype: I1, cprm: F2, sdf: F1,
                  wpair: F1, kern: ti.template(), tension: ti.template(), terms: ti.template()):
    """Gravity, viscosity, XSPH smoothing and the color-field surface tension; stats[0] is
    raised to the largest |v + a dt_guess| of particles with a neighbour (the CFL speed), stats[1]
    to that of particles with none (stable_dt). Morris's term goes to `viscous`,
    apart, to be taken explicitly or implicitly once the step is known (solver.viscosity), with
    the walls' no-slip pull wall_visc[i] (0 - v_i); it is left out of the CFL speed (viscosity
    only draws a velocity towards its neighbours' and the walls').
    Viscosity is the sum of
      Müller et al. 2003 (particle-scale mu):  sum_j mu_ij (v_j - v_i) / (delta_i delta_j) lap W_visc / m_i
      Morris et al. 1997 (dynamic eta, Pa s):  sum_j (eta_i + eta_j) (x_ij . grad W_ij) v_ij
                                                / (m_i delta_i delta_j (r^2 + 0.01 h^2))
    and XSPH (Monaghan 1989) pulls v_i towards its neighbours' mean, xsph of the difference a
    step: (xsph / dt_guess) sum_j (v_j - v_i) W_ij / delta_j. Surface tension (`tension`):
    0 none, MUELLER the color field's (see wcsph.color_tension), AKINCI Akinci et al. 2013's
    cohesion and curvature between particles of one fluid, with gamma = the fluid's tension:
      a_i = sum_j K_ij (-gamma m_j C(r) x_ij / r - gamma (n_i - n_j)),  K_ij = 2 rho0 / (rho_i + rho_j)
    (n: `normal`, from k_surface_normals), which pulls a drop together instead of pushing its
    surface particles off it; the walls' images take part as neighbours (image_tension).
    `terms`: the viscosity terms any fluid of the shot has (MU_TERM, ETA_TERM, XSPH_TERM); the
    others are zero for every pair and are not summed. warm_push[i]: as k_density_factor's, of
    warm_kappa = the density solve's last total, for that solve's warm start: nothing moves the
    particles between this pass and the solve. With Morris's term, each pair's weight w_ij
    (solver.viscosity's) is kept beside its list entry (`wpair`, laid out as gfac), every step:
    the implicit solve reads them where the step turns out beyond the explicit limit."""
    h = prm[P_H]
    for i in position:
        c = consts_of(prm)
        xi, vi = position[i], velocity[i]
        fi = fluid[i]
        di = number_density[i]
        a_v = vec3(0.0)
        a_eta = vec3(0.0)
        smooth = vec3(0.0)
        n = vec3(0.0)
        a_st = vec3(0.0)
        lap = K.lap_poly6(0.0, h) / di
        ki = warm_kappa[i]
        push = ki * wall_grad[i]
        base = i * lay.x
        step = list_step(lay, rows)
        close = 0.0
        for m in range(near_count[i]):
            j = near[base + m * step]
            rv = xi - position[j]
            r2 = rv.norm_sqr()
            r = ti.sqrt(r2)
            dj = number_density[j]
            fj = fluid[j]
            close = ti.max(close, (velocity[j] - vi).dot(rv) / r)
            push += (ki + warm_kappa[j]) * gfac[base + m * step] * rv
            if ti.static(terms & MU_TERM):
                mu = 0.5 * (ftab[fi, F_MU] + ftab[fj, F_MU])
                a_v += mu * (velocity[j] - vi) / (di * dj) * K.lap_viscosity(r, h)
            if ti.static(terms & ETA_TERM):
                # with the pair's dW/dr / r from the density pass
                q = morris(ftab[fi, F_ETA] + ftab[fj, F_ETA], dj, gfac[base + m * step], r2, h, 1.0)
                a_eta += q * (vi - velocity[j])
                wpair[base + m * step] = -q / di
            if ti.static(terms & XSPH_TERM):
                smooth += (velocity[j] - vi) * K.w(kern, r, h) / dj
            if ti.static(tension == MUELLER):
                n += K.grad_w(K.POLY6, rv, r, h) / dj
                lap += K.lap_poly6(r, h) / dj
            if ti.static(tension == AKINCI):
                if fj == fi:
                    a_st += akinci_pair(rv, r, h, density[i], density[j], normal[i], normal[j], ftab, fi)
        a = a_v / ftab[fi, F_MASS] + c.gravity + ftab[fi, F_XSPH] / dt_guess * smooth
        if ti.static(tension == MUELLER):
            a += color_tension(ftab[fi, F_SIGMA], n, lap, density[i], h, c.threshold)
        if ti.static(tension == AKINCI):
            a += a_st + image_tension(i, fi, position, fluid, density, img, img_g, img_span, prm, ftab, normal)
        acceleration[i] = a
        warm_push[i] = image_terms(push, i, img, img_g, img_span, warm_kappa, ki, False)
        viscous[i] = (a_eta / di - wall_visc[i] * vi) / ftab[fi, F_MASS]
        raise_max(stats, ti.select(near_count[i] > 0, 0, 1), (vi + dt_guess * a).norm())
        if near_count[i] > 0:
            # the closing speed (stable_dt): of i and its neighbours, and of i and its images in
            # the walls and colliders within h (2 w_n towards them), with what this step's
            # accelerations other than gravity, which all share, could add
            w = vi + dt_guess * a
            box = box_of(prm)
            _a, side = nearest_walls(xi, box.lo, box.hi, h)
            for ax in ti.static(range(3)):
                close = ti.max(close, -2.0 * side[ax] * w[ax])
            for k in range(ctype.shape[0]):
                phi, nk = collider_sdf(ctype[k], cprm, sdf, k, xi)
                if phi < h:
                    close = ti.max(close, -2.0 * w.dot(nk))
            raise_max(stats, 2, close + dt_guess * (a - c.gravity).norm())


F32_BIG = 3.0e38     # an empty box's bounds (k_around_bounds)

# k_far_rate's culls take the step already found as known, less this margin (far above f32
# round-off), so that a rate it left out could not have shortened the step
KNOWN_RATE_MARGIN = 0.999


@ti.kernel
def k_far_rate(position: V3, velocity: V3, acceleration: V3, near_count: I1, start: I1, count: I1, origin: vec3,
               inv_cell: ti.f32, dims: ivec3, reach: ti.i32, prm: F1, ctype: I1, cprm: F2, sdf: F1, r: ti.f32,
               cfl: ti.f32, dt_guess: ti.f32, others: ti.f32, fast: ti.f32, cull: ti.i32, known: ti.f32,
               lo_x: V3, hi_x: V3, lo_w: V3, hi_w: V3, around_lo: V3, around_hi: V3, out: F1):
    """The step's bound from what lies beyond a particle's neighbourhood (named k_lone_rate until
    it also took fast particles with neighbours), for spray and for particles that could outrun
    their neighbourhood in one step.

    out[0] raised to 1 / dt for the longest step each particle with no neighbour (spray in
    flight) may take, its velocity w_i = v_i + a_i dt_guess: coming no nearer than 2r to another
    particle, and moving towards a wall no farther than it is from it (at least h - 2r: the box
    keeps it in), towards a collider no farther than it is from it (at least the CFL's cfl r: a
    thin collider could be crossed). A particle j in the `reach` cells around it (all within
    R = reach / inv_cell >= 2h of it) closes on it at most |w_i - w_j| dt, one beyond R at most
    (|w_i| + others) dt, and a wall or collider at w_i's component towards it. (stable_dt)

    A particle with neighbours and |w_i| over `fast` (the closing-speed step lets it outrun its
    neighbourhood: stable_dt) is bounded as well: each particle now beyond h (and within R) by
    coming no nearer than 2r, beyond R as above, and each wall and collider now beyond h by
    coming no nearer than r (those within h are in the closing speed already). With `cull`, a
    cell is walked only where the boxes its particles' positions and velocities span (lo_x,
    hi_x, lo_w, hi_w: k_cell_bounds) allow one of them a higher rate than found so far: the same
    maximum from fewer candidates (on bench/solver.py's dam break, stable_dt's time to 0.5 s fell
    from 4.4 to 2.0 s). `known`: a rate the step is bounded by already (under 1 / dt by a margin
    far above round-off); a cell that can raise no rate above it is not walked either, for the
    caller takes the step min(dt, 1 / out[0]), which rates under `known` do not change. And a
    fast particle with neighbours walks no cell at all where the box of the velocities within
    `reach` cells of its own (around_lo, around_hi: k_around_bounds) lets no particle beyond h
    close on it faster than known (h - 2r): a flood moving as a body, the bench's commonest
    fast particle."""
    for i in position:
        lone = near_count[i] == 0
        wi = velocity[i] + dt_guess * acceleration[i]
        if lone or wi.norm() > fast:
            c, box = consts_of(prm), box_of(prm)
            xi = position[i]
            far = reach / inv_cell
            nearest = ti.select(lone, 0.0, c.h)     # a fast particle's fluid within h: its neighbours
            rate = (wi.norm() + others) / ti.max(far - 2.0 * r, cfl * r)
            ci = cell_of(xi, origin, inv_cell, dims)
            span = reach
            if cull != 0 and not lone:
                k0 = flat(ci, dims)
                most = ti.max(ti.abs(wi - around_lo[k0]), ti.abs(around_hi[k0] - wi)).norm()
                if 1.001 * most <= known * (c.h - 2.0 * r):
                    span = -1       # (an empty range: no cell walked)
            for dz, dy, dx in ti.ndrange((-reach, span + 1), (-reach, span + 1), (-reach, span + 1)):
                cc = ci + ivec3(dx, dy, dz)
                if (0 <= cc).all() and (cc < dims).all():
                    k = flat(cc, dims)
                    walk = count[k] > 0
                    if walk and cull != 0:
                        gap = ti.max(ti.max(lo_x[k] - xi, xi - hi_x[k]), 0.0).norm()
                        most = ti.max(ti.abs(wi - lo_w[k]), ti.abs(hi_w[k] - wi)).norm()
                        # (with a margin far above round-off: a cell walked needlessly costs time,
                        # one skipped wrongly another maximum)
                        walk = 1.001 * most > ti.max(rate, known) * ti.max(0.999 * gap - 2.0 * r, cfl * r)
                    if walk:
                        for j in range(start[k], start[k] + count[k]):
                            d = (xi - position[j]).norm()
                            if j != i and d >= nearest and d < far:
                                wj = velocity[j] + dt_guess * acceleration[j]
                                rate = ti.max(rate, (wi - wj).norm() / ti.max(d - 2.0 * r, cfl * r))
            if lone:
                least = c.h - 2.0 * r
                for ax in ti.static(range(3)):
                    rate = ti.max(rate, -wi[ax] / ti.max(xi[ax] - box.lo[ax], least))
                    rate = ti.max(rate, wi[ax] / ti.max(box.hi[ax] - xi[ax], least))
                for k in range(ctype.shape[0]):
                    phi, n = collider_sdf(ctype[k], cprm, sdf, k, xi)
                    rate = ti.max(rate, -wi.dot(n) / ti.max(phi, cfl * r))
            else:
                for ax in ti.static(range(3)):
                    lo, hi = xi[ax] - box.lo[ax], box.hi[ax] - xi[ax]
                    if lo >= c.h:
                        rate = ti.max(rate, -wi[ax] / (lo - r))
                    if hi >= c.h:
                        rate = ti.max(rate, wi[ax] / (hi - r))
                for k in range(ctype.shape[0]):
                    phi, n = collider_sdf(ctype[k], cprm, sdf, k, xi)
                    if phi >= c.h:
                        rate = ti.max(rate, -wi.dot(n) / (phi - r))
            raise_max(out, 0, rate)


@ti.kernel
def k_cell_bounds(position: V3, velocity: V3, acceleration: V3, start: I1, count: I1, dt_guess: ti.f32, lo_x: V3,
                  hi_x: V3, lo_w: V3, hi_w: V3):
    """Per cell, the boxes its particles' positions and velocities w = v + a dt_guess span (for
    k_far_rate; an empty cell's are left as they were, and it is never read)."""
    for k in start:
        if count[k] > 0:
            j0 = start[k]
            x0, w0 = position[j0], velocity[j0] + dt_guess * acceleration[j0]
            a, b, p, q = x0, x0, w0, w0
            for j in range(j0 + 1, j0 + count[k]):
                x, w = position[j], velocity[j] + dt_guess * acceleration[j]
                a, b, p, q = ti.min(a, x), ti.max(b, x), ti.min(p, w), ti.max(q, w)
            lo_x[k], hi_x[k], lo_w[k], hi_w[k] = a, b, p, q


@ti.kernel
def k_around_bounds(count: I1, dims: ivec3, reach: ti.i32, axis: ti.i32, lo: V3, hi: V3, lo_o: V3, hi_o: V3):
    """One axis of the velocity boxes over the cells within `reach` (each axis in turn, the
    first from k_cell_bounds's boxes, whose empty cells it leaves out: they hold stale values)."""
    for k in count:
        c = ivec3(k % dims.x, (k // dims.x) % dims.y, k // (dims.x * dims.y))
        a, b = vec3(F32_BIG), vec3(-F32_BIG)
        unit = ivec3(ti.select(axis == 0, 1, 0), ti.select(axis == 1, 1, 0), ti.select(axis == 2, 1, 0))
        for d in range(-reach, reach + 1):
            cc = c + d * unit
            if (0 <= cc).all() and (cc < dims).all():
                kk = flat(cc, dims)
                if axis != 0 or count[kk] > 0:
                    a, b = ti.min(a, lo[kk]), ti.max(b, hi[kk])
        lo_o[k], hi_o[k] = a, b


@ti.func
def akinci_pair(rv, r: ti.f32, h: ti.f32, rho_i: ti.f32, rho_j: ti.f32, n_i, n_j, ftab: ti.template(), fi: ti.i32):
    """Akinci et al. 2013's cohesion and curvature between i and a neighbour of its fluid at
    x_i - x_j = rv (|rv| = r, normals n_i, n_j): -K_ij gamma (m C(r) rv / r + n_i - n_j)."""
    k_ij = 2.0 * ftab[fi, F_RHO0] / (rho_i + rho_j)
    return -k_ij * ftab[fi, F_SIGMA] * (ftab[fi, F_MASS] * cohesion(r, h) * rv / r + n_i - n_j)


@ti.func
def image_tension(i, fi, position: ti.template(), fluid: ti.template(), density: ti.template(), img: ti.template(),
                  img_g: ti.template(), img_span: ti.template(), prm: ti.template(), ftab: ti.template(),
                  normal: ti.template()):
    """Akinci et al. 2013's cohesion and curvature terms between i and the walls' images j' of
    i and its neighbours of its fluid (k_density_factor's list; normals mirrored as velocities
    are), as k_nonpressure takes them between neighbours. The walls mirror the fluid for its
    density and pressure; without its images in the tension too, cohesion pulled the layer
    along a wall away from it (a non-wetting, rounded rim a radius or two wide all round the
    example's pool)."""
    h = prm[P_H]
    xi = position[i]
    a = vec3(0.0)
    span = img_span[i]
    if span.y > 0:
        _, planes = mirror_walls(xi, box_of(prm), h)
        for q in range(span.x, span.x + span.y):
            j, sub = image_of(img[q])
            if fluid[j] == fi:
                rv = xi - reflect(position[j], sub, planes)
                a += akinci_pair(rv, rv.norm(), h, density[i], density[j], normal[i],
                                 reflect_velocity(normal[j], sub), ftab, fi)
    return a


@ti.func
def cohesion(r: ti.f32, h: ti.f32) -> ti.f32:
    """Akinci et al. 2013's cohesion spline C(r): attracting beyond h/2, repelling inside."""
    s = 32.0 / (math.pi * h ** 9)
    d = (h - r) ** 3 * r ** 3
    return s * ti.select(2.0 * r > h, d, 2.0 * d - h ** 6 / 64.0) * ti.select(r < h, 1.0, 0.0)


@ti.kernel
def k_surface_normals(position: V3, number_density: F1, near: I1, near_count: I1, lay: ivec2, rows: ti.template(),
                      img: I1, img_g: V3, img_span: IV2, normal: V3, prm: F1, kern: ti.template()):
    """Akinci et al. 2013's surface normal n_i = h sum_j grad W_ij / delta_j (0 inside), the
    walls' images j' of i and its neighbours included (k_density_factor's list): a wall is no
    surface."""
    h = prm[P_H]
    for i in position:
        xi = position[i]
        n = vec3(0.0)
        base = i * lay.x
        step = list_step(lay, rows)
        for m in range(near_count[i]):
            j = near[base + m * step]
            rv = xi - position[j]
            n += K.grad_w(kern, rv, rv.norm(), h) / number_density[j]
        span = img_span[i]
        for q in range(span.x, span.x + span.y):
            j, _ = image_of(img[q])
            n += img_g[q] / number_density[j]
        normal[i] = h * n


@ti.kernel
def k_kick(velocity: V3, acceleration: V3, dt: ti.f32):
    for i in velocity:
        velocity[i] += dt * acceleration[i]


@ti.kernel
def k_kick_both(velocity: V3, acceleration: V3, viscous: V3, dt: ti.f32):
    for i in velocity:
        velocity[i] += dt * (acceleration[i] + viscous[i])


@ti.kernel
def k_drift(position: V3, velocity: V3, dt: ti.f32):
    for i in position:
        position[i] += dt * velocity[i]


@ti.kernel
def k_pressure(number_density: F1, kappa_dt2: F1, kappa_dt: F1, inv_dt: ti.f32, pressure: F1):
    """p_i = kappa_i delta_i^2 (kappa being p / delta^2 in equation (1)), kappa the sum of both
    solves' (the density solve's kappa dt^2 and the divergence solve's kappa dt): each pushes
    the particles, and at rest the divergence solve carries part of the weight."""
    for i in pressure:
        pressure[i] = (kappa_dt2[i] * inv_dt + kappa_dt[i]) * inv_dt * number_density[i] ** 2


class DFSPHSolver(SPHSolver):
    """DFSPH on the WCSPH solver's particles, neighbour search, boundaries and read-out.

    Extra state (kept sorted with the particles, saved in checkpoints for bit-exact resume):
      kappa_density     (N,) the last density solve's kappa times dt^2 (warm start)
      kappa_divergence  (N,) the last divergence solve's kappa times dt (warm start)
      viscous_dv        (N, 3) the last implicit viscosity solve's correction v - v* (its warm
                        start)
    Per-step counters for the frame report: iterations of both solves and their final errors.
    """
    EXTRA = ("kappa_density", "kappa_divergence")
    EXTRA_VECTORS = ("viscous_dv",)
    LISTS_CHECKED_AT_ONCE = True      # DFSPH decides on the host
    # A list rebuild and a solve's sweep one launch each on every backend (k_rebuild, k_sweeps):
    # on a GPU the host reads once for several sweeps; on the CPU it reads every sweep (a sweep
    # launched past the end would cost a pass), and the fewer launches save host time: 107 against
    # 116 ms a step on the anchor bench's first 0.15 s (2 threads)
    FUSED = True
    # No Verlet skin: a DFSPH step moves the fastest particle sim.cfl radii (0.4, the bench 0.8)
    # or, in a body moving as one, farther (stable_dt),
    # as far as the WCSPH skin lets anyone move before a rebuild (0.2 h / 2 = 0.4 r), so the
    # lists were rebuilt nearly every step anyway and the skin only made every sweep longer
    # (bench/solver.py's dam break, 0.25 s: 141 ms a step without a skin, 154 with 0.2 h, 198
    # with 0.4 h)
    SKIN = 0.0

    def __init__(self, params: SolverParams, state: dict[str, np.ndarray], time_s: float = 0.0,
                 step: int = 0, dt_prev: float = 0.0, max_density_error: float = 1e-3,
                 max_divergence_error: float = 1e-3, max_iterations: int = 100, expected_speed: float = 0.0):
        if params.density_kind != params.pressure_kind:
            raise ValueError("DFSPH takes one kernel for the density and its gradient")
        super().__init__(params, state, time_s, step, dt_prev)
        n = self.n
        self.max_density_error = float(max_density_error)
        self.max_divergence_error = float(max_divergence_error)
        self.max_iterations = int(max_iterations)
        # the CFL speed's floor (see stable_dt); 0 without an expected speed
        self.speed_floor = SPEED_FLOOR * float(expected_speed)
        self.vmax_lone = 0.0        # the fastest particle with no neighbour (stable_dt)
        # stable_dt's search around such particles: the cells within 2h (k_far_rate)
        self.far_reach = int(math.ceil(2.0 * self.h * self.inv_cell - 1e-6))
        self.far_rate = ti.ndarray(ti.f32, 1)
        # the cells' position and velocity boxes for k_far_rate's fast particles (k_cell_bounds),
        # and the velocity boxes over the search's reach (k_around_bounds), made when first
        # needed; stand-ins while there are none to search
        self.cell_bounds = self.around_bounds = None
        self._no_bounds = [ti.Vector.ndarray(3, ti.f32, shape=1) for _ in range(6)]
        self.alpha = ti.ndarray(ti.f32, n)
        # a solve's sweeps read these (the passes' note): positions with the sweep's kappa, velocities
        self.xk, self.v4 = ti.Vector.ndarray(4, ti.f32, shape=n), ti.Vector.ndarray(4, ti.f32, shape=n)
        # Chebyshev's acceleration (CHEBYSHEV_RHO): each particle's last sweep change, each
        # sweep's weight per solve
        self.delta = ti.Vector.ndarray(4, ti.f32, shape=n if any(CHEBYSHEV_RHO.values()) else 1)
        self._omegas_np = {k: chebyshev_weights(rho, self.max_iterations) for k, rho in CHEBYSHEV_RHO.items()}
        self._omegas = {}
        for k, w in self._omegas_np.items():
            self._omegas[k] = ti.ndarray(ti.f32, w.shape[0])
            self._omegas[k].from_numpy(w)
        self._ones = ti.ndarray(ti.f32, self.max_iterations)
        self._ones.fill(1.0)
        self.dt_speed = math.inf
        self.target = ti.ndarray(ti.f32, n)      # each particle's own rest number density (SURFACE_FROM)
        self.wall_grad = ti.Vector.ndarray(3, ti.f32, shape=n)
        self.warm_push = ti.Vector.ndarray(3, ti.f32, shape=n)     # the next solve's warm start (warm_start_pass)
        self.normal = ti.Vector.ndarray(3, ti.f32, shape=n)     # Akinci et al. 2013's surface normals
        self.residual = ti.ndarray(ti.f32, n)
        # the walls' images beside the neighbour lists (k_density_factor), grown as needed
        self.img_top = ti.ndarray(ti.i32, 1)
        self.img_span = ti.Vector.ndarray(2, ti.i32, shape=n)
        self._grow_images(max(n, 1))
        self._summer = Summer(n)
        self._sum = self._summer.total
        # the gated sweeps' controller (k_sweeps: DONE, ITER, ERR) and how many sweeps each
        # solve took last (as many are launched before the first read)
        self.sweep_ctl = ti.ndarray(ti.f64, 3)
        self._last_sweeps = {DIVERGENCE: MIN_DIVERGENCE_ITERATIONS, DENSITY: MIN_DENSITY_ITERATIONS}
        self._one_sweep_ready = set()     # the solves whose one-sweep k_sweeps has been launched
        # Viscosity: Müller's particle-scale mu is explicit and caps the step; Morris's eta is
        # explicit while the step is within its limit, and solved implicitly beyond it
        table = params.fluid_table
        self.dt_mu = explicit_viscous_limit(self.h, table[:, F_MU] / table[:, F_RHO0])
        self.dt_eta = explicit_viscous_limit(self.h, table[:, F_ETA] / table[:, F_RHO0])
        self.viscous_terms = sum(bit for bit, col in ((MU_TERM, F_MU), (ETA_TERM, F_ETA), (XSPH_TERM, F_XSPH))
                                 if np.any(table[:, col] != 0))
        self.viscous = ti.Vector.ndarray(3, ti.f32, shape=n)
        self.wall_visc = ti.ndarray(ti.f32, n)
        # rows: the faces -x, +x, -y, +y, -z, +z, then the colliders; a free-slip one's is zeros
        wall = K.wall_viscosity_table(params.pressure_kind, self.h, params.particle_radius)
        self.visc_t = ti.ndarray(ti.f32, (7, wall.shape[1]))
        self.visc_t.from_numpy(np.concatenate([wall * (w in params.no_slip) for w in NO_SLIP_ROWS]))
        self.implicit = None        # the CG's arrays, made on the first step past dt_eta
        for name in self.EXTRA:
            a, b = ti.ndarray(ti.f32, n), ti.ndarray(ti.f32, n)
            a.from_numpy(np.asarray(state.get(name, np.zeros(n)), np.float32))
            setattr(self, name, a)
            setattr(self, name + "_b", b)
        for name in self.EXTRA_VECTORS:
            a, b = ti.Vector.ndarray(3, ti.f32, shape=n), ti.Vector.ndarray(3, ti.f32, shape=n)
            a.from_numpy(np.asarray(state.get(name, np.zeros((n, 3))), np.float32).reshape(n, 3))
            setattr(self, name, a)
            setattr(self, name + "_b", b)
        self.kern = params.density_kind
        self.reset_counters()

    # ----------------------------------------------------------------------------- phases
    def build_lists(self, from_position: bool = False) -> None:
        super().build_lists(from_position)     # sorts the particles: the warm-start arrays follow them
        for name in self.EXTRA + self.EXTRA_VECTORS:
            a, b = getattr(self, name), getattr(self, name + "_b")
            k_follow(self.order, a, b)
            setattr(self, name, b)
            setattr(self, name + "_b", a)

    def _grow_neighbours(self, cap: int) -> None:
        super()._grow_neighbours(cap)
        self.gfac = ti.ndarray(ti.f32, max(self.n * self.nb_cap, 1))     # dW/dr / r beside each `near` entry
        # Morris's pair weights beside them (k_nonpressure, for the implicit viscosity), where a
        # fluid has a dynamic viscosity
        eta = bool(np.any(self.params.fluid_table[:, F_ETA] != 0))
        self.wpair = ti.ndarray(ti.f32, max(self.n * self.nb_cap, 1) if eta else 1)
        # `near` (and gfac) in rows of near_lay (SPHSolver.build_lists): on the CPU a copy of its
        # own, on a GPU the interleaved Verlet lists themselves where there is no skin (they hold
        # only pairs within h: the density pass filters them in place, entry k <= m written after
        # entry m is read, and saves 4 bytes a slot)
        if self.skin == 0 and not self.rows:
            self.near, self.near_count = self.verlet, self.verlet_count

    def update_lists(self) -> None:
        """With no skin, the lists are built at the current positions every step, without
        asking who moved: also on resuming, where a checkpoint's reference positions (written
        mid-frame, on a stop) are those of the last step's start, and lists built there would
        miss the pairs that came within h during it (and differ from an uninterrupted run's)."""
        if self.skin == 0:
            self._lists_valid = self._lists_from_ref = False
        super().update_lists()

    def _grow_images(self, cap: int) -> None:
        self.img, self.img_g = ti.ndarray(ti.i32, cap), ti.Vector.ndarray(3, ti.f32, shape=cap)

    @property
    def images(self) -> tuple:
        """The walls' images listed beside the neighbours (k_density_factor)."""
        return self.img, self.img_g, self.img_span

    def compute_density(self) -> None:
        """Number density, alpha and the pairs' gradients, with the walls' images listed: where
        the list outgrew its pool, the pool grows by a quarter over what was asked and the pass
        runs again (once)."""
        self._density_factor()
        need = int(self.read(self.img_top, 0))
        if need > self.img.shape[0]:
            self._grow_images(need + need // 4)
            self._density_factor()

    def _density_factor(self) -> None:
        k_density_factor(self.position, self.fluid, self.number_density, self.density, self.alpha, self.target,
                         self.wall_grad, self.verlet, self.verlet_count, self.near, self.near_count, self.gfac,
                         self.lay, self.near_lay, self.rows, *self.images, self.img_top, self.prm, self.ftab,
                         self.ghost_t, self.ghost_g, self.visc_t, self.wall_visc, self.ctype, self.cprm, self.sdf,
                         *self.params.surface_deficit, self.kappa_divergence, self.warm_push, self.kern)

    def _solve(self, solve: int, total, warm_scale: float, bound: float, dt: float,
               min_iterations: int) -> tuple[int, float]:
        """Jacobi sweeps of equation (1) until the mean error a sweep's kappa removes is under
        `bound` (at least min_iterations), that kappa applied (Bender & Koschier 2017, Algorithms
        2 and 3: the error is read before the sweep's correction, so no pass computes a kappa
        only to measure the error after the last one; on the example, which sweeps at the
        minimum, 8 % less time a step). `total` holds the last solve's kappa times dt^k: it is
        applied first (warm start) and then accumulates this solve's. Returns (sweeps, error).
        Fused (the default), the sweeps decide on the device (k_sweeps); else three launches a
        sweep."""
        if self.fused:
            out = self._gated_solve(solve, total, warm_scale, bound, dt, min_iterations)
            k_unpack(self.v4, self.velocity)
            return out
        chebyshev = CHEBYSHEV_RHO[solve] > 0.0
        k_warm_start(self.position, self.velocity, self.xk, self.v4, self.fluid, total, self.warm_push, dt, warm_scale,
                     self.ftab, self.delta, chebyshev)
        iterations, err = 0, math.inf
        while iterations < self.max_iterations:
            self._kappa(solve, dt)
            err = self._sum(self.residual) / (self.n * self.params.lattice_density)
            last = (err <= bound and iterations + 1 >= min_iterations) or iterations + 1 >= self.max_iterations
            accelerate = chebyshev and not last and self.accelerated(dt)
            omega = float(self._omegas_np[solve][iterations]) if accelerate else 0.0
            self._apply(total, dt, omega, chebyshev)
            iterations += 1
            if last:
                break
        k_unpack(self.v4, self.velocity)
        return iterations, err

    def _gated_solve(self, solve: int, total, warm_scale: float, bound: float, dt: float,
                     min_iterations: int) -> tuple[int, float]:
        """_solve with the sweeps gated on the device: the warm start and the sweeps the solve is
        sure to take (min_iterations) in one launch, then, on a GPU, as many more before the
        first read as it took last time (a read there waits for the device), then one more per
        read (on the 2-core CPU a read of the controller costs the host about 25 us, a launch
        past the end about 0.25 ms)."""
        def sweeps(warm_start: bool, count: int) -> None:
            k_sweeps(self.position, self.velocity, self.xk, self.v4, self.fluid, self.number_density, self.target,
                     self.near, self.near_count, self.gfac, self.near_lay, self.rows, *self.images, self.alpha,
                     self.wall_grad, total, self.warm_push, self.residual, self._summer.partial, self._summer.groups, dt,
                     warm_scale, self.prm, self.ftab, self.sweep_ctl, bound, self.n * self.params.lattice_density,
                     min_iterations, self.max_iterations, self.delta,
                     self._omegas[solve] if self.accelerated(dt) else self._ones, solve, warm_start, count)

        sweeps(True, min_iterations)
        for _ in range(0 if self.on_cpu else self._last_sweeps[solve] - min_iterations):
            sweeps(False, 1)
        while True:
            done, iterations, err = self.read(self.sweep_ctl)
            if done:
                break
            sweeps(False, 1)
        if solve not in self._one_sweep_ready:
            sweeps(False, 1)        # gated off: compiles the one-sweep launch in the first step, not mid-run
            self._one_sweep_ready.add(solve)
        self._last_sweeps[solve] = max(int(iterations), 1)
        return int(iterations), float(err)

    def _kappa(self, solve: int, dt: float) -> None:
        """This sweep's kappa and residual (one launch)."""
        if solve == DIVERGENCE:
            k_divergence_kappa(self.xk, self.v4, self.number_density, self.target, self.near, self.near_count,
                               self.gfac, self.near_lay, self.rows, *self.images, self.alpha, self.wall_grad,
                               self.residual, dt)
        else:
            k_density_kappa(self.xk, self.v4, self.number_density, self.target, self.near, self.near_count,
                            self.gfac, self.near_lay, self.rows, *self.images, self.alpha, self.wall_grad,
                            self.residual, dt, self.prm)

    def accelerated(self, dt: float) -> bool:
        """Whether a density solve of a step dt takes Chebyshev's acceleration (CHEBYSHEV_RHO):
        where the closing-speed CFL made the step longer than the speed CFL's (stable_dt)."""
        return dt > self.dt_speed * (1.0 + 1e-6)

    def _apply(self, total, dt: float, omega: float, chebyshev: bool) -> None:
        k_apply_kappa(self.xk, self.v4, self.fluid, self.near, self.near_count, self.gfac, self.near_lay, self.rows,
                      *self.images, total, self.wall_grad, dt, self.ftab, self.delta, omega, chebyshev)

    def divergence_solve(self, dt: float) -> None:
        """Make the velocity field divergence-free where it compresses (step 2)."""
        it, err = self._solve(DIVERGENCE, self.kappa_divergence, WARM_START / dt, self.max_divergence_error / dt, dt,
                              MIN_DIVERGENCE_ITERATIONS)
        k_scale(self.kappa_divergence, dt)
        self.counters["divergence_iterations"] += it
        self.counters["divergence_error"] = max(self.counters["divergence_error"], err * dt)
        self.counters["divergence_capped"] += it >= self.max_iterations and err * dt > self.max_divergence_error

    def density_solve(self, dt: float) -> None:
        """Correct v* so the predicted number density is delta0 where compressed (step 6)."""
        it, err = self._solve(DENSITY, self.kappa_density, WARM_START / (dt * dt), self.max_density_error, dt,
                              MIN_DENSITY_ITERATIONS)
        k_scale(self.kappa_density, dt * dt)
        self.counters["density_iterations"] += it
        self.counters["density_error"] = max(self.counters["density_error"], err)
        self.counters["density_capped"] += it >= self.max_iterations and err > self.max_density_error
        self.counters["density_accelerated"] += self.accelerated(dt)

    def nonpressure(self) -> None:
        self.stats.fill(0.0)
        guess = self.dt_prev or self.params.max_dt
        mode = (AKINCI if self.params.surface_tension_model == "akinci" else MUELLER) if self.tension else 0
        if mode == AKINCI:
            k_surface_normals(self.position, self.number_density, self.near, self.near_count, self.near_lay,
                              self.rows, *self.images, self.normal, self.prm, self.kern)
        k_nonpressure(self.position, self.velocity, self.acceleration, self.fluid, self.number_density,
                      self.density, self.near, self.near_count, self.gfac, self.near_lay, self.rows, *self.images,
                      self.prm, self.ftab, self.stats, guess, self.normal, self.viscous, self.wall_visc,
                      self.wall_grad, self.kappa_density, self.warm_push, self.ctype, self.cprm, self.sdf, self.wpair,
                      self.kern, mode, self.viscous_terms)
        self.vmax, self.vmax_lone, self.vclose = (float(v) for v in self.read(self.stats))

    def kick(self, dt: float) -> None:
        """v* = v + dt a (step 5), with Morris's viscosity explicit while dt is within its
        limit and implicit beyond it (solver.viscosity)."""
        if dt <= self.dt_eta:
            k_kick_both(self.velocity, self.acceleration, self.viscous, dt)
            return
        k_kick(self.velocity, self.acceleration, dt)
        if self.implicit is None:
            self.implicit = ImplicitViscosity(self.n, read=self.read, on_cpu=self.on_cpu)
        it, res = self.implicit.solve(self.velocity, self.fluid, self.near, self.near_count, self.wpair,
                                      self.near_lay, self.rows, self.ftab, self.wall_visc, dt, self.viscous_dv)
        self.counters["viscosity_steps"] += 1
        self.counters["viscosity_iterations"] += it
        self.counters["viscosity_residual"] = max(self.counters["viscosity_residual"], res)

    def time_step(self, t_target: float | None) -> float:
        """The stable step, shortened to land on t_target without a sliver step (the host's
        twin of clock.land_on_target, which WCSPH runs on the device)."""
        dt = self.stable_dt()
        if t_target is not None:
            remaining = t_target - self.time
            if remaining <= dt * 1.0001:
                dt = remaining
            elif remaining < 2 * dt:       # split the last two steps evenly, no sliver step
                dt = 0.5 * remaining
        return dt

    def advance_clock(self, dt: float) -> None:
        """The step of length dt is done: time, step count and dt_{n-1/2} move on."""
        self.dt_prev = dt
        self.time += dt
        self.steps += 1

    def stable_dt(self) -> float:
        """The longest step no particle pair closes in by more than cfl particle radii: a CFL on
        the particles' speeds relative to each other (Galilean-invariant, no speed of sound),
        never shorter than the CFL on their speed alone.

        The speed CFL (the seeds', and SPlisHSPlasH's): no particle with a neighbour moves more
        than cfl r a step, dt = cfl r / v_max, v_max the largest |v + a dt| (k_nonpressure),
        taken as at least SPEED_FLOOR of the shot's expected largest speed, so that a column at
        rest does not take steps of max_dt whatever the resolution. A head-on pair then closes
        by at most 2 cfl r.

        The closing-speed CFL: dt = cfl r / v_close, v_close the largest speed at which a
        particle and a neighbour approach each other, or a particle and its image in a wall or
        collider within h (twice its speed towards it), with what the step's accelerations
        besides gravity could add (k_nonpressure). Where the flow moves faster than it deforms
        (water falling or flooding along a floor as a body) that is the longer step: on
        bench/solver.py's dam break 167 steps to 0.5 s against 353 (bench/RESULTS.md, fiftieth
        session). The step is the longer of the two, so no pair closes faster than the speed
        CFL lets it.

        A longer step lets a particle travel farther than its neighbourhood reaches, so the
        particles that could meet fluid now beyond h within one step are searched (k_far_rate):
        any particle faster than (h - 2r) / (2 dt), for whom a particle now beyond h may come
        within 2r, and the walls and colliders beyond h within r. A particle with no neighbour
        (spray in flight) has no neighbourhood to keep and no pressure to solve: it need only
        not come nearer than a particle diameter 2r to any other in one step, nor pass a
        collider; k_far_rate bounds that by what lies around it: each particle within 2h by
        its distance and their relative velocity, anything farther by 2h and the sum of their
        speeds, each wall and collider by its distance and the speed towards it. (Until the
        forty-fourth session the bound was the worst case, nothing nearer than h and everyone
        closing at the fastest speed: dt (v_lone + v) <= h - 2r. On bench/solver.py's dam break
        the particles thrown up the tank's back edges at 6-8 m/s, three times the water's
        fastest, then set the step from 0.12 to 0.20 s.)"""
        fastest = max(self.vmax, self.vmax_lone)
        if not math.isfinite(fastest):
            raise Unstable(NOT_FINITE, where=self.fastest_position())
        if fastest > self.params.speed_of_sound:
            # (a blow-up: without this the step shrinks with 1/v and the run crawls on; the
            # example at four times its resolution once took 21,675 steps for one frame)
            raise Unstable(f"a particle's speed is {fastest:.3g} m/s, over 10 times the shot's expected "
                           f"largest speed", where=self.fastest_position())
        r, cfl = self.params.particle_radius, self.params.cfl
        self.dt_speed = cfl * r / max(self.vmax, self.speed_floor, 1e-9)
        # the step before the search, so that it looks only for who could outrun the step taken
        # (on the bench, max_dt caps it from 0.22 s: 10-22k particles faster than the closing
        # step's threshold, a third as many faster than the step's)
        dt = min(cfl * r / max(min(self.vclose, self.vmax), self.speed_floor, 1e-9), self.dt_mu, self.params.max_dt)
        fast = (self.h - 2.0 * r) / (2.0 * dt)
        if self.vmax_lone > 0.0 or self.vmax > fast:
            guess = self.dt_prev or self.params.max_dt
            if self.vmax > fast:
                if self.cell_bounds is None:
                    self.cell_bounds, self.around_bounds = ([ti.Vector.ndarray(3, ti.f32, shape=self.n_cells)
                                                             for _ in range(4)] for _ in range(2))
                k_cell_bounds(self.position, self.velocity, self.acceleration, self.start, self.count, guess,
                              *self.cell_bounds)
                lo_w, hi_w = self.cell_bounds[2:]
                lo, hi, lo_t, hi_t = self.around_bounds      # the boxes, and their scratch pair
                k_around_bounds(self.count, self.dims, self.far_reach, 0, lo_w, hi_w, lo, hi)
                k_around_bounds(self.count, self.dims, self.far_reach, 1, lo, hi, lo_t, hi_t)
                k_around_bounds(self.count, self.dims, self.far_reach, 2, lo_t, hi_t, lo, hi)
            self.far_rate.fill(0.0)
            k_far_rate(self.position, self.velocity, self.acceleration, self.near_count, self.start, self.count,
                       self.origin, self.inv_cell, self.dims, self.far_reach, self.prm, self.ctype, self.cprm,
                       self.sdf, r, cfl, guess, max(self.vmax, self.speed_floor, self.vmax_lone), fast,
                       int(self.vmax > fast), KNOWN_RATE_MARGIN / dt,
                       *(self.cell_bounds + self.around_bounds[:2] if self.cell_bounds else self._no_bounds),
                       self.far_rate)
            dt = min(dt, 1.0 / float(self.read(self.far_rate, 0)))
        return dt

    def drift(self, dt: float) -> None:
        k_drift(self.position, self.velocity, dt)
        self.advance_clock(dt)
        self.counters["steps"] += 1

    # ------------------------------------------------------------------------------- step
    def step(self, t_target: float | None = None, timed: bool = False) -> float:
        """One step of Algorithm 1 (Bender & Koschier 2017); never steps past t_target."""
        run = self.phase_runner(timed)
        run("neighbours", self.update_lists)
        run("density", self.compute_density)
        if self.dt_prev > 0:
            run("divergence", self.divergence_solve, self.dt_prev)
        run("forces", self.nonpressure)
        dt = self.time_step(t_target)
        run("kick", self.kick, dt)
        run("pressure", self.density_solve, dt)
        run("integrate", self.drift, dt)
        run("collide", self.collide)
        return dt

    def advance_some(self, t_target: float) -> None:
        self.step(t_target)       # DFSPH decides on the host: one step at a time

    # --------------------------------------------------------------------------- read out
    def refresh_fields(self) -> None:
        """Density, and the last density solve's pressure, at the current positions."""
        super().refresh_fields()
        inv_dt = 1.0 / self.dt_prev if self.dt_prev > 0 else 0.0
        k_pressure(self.number_density, self.kappa_density, self.kappa_divergence, inv_dt, self.pressure)

    def output_velocity(self):
        return self.velocity        # DFSPH's velocities are at the step's time already

    def reset_counters(self) -> None:
        self.counters = {"steps": 0, "density_iterations": 0, "divergence_iterations": 0,
                         "density_error": 0.0, "divergence_error": 0.0, "density_capped": 0, "divergence_capped": 0,
                         "density_accelerated": 0,
                         "viscosity_steps": 0, "viscosity_iterations": 0, "viscosity_residual": 0.0}

    def frame_report(self) -> dict[str, float]:
        """Since the last call: mean iterations per step of both solves, and the largest final
        mean errors (density: relative compression; divergence: relative rate times dt); the
        steps that solved viscosity implicitly, their mean CG iterations and largest final
        residual (relative to the first); and the steps whose solve stopped at max_iterations
        with its error still above the bound (`*_capped_steps`), and those whose density solve
        took Chebyshev's acceleration (`density_accelerated_steps`: accelerated)."""
        c, steps = self.counters, max(self.counters["steps"], 1)
        out = {"dfsph_steps": c["steps"], "density_iterations": c["density_iterations"] / steps,
               "divergence_iterations": c["divergence_iterations"] / steps,
               "density_error": c["density_error"], "divergence_error": c["divergence_error"],
               "max_density_error": self.max_density_error, "max_divergence_error": self.max_divergence_error,
               "max_iterations": self.max_iterations,
               "density_capped_steps": c["density_capped"], "divergence_capped_steps": c["divergence_capped"],
               "density_accelerated_steps": c["density_accelerated"],
               "viscosity_steps": c["viscosity_steps"],
               "viscosity_iterations": c["viscosity_iterations"] / max(c["viscosity_steps"], 1),
               "viscosity_residual": c["viscosity_residual"]}
        self.reset_counters()
        return out

    def state(self) -> dict[str, np.ndarray]:
        out = super().state()
        for name in self.EXTRA + self.EXTRA_VECTORS:
            out[name] = getattr(self, name).to_numpy()
        return out
