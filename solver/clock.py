"""The step's controller on the device: time, step length and the decisions that end a run of
steps, kept in one small float64 array so that a GPU can take several steps without the host
reading anything back.

A run of steps is armed with a target time; every kernel of a step is gated on GO and does
nothing once it is 0. The last kernel of a step clears GO when the neighbour lists must be
rebuilt (a particle moved skin/2 from where they were built) or the target time is reached; the
step length clears it when the step has blown up; a list build that overflowed its room keeps
it closed (OVERFLOW holds the longest list; LONGEST, the longest any build listed). The host
launches a batch of gated steps, reads the array once, and acts on what it says.
"""
import taichi as ti

from .types import D1

# entries of the controller array: the clock and the run's state, then the constants of the
# step length (set once)
# (the list passes write OVERFLOW and the slot after it, LONGEST: neighbours.list_pass)
TIME, DT_PREV, DT, KICK, TARGET, GO, MOVED, STEPS, UNSTABLE, VMAX, AMAX, OVERFLOW, LONGEST = range(13)
CFL_HS, HS, SOUND, MIN_DT, CAP = range(13, 18)
SIZE = 18
NEVER = 1e30       # the target of a step with no target time


@ti.func
def gate_open(ctl: ti.template()) -> bool:
    return ctl[GO] > 0.5


@ti.kernel
def k_arm(ctl: D1, target: ti.f64):
    """Open the gate for steps towards `target` (closed at once if it is reached already, or
    if the lists overflowed)."""
    ctl[TARGET] = target
    ctl[MOVED] = 0.0
    ctl[GO] = ti.select((ctl[TIME] < target - 1e-9) & (ctl[OVERFLOW] == 0.0), 1.0, 0.0)


@ti.func
def land_on_target(ctl: ti.template(), dt: ti.f64):
    """Shorten dt to land on the target time without a sliver step, then advance the clock:
    KICK = (dt_{n-1/2} + dt_{n+1/2}) / 2 for the leapfrog, DT_PREV = DT = dt, TIME += dt."""
    remaining = ctl[TARGET] - ctl[TIME]
    if remaining <= dt * 1.0001:
        dt = remaining
    elif remaining < 2.0 * dt:          # split the last two steps evenly
        dt = 0.5 * remaining
    ctl[KICK] = 0.5 * (ctl[DT_PREV] + dt)
    ctl[DT] = dt
    ctl[DT_PREV] = dt
    ctl[TIME] += dt


@ti.func
def end_step(ctl: ti.template()):
    """The step is done: count it, and close the gate if the lists must be rebuilt or the
    target is reached."""
    ctl[STEPS] += 1.0
    if ctl[MOVED] > 0.5 or ctl[TIME] >= ctl[TARGET] - 1e-9:
        ctl[GO] = 0.0
