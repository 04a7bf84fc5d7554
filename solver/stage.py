"""The sim stage: run the solver through the shot's frames, writing frames and checkpoints.

Resume: the stage starts from the latest checkpoint at or before the first frame it must
write (or from the initial fill), so a killed run continues where its last checkpoint left it.
"""
from __future__ import annotations

import logging
import math
import signal
import time

import numpy as np

from pipeline.errors import Interrupted, StageError
from pipeline.particles import read_h5, write_frame, write_h5

from .backend import BackendUnavailable, init_taichi

log = logging.getLogger("sphshot")
_STOP = {"signal": None}


def _request_stop(signum, _frame):
    _STOP["signal"] = signal.Signals(signum).name


def frame_attrs(spec, cfg, frame: int, solver) -> dict:
    return {"frame": frame, "time": spec.frame_time(frame), "particle_radius": spec.sim.particle_radius,
            "kernel_radius": spec.smoothing_radius, "fluid_names": [f.name for f in spec.fluids],
            "fluid_rest_density": cfg.fluid_table[:, 1], "fluid_mass": cfg.fluid_table[:, 0],
            "steps": solver.steps, "speed_of_sound": cfg.speed_of_sound}


def check_stable(spec, cfg, frame: int, data: dict) -> None:
    """Stop with a clear message when the state has blown up; frames before stay on disk."""
    where = f"frame {frame:04d}: sim unstable"
    if not np.isfinite(data["position"]).all() or not np.isfinite(data["velocity"]).all():
        raise StageError(f"{where}: NaN/inf in particle state; lower sim.cfl or sim.max_dt")
    lo, hi = np.array(spec.domain.min), np.array(spec.domain.max)
    out = ((data["position"] < lo - 1e-4) | (data["position"] > hi + 1e-4)).any(axis=1)
    if out.any():
        raise StageError(f"{where}: {int(out.sum())} particle(s) escaped the domain; lower sim.cfl")
    rho0 = cfg.fluid_table[data["fluid"], 1]
    ratio = float(np.max(data["density"] / rho0)) if len(rho0) else 1.0
    if ratio > spec.sim.max_density_ratio:
        raise StageError(f"{where}: density reached {ratio:.2f}x rest (bound sim.max_density_ratio = "
                         f"{spec.sim.max_density_ratio}); raise sim.speed_of_sound or lower sim.cfl")


def build_solver(spec, paths, first_frame: int):
    """A solver at the latest checkpoint before first_frame, or at the initial fill."""
    from .sph import SolverConfig, SPHSolver, fill_blocks

    cfg = SolverConfig.from_spec(spec)
    ckpts = [c for c in paths.checkpoints() if c < first_frame]
    if ckpts:
        frame = ckpts[-1]
        data, attrs = read_h5(paths.checkpoint(frame))
        solver = SPHSolver(cfg, data, time_s=attrs["time"], step=attrs["step"], dt_prev=attrs["dt_prev"])
        log.info("sim: resuming from checkpoint at frame %d (t = %.4f s, step %d)", frame,
                 attrs["time"], attrs["step"])
        return cfg, solver, frame
    solver = SPHSolver(cfg, fill_blocks(spec, cfg))
    log.info("sim: %d particles, h = %.4g m, c = %.3g m/s", solver.n, cfg.h, cfg.speed_of_sound)
    return cfg, solver, None


def write_checkpoint(paths, frame: int, solver) -> None:
    write_h5(paths.checkpoint(frame), solver.state(), {"frame": frame, **solver.controller()})


def run(spec, frames, paths, progress) -> None:
    try:
        init_taichi(spec.sim.backend, spec.sim.threads)
    except BackendUnavailable as exc:
        raise StageError(str(exc)) from None
    from .sph import TooLarge, Unstable

    todo = sorted(frames)
    last = todo[-1]
    try:
        cfg, solver, ckpt_frame = build_solver(spec, paths, todo[0])
    except TooLarge as exc:
        raise StageError(f"sim: {exc}") from None
    start = spec.shot.frame_start if ckpt_frame is None else ckpt_frame
    if ckpt_frame is None:
        data = solver.snapshot()
        if start in todo or not paths.sim_frame(start).exists():
            progress.frame_done(start, [write_frame(paths.sim_frame(start), data,
                                                    frame_attrs(spec, cfg, start, solver))])
        write_checkpoint(paths, start, solver)

    previous = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGUSR1)}
    for s in previous:
        signal.signal(s, _request_stop)
    _STOP["signal"] = None
    wall0, steps0 = time.perf_counter(), solver.steps
    try:
        for frame in range(start + 1, last + 1):
            try:
                done = solver.advance_to(spec.frame_time(frame), should_stop=lambda: _STOP["signal"] is not None)
            except Unstable as exc:
                raise StageError(f"frame {frame:04d}: sim unstable: {exc}; lower sim.cfl or sim.max_dt") from None
            except TooLarge as exc:     # particles crowding together: usually a blow-up too
                raise StageError(f"frame {frame:04d}: sim: {exc}") from None
            if not done:
                # checkpoint named after the last finished frame, holding the exact mid-frame state
                write_checkpoint(paths, frame - 1, solver)
                raise Interrupted(f"sim: stopped by {_STOP['signal']} during frame {frame:04d}; "
                                  f"checkpoint written, run again to resume")
            data = solver.snapshot()
            check_stable(spec, cfg, frame, data)
            if frame in todo or not paths.sim_frame(frame).exists():
                path = write_frame(paths.sim_frame(frame), data, frame_attrs(spec, cfg, frame, solver))
                progress.frame_done(frame, [path])
            if (frame - spec.shot.frame_start) % spec.shot.checkpoint_every == 0 or frame == last:
                write_checkpoint(paths, frame, solver)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
    wall = time.perf_counter() - wall0
    steps = solver.steps - steps0
    if steps:
        log.info("sim: %d steps, %.3g particle-steps/s, %.3g simulated s per wall s", steps,
                 solver.n * steps / wall, (solver.time - spec.frame_time(start)) / wall)
