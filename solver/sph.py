"""A weakly compressible SPH solver (Müller, Charypar & Gross 2003, Tait's equation of state).

One step, as in the paper; each phase is one or a few kernel launches, timed:
  1. neighbours   Verlet lists of the pairs within h + skin, rebuilt only once some particle has
                  moved skin/2 since the last build (solver/neighbours.py)
  2. density      number density, density and Tait pressure (solver/wcsph.py)
  3. forces       pressure, viscosity, surface tension, gravity and the walls' pressure
  4. time step    CFL, force and viscous limits, clamped to land on the next frame time
  5. integrate    leapfrog kick and drift
  6. collide      project out of colliders and the domain, restitution and Coulomb friction
                  (solver/boundaries.py)

Kernels are pure: every array and scalar comes in as an argument (Taichi ndarrays), so the same
compiled kernels serve every particle count and no field lives at module level.
"""
import math
import time
from dataclasses import dataclass, field

import numpy as np
import taichi as ti

from . import kernels as K
from .backend import current_arch
from . import clock
from .boundaries import collider_arrays, k_collide
from .errors import TooLarge, Unstable
from .neighbours import (CELL_DIV, GROUP, SCAN_BLOCK, SKIN, exclusive_scan, k_clear2, k_count, k_gather, k_moved_beyond,
                         k_neighbours, k_rebuild, k_scatter)
from .params import F_ETA, F_MU, F_RHO0, F_SIGMA, SolverParams
from .stability import explicit_viscous_limit
from .types import ivec2, ivec3, pack_constants, vec3
from .wcsph import k_advance, k_density, k_forces, k_step, k_synced_velocity

# A step shorter than this fraction of the acoustic CFL step means the state has blown up. The
# three example shots at their own resolution, all frames, never went below 0.75 of it.
MIN_DT_FRACTION = 1e-3
MAX_LIST_ENTRIES = 2 ** 31 - 1     # Taichi's ndarray index is int32
# On the CPU the passes after the density pass read the pairs within h (`near`, and DFSPH's
# `gfac`) in rows as wide as the longest list rounded up to this, not the Verlet lists' room
# (1.5 times a lattice's pairs plus a skin, grown by a quarter on overflow): on bench/solver.py's
# DFSPH dam break at 0.15 s, rows of 44 where the room is 64 (28.6 entries on average) made a
# density sweep's kappa and apply passes 0.77-0.88 of their time, and whole steps 0.80 (2-core
# AMD EPYC; bench/RESULTS.md, forty-second session): the memory a pass walks, not its arithmetic.
NEAR_ROUND = 4


@dataclass
class PhaseTimer:
    """Wall time per step phase (synchronised), for logs and benchmarks."""
    totals: dict[str, float] = field(default_factory=dict)

    def add(self, name: str, seconds: float) -> None:
        self.totals[name] = self.totals.get(name, 0.0) + seconds


class SPHSolver:
    """One data-oriented solver: struct-of-arrays particle state and its step.

    State (Taichi ndarrays, N particles, kept sorted by grid cell):
      position        (N,3) x_n, m
      velocity        (N,3) half-step velocity v_{n-1/2}, m/s
      acceleration    (N,3) last acceleration a_{n-1}, m/s^2 (for the synchronised output velocity)
      fluid           (N,)  fluid index into the fluid table
      id              (N,)  particle id, stable over the shot
      number_density  (N,)  delta = sum_j W, 1/m^3
      density         (N,)  rho = m_i delta_i, kg/m^3
      pressure        (N,)  Tait pressure, Pa
      ref             (N,3) positions when the neighbour lists were last built
    Controller state: time t, step count, dt_prev (dt_{n-1/2}).

    Neighbour lists (Verlet lists) hold every pair within h + skin at the reference positions.
    They stay complete while no particle has moved skin/2 from its reference position, so they
    (and the sort by cell) are rebuilt only when one has: about every few steps instead of
    every step. The lists are a function of the reference positions, which checkpoints keep,
    so a resumed run rebuilds exactly the lists it had.
    """

    KEEP = 0.5      # particle centres stay this many radii from any wall or collider
    INTERLEAVED_LISTS: bool | None = None     # None: by the backend (see _grow_neighbours)
    BATCH: int | None = None                  # gated steps per read of the controller; None: by the backend
    FUSED: bool | None = None                 # a step, and a list rebuild, in one launch each (wcsph.k_step,
                                              # neighbours.k_rebuild); None: on a GPU
    LISTS_CHECKED_AT_ONCE = False             # WCSPH: an overflow is read with the controller, after the batch
    GROUPED: bool | None = None               # lists a cell's particles GROUP at a time, over cells h + skin
                                              # wide (neighbours.grouped_list_pass); None: on the CPU
    SKIN = SKIN                               # Verlet skin in units of h (neighbours.SKIN)

    def __init__(self, params: SolverParams, state: dict[str, np.ndarray], time_s: float = 0.0,
                 step: int = 0, dt_prev: float = 0.0):
        self.params = params
        n = len(state["position"])
        self.n = n
        self.time = float(time_s)
        self.steps = int(step)
        self.dt_prev = float(dt_prev)
        self.timer = PhaseTimer()
        h = params.h
        self.h = h
        self.origin = vec3(*params.domain_min)
        size = np.array(params.domain_max) - np.array(params.domain_min)
        self.skin = self.SKIN * h
        self.on_cpu = current_arch() == "cpu"
        grouped = self.on_cpu if self.GROUPED is None else self.GROUPED
        self.list_group = GROUP if grouped else 1
        cell = (h + self.skin) / (1 if grouped else CELL_DIV)        # the lists reach h + skin
        dims = np.maximum(np.ceil(size / cell).astype(int), 1)
        self.dims = ivec3(*map(int, dims))
        self.n_cells = int(np.prod(dims))
        self.inv_cell = 1.0 / cell

        def v3():
            return ti.Vector.ndarray(3, ti.f32, shape=n)

        self.position, self.velocity, self.acceleration, self.ref = v3(), v3(), v3(), v3()
        self.position_b, self.velocity_b, self.acceleration_b, self.ref_b = v3(), v3(), v3(), v3()
        self.fluid, self.id = ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, n)
        self.fluid_b, self.id_b = ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, n)
        self.number_density, self.density, self.pressure = (ti.ndarray(ti.f32, n) for _ in range(3))
        self.cell, self.order = ti.ndarray(ti.i32, n), ti.ndarray(ti.i32, n)
        self.velocity_out = v3()
        self.count = ti.ndarray(ti.i32, self.n_cells)
        self.start = ti.ndarray(ti.i32, self.n_cells)
        self.fill = ti.ndarray(ti.i32, self.n_cells)
        self._scan_buffers: dict[int, object] = {}
        self._fused_sums = None               # k_rebuild's (see _block_sums)
        self.stats = ti.ndarray(ti.f32, 3)    # WCSPH: max speed, acceleration; DFSPH: k_nonpressure's
        self.moved = ti.ndarray(ti.i32, 1)    # 1: a particle moved skin/2 from its reference position
        # the step's controller on the device (clock.py), and a gate that stays open
        self.ctl, self.open_gate = ti.ndarray(ti.f64, clock.SIZE), ti.ndarray(ti.f64, clock.SIZE)
        self.open_gate.fill(1.0)
        self._moved: bool | None = None       # the last batch's MOVED, while still current
        self._built_at, self._life = self.steps, 1     # when the lists were built, how long the last lasted
        # neighbour lists: room for 1.5x the fill lattice's pairs within h + skin, grown on overflow
        self.nb_cap = 0
        self.fused = (not self.on_cpu) if self.FUSED is None else self.FUSED
        self._grow_neighbours(int(1.5 * 4.0 / 3.0 * math.pi * ((h + self.skin) / params.spacing) ** 3) + 8)
        self.lists_built = 0

        self.ftab = _ndarray(params.fluid_table)
        self.ctype, self.cprm, self.sdf = collider_arrays(params)
        ghost_t, ghost_g = K.ghost_tables(params.density_kind, params.pressure_kind, h, params.particle_radius)
        self.ghost_t, self.ghost_g = _ndarray(ghost_t), _ndarray(ghost_g)
        self.ghost_mom = _ndarray(K.ghost_moment_tables(params.pressure_kind, h, params.particle_radius))
        self.position.from_numpy(state["position"].astype(np.float32))
        self.velocity.from_numpy(state["velocity"].astype(np.float32))
        self.acceleration.from_numpy(state.get("acceleration", np.zeros((n, 3), np.float32)).astype(np.float32))
        self.fluid.from_numpy(state["fluid"].astype(np.int32))
        self.id.from_numpy(state["id"].astype(np.int32))
        # a checkpoint's reference positions give back its lists; without them, build afresh
        self._lists_from_ref = "position_ref" in state
        if self._lists_from_ref:
            self.ref.from_numpy(state["position_ref"].astype(np.float32))
        self._lists_valid = False
        lo, hi = open_box(params)
        self.prm = _ndarray(np.asarray(pack_constants(
            h=h, gravity=params.gravity, gamma=params.gamma, lattice=params.lattice_density,
            grad_scale=params.grad_scale, threshold=params.surface_threshold, lo=lo, hi=hi,
            restitution=params.domain_restitution, friction=params.domain_friction,
            keep=self.KEEP * params.particle_radius), np.float32))
        table = params.fluid_table
        self.dt_visc = explicit_viscous_limit(h, np.maximum(table[:, F_MU], table[:, F_ETA]) / table[:, F_RHO0])
        self.vmax = 0.0
        self.amax = 0.0
        self.tension = bool((params.fluid_table[:, F_SIGMA] > 0).any())   # compile the color field in?
        ctl = np.zeros(clock.SIZE)
        ctl[[clock.TIME, clock.DT_PREV, clock.STEPS]] = self.time, self.dt_prev, self.steps
        hs = 0.5 * h
        ctl[[clock.CFL_HS, clock.HS, clock.SOUND, clock.MIN_DT, clock.CAP]] = (
            params.cfl * hs, hs, params.speed_of_sound, MIN_DT_FRACTION * params.cfl * hs / params.speed_of_sound,
            min(self.dt_visc, params.max_dt))
        self.ctl.from_numpy(ctl)

    # ----------------------------------------------------------------------------- phases
    def build_lists(self, from_position: bool = False) -> None:
        """Sort the particles by the cell of their reference position (a counting sort: count,
        scan, scatter, gather) and list the pairs within h + skin there; `from_position`: the
        reference positions are the current ones first. Fused, all in one launch."""
        if self.fused:
            sums = self._block_sums()
            k_rebuild(self.position, self.ref, self.velocity, self.acceleration, self.fluid, self.id,
                      self.position_b, self.ref_b, self.velocity_b, self.acceleration_b, self.fluid_b, self.id_b,
                      self.cell, self.count, self.fill, self.start, self.order, *sums,
                      self.verlet, self.verlet_count, self.nb_cap, self.lay, self.rows, self.h + self.skin, self.origin,
                      self.inv_cell, self.dims, self.ctl, clock.OVERFLOW, self.n_cells,
                      *(a.shape[0] for a in sums), from_position, self.list_group)
            self._swap_sorted()
        else:
            if from_position:
                self.ref.copy_from(self.position)
            self._sort()
            self.list_pairs()
        while self.LISTS_CHECKED_AT_ONCE and self._overflowed():
            self.list_pairs()
        if self.rows:      # `near`'s rows as wide as the longest list (NEAR_ROUND)
            longest = int(self.read(self.ctl, clock.LONGEST))
            self.near_lay = ivec2(min(max(-(-longest // NEAR_ROUND), 1) * NEAR_ROUND, self.nb_cap), 1)
        self.lists_built += 1
        self._life, self._built_at = self.steps - self._built_at, self.steps     # see batch()

    def _sort(self) -> None:
        k_clear2(self.count, self.fill)
        k_count(self.ref, self.cell, self.count, self.origin, self.inv_cell, self.dims)
        exclusive_scan(self.count, self.start, self.n_cells, self._scan_buffer)
        k_scatter(self.cell, self.start, self.count, self.fill, self.order)
        k_gather(self.order, self.position, self.ref, self.velocity, self.acceleration, self.fluid, self.id,
                 self.position_b, self.ref_b, self.velocity_b, self.acceleration_b, self.fluid_b, self.id_b)
        self._swap_sorted()

    def _swap_sorted(self) -> None:
        """The sorted copies (*_b) become the particle arrays."""
        for name in ("position", "ref", "velocity", "acceleration", "fluid", "id"):
            a, b = getattr(self, name), getattr(self, name + "_b")
            setattr(self, name, b)
            setattr(self, name + "_b", a)

    def list_pairs(self) -> None:
        """The Verlet lists at the sorted reference positions; a list longer than the room
        leaves its length in the controller's OVERFLOW, which keeps the step gate closed."""
        k_neighbours(self.ref, self.verlet, self.verlet_count, self.nb_cap, self.lay, self.rows, self.h + self.skin,
                     self.start, self.count, self.origin, self.inv_cell, self.dims, self.ctl, clock.OVERFLOW,
                     self.list_group)

    def read(self, a, k: int | None = None):
        """The values of a small array (a controller, a count), or its element k, synced. On the
        CPU element by element: to_numpy launches a copy kernel and costs the host about 115 us
        however short the array, an element 8 (measured on the 2-core CPU; bench/RESULTS.md,
        thirty-ninth session), and a DFSPH step reads six or seven such arrays."""
        if k is not None:
            return a[k] if self.on_cpu else a.to_numpy()[k]
        if self.on_cpu:
            return [a[i] for i in range(a.shape[0])]
        return a.to_numpy().tolist()

    def _overflowed(self, longest: float | None = None) -> bool:
        """If the last lists overflowed, make room for 1.25x the longest and say so."""
        if longest is None:
            longest = float(self.read(self.ctl, clock.OVERFLOW))
        if longest <= 0:
            return False
        self._grow_neighbours(int(1.25 * longest) + 8)
        return True

    def update_lists(self) -> None:
        """Rebuild the neighbour lists if a particle moved skin/2 from its reference position
        (two such particles may then be within h but not listed)."""
        if self._lists_valid:
            moved, self._moved = self._moved, None
            if moved is None:         # not known from the last batch of steps: look
                self.moved.fill(0)
                k_moved_beyond(self.position, self.ref, 0.5 * self.skin, self.moved)
                moved = int(self.read(self.moved, 0)) != 0
            if not moved:
                return
        from_position, self._lists_from_ref = not self._lists_from_ref, False
        self.build_lists(from_position)
        self._lists_valid = True

    def _block_sums(self):
        """k_rebuild's cell-scan totals: one per SCAN_BLOCK cells, and one per SCAN_BLOCK of those
        (made on the first fused rebuild, kept: the grid's size never changes)."""
        if self._fused_sums is None:
            n_blocks = -(-self.n_cells // SCAN_BLOCK)
            self._fused_sums = (ti.ndarray(ti.i32, n_blocks), ti.ndarray(ti.i32, -(-n_blocks // SCAN_BLOCK)))
        return self._fused_sums

    def _scan_buffer(self, level: int, size: int):
        """The cell scan's totals at one level (kept: the grid's size never changes)."""
        if level not in self._scan_buffers:
            self._scan_buffers[level] = ti.ndarray(ti.i32, max(size, 1))
        return self._scan_buffers[level]

    def _grow_neighbours(self, cap: int) -> None:
        cap = -(-cap // 8) * 8
        if self.n * cap > MAX_LIST_ENTRIES:
            raise TooLarge(f"{self.n:,} particles with up to {cap} neighbours each need neighbour lists "
                           f"of {self.n * cap:,} entries, over the limit of {MAX_LIST_ENTRIES:,}")
        self.nb_cap = cap
        # list entry m of particle i at i * lay.x + m * lay.y: each particle's list contiguous on
        # the CPU (one thread walks it through its cache), interleaved on a GPU (the threads of
        # a warp read entry m of 32 particles from one memory line: coalesced loads)
        interleave = (not self.on_cpu) if self.INTERLEAVED_LISTS is None else self.INTERLEAVED_LISTS
        self.lay = ivec2(1, self.n) if interleave else ivec2(cap, 1)
        self.rows = not interleave         # the kernels' compile-time flag for it (neighbours.list_step)
        self.verlet = ti.ndarray(ti.i32, max(self.n * cap, 1))     # within h + skin at `ref`
        self.verlet_count = ti.ndarray(ti.i32, self.n)
        self.near = ti.ndarray(ti.i32, max(self.n * cap, 1))      # within h now (a subset)
        self.near_count = ti.ndarray(ti.i32, self.n)
        self.near_lay = self.lay       # `near`'s rows: on the CPU narrower once built (build_lists)

    def compute_density(self, gate=None) -> None:
        k_density(self.position, self.fluid, self.number_density, self.density, self.pressure,
                  self.verlet, self.verlet_count, self.near, self.near_count, self.lay, self.near_lay, self.rows,
                  self.prm, self.ftab, self.ghost_t, self.ghost_g,
                  self.ctype, self.cprm, self.sdf, self.open_gate if gate is None else gate,
                  self.params.density_kind)

    def compute_forces(self) -> None:
        """Accelerations, then the step length on the device (wcsph.time_step): CFL (sound +
        flow speed), force and viscous limits, capped by max_dt, landed on the target time. A
        step under MIN_DT_FRACTION of the acoustic CFL step means the accelerations have blown
        up (stepping on either crawls -- every particle pushed into one corner ran for over ten
        minutes on one frame -- or flings particles apart): the controller says UNSTABLE and
        pull_clock raises."""
        k_forces(self.position, self.velocity, self.acceleration, self.fluid, self.number_density,
                 self.density, self.pressure, self.near, self.near_count, self.near_lay, self.rows,
                 self.prm, self.ftab, self.ghost_t, self.ghost_g, self.ghost_mom,
                 self.ctype, self.cprm, self.sdf, self.stats, self.ctl, self.params.pressure_kind, self.tension)

    def advance(self) -> None:
        k_advance(self.position, self.velocity, self.acceleration, self.ref, 0.5 * self.skin,
                  self.prm, self.ctype, self.cprm, self.sdf, self.ctl)

    def collide(self) -> None:
        k_collide(self.position, self.velocity, self.prm, self.ctype, self.cprm, self.sdf)

    # ------------------------------------------------------------------------------- step
    def gated_step(self, run) -> None:
        """One WCSPH step, every launch gated on the controller (clock.py): nothing here reads
        back to the host."""
        run("density", self.compute_density, self.ctl)
        run("forces", self.compute_forces)
        run("integrate", self.advance)

    def step(self, t_target: float | None = None, timed: bool = False) -> float:
        """One substep; never steps past t_target. Returns dt."""
        run = self.phase_runner(timed)
        steps = self.steps
        while self.steps == steps:      # (again after lists that overflowed: no step was taken)
            run("neighbours", self.update_lists)
            clock.k_arm(self.ctl, clock.NEVER if t_target is None else t_target)
            self.gated_step(run)
            self.pull_clock()
        return self.dt_prev

    def advance_some(self, t_target: float) -> None:
        """batch() gated steps towards t_target, then one read of the controller."""
        self.update_lists()
        clock.k_arm(self.ctl, t_target)
        run = self.phase_runner(False)
        for _ in range(self.batch()):
            if self.fused:
                self.fused_step()
            else:
                self.gated_step(run)
        self.pull_clock()

    def fused_step(self) -> None:
        """One gated step in one launch (wcsph.k_step)."""
        k_step(self.position, self.velocity, self.acceleration, self.ref, self.fluid, self.number_density,
               self.density, self.pressure, self.verlet, self.verlet_count, self.near, self.near_count, self.lay,
               self.near_lay, self.rows, self.prm, self.ftab, self.ghost_t, self.ghost_g, self.ghost_mom, self.ctype,
               self.cprm, self.sdf, self.stats, self.ctl, 0.5 * self.skin, self.params.density_kind,
               self.params.pressure_kind, self.tension)

    def batch(self) -> int:
        """Gated steps to launch before the next read: on a GPU, about as many as the current
        lists have left if they last as long as the last ones did, and a quarter of that once
        they outlive it (steps launched after the gate closes do nothing and cost the device a
        few microseconds each); on the CPU one, since a launch there waits for its kernel anyway
        and reading the controller costs nothing."""
        if self.BATCH is not None:
            return self.BATCH
        if self.on_cpu:
            return 1
        return min(max(self._life - (self.steps - self._built_at), self._life // 4, 1), 32)

    def pull_clock(self) -> None:
        """Read the controller: time, steps, the last dt and whether the lists must be rebuilt
        (moved, or overflowed: then larger). Raises Unstable if the step blew up."""
        c = self.ctl.to_numpy()
        self.time, self.dt_prev, self.steps = float(c[clock.TIME]), float(c[clock.DT_PREV]), int(c[clock.STEPS])
        self.vmax, self.amax = float(c[clock.VMAX]), float(c[clock.AMAX])
        self._moved = bool(c[clock.MOVED] > 0.5) or self._overflowed(float(c[clock.OVERFLOW]))
        if c[clock.UNSTABLE] > 0.5:
            if not (math.isfinite(self.vmax) and math.isfinite(self.amax)):
                raise Unstable(NOT_FINITE, where=self.fastest_position())
            raise Unstable(f"the time step fell to {c[clock.DT]:.3g} s (max acceleration {self.amax:.3g} m/s^2, "
                           f"max speed {self.vmax:.3g} m/s)", where=self.fastest_position())

    def fastest_position(self) -> tuple[float, float, float]:
        """The fastest particle's position (m; a non-finite speed counts as fastest), for an
        error message: it reads the particle arrays back."""
        v = self.velocity.to_numpy().astype(np.float64)
        speed = np.einsum("ij,ij->i", v, v)
        i = int(np.argmax(np.where(np.isfinite(speed), speed, np.inf)))
        return tuple(float(x) for x in self.position.to_numpy()[i])

    def phase_runner(self, timed: bool):
        """run(name, fn, *args): calls fn, and with `timed` adds its synchronised wall time
        to self.timer under name."""
        return self._timed if timed else (lambda _name, fn, *args: fn(*args))

    def _timed(self, name: str, fn, *args):
        ti.sync()
        t0 = time.perf_counter()
        out = fn(*args)
        ti.sync()
        self.timer.add(name, time.perf_counter() - t0)
        return out

    def advance_to(self, t_target: float, should_stop=None) -> bool:
        """Step until t_target. Returns False if should_stop() asked to stop early."""
        while self.time < t_target - 1e-9:
            self.advance_some(t_target)
            if should_stop is not None and should_stop():
                return self.time >= t_target - 1e-9
        self.time = max(self.time, t_target) if abs(self.time - t_target) < 1e-9 else self.time
        return True

    # --------------------------------------------------------------------------- read out
    def refresh_fields(self) -> None:
        """Density and pressure for the current positions (after the last integrate)."""
        self.update_lists()
        self.compute_density()

    def snapshot(self) -> dict[str, np.ndarray]:
        """Frame data at the current time, ordered by particle id."""
        self.refresh_fields()
        velocity = self.output_velocity()
        ids = self.id.to_numpy()
        order = np.argsort(ids, kind="stable")
        return {"position": self.position.to_numpy()[order], "velocity": velocity.to_numpy()[order],
                "density": self.density.to_numpy()[order], "pressure": self.pressure.to_numpy()[order],
                "id": ids[order], "fluid": self.fluid.to_numpy()[order]}

    def output_velocity(self):
        """Velocity at the current time: the leapfrog's half-step velocity plus half a step of
        the last acceleration."""
        k_synced_velocity(self.velocity, self.acceleration, 0.5 * self.dt_prev, self.velocity_out)
        return self.velocity_out

    def frame_report(self) -> dict[str, float]:
        """Solver figures for the frame just finished (none for WCSPH)."""
        return {}

    def state(self) -> dict[str, np.ndarray]:
        """Full state in the solver's own order, for bit-exact checkpoints."""
        out = {"position": self.position.to_numpy(), "velocity": self.velocity.to_numpy(),
               "acceleration": self.acceleration.to_numpy(), "fluid": self.fluid.to_numpy(),
               "id": self.id.to_numpy()}
        if self._lists_valid or self._lists_from_ref:
            out["position_ref"] = self.ref.to_numpy()
        return out

    def controller(self) -> dict[str, float]:
        return {"time": self.time, "step": self.steps, "dt_prev": self.dt_prev}


# What a solver says when a particle's speed or acceleration is NaN or infinite (types.raise_max
# counts a NaN as +inf, so it reaches the maxima the step is set from).
NOT_FINITE = "a particle's speed or acceleration is not a finite number (NaN or inf)"

OPEN_FAR = 1e6     # m: where an open face's wall goes (no wall samples, no collision)


def open_box(params: SolverParams) -> tuple[list[float], list[float]]:
    """The walls' box: the domain, with each open face moved out of reach."""
    lo, hi = list(params.domain_min), list(params.domain_max)
    for face in params.open_faces:
        ax = "xyz".index(face[1])
        if face[0] == "-":
            lo[ax] = -OPEN_FAR
        else:
            hi[ax] = OPEN_FAR
    return lo, hi


def left_through_open_faces(params: SolverParams, position: np.ndarray) -> np.ndarray:
    """Mask of the particles outside the domain past an open face."""
    out = np.zeros(len(position), bool)
    for face in params.open_faces:
        ax = "xyz".index(face[1])
        out |= position[:, ax] < params.domain_min[ax] if face[0] == "-" else position[:, ax] > params.domain_max[ax]
    return out


def _ndarray(a: np.ndarray):
    nd = ti.ndarray(ti.f32, a.shape)
    nd.from_numpy(a)
    return nd
