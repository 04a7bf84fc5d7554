"""What the solver is given: plain parameters in SI units (metres, seconds, kg/m^3, Pa s, N/m).

`SolverParams` is the one input of a solver. The tables the kernels read (per-fluid constants,
the collider table, the lattice moments) are derived from it once, on first use.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from . import kernels as K
from .lattice import Domain
from .meshsdf import SDFGrid

SPHERE, BOX, CAPSULE, MESH = 0, 1, 2, 3
COLLIDER_TYPES = {"sphere": SPHERE, "box": BOX, "capsule": CAPSULE, "mesh": MESH}
# Fluid table columns: particle mass, rest density rho0, Tait stiffness B, Müller's particle-scale
# viscosity mu, tension sigma, dynamic viscosity (Morris, Pa s), XSPH smoothing, and 1 / mass (so
# that a pair loop multiplies where it divided: kernels.w_dwr says why that matters)
F_MASS, F_RHO0, F_B, F_MU, F_SIGMA, F_ETA, F_XSPH, F_INV_MASS = range(8)
# Collider table columns: 8 shape params, restitution, friction, sign (+1 obstacle, -1 container).
# A mesh's shape params: its distance grid's origin (3), voxel size, node counts (3) and offset
# into the flat array of all mesh grids (exact in float32 up to 2^24).
C_REST, C_FRIC, C_SIGN = 8, 9, 10


@dataclass(frozen=True)
class Fluid:
    rest_density: float                # kg/m^3
    viscosity: float = 0.0             # Müller et al. 2003's particle-scale viscosity
    surface_tension: float = 0.0       # N/m
    dynamic_viscosity: float = 0.0     # Pa s, physical (Morris et al. 1997): water 1e-3
    xsph: float = 0.0                  # artist smoothing: share of the neighbours' mean velocity


@dataclass(frozen=True)
class Block:
    """An axis-aligned box of fluid `fluid` (index into SolverParams.fluids), filled on the lattice."""
    fluid: int
    min: tuple[float, float, float]
    max: tuple[float, float, float]
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Collider:
    """A solid: `kind` sphere (shape: centre, radius), box (min, max), capsule (a, b, radius) or
    mesh (`sdf`: its signed distance grid). A container keeps the fluid inside instead of out."""
    kind: str
    shape: tuple[float, ...] = ()
    restitution: float = 0.0
    friction: float = 0.2
    container: bool = False
    sdf: SDFGrid | None = None


# The walls that can hold a fluid's dynamic viscosity (no slip): the box's faces and the colliders
NO_SLIP_ROWS = ("-x", "+x", "-y", "+y", "-z", "+z", "colliders")


@dataclass(frozen=True)
class SolverParams:
    """Everything a solver needs. Every length is in metres."""
    particle_radius: float
    kernel_radius: float                        # support h of every kernel
    fluids: tuple[Fluid, ...]
    speed_of_sound: float                       # m/s, sets the Tait stiffness B = rho0 c^2 / gamma
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    domain_min: tuple[float, float, float] = (0.0, 0.0, 0.0)
    domain_max: tuple[float, float, float] = (1.0, 1.0, 1.0)
    open_faces: tuple[str, ...] = ()            # "-x" ... "+z": faces with no wall
    domain_restitution: float = 0.0
    domain_friction: float = 0.1
    no_slip: tuple[str, ...] = NO_SLIP_ROWS     # the walls that hold the dynamic viscosity (DFSPH)
    colliders: tuple[Collider, ...] = ()
    gamma: float = 7.0
    cfl: float = 0.4
    max_dt: float = 1.0 / 120.0
    surface_threshold: float = 0.4              # |grad c| h above which surface tension acts
    surface_tension_model: str = "mueller"      # "mueller" (color field) or "akinci" (2013; DFSPH)
    density_kernel: str = "poly6"
    pressure_kernel: str = "spiky"
    lattice: str = "cubic"                      # the fill's lattice (solver.lattice): "cubic" or "fcc"
    blocks: tuple[Block, ...] = ()              # the fluid blocks filled ("fcc": the lattice fits them)

    @property
    def spacing(self) -> float:
        """The cubic fill lattice's spacing, 2 particle radii: one particle per spacing^3 on
        either lattice."""
        return 2.0 * self.particle_radius

    @property
    def h(self) -> float:
        """The kernel support (the papers' h)."""
        return self.kernel_radius

    @property
    def density_kind(self) -> int:
        return K.DENSITY_KERNELS[self.density_kernel]

    @property
    def pressure_kind(self) -> int:
        return K.PRESSURE_KERNELS[self.pressure_kernel]

    @cached_property
    def lattice_density(self) -> float:
        """Number density sum_j W of the fill lattice: the rest state."""
        return K.lattice_number_density(self.density_kind, self.h, self.spacing, self.lattice,
                                        self.fill_domain.step)

    @cached_property
    def surface_deficit(self) -> tuple[float, float]:
        """(g, D) of the fill's flat top layer (kernels.surface_deficit), on the planes the fill
        lays, as lattice_density is: DFSPH's free-surface target is calibrated on it."""
        return K.surface_deficit(self.density_kind, self.h, self.spacing, self.lattice, self.fill_domain.step)

    @cached_property
    def fill_domain(self) -> Domain:
        """The fill's lattice over the domain, fitted to `blocks` (solver.lattice)."""
        return Domain(self.domain_min, self.domain_max, self.open_faces, self.spacing, self.lattice,
                      [(b.min, b.max) for b in self.blocks])

    @cached_property
    def grad_scale(self) -> float:
        """1 / the pressure kernel gradient's first moment on the cubic lattice (see kernels; WCSPH,
        which fills only that lattice)."""
        return 1.0 / K.lattice_gradient_moment(self.pressure_kind, self.h, self.spacing,
                                               K.lattice_number_density(self.density_kind, self.h, self.spacing))

    @cached_property
    def viscous_scale(self) -> float:
        """Morris's viscous term's moment on the cubic lattice over its moment on the fill's
        lattice (kernels.lattice_viscous_moment): 1 on the cubic fill, where the viscosity was
        checked against the analytic rates; 1.054 on the fcc one (cubic kernel), so that a
        viscosity reads there as it did on the cubic fill. (Not 1 / the moment: that would
        change the cubic fill's too, WCSPH's spiky kernel by 33 % on a lattice whose moment is
        0.75 against 0.96 in the continuum, which a disordered fluid comes close to.)"""
        return (K.lattice_viscous_moment(self.pressure_kind, self.h, self.spacing, "cubic")
                / K.lattice_viscous_moment(self.pressure_kind, self.h, self.spacing, self.lattice,
                                           self.fill_domain.step))

    @cached_property
    def fluid_table(self) -> np.ndarray:
        """(F, 8) float32: mass, rho0, B, mu, sigma, eta, xsph, 1 / mass (columns F_*). eta is
        the dynamic viscosity times `viscous_scale`, which every use of it (Morris's term, the
        walls' no-slip pull, the explicit limit) takes."""
        c = self.speed_of_sound
        return np.array([[f.rest_density / self.lattice_density, f.rest_density,
                          f.rest_density * c * c / self.gamma, f.viscosity, f.surface_tension,
                          f.dynamic_viscosity * self.viscous_scale, f.xsph,
                          self.lattice_density / f.rest_density]
                         for f in self.fluids], dtype=np.float32)

    @cached_property
    def collider_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(types (K,) int32, parameters (K, 11) float32, mesh distance grids flat float32)."""
        cf, ct, grids = [], [], []
        offset = 0
        for col in self.colliders:
            if col.kind == "mesh":
                g = col.sdf
                shape = [*g.origin, g.voxel, *g.phi.shape, offset]
                offset += g.phi.size
                grids.append(g.phi.ravel())
            else:
                shape = list(col.shape) + [0.0] * (8 - len(col.shape))
            cf.append(shape + [col.restitution, col.friction, -1.0 if col.container else 1.0])
            ct.append(COLLIDER_TYPES[col.kind])
        if not cf:  # Taichi ndarrays cannot be empty: one inert collider far away
            cf, ct = [[1e9, 1e9, 1e9, 1.0, 0, 0, 0, 0, 0, 0, 1.0]], [SPHERE]
        return (np.asarray(ct, np.int32), np.asarray(cf, np.float32),
                np.concatenate(grids or [np.zeros(1)]).astype(np.float32))
