"""The sim stage: run the solver through the shot's frames, writing frames and checkpoints.

The spec becomes the solver's parameters here (solver_params, fluid_blocks), and the solver's
errors become one-line stage errors. Resume: the stage starts from the latest checkpoint at or
before the first frame it must write (or from the initial fill), so a killed run continues
where its last checkpoint left it. Frames and checkpoints go to disk from a background thread
while the solver steps on (BackgroundWriter), in order, each published atomically.
"""
from __future__ import annotations

import logging
import signal
import time

import numpy as np

from solver.backend import BackendUnavailable, init_taichi
from solver.errors import NoParticles, TooLarge, Unstable
from solver.meshsdf import sample_sdf
from solver.params import Block, Collider, Fluid, SolverParams

from ..cache import check_file, stage_hashes, stamp
from ..errors import Interrupted, StageError
from ..formats import read_h5, write_frame, write_h5
from . import device_failed, device_failures

log = logging.getLogger("sphshot")
_STOP = {"signal": None}
FEWER = "use fewer particles (a larger sim.particle_radius or smaller fluid blocks)"


def _request_stop(signum, _frame):
    _STOP["signal"] = signal.Signals(signum).name


def solver_params(spec) -> SolverParams:
    """The solver's parameters for a shot: every length in metres, each mesh collider's signed
    distance sampled where particles can meet it."""
    sim = spec.sim
    colliders = []
    for ci, col in enumerate(spec.colliders):
        common = {"restitution": col.restitution, "friction": col.friction,
                  "container": col.mode == "container"}
        if col.type == "sphere":
            colliders.append(Collider("sphere", (*col.center, col.radius), **common))
        elif col.type == "box":
            colliders.append(Collider("box", (*col.min, *col.max), **common))
        elif col.type == "capsule":
            colliders.append(Collider("capsule", (*col.a, *col.b, col.radius), **common))
        else:
            verts, tris = spec.collider_mesh(ci)
            lo, hi = spec.sdf_box(verts, col)
            grid = sample_sdf(verts, tris, lo, hi, spec.collider_voxel_m(col), depth=spec.sdf_pad(col))
            colliders.append(Collider("mesh", **common, sdf=grid))
    return SolverParams(
        particle_radius=sim.particle_radius, kernel_radius=spec.kernel_radius_m,
        fluids=tuple(fluid(spec, fi) for fi in range(len(spec.fluids))),
        speed_of_sound=sim.speed_of_sound or 10.0 * spec.expected_max_speed(),
        gravity=tuple(sim.gravity), domain_min=tuple(spec.domain.min), domain_max=tuple(spec.domain.max),
        open_faces=tuple(spec.domain.open),
        domain_restitution=spec.domain.restitution, domain_friction=spec.domain.friction,
        no_slip=spec.domain.no_slip_walls,
        colliders=tuple(colliders), gamma=sim.gamma, cfl=sim.cfl, max_dt=sim.max_dt,
        surface_threshold=sim.surface_threshold, surface_tension_model=sim.surface_tension_model,
        density_kernel=sim.density_kernel,
        pressure_kernel=sim.pressure_kernel, lattice=sim.fill_lattice, blocks=tuple(fluid_blocks(spec)))


def fluid(spec, fi: int) -> Fluid:
    f = spec.fluids[fi]
    mu, eta = spec.fluid_viscosity(fi)
    return Fluid(rest_density=f.rest_density, viscosity=mu, surface_tension=f.surface_tension,
                 dynamic_viscosity=eta, xsph=f.xsph)


def fluid_blocks(spec) -> list[Block]:
    """Every fluid block of the shot, in the job file's order."""
    return [Block(fi, b.min, b.max, b.velocity) for fi, f in enumerate(spec.fluids) for b in f.blocks]


def initial_state(spec, params: SolverParams) -> dict:
    """The fluid blocks filled on the lattice (pre-compressed to hydrostatic density for the
    weakly compressible solver), colliders cut out."""
    from solver.fill import fill_blocks

    return fill_blocks(params, fluid_blocks(spec), compressible=spec.sim.solver == "wcsph")


def frame_attrs(spec, params: SolverParams, frame: int, solver, report: dict) -> dict:
    """The sim frame's attributes: time, sizes, fluids, and the solver's figures for the frame
    (DFSPH: iterations per step and final mean errors of both solves, with their bounds)."""
    return {"frame": frame, "time": spec.frame_time(frame), "particle_radius": spec.sim.particle_radius,
            "kernel_radius": spec.kernel_radius_m, "fluid_names": [f.name for f in spec.fluids],
            "fluid_rest_density": params.fluid_table[:, 1], "fluid_mass": params.fluid_table[:, 0],
            "solver": spec.sim.solver, "steps": solver.steps, "speed_of_sound": params.speed_of_sound,
            **report}


def make_solver(spec, params: SolverParams, state: dict, **controller):
    """The solver the spec names, on `state` (an initial fill or a checkpoint)."""
    from solver.dfsph import DFSPHSolver
    from solver.sph import SPHSolver

    if spec.sim.solver == "dfsph":
        return DFSPHSolver(params, state, **controller, max_density_error=spec.sim.max_density_error,
                           max_divergence_error=spec.sim.max_divergence_error,
                           max_iterations=spec.sim.max_iterations, expected_speed=spec.expected_max_speed())
    return SPHSolver(params, state, **controller)


def log_frame(frame: int, report: dict) -> None:
    if report:
        log.info("sim: frame %04d: %d steps; density solve %.1f iterations a step, error %.3g%% "
                 "(bound %.3g%%); divergence solve %.1f, error %.3g%% (bound %.3g%%)", frame,
                 report["dfsph_steps"], report["density_iterations"], 100 * report["density_error"],
                 100 * report["max_density_error"], report["divergence_iterations"],
                 100 * report["divergence_error"], 100 * report["max_divergence_error"])
        for solve, key in (("density", "max_density_error"), ("divergence", "max_divergence_error")):
            if report.get(f"{solve}_capped_steps"):
                log.warning("sim: frame %04d: the %s solve stopped at its cap (sim.max_iterations = %d) above its "
                            "bound on %d of %d steps (error up to %.3g%%, sim.%s %.3g%%): raise sim.max_iterations "
                            "or lower sim.max_dt", frame, solve, report["max_iterations"],
                            report[f"{solve}_capped_steps"], report["dfsph_steps"],
                            100 * report[f"{solve}_error"], key, 100 * report[key])
        if report.get("viscosity_steps"):
            log.info("sim: frame %04d: viscosity implicit on %d steps, %.1f CG iterations a step, residual %.2g",
                     frame, report["viscosity_steps"], report["viscosity_iterations"], report["viscosity_residual"])


def place(spec, params: SolverParams, point) -> str:
    """', at (x, y, z) m, D mm from (or inside) <the nearest solid>' for an error message ('' without a
    point): the domain's nearest wall or the nearest collider, named as the job names it."""
    if point is None or not np.isfinite(point).all():
        return ""
    import dataclasses

    from solver.boundaries import collider_clearance

    p = np.asarray(point, np.float64)
    lo, hi = np.array(spec.domain.min), np.array(spec.domain.max)
    gaps = np.concatenate([p - lo, hi - p])
    k = int(np.argmin(gaps))
    best, name = float(gaps[k]), f"the domain's {'+' if k >= 3 else '-'}{'xyz'[k % 3]} wall"
    for ci, col in enumerate(spec.colliders):
        one = dataclasses.replace(params, colliders=(params.colliders[ci],))
        d = float(collider_clearance(one, p[None].astype(np.float32))[0])
        if d < best:
            what = f"mesh {col.path}" if col.type == "mesh" else col.type
            best, name = d, f"colliders[{ci}] ({what})"
    return f", at ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m, {1000 * abs(best):.1f} mm {'inside' if best < 0 else 'from'} {name}"


def check_stable(spec, params: SolverParams, frame: int, data: dict) -> None:
    """Stop with a clear message when the state has blown up; frames before stay on disk."""
    where = f"frame {frame:04d}: sim unstable"
    if not np.isfinite(data["position"]).all() or not np.isfinite(data["velocity"]).all():
        raise StageError(f"{where}: NaN/inf in particle state; lower sim.cfl or sim.max_dt")
    lo, hi = np.array(spec.domain.min), np.array(spec.domain.max)
    out = ((data["position"] < lo - 1e-4) | (data["position"] > hi + 1e-4)).any(axis=1)
    if out.any():
        raise StageError(f"{where}: {int(out.sum())} particle(s) escaped the domain; lower sim.cfl")
    rho0 = params.fluid_table[data["fluid"], 1]
    ratio = float(np.max(data["density"] / rho0)) if len(rho0) else 1.0
    if ratio > spec.sim.max_density_ratio:
        hint = "raise sim.speed_of_sound or lower sim.cfl" if spec.sim.solver == "wcsph" else \
            "lower sim.max_density_error or sim.cfl"
        at = place(spec, params, data["position"][int(np.argmax(data["density"] / rho0))])
        raise StageError(f"{where}: density reached {ratio:.2f}x rest{at} (bound sim.max_density_ratio = "
                         f"{spec.sim.max_density_ratio}); {hint}")


def build_solver(spec, paths, first_frame: int):
    """A solver at the latest checkpoint before first_frame, or at the initial fill."""
    params = solver_params(spec)
    current = stage_hashes(spec)["sim"]
    ckpts = [c for c in paths.checkpoints() if c < first_frame and check_file(paths.checkpoint(c), current) == "valid"]
    if ckpts:
        frame = ckpts[-1]
        data, attrs = read_h5(paths.checkpoint(frame))
        solver = make_solver(spec, params, data, time_s=attrs["time"], step=attrs["step"],
                             dt_prev=attrs["dt_prev"])
        log.info("sim: resuming from checkpoint at frame %d (t = %.4f s, step %d)", frame,
                 attrs["time"], attrs["step"])
        return params, solver, frame
    _params, solver = fresh_solver(spec, params)
    log.info("sim: %s, %d particles, h = %.4g m", spec.sim.solver, solver.n, params.h)
    return params, solver, None


def fresh_solver(spec, params: SolverParams | None = None) -> tuple[SolverParams, object]:
    """(params, solver) at the shot's first frame, the fluid blocks just filled: what the stage
    starts from without a checkpoint (benches and tests start here too). `params`: the spec's
    solver_params where the caller has them already (a mesh collider's are costly)."""
    params = params or solver_params(spec)
    return params, make_solver(spec, params, initial_state(spec, params))


class BackgroundWriter:
    """Writes files on one thread beside the solver, in submission order, so the GPU steps on
    while a frame goes to disk; at most MAX_PENDING writes wait (each holds a frame's arrays).
    A write's `done(result)` runs on the writer thread right after it (the frame is stamped and
    reported as soon as it is published: a kill then loses no finished frame); write errors
    come back on the calling thread, in order, at the next submit, drain or close."""
    MAX_PENDING = 2

    def __init__(self):
        from concurrent.futures import ThreadPoolExecutor
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="sphshot-writer")
        self._pending: list = []

    def submit(self, fn, *args, done=None) -> None:
        def task():
            result = fn(*args)
            if done is not None:
                done(result)
        self._pending.append(self._pool.submit(task))
        self._collect(wait_for=len(self._pending) - self.MAX_PENDING)

    def drain(self) -> None:
        """Wait for every write so far (raising the first write error)."""
        self._collect(wait_for=len(self._pending))

    def _collect(self, wait_for: int) -> None:
        while self._pending and (wait_for > 0 or self._pending[0].done()):
            future = self._pending.pop(0)
            wait_for -= 1
            future.result()

    def close(self, quiet: bool = False) -> None:
        """Wait for every write; `quiet`: while another error is on its way, drop write errors."""
        try:
            self.drain()
        except Exception:
            if not quiet:
                raise
        finally:
            self._pool.shutdown(wait=True)


def remove_leaving(spec, params: SolverParams, solver, frame: int):
    """The solver without the particles that have left through an open face of the domain (a
    new solver on the rest of the state, same clock), and the count in the log."""
    from solver.sph import left_through_open_faces

    gone = left_through_open_faces(params, solver.position.to_numpy())     # (the state's order)
    if not gone.any():
        return solver
    if gone.all():
        raise StageError(f"frame {frame:04d}: sim: every particle has left the domain through its open "
                         f"face(s) {', '.join(params.open_faces)}")
    c = solver.controller()
    kept = make_solver(spec, params, {k: v[~gone] for k, v in solver.state().items()}, time_s=c["time"], step=c["step"],
                       dt_prev=c["dt_prev"])
    log.info("sim: frame %04d: %d particle(s) left through the open face(s) %s and were removed; %d remain",
             frame, int(gone.sum()), " ".join(params.open_faces), kept.n)
    return kept


def write_checkpoint(paths, frame: int, solver, stage_hash: str, writer: BackgroundWriter | None = None) -> None:
    """The solver's state (read from the device now), written now or by `writer`, and stamped
    with the sim's parameter hash: a resume takes only checkpoints made with the current
    parameters (build_solver)."""
    path, state, attrs = paths.checkpoint(frame), solver.state(), {"frame": frame, **solver.controller()}

    def write() -> None:
        stamp(write_h5(path, state, attrs), stage_hash)
    if writer is None:
        write()
    else:
        writer.submit(write)


def run(spec, frames, paths, progress) -> None:
    try:
        init_taichi(spec.sim.backend, spec.sim.threads)
    except BackendUnavailable as exc:
        raise StageError(str(exc)) from exc

    todo = sorted(frames)
    last = todo[-1]
    stage_hash = stage_hashes(spec)["sim"]
    try:
        with device_failures("sim: setting up", "use fewer particles"):
            params, solver, ckpt_frame = build_solver(spec, paths, todo[0])
    except TooLarge as exc:
        raise StageError(f"sim: {exc}; {FEWER}") from exc
    except NoParticles as exc:
        raise StageError(f"sim: {exc}") from exc
    start = spec.shot.frame_start if ckpt_frame is None else ckpt_frame
    if ckpt_frame is None:
        data = solver.snapshot()
        if start in todo or not paths.sim_frame(start).exists():
            progress.frame_done(start, [write_frame(paths.sim_frame(start), data,
                                                    frame_attrs(spec, params, start, solver, {}))])
        write_checkpoint(paths, start, solver, stage_hash)

    previous = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGUSR1)}
    for s in previous:
        signal.signal(s, _request_stop)
    _STOP["signal"] = None
    wall0, steps0 = time.perf_counter(), solver.steps
    writer = BackgroundWriter()
    frame = start + 1                  # (named by an error raised before the loop's first frame)
    try:
        for frame in range(start + 1, last + 1):
            try:
                done = solver.advance_to(spec.frame_time(frame), should_stop=lambda: _STOP["signal"] is not None)
            except Unstable as exc:
                raise StageError(f"frame {frame:04d}: sim unstable: {exc}{place(spec, params, exc.where)}; "
                                 f"lower sim.cfl or sim.max_dt") from exc
            except TooLarge as exc:     # particles crowding together: usually a blow-up too
                raise StageError(f"frame {frame:04d}: sim: {exc}; {FEWER}") from exc
            if not done:
                # checkpoint named after the last finished frame, holding the exact mid-frame state
                writer.drain()
                write_checkpoint(paths, frame - 1, solver, stage_hash)
                raise Interrupted(f"sim: stopped by {_STOP['signal']} during frame {frame:04d}; "
                                  f"checkpoint written, run again to resume")
            report = solver.frame_report()
            if params.open_faces:
                solver = remove_leaving(spec, params, solver, frame)
            data = solver.snapshot()
            check_stable(spec, params, frame, data)
            log_frame(frame, report)
            if frame in todo or not paths.sim_frame(frame).exists():
                # written beside the next frame's steps; stamped and reported once on disk
                writer.submit(write_frame, paths.sim_frame(frame), data,
                              frame_attrs(spec, params, frame, solver, report),
                              done=lambda path, f=frame: progress.frame_done(f, [path]))
            if (frame - spec.shot.frame_start) % spec.shot.checkpoint_every == 0 or frame == last:
                write_checkpoint(paths, frame, solver, stage_hash, writer)
    except BaseException as exc:
        writer.close(quiet=True)       # the frames before the error still reach the disk
        failure = device_failed(exc, f"frame {frame:04d}: sim", "the frames before it are kept: run again "
                                "to resume from the last checkpoint")
        if failure is not None:
            raise failure from exc
        raise
    else:
        writer.close()
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
    wall = time.perf_counter() - wall0
    steps = solver.steps - steps0
    if steps:
        log.info("sim: %d steps, %.3g particle-steps/s, %.3g simulated s per wall s", steps,
                 solver.n * steps / wall, (solver.time - spec.frame_time(start)) / wall)
