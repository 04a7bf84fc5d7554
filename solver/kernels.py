"""SPH smoothing kernels in 3D, all with compact support radius h (W = 0 for r >= h).

Müller, Charypar & Gross 2003, "Particle-Based Fluid Simulation for Interactive Applications":
  poly6      W = 315 / (64 pi h^9) (h^2 - r^2)^3                       (density, color field)
  spiky      W = 15 / (pi h^6) (h - r)^3, grad W = -45/(pi h^6)(h - r)^2 r_hat   (pressure)
  viscosity  W = 15/(2 pi h^3)(-r^3/(2h^3) + r^2/h^2 + h/(2r) - 1), lap W = 45/(pi h^6)(h - r)
Monaghan 1992 cubic spline, written with support h (q = r/h, sigma = 8 / (pi h^3)), and
Wendland 1995 C2, W = 21/(2 pi h^3) (1 - q)^4 (1 + 4q).

Each kernel exists twice: a Taichi function for the solver and surfacer, and a NumPy function
for the tests and for tabulating boundary integrals. Kernel ids are compile-time constants.
"""

import math

import numpy as np
import taichi as ti

from .lattice import FCC_PLANE, sites_near

POLY6, SPIKY, CUBIC, WENDLAND, VISCOSITY = 0, 1, 2, 3, 4
DENSITY_KERNELS = {"poly6": POLY6, "cubic": CUBIC, "wendland": WENDLAND}
PRESSURE_KERNELS = {"spiky": SPIKY, "cubic": CUBIC, "wendland": WENDLAND}
PI = math.pi


# ----------------------------------------------------------------------------------- Taichi
@ti.func
def w(kind: ti.template(), r: ti.f32, h: ti.f32) -> ti.f32:
    """Kernel value W(r)."""
    out = 0.0
    if r < h:
        q = r / h
        if ti.static(kind == POLY6):
            d = h * h - r * r
            out = 315.0 / (64.0 * PI * h ** 9) * d * d * d
        elif ti.static(kind == SPIKY):
            d = h - r
            out = 15.0 / (PI * h ** 6) * d * d * d
        elif ti.static(kind == CUBIC):
            s = 8.0 / (PI * h * h * h)
            if q <= 0.5:
                out = s * (6.0 * (q * q * q - q * q) + 1.0)
            else:
                out = s * 2.0 * (1.0 - q) ** 3
        elif ti.static(kind == WENDLAND):
            s = 21.0 / (2.0 * PI * h * h * h)
            out = s * (1.0 - q) ** 4 * (1.0 + 4.0 * q)
    return out


@ti.func
def w_r2(kind: ti.template(), r2: ti.f32, h: ti.f32) -> ti.f32:
    """W from the squared distance. Poly6 needs no square root and no branch (the clamp makes it
    0 beyond h): in the density loop, whether an entry lies within h is unpredictable."""
    out = 0.0
    if ti.static(kind == POLY6):
        d = ti.max(h * h - r2, 0.0)
        out = 315.0 / (64.0 * PI * h ** 9) * d * d * d
    else:
        out = w(kind, ti.sqrt(r2), h)
    return out


def sigma(kind: int, h: float) -> float:
    """The normalisation of a density kernel: W(r) = sigma * shape(kind, r^2 / h^2)."""
    return {POLY6: 315.0 / 64.0, CUBIC: 8.0, WENDLAND: 10.5}[kind] / (PI * h ** 3)


@ti.func
def shape(kind: ti.template(), s):
    """W(r) / sigma of a density kernel at s = r^2 / h^2, 0 from s = 1 on. Branch-free (the
    pieces of the cubic spline are both computed, then selected), and element by element when
    s is a vector, so that a loop over a row of grid nodes compiles to SIMD instructions."""
    out = s * 0.0
    if ti.static(kind == POLY6):
        d = ti.max(1.0 - s, 0.0)
        out = d * d * d
    elif ti.static(kind == CUBIC):
        q = ti.sqrt(s)
        a = ti.max(1.0 - q, 0.0)
        out = ti.select(q <= 0.5, 6.0 * (q * s - s) + 1.0, 2.0 * a * a * a)
    elif ti.static(kind == WENDLAND):
        q = ti.sqrt(s)
        a = ti.max(1.0 - q, 0.0)
        a2 = a * a
        out = a2 * a2 * (1.0 + 4.0 * q)
    return out


@ti.func
def dw(kind: ti.template(), r: ti.f32, h: ti.f32) -> ti.f32:
    """Radial derivative dW/dr (<= 0); grad W = dW/dr * r_vec / r."""
    out = 0.0
    if r < h:
        q = r / h
        if ti.static(kind == POLY6):
            d = h * h - r * r
            out = -945.0 / (32.0 * PI * h ** 9) * d * d * r
        elif ti.static(kind == SPIKY):
            d = h - r
            out = -45.0 / (PI * h ** 6) * d * d
        elif ti.static(kind == CUBIC):
            s = 8.0 / (PI * h * h * h)
            if q <= 0.5:
                out = s / h * 6.0 * (3.0 * q * q - 2.0 * q)
            else:
                out = -s / h * 6.0 * (1.0 - q) ** 2
        elif ti.static(kind == WENDLAND):
            s = 21.0 / (2.0 * PI * h * h * h)
            out = -s / h * 20.0 * q * (1.0 - q) ** 3
    return out


@ti.func
def w_dwr(kind: ti.template(), r2: ti.f32, inv_h: ti.f32):
    """(W(r), dW/dr / r) at the squared distance r2 (0 < r2 <= h^2; W alone from r2 = 0 on, and
    0 at h) for a pair loop, with inv_h = 1 / h computed once before it: the normalisations are
    powers of inv_h, and a pair costs at most one square root and one division (the cubic
    spline's outer part and spiky's 1 / r; poly6 neither). w and dw divide by h and by the
    normalisation at every call, and in a loop those divisions stay divisions: Taichi's fast math
    lets LLVM reassociate but not turn x / c into x * (1 / c), and a loop that stores (the density
    pass) reloads h every pair. Their five divisions a pair, each on the one divider with the
    square root, bound DFSPH's density pass: without them it takes 0.80-0.85 of its time
    (bench/RESULTS.md, forty-third session)."""
    w, f = 0.0, 0.0
    if ti.static(kind == POLY6):
        d = 1.0 - r2 * inv_h * inv_h
        c = inv_h * inv_h * inv_h
        w = 315.0 / (64.0 * PI) * c * d * d * d
        f = -945.0 / (32.0 * PI) * c * inv_h * inv_h * d * d
    else:
        r = ti.sqrt(r2)
        q = r * inv_h
        u = 1.0 - q
        c = inv_h * inv_h * inv_h
        if ti.static(kind == SPIKY):
            w = 15.0 / PI * c * u * u * u
            f = -45.0 / PI * c * inv_h * u * u / r
        elif ti.static(kind == CUBIC):
            if q <= 0.5:
                w = 8.0 / PI * c * (6.0 * (q * q * q - q * q) + 1.0)
                f = 48.0 / PI * c * inv_h * inv_h * (3.0 * q - 2.0)
            else:
                w = 16.0 / PI * c * u * u * u
                f = -48.0 / PI * c * inv_h * u * u / r
        elif ti.static(kind == WENDLAND):
            w = 21.0 / (2.0 * PI) * c * u * u * u * u * (1.0 + 4.0 * q)
            f = -210.0 / PI * c * inv_h * inv_h * u * u * u
    return w, f


@ti.func
def grad_w(kind: ti.template(), rv, r: ti.f32, h: ti.f32):
    """grad_i W(x_i - x_j) for rv = x_i - x_j, r = |rv| > 0."""
    return dw(kind, r, h) / r * rv


@ti.func
def lap_viscosity(r: ti.f32, h: ti.f32) -> ti.f32:
    """Laplacian of Müller's viscosity kernel, 45 / (pi h^6) (h - r)."""
    out = 0.0
    if r < h:
        out = 45.0 / (PI * h ** 6) * (h - r)
    return out


@ti.func
def lap_poly6(r: ti.f32, h: ti.f32) -> ti.f32:
    """Laplacian of poly6, -945/(32 pi h^9) (h^2 - r^2)(3h^2 - 7r^2); used for color-field curvature."""
    out = 0.0
    if r < h:
        d = h * h - r * r
        out = -945.0 / (32.0 * PI * h ** 9) * d * (3.0 * h * h - 7.0 * r * r)
    return out


# ------------------------------------------------------------------------------------ NumPy
def w_np(kind: int, r, h: float):
    r = np.asarray(r, dtype=np.float64)
    q = r / h
    inside = r < h
    if kind == POLY6:
        out = 315.0 / (64.0 * PI * h ** 9) * (h * h - r * r) ** 3
    elif kind == SPIKY:
        out = 15.0 / (PI * h ** 6) * (h - r) ** 3
    elif kind == CUBIC:
        s = 8.0 / (PI * h ** 3)
        out = np.where(q <= 0.5, s * (6.0 * (q ** 3 - q ** 2) + 1.0), s * 2.0 * (1.0 - q) ** 3)
    elif kind == WENDLAND:
        out = 21.0 / (2.0 * PI * h ** 3) * (1.0 - q) ** 4 * (1.0 + 4.0 * q)
    elif kind == VISCOSITY:
        rr = np.maximum(r, 1e-12)
        out = 15.0 / (2.0 * PI * h ** 3) * (-rr ** 3 / (2 * h ** 3) + rr ** 2 / h ** 2 + h / (2 * rr) - 1.0)
    else:
        raise ValueError(kind)
    return np.where(inside, out, 0.0)


def dw_np(kind: int, r, h: float):
    r = np.asarray(r, dtype=np.float64)
    q = r / h
    inside = r < h
    if kind == POLY6:
        out = -945.0 / (32.0 * PI * h ** 9) * (h * h - r * r) ** 2 * r
    elif kind == SPIKY:
        out = -45.0 / (PI * h ** 6) * (h - r) ** 2
    elif kind == CUBIC:
        s = 8.0 / (PI * h ** 3)
        out = np.where(q <= 0.5, s / h * 6.0 * (3 * q * q - 2 * q), -s / h * 6.0 * (1.0 - q) ** 2)
    elif kind == WENDLAND:
        out = -21.0 / (2.0 * PI * h ** 3) / h * 20.0 * q * (1.0 - q) ** 3
    else:
        raise ValueError(kind)
    return np.where(inside, out, 0.0)


def lattice_number_density(kind: int, h: float, spacing: float, lattice: str = "cubic", steps=None) -> float:
    """sum_j W(x_i - x_j) over the fill's lattice (solver.lattice: "cubic" of the given spacing, or
    "fcc" with plane steps `steps`, by default those of the same number density), self included.

    Setting each particle's mass to rho0 / this sum makes a particle inside a lattice-filled
    block start exactly at rest density.
    """
    p = _lattice_sites(spacing, lattice, steps, h)
    return float(w_np(kind, np.linalg.norm(p, axis=1), h).sum())


def lattice_viscous_moment(kind: int, h: float, spacing: float, lattice: str = "cubic", steps=None) -> float:
    """M = -sum_j V |x_ij| W'(|x_ij|) y_ij^2 / (|x_ij|^2 + 0.01 h^2) over the fill's lattice
    (V = 1 / its number density), averaged over the three axes: the factor by which Morris et
    al. 1997's viscous term, sum_j V (x_ij . grad W_ij) / (r^2 + 0.01 h^2) 2 nu v_ij, reads
    nu lap v on the lattice. The continuum value is 0.963 (the 0.01 h^2); the cubic lattice of
    spacing h / 2 gives 0.992, the fcc lattice of one particle per the same volume 0.941, so a
    shear wave on the fcc fill decayed 6-7 % slower than on the cubic fill (tests/test_dfsph.py)."""
    p = _lattice_sites(spacing, lattice, steps, h)
    r = np.linalg.norm(p, axis=1)
    number_density = float(w_np(kind, r, h).sum())        # lattice_number_density, from these sites
    p, r = p[r > 0], r[r > 0]
    moment = -(dw_np(kind, r, h) * r / (r * r + 0.01 * h * h))[:, None] * p * p
    return float(moment.sum(0).mean() / number_density)


def _lattice_sites(spacing: float, lattice: str, steps, h: float) -> np.ndarray:
    """The fill lattice's sites within h of one of them (solver.lattice): plane steps `steps`,
    by default the cubic spacing or the fcc step of the same number density."""
    if steps is None:
        steps = spacing * (FCC_PLANE if lattice == "fcc" else 1.0)
    return sites_near(steps, lattice, h)


def lattice_gradient_moment(kind: int, h: float, spacing: float, number_density: float) -> float:
    """M = (1/3) trace sum_j V (x_j - x_i) (x) grad_i W_ij over the fill lattice, V = 1/number
    density. The continuum value is 1; on a lattice with h = 2 spacings the spiky kernel gives
    0.947, so an unscaled SPH gradient of a linear pressure field comes out 5% short and a
    resting column needs a 5% steeper pressure profile to stand."""
    n = int(math.ceil(h / spacing)) + 1
    ax = np.arange(-n, n + 1) * spacing
    x, y, z = np.meshgrid(ax, ax, ax, indexing="ij")
    r = np.sqrt(x * x + y * y + z * z)
    return float((np.abs(dw_np(kind, r, h)) * r).sum() / (3.0 * number_density))


def ghost_tables(density_kind: int, pressure_kind: int, h: float, radius: float, n: int = 25):
    """Boundary sums for walls, consistent with the fill lattice (spacing d = 2 radius).

    A particle at distance a from a plane wall misses the fluid that a mirrored lattice would put
    beyond it: layers at a + r + i d (i >= 0) along the normal, the particle's own lattice in the
    plane. For the box, with distances (a, b, c) to the nearest wall along each axis:
        H(a)       = sum_{i >= 0; j, k in Z} W(a + r + i d, j d, k d)          half-space
        Q(a, b)    = sum_{i, j >= 0; k in Z} W(a + r + i d, b + r + j d, k d)  quarter-space (edge)
        O(a, b, c) = sum_{i, j, k >= 0}      W(a + r + i d, ...)               octant (corner)
    and the missing sum is H(a) + H(b) + H(c) - Q(a,b) - Q(a,c) - Q(b,c) + O(a,b,c) by
    inclusion-exclusion. The same sums of |dW/dr| x/r give the normal gradient (first argument
    is the component's axis). A block filled on the lattice therefore starts at exactly rest
    density at walls, edges and corners. Distances are sampled on [0, h]; at h every sum is 0.

    Returns two (3, n, n, n) arrays, [H, Q, O] for density and for the gradient, where H ignores
    its 2nd and 3rd index and Q its 3rd.
    """
    d = 2.0 * radius
    m = int(math.ceil(h / d)) + 1
    a = np.linspace(0.0, h, n)
    beyond = radius + d * np.arange(m)                 # ghost layers past the wall, from it
    inplane = d * np.arange(-m, m + 1)

    def sums(X, Y, Z):
        R = np.sqrt(X * X + Y * Y + Z * Z)
        wv = w_np(density_kind, R, h)
        gv = np.abs(dw_np(pressure_kind, R, h)) * X / np.maximum(R, 1e-30)
        return wv.sum(axis=(-3, -2, -1)), gv.sum(axis=(-3, -2, -1))

    # H: only the first distance matters
    hx = (a[:, None, None, None] + beyond[None, :, None, None])
    Hd, Hg = sums(hx, inplane[None, None, :, None], inplane[None, None, None, :])
    # Q: two distances
    qx = a[:, None, None, None, None] + beyond[None, None, :, None, None]
    qy = a[None, :, None, None, None] + beyond[None, None, None, :, None]
    Qd, Qg = sums(qx, qy, inplane[None, None, None, None, :])
    # O: three distances
    Od, Og = sums(a[:, None, None, None, None, None] + beyond[None, None, None, :, None, None],
                  a[None, :, None, None, None, None] + beyond[None, None, None, None, :, None],
                  a[None, None, :, None, None, None] + beyond[None, None, None, None, None, :])
    dens = np.stack([np.broadcast_to(Hd[:, None, None], (n, n, n)),
                     np.broadcast_to(Qd[:, :, None], (n, n, n)), Od])
    grad = np.stack([np.broadcast_to(Hg[:, None, None], (n, n, n)),
                     np.broadcast_to(Qg[:, :, None], (n, n, n)), Og])
    return dens.astype(np.float32), grad.astype(np.float32)


def _half_space_samples(h: float, radius: float, n: int):
    """The boundary samples beyond one plane wall, on the fill lattice (as in `ghost_tables`),
    seen from a particle at each of n distances a in [0, h] from the wall: (a, X, Y, Z, R), with
    X the (n, layers, 1, 1) distance along the wall's normal, Y and Z the in-plane offsets and R
    the (n, layers, rows, columns) distances."""
    d = 2.0 * radius
    m = int(math.ceil(h / d)) + 1
    a = np.linspace(0.0, h, n)
    X = a[:, None, None, None] + radius + d * np.arange(m)[None, :, None, None]
    Y = (d * np.arange(-m, m + 1))[None, None, :, None]
    Z = (d * np.arange(-m, m + 1))[None, None, None, :]
    return a, X, Y, Z, np.sqrt(X * X + Y * Y + Z * Z)


def ghost_moment_tables(pressure_kind: int, h: float, radius: float, n: int = 25):
    """Moment of the boundary samples beyond one plane wall, for the hydrostatic pressure
    extrapolation of Adami, Hu & Adams 2012: sample b gets p_b = p_i + rho_i g.(x_b - x_i).

    With the lattice of `ghost_tables` (half-space only), and grad W_ib = |W'| x_bi / r:
        nn(a) = sum_b |W'|/r (x_bi . n)^2         normal-normal
        tt(a) = sum_b |W'|/r (x_bi . t)^2         tangential-tangential (any in-plane t)
    so that sum_b (g . x_bi) grad W_ib = nn (g.n) n + tt (g - (g.n) n). Returns (2, n).
    """
    _a, X, Y, _Z, R = _half_space_samples(h, radius, n)
    f = np.abs(dw_np(pressure_kind, R, h)) / np.maximum(R, 1e-30)
    nn = (f * X * X).sum(axis=(1, 2, 3))
    tt = (f * Y * Y).sum(axis=(1, 2, 3))
    return np.stack([nn, tt]).astype(np.float32)


BETA_MAX = 1.5          # Morris et al. 1997: cap of the boundary velocity extrapolation


def wall_viscosity_table(pressure_kind: int, h: float, radius: float, n: int = 25):
    """Morris et al. 1997's viscous weight of the boundary samples beyond one plane wall, for a
    wall at rest (no slip): with the half-space lattice of `ghost_tables` and
    -x_ib . grad W_ib = |W'| r,
        S(a) = sum_b beta_b |W'(r)| r / (r^2 + 0.01 h^2)
    so that the wall adds (2 eta_i S / (delta_i delta0)) (0 - v_i) to m_i dv_i / dt
    (solver.viscosity). Each sample's term is weighted by Morris's beta = min(BETA_MAX, 1 + d_b / a)
    (d_b: the sample's depth beyond the wall): the mirrored fluid's velocity extrapolated to zero
    at the wall, so that the no-slip plane is the wall itself. Returns (1, n), sampled on [0, h]."""
    a, X, _Y, _Z, R = _half_space_samples(h, radius, n)
    beta = np.minimum(BETA_MAX, X / np.maximum(a[:, None, None, None], 1e-30))
    s = (beta * np.abs(dw_np(pressure_kind, R, h)) * R / (R * R + 0.01 * h * h)).sum(axis=(1, 2, 3))
    return s[None, :].astype(np.float32)


def surface_deficit(kind: int, h: float, spacing: float, lattice: str = "cubic", steps=None) -> tuple[float, float]:
    """(g, D) of a particle in the fill lattice's flat top layer: how one-sided its neighbourhood
    is, g = |sum_j grad W_ij| h / delta0, and the share of the full number density delta0 it
    misses, D = 1 - delta / delta0 (the lattice's sites within h with none above its plane).
    The fcc fill with the cubic spline at h = 4 r gives g = 1.134, D = 0.221; a settled pool's
    top layer in the solver read 1.138 and 0.224 (its planes stretched to fit the walls)."""
    p = _lattice_sites(spacing, lattice, steps, h)
    r = np.linalg.norm(p, axis=1)
    full = float(w_np(kind, r, h).sum())
    below = p[:, 1] <= 1e-9 * h
    p, r = p[below], r[below]
    inside = r > 0
    grad = -(dw_np(kind, r[inside], h) / r[inside])[:, None] * p[inside]
    g = float(np.linalg.norm(grad.sum(axis=0))) * h / full
    return g, 1.0 - float(w_np(kind, r, h).sum()) / full
