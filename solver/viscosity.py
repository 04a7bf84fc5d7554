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

Sums over particles are solver.sums's, the same on every run and backend.
"""
import math

import taichi as ti

from .neighbours import list_step
from .params import F_MASS
from .sums import Summer
from .types import F1, F2, I1, V3, ivec2


@ti.kernel
def k_first_residual(velocity: V3, fluid: I1, near: I1, near_count: I1, wpair: F1, lay: ivec2, rows: ti.template(),
                     ftab: F2, wall: F1, dt: ti.f32, diag: F1, res: V3, direction: V3, rr: F1, rz: F1, dv: V3,
                     rr_cold: F1, rz_cold: F1):
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


@ti.kernel
def k_start(velocity: V3, dv: V3, res: V3, direction: V3, diag: F1, warm: ti.i32):
    """The first direction z = r / diag from the start taken: from v* + dv (`warm`: velocity
    += dv), or from v* (res = r0, dv = 0)."""
    for i in velocity:
        if warm:
            velocity[i] += dv[i]
        else:
            res[i] = direction[i]
            dv[i] = ti.Vector([0.0, 0.0, 0.0])
        direction[i] = res[i] / diag[i]


@ti.kernel
def k_product(fluid: I1, near: I1, near_count: I1, wpair: F1, lay: ivec2, rows: ti.template(), ftab: F2, wall: F1,
              dt: ti.f32, p: V3, ap: V3, pap: F1):
    """ap = A p and per particle p . A p, with the pairs' w_ij beside the list entries (the
    positions and densities do not change during the solve; recomputed, each took a division and
    three gathers a pair, every iteration)."""
    for i in p:
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


@ti.kernel
def k_move(velocity: V3, dv: V3, res: V3, p: V3, ap: V3, diag: F1, alpha: ti.f32, rr: F1, rz: F1):
    """x += alpha p (and the correction dv = x - v* with it), r -= alpha A p; per particle r.r
    and r.z (z = r / diag)."""
    for i in velocity:
        velocity[i] += alpha * p[i]
        dv[i] += alpha * p[i]
        r = res[i] - alpha * ap[i]
        res[i] = r
        rr[i] = r.dot(r)
        rz[i] = r.dot(r) / diag[i]


@ti.kernel
def k_turn(res: V3, p: V3, diag: F1, beta: ti.f32):
    """p = z + beta p."""
    for i in p:
        p[i] = res[i] / diag[i] + beta * p[i]


class ImplicitViscosity:
    """The scratch arrays and the CG loop for a solver's n particles."""

    def __init__(self, n: int, tolerance: float = 1e-3, max_iterations: int = 100, warm_start: bool = True):
        self.tolerance, self.max_iterations = float(tolerance), int(max_iterations)
        self.warm_start = bool(warm_start)      # False: every solve from v* (the tests' reference)
        self.diag, self.rr, self.rz, self.rr_cold, self.rz_cold = (ti.ndarray(ti.f32, n) for _ in range(5))
        self.res, self.p, self.ap = (ti.Vector.ndarray(3, ti.f32, shape=n) for _ in range(3))
        summer = Summer(n)
        self._sum, self._sums = summer.total, summer.totals
        self.warm_starts = 0        # the solves that started from v* + dv

    def solve(self, velocity, fluid, near, near_count, wpair, lay, rows, ftab, wall, dt: float, dv) -> tuple[int, float]:
        """Replace `velocity` (v*) by the solution of A v = M v*, from v* + dv where that is the
        closer start, and leave the correction v - v* in `dv` (the next solve's start); w_ij
        beside the list entries in `wpair`. Returns (iterations, the final residual relative
        to v*'s)."""
        k_first_residual(velocity, fluid, near, near_count, wpair, lay, rows, ftab, wall, dt, self.diag, self.res,
                         self.p, self.rr, self.rz, dv, self.rr_cold, self.rz_cold)
        (rr, rz), (rr0, rz0) = self._sums(self.rr, self.rz), self._sums(self.rr_cold, self.rz_cold)
        if rr0 <= 0.0:
            dv.fill(0.0)
            return 0, 0.0
        warm = self.warm_start and rr < rr0
        if not warm:
            rr, rz = rr0, rz0
        self.warm_starts += int(warm)
        k_start(velocity, dv, self.res, self.p, self.diag, int(warm))
        iterations = 0
        while iterations < self.max_iterations and rr > self.tolerance ** 2 * rr0:
            k_product(fluid, near, near_count, wpair, lay, rows, ftab, wall, dt, self.p, self.ap, self.rr)
            pap = self._sum(self.rr)
            if not pap > 0.0:       # round-off at convergence, or a broken matrix: stop where we are
                break
            k_move(velocity, dv, self.res, self.p, self.ap, self.diag, rz / pap, self.rr, self.rz)
            rr, rz_next = self._sums(self.rr, self.rz)
            iterations += 1
            k_turn(self.res, self.p, self.diag, rz_next / rz if rz > 0 else 0.0)
            rz = rz_next
        return iterations, math.sqrt(rr / rr0)
