"""Implicit viscosity: Morris et al. 1997's viscous term taken backward in time and solved with
conjugate gradients, matrix-free, as Weiler et al. 2018 solve theirs, so that a viscous fluid
(honey, about 10 Pa s) moves with the flow's own time step instead of the explicit limit
dt < (h / 2)^2 / (8 nu).

The explicit term (wcsph.morris's, summed in dfsph.k_nonpressure) is

    m_i dv_i / dt = sum_j w_ij (v_j - v_i),
    w_ij = -(eta_i + eta_j) (x_ij . grad W_ij) / ((|x_ij|^2 + 0.01 h^2) delta_i delta_j)  >= 0

and the backward step solves, for the new velocities v from v* (after the other forces),

    A v = M v*,   A = M + dt L,   (L v)_i = sum_j w_ij (v_i - v_j) + w_i v_i.

w_i = 2 eta_i S_i / (delta_i delta0) >= 0 is the no-slip pull of the walls and colliders near i:
mirrored fluid beyond them, its velocity extrapolated to zero at the wall (Morris et al. 1997,
kernels.wall_viscosity_table). w_ij = w_ji and w_ij >= 0, so
L is a weighted graph Laplacian plus a non-negative diagonal and A is symmetric positive
definite: CG converges, here with A's diagonal m_i + dt sum_j w_ij as the preconditioner. The three
velocity components share A and are solved together, as one system of 3N unknowns. The solve
starts from v* and stops when the residual is under `tolerance` of the first one (which is dt L v*,
the explicit step's viscous impulse), so a fluid as thin as water still gets its viscosity.

Warm start (as SPlisHSPlasH's Viscosity_Weiler2018 does): the solve starts from v* + dv, where dv
is the correction the last implicit step made (v - v*, kept sorted with the particles and in
checkpoints by the solver), and stops on the same bound as from v*, a fraction `tolerance` of the
residual v* alone would start from: the warm start changes where the iteration begins, not how
close it must come. Where dv is a worse start than v* (the flow turned), the solve starts from
v*. The pairs' w_ij come from dfsph.k_nonpressure, which sums the explicit term from them.

The loop runs on the device, as the density solves' sweeps do (dfsph.k_sweeps): a launch
(k_cg) takes one iteration, its two sums (p . A p, then r . r and r . z) and the step lengths
alpha = r.z / p.A p and beta computed there, and the controller `go` says when the solve is done;
iterations launched after that do nothing. The first launch also takes both starts' residuals
and chooses between them. The host reads the controller once a launch on the CPU; on a GPU
(where a read waits for the device) it first launches as many iterations as the last solve took.
(The host's loop, a sum read back after each of the two passes, took seven launches an iteration
at about 0.23 ms each on the 2-core CPU: bench/solver.py's dam break made 7,660 launches, 4,697
with this one.) Sums over particles are solver.sums's, in float64 in the same order on every run
and backend, so the device decides as the host did, bit for bit.
"""
import math

import taichi as ti

from .neighbours import list_step
from .params import F_MASS
from .sums import Summer, chunk_sums_pass, sweep_open, total_pass
from .types import D1, F1, F2, I1, V3, ivec2

# the controller `go` (float64): DONE must be 0 (sums.sweep_open's gate)
DONE, ITER, RR, RZ, RR0, WARM = range(6)


@ti.func
def first_residual_pass(velocity: ti.template(), fluid: ti.template(), near: ti.template(),
                        near_count: ti.template(), wpair: ti.template(), lay: ti.template(), rows: ti.template(),
                        ftab: ti.template(), wall: ti.template(), dt: ti.template(), diag: ti.template(),
                        res: ti.template(), direction: ti.template(), rr: ti.template(), rz: ti.template(),
                        dv: ti.template(), rr_cold: ti.template(), rz_cold: ti.template()):
    """The residuals of both starts: from x0 = v*, r0 = M v* - A v* = -dt L v*, in `direction`
    (r0.r0 and r0.z0 per particle in rr_cold, rz_cold); from x0 = v* + dv, r = r0 - A dv, in
    `res` (r.r and r.z in rr, rz); and the diagonal of A (z = r / diag). The pairs' w_ij come
    beside the list entries (`wpair`, laid out as the lists: dfsph.k_nonpressure sums the
    explicit term from the same weights)."""
    for i in velocity:
        vi, dvi = velocity[i], dv[i]
        wsum = wall[i]              # the walls: neighbours at rest
        lv, ldv = wsum * vi, wsum * dvi
        base = i * lay.x
        step = list_step(lay, rows)
        for m in range(near_count[i]):
            j = near[base + m * step]
            w = wpair[base + m * step]
            wsum += w
            lv += w * (vi - velocity[j])
            ldv += w * (dvi - dv[j])
        mass = ftab[fluid[i], F_MASS]
        d = mass + dt * wsum
        r0 = -dt * lv
        r = r0 - (mass * dvi + dt * ldv)
        diag[i] = d
        res[i] = r
        direction[i] = r0
        rr[i] = r.dot(r)
        rz[i] = r.dot(r) / d
        rr_cold[i] = r0.dot(r0)
        rz_cold[i] = r0.dot(r0) / d


@ti.func
def start_pass(velocity: ti.template(), dv: ti.template(), res: ti.template(), direction: ti.template(),
               diag: ti.template(), warm: ti.template()):
    """The first direction z = r / diag from the start taken: from v* + dv (`warm`: velocity
    += dv), or from v* (res = r0, dv = 0)."""
    for i in velocity:
        if warm:
            velocity[i] += dv[i]
        else:
            res[i] = direction[i]
            dv[i] = ti.Vector([0.0, 0.0, 0.0])
        direction[i] = res[i] / diag[i]


@ti.func
def product_pass(fluid: ti.template(), near: ti.template(), near_count: ti.template(), wpair: ti.template(),
                 lay: ti.template(), rows: ti.template(), ftab: ti.template(), wall: ti.template(),
                 dt: ti.template(), p: ti.template(), ap: ti.template(), pap: ti.template(), go: ti.template()):
    """ap = A p and per particle p . A p, with the pairs' w_ij beside the list entries (the
    positions and densities do not change during the solve; recomputed, each took a division and
    three gathers a pair, every iteration)."""
    for i in p:
        if sweep_open(go):
            pi = p[i]
            lp = wall[i] * pi
            base = i * lay.x
            step = list_step(lay, rows)
            for m in range(near_count[i]):
                j = near[base + m * step]
                lp += wpair[base + m * step] * (pi - p[j])
            a = ftab[fluid[i], F_MASS] * pi + dt * lp
            ap[i] = a
            pap[i] = pi.dot(a)


@ti.func
def move_pass(velocity: ti.template(), dv: ti.template(), res: ti.template(), p: ti.template(),
              ap: ti.template(), diag: ti.template(), alpha: ti.template(), rr: ti.template(), rz: ti.template(),
              go: ti.template()):
    """x += alpha p (and the correction dv = x - v* with it), r -= alpha A p; per particle r.r
    and r.z (z = r / diag)."""
    for i in velocity:
        if sweep_open(go):
            velocity[i] += alpha * p[i]
            dv[i] += alpha * p[i]
            r = res[i] - alpha * ap[i]
            res[i] = r
            rr[i] = r.dot(r)
            rz[i] = r.dot(r) / diag[i]


@ti.func
def turn_pass(res: ti.template(), p: ti.template(), diag: ti.template(), beta: ti.template(), go: ti.template()):
    """p = z + beta p."""
    for i in p:
        if sweep_open(go):
            p[i] = res[i] / diag[i] + beta * p[i]


@ti.func
def total(a: ti.template(), partial: ti.template(), groups: ti.template(), go: ti.template()):
    """The sum of a over the particles (solver.sums: float64, in order), 0 where gated off."""
    chunk_sums_pass(a, partial, go)
    return total_pass(partial, groups, go)


@ti.kernel
def k_cg(velocity: V3, fluid: I1, near: I1, near_count: I1, wpair: F1, lay: ivec2, rows: ti.template(), ftab: F2,
         wall: F1, dt: ti.f32, diag: F1, res: V3, p: V3, ap: V3, rr: F1, rz: F1, dv: V3, rr_cold: F1, rz_cold: F1,
         partial: F1, groups: D1, go: D1, tol2: ti.f64, max_iterations: ti.i32, warm_start: ti.i32,
         start: ti.template()):
    """`start`: first both starts' residuals and sums, the start taken (from v* + dv where
    `warm_start` and that residual is the smaller) and the controller set (RR0 v*'s r.r, RR and
    RZ the start's r.r and r.z, WARM, DONE where the start is within the bound already). Then one
    iteration unless DONE: p . A p, x and r moved by alpha = r.z / p.A p, the new r.r and r.z,
    ITER + 1, DONE once r.r <= tol2 RR0 or after max_iterations (or where p . A p is not positive:
    round-off at convergence, or a broken matrix: stop where we are), else p turned by
    beta = r.z_new / r.z. The scalars in float64, alpha and beta taken to float32 as the passes
    use them."""
    if ti.static(start):
        first_residual_pass(velocity, fluid, near, near_count, wpair, lay, rows, ftab, wall, dt, diag, res, p, rr,
                            rz, dv, rr_cold, rz_cold)
        go[DONE] = 0.0
        s_rr = total(rr, partial, groups, go)
        s_rz = total(rz, partial, groups, go)
        s_rr0 = total(rr_cold, partial, groups, go)
        s_rz0 = total(rz_cold, partial, groups, go)
        warm = 0
        if warm_start != 0 and s_rr < s_rr0:
            warm = 1
        else:
            s_rr, s_rz = s_rr0, s_rz0
        go[ITER], go[RR], go[RZ], go[RR0], go[WARM] = 0.0, s_rr, s_rz, s_rr0, ti.cast(warm, ti.f64)
        start_pass(velocity, dv, res, p, diag, warm)
        if not (max_iterations > 0 and s_rr > tol2 * s_rr0):
            go[DONE] = 1.0
    product_pass(fluid, near, near_count, wpair, lay, rows, ftab, wall, dt, p, ap, rr, go)
    pap = total(rr, partial, groups, go)
    alpha = ti.cast(0.0, ti.f32)
    if sweep_open(go):
        if pap > 0.0:
            alpha = ti.cast(go[RZ] / pap, ti.f32)
        else:
            go[DONE] = 1.0
    move_pass(velocity, dv, res, p, ap, diag, alpha, rr, rz, go)
    s_rr = total(rr, partial, groups, go)
    s_rz = total(rz, partial, groups, go)
    beta = ti.cast(0.0, ti.f32)
    if sweep_open(go):
        if go[RZ] > 0.0:
            beta = ti.cast(s_rz / go[RZ], ti.f32)
        go[ITER] += 1.0
        go[RR], go[RZ] = s_rr, s_rz
        if go[ITER] >= max_iterations or not s_rr > tol2 * go[RR0]:
            go[DONE] = 1.0
    turn_pass(res, p, diag, beta, go)


class ImplicitViscosity:
    """The scratch arrays and the CG loop for a solver's n particles. `read(array)`: a small
    array's values (the solver's reads the CPU's element by element); `on_cpu`: the host reads the
    controller after each launch (on a GPU it first launches as many iterations as the last solve
    took, and each read waits for the device)."""

    def __init__(self, n: int, tolerance: float = 1e-3, max_iterations: int = 100, warm_start: bool = True,
                 read=None, on_cpu: bool = True):
        self.tolerance, self.max_iterations = float(tolerance), int(max_iterations)
        self.warm_start = bool(warm_start)      # False: every solve from v* (the tests' reference)
        self.diag, self.rr, self.rz, self.rr_cold, self.rz_cold = (ti.ndarray(ti.f32, n) for _ in range(5))
        self.res, self.p, self.ap = (ti.Vector.ndarray(3, ti.f32, shape=n) for _ in range(3))
        summer = Summer(n)
        self.partial, self.groups = summer.partial, summer.groups
        self.go = ti.ndarray(ti.f64, 6)
        self.read = read or (lambda a: a.to_numpy().tolist())
        self.on_cpu = on_cpu
        self.last_iterations = 1
        self.warm_starts = 0        # the solves that started from v* + dv

    def solve(self, velocity, fluid, near, near_count, wpair, lay, rows, ftab, wall, dt: float, dv) -> tuple[int, float]:
        """Replace `velocity` (v*) by the solution of A v = M v*, from v* + dv where that is the
        closer start, and leave the correction v - v* in `dv` (the next solve's start); w_ij
        beside the list entries in `wpair`. Returns (iterations, the final residual relative
        to v*'s)."""
        def iterate(start: bool) -> None:
            k_cg(velocity, fluid, near, near_count, wpair, lay, rows, ftab, wall, dt, self.diag, self.res, self.p,
                 self.ap, self.rr, self.rz, dv, self.rr_cold, self.rz_cold, self.partial, self.groups, self.go,
                 self.tolerance ** 2, self.max_iterations, int(self.warm_start), start)

        iterate(True)
        for _ in range(0 if self.on_cpu else self.last_iterations - 1):
            iterate(False)
        while (go := self.read(self.go))[DONE] < 0.5:
            iterate(False)
        iterations, rr, rr0, warm = go[ITER], go[RR], go[RR0], go[WARM]
        self.warm_starts += int(warm)
        self.last_iterations = max(int(iterations), 1)
        return int(iterations), (math.sqrt(rr / rr0) if rr0 > 0.0 else 0.0)
