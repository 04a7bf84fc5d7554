"""Anisotropic kernels after Yu & Turk 2013 ("Reconstructing surfaces of particle-based fluids
using anisotropic kernels", ACM TOG 32(1)).

For every particle i, over its neighbours j within R (the splat support), with the weights
w_ij = 1 - (|x_ij| / R)^3:

  x_w,i  = sum_j w_ij x_j / sum_j w_ij                       (weighted mean)
  C_i    = sum_j w_ij (x_j - x_w,i)(x_j - x_w,i)^T / sum_j w_ij  (weighted covariance)
  x̄_i   = (1 - lambda) x_i + lambda x_h,i                    (Laplacian smoothing of centres)

where x_h,i is the weighted mean over the neighbours within h only (over R it pulls a flat
surface's particles in by about R / 3). lambda is the caller's: Yu & Turk take 0.9, which on
the example's first frame pulled every face of the column in by 1.7 r (mesh volume -13 %,
measured). So the surface stage follows it with Taubin's second pass (k_inflate), the same
Laplacian taken of the smoothed centres and applied with -mu: lambda 0.5, mu 0.53 (its
defaults) take a pool jittered by 0.1 r from a top of rms height 0.059 r to 0.052 r (the
isotropic kernels: 0.058 r) and keep its volume within 2 % (lambda 0.5 alone: 0.037 r and 10 %
less volume).

C_i = U diag(s_1 >= s_2 >= s_3) U^T. The kernel of particle i is stretched along U:
W(|A_i (x - x̄_i)| / h) det(A_i), A_i = U diag(s_1 / s~_k) U^T, s~_k = max(s_k, s_1 / KR):
its longest axis is the isotropic support h and no axis is shorter than h / KR. Where no
axis is clamped (s_3 > s_1 / KR: on the example's frames 1, 11 and 30 every particle but
0, 5 and 0.5 %, those in thin sheets and at sharp edges) that is A_i = s_1 C_i^-1, taken so: s_1 and s_3 in closed form and an inverse cost less than
the 3x3 SVD the others take (k_anisotropy 0.68 -> 0.57 s at 500k particles, the same table to
float32 round-off: bench/RESULTS.md, 2026-11-28). So a particle's support always lies inside the isotropic sphere of radius h (the splat's blocks,
phases and pruning stay as they are); det(A_i) keeps the kernel's integral, so each particle
still adds its own volume. A flat surface's kernels flatten along the normal (a flat, sharp
surface instead of the isotropic kernels' bumps); a thin sheet keeps its kernels in its plane.
A particle with fewer than N_EPS neighbours (spray, a thin filament) takes the isotropic kernel
shrunk by KN: a small droplet of about its own volume instead of a ball of radius h.

The neighbour search sorts the particles into cells of edge h (splat.sort_by_cell).
"""
import math

import taichi as ti

from solver.types import F1, I1, V3, ivec3, vec3

RADIUS = 2.0        # the neighbourhood's radius R, in units of the splat support h (their r = 2 h)
KR = 4.0            # largest ratio of a kernel's axes (Yu & Turk's k_r)
UNCLAMPED = 1.01    # an eigenvalue this far above s_1 / KR: no axis clamped, A from C's inverse
KN = 0.5            # a lone particle's kernel, in units of h (their k_n)
N_EPS = 25          # fewer neighbours within R than this: the lone-particle kernel (their N_eps;
                    # a full neighbourhood within R = 8 r on the fill lattice holds 257)
# columns of the per-particle table: the symmetric M = A^T A (6 entries) and det(A); a row is
# one vector (device.empty(ti.f32, n, COLUMNS): numpy (n, 7) on the CPU, a vector ndarray on a GPU)
M00, M11, M22, M01, M02, M12, DET = range(7)
COLUMNS = 7
R7 = ti.types.ndarray(dtype=ti.types.vector(COLUMNS, ti.f32), ndim=1)


@ti.func
def cells_around(x, radius: ti.f32, origin, inv_edge: ti.f32, dims):
    """The lowest and highest cells (clamped to the grid) of the cube of half-width `radius`
    about x, in cells of edge 1 / inv_edge from `origin`."""
    lo = ti.math.clamp(ti.cast(ti.floor((x - radius - origin) * inv_edge), ti.i32), 0, dims - 1)
    hi = ti.math.clamp(ti.cast(ti.floor((x + radius - origin) * inv_edge), ti.i32), 0, dims - 1)
    return lo, hi


@ti.func
def row_run(cx, cy, lo, hi, dims, start: ti.template(), count: ti.template()):
    """The particles of cells (cx, cy, lo.z .. hi.z): one run [begin, end) in the sorted order
    (cells numbered row by row, a row along z)."""
    k0 = (cx * dims.y + cy) * dims.z + lo.z
    k1 = (cx * dims.y + cy) * dims.z + hi.z
    return start[k0], start[k1] + count[k1]


@ti.func
def ball_run(x, cx, cy, radius: ti.f32, origin, edge: ti.f32, inv_edge: ti.f32, dims, start: ti.template(),
             count: ti.template()):
    """The run [begin, end) of the particles of row (cx, cy) in the cells that the ball of
    `radius` about x reaches: the ball's chord along z through the row's nearest point to x
    (empty where the ball misses the row). Every particle left out is farther than `radius`
    (the chord is taken a millionth longer, for round-off), so a sum whose terms vanish beyond
    it is the same over this run as over the whole cube of cells_around."""
    gx = origin.x + cx * edge
    gy = origin.y + cy * edge
    dx = ti.max(ti.max(gx - x.x, x.x - gx - edge), 0.0)
    dy = ti.max(ti.max(gy - x.y, x.y - gy - edge), 0.0)
    reach2 = (radius * 1.000001) ** 2 - dx * dx - dy * dy
    begin, end = 0, 0
    if reach2 > 0.0:
        zr = ti.sqrt(reach2)
        lo = ti.math.clamp(ti.cast(ti.floor((x.z - zr - origin.z) * inv_edge), ti.i32), 0, dims.z - 1)
        hi = ti.math.clamp(ti.cast(ti.floor((x.z + zr - origin.z) * inv_edge), ti.i32), 0, dims.z - 1)
        k = (cx * dims.y + cy) * dims.z
        begin, end = start[k + lo], start[k + hi] + count[k + hi]
    return begin, end


@ti.func
def _extreme_eigenvalues(c):
    """The largest and smallest eigenvalues of the symmetric 3x3 matrix c (the trigonometric
    closed form, Smith 1961). Its sums are taken in float64 (in float32 p^3 - q^2 cancels to a
    few 1e-4 of the eigenvalues); the angle in float32 (Vulkan has no 64-bit atan2 or cos)."""
    d = ti.cast(c, ti.f64)
    m = d.trace() / 3.0
    k = d - m * ti.Matrix.identity(ti.f64, 3)
    p = ((k[0, 0] ** 2 + k[1, 1] ** 2 + k[2, 2] ** 2) + 2.0 * (k[0, 1] ** 2 + k[0, 2] ** 2 + k[1, 2] ** 2)) / 6.0
    q = 0.5 * k.determinant()
    phi = ti.atan2(ti.cast(ti.sqrt(ti.max(p * p * p - q * q, 0.0)), ti.f32), ti.cast(q, ti.f32)) / 3.0
    r = 2.0 * ti.sqrt(p)
    largest = m + r * ti.cast(ti.cos(phi), ti.f64)
    smallest = m + r * ti.cast(ti.cos(phi + 2.0 * math.pi / 3.0), ti.f64)
    return ti.cast(largest, ti.f32), ti.cast(smallest, ti.f32)


@ti.kernel
def k_anisotropy(pos: V3, start: I1, count: I1, origin: vec3, edge: ti.f32, dims: ivec3,
                 radius: ti.f32, lam: ti.f32, center: V3, table: R7, neighbours: I1, smooth: ti.template()):
    """center[p] = x̄_p (with `smooth`; else x_p), table[p] = (M, det A) and neighbours[p] = the
    particles within `radius` (itself included), for the particles `pos` sorted by cells of
    `edge` numbered row by row (splat.sort_by_cell: start/count per cell; a row along z is one
    run). The candidates of a row are those of the cells its chord of the ball reaches
    (ball_run); the loop over them has no branch: a candidate beyond the radius weighs 0."""
    inv_edge = 1.0 / edge
    inv_r = 1.0 / radius
    for p in pos:
        x = pos[p]
        lo, hi = cells_around(x, radius, origin, inv_edge, dims)
        wsum = 0.0
        m1 = vec3(0.0)                           # sum w d, d = (x_j - x_p) / R: O(1) for the SVD
        c0 = vec3(0.0)                           # sum w d d^T: the diagonal
        c1 = vec3(0.0)                           # and (xy, xz, yz)
        wsum_h = 0.0                             # the same within h = R / RADIUS, for the centre
        m1_h = vec3(0.0)
        n = 0
        for cx, cy in ti.ndrange((lo.x, hi.x + 1), (lo.y, hi.y + 1)):
            begin, end = ball_run(x, cx, cy, radius, origin, edge, inv_edge, dims, start, count)
            for q in range(begin, end):
                d = (pos[q] - x) * inv_r
                s = d.norm_sqr()
                t = ti.sqrt(ti.min(s, 1.0))
                w = 1.0 - t * t * t
                wd = w * d
                wsum += w
                m1 += wd
                c0 += wd * d
                c1 += vec3(wd.x * d.y, wd.x * d.z, wd.y * d.z)
                n += ti.select(s < 1.0, 1, 0)
                if ti.static(smooth):
                    th = ti.min(t * RADIUS, 1.0)
                    wh = 1.0 - th * th * th
                    wsum_h += wh
                    m1_h += wh * d
        mean = m1 / wsum
        cov = ti.Matrix([[c0.x, c1.x, c1.y], [c1.x, c0.y, c1.z], [c1.y, c1.z, c0.z]]) / wsum - mean.outer_product(mean)
        c = x
        if ti.static(smooth):
            c = x + lam * radius * m1_h / wsum_h
        center[p] = c
        neighbours[p] = n
        a = ti.Matrix.identity(ti.f32, 3) / KN
        if n >= N_EPS:
            largest, smallest = _extreme_eigenvalues(cov)
            if smallest * KR > largest * UNCLAMPED and smallest > 0.0:
                a = largest * cov.inverse()         # no axis clamped: A = s_1 C^-1
            else:
                u, sig, _v = ti.svd(cov)
                s1 = ti.max(ti.max(sig[0, 0], sig[1, 1]), ti.max(sig[2, 2], 1e-30))
                inv_axis = vec3(s1 / ti.max(sig[0, 0], s1 / KR), s1 / ti.max(sig[1, 1], s1 / KR),
                                s1 / ti.max(sig[2, 2], s1 / KR))
                a = u @ ti.Matrix([[inv_axis[0], 0.0, 0.0], [0.0, inv_axis[1], 0.0],
                                   [0.0, 0.0, inv_axis[2]]]) @ u.transpose()
        mm = a.transpose() @ a
        table[p] = ti.Vector([mm[0, 0], mm[1, 1], mm[2, 2], mm[0, 1], mm[0, 2], mm[1, 2], a.determinant()])


@ti.kernel
def k_inflate(pos: V3, center: V3, start: I1, count: I1, origin: vec3, edge: ti.f32, dims: ivec3,
              h: ti.f32, mu: ti.f32, out: V3):
    """Taubin's second pass (Taubin 1995, "A signal processing approach to fair surface design")
    on the smoothed centres c: out[p] = c_p - mu (c_h,p - c_p), c_h,p the mean of c over the
    neighbours within h of x_p (itself included), with the first pass's weights 1 - (|x_pq| / h)^3.
    The first pass (lambda) takes out the particle-scale noise and shrinks every face; this one
    pushes the faces back out and leaves the finer noise damped. Same cells as k_anisotropy."""
    inv_edge = 1.0 / edge
    inv_h = 1.0 / h
    for p in pos:
        x = pos[p]
        cp = center[p]
        lo, hi = cells_around(x, h, origin, inv_edge, dims)
        wsum = 0.0
        acc = vec3(0.0)
        for cx, cy in ti.ndrange((lo.x, hi.x + 1), (lo.y, hi.y + 1)):
            begin, end = row_run(cx, cy, lo, hi, dims, start, count)
            for q in range(begin, end):
                t = ti.sqrt(ti.min((pos[q] - x).norm_sqr() * inv_h * inv_h, 1.0))
                w = 1.0 - t * t * t
                wsum += w
                acc += w * (center[q] - cp)
        out[p] = cp - mu * acc / wsum


@ti.func
def quad(t: ti.template(), p, dx, dy, z):
    """q = |A_p d|^2 for d = (dx, dy, z) in units of h (z a scalar, or a vector of a row's
    lanes: then q is too)."""
    m = t[p]
    a0 = m[M00] * dx * dx + m[M11] * dy * dy + 2.0 * m[M01] * dx * dy
    a1 = 2.0 * (m[M02] * dx + m[M12] * dy)
    return a0 + (a1 + m[M22] * z) * z


@ti.kernel
def k_weigh(vol: F1, table: R7, neighbours: I1, fewest: ti.i32, anisotropic: ti.template()):
    """vol[p] *= det(A_p) (with `anisotropic`: each kernel keeps its integral); 0 for the
    particles with fewer than `fewest` neighbours (spray, left out of the field)."""
    for p in vol:
        v = vol[p]
        if ti.static(anisotropic):
            v *= table[p][DET]
        vol[p] = ti.select(neighbours[p] >= fewest, v, 0.0)


@ti.kernel
def k_take_rows(order: I1, src: R7, dst: R7):
    for s in order:
        dst[s] = src[order[s]]
