"""DFSPH (Bender & Koschier 2017) against hydrostatics, volume, layering and an experiment."""
import math

import numpy as np
import pytest

import experiments as mm
from conftest import tiny_spec
from pipeline.spec import ShotSpec
from solver import kernels as K


@pytest.fixture(scope="module", autouse=True)
def _taichi(taichi_cpu):
    pass


def dfsph(spec_dict):
    """(spec, params, solver) for a job dict, started as the sim stage starts it."""
    from pipeline.stages.sim import fresh_solver

    spec = ShotSpec.model_validate(spec_dict)
    assert spec.sim.solver == "dfsph"
    return (spec, *fresh_solver(spec))


# ------------------------------------------------------------------------------- hydrostatics
H, W = 0.3, 0.2


@pytest.fixture(scope="module")
def resting_column():
    """A 0.2 x 0.3 x 0.2 m water column from the lattice, settled 0.6 s, then sampled every
    4 ms for 0.4 s: per sample (median interior density, floor pressure extrapolated from the
    interior profile, rho g H, the solver's density error), plus the positions at 0.6 s and at
    the end. (DFSPH's pressure, the last density solve's kappa, swings by +-30 % from step to
    step: the solve stops as soon as the mean error is under its bound. Sampled every 16 ms,
    the mean of 25 samples moved between 0.97 and 1.10 x rho g H when the walls' clamp distance
    changed by 1e-7 r; 100 samples average that out.)"""
    spec, params, s = dfsph(tiny_spec(((0, 0, 0), (W, H, W)), ((0, 0, 0), (W, H + 0.1, W)),
                                      fluid={"viscosity": 1.0}))
    s.advance_to(0.6)
    settled = s.snapshot()["position"]
    s.frame_report()
    h, samples = params.h, []
    for k in range(100):
        s.advance_to(0.6 + 0.004 * (k + 1))
        d = s.snapshot()
        p, y = d["position"], d["position"][:, 1]
        top = np.percentile(y, 99.5) + spec.sim.particle_radius
        inner = (y > h) & (y < top - h) & (p[:, 0] > h) & (p[:, 0] < W - h) & (p[:, 2] > h) & (p[:, 2] < W - h)
        _slope, p_floor = np.polyfit(y[inner], d["pressure"][inner], 1)
        samples.append((np.median(d["density"][inner]), p_floor, 1000.0 * 9.81 * top,
                        s.frame_report()["density_error"]))
    return np.array(samples), settled, d["position"], 0.5 * params.fill_domain.step


def test_resting_column_density(resting_column):
    """The solver meets its bound (mean compression under sim.max_density_error = 0.1 %) and
    the interior sits within 0.5 % of rest density (the issue's bound; measured +0.07 %)."""
    samples, _, _, _ = resting_column
    assert samples[:, 3].max() <= 1e-3, f"density solve ended at {samples[:, 3].max():.2e} mean compression"
    rho = samples[:, 0].mean()
    assert abs(rho / 1000.0 - 1.0) < 0.005, f"median interior density {rho:.2f} kg/m^3"


def test_resting_column_floor_pressure(resting_column):
    """Hydrostatics: the interior pressure profile extrapolated to the floor, averaged over
    time, is rho g H within 5 %. The pressure is both solves' kappa: at rest the divergence
    solve carries part of the weight, and the density solve's alone read 0.942 rho g H once the
    walls were mirrored (measured now: +1.5 % over 100 samples, single samples 0.41-1.85; the
    layer touching the floor is left out of the fit)."""
    samples, _, _, _ = resting_column
    ratio = samples[:, 1].mean() / samples[:, 2].mean()
    assert abs(ratio - 1.0) < 0.05, f"floor pressure {ratio:.3f} x rho g H"


def test_resting_column_stays_put(resting_column):
    """After settling, 99 % of the particles stay within one radius of where they were over
    0.4 s (measured: 2 of 1,480 moved further; 31 of 1,500 with the cubic fill and 4.2 ms steps),
    and none moves more than three radii."""
    _, settled, end, _ = resting_column
    moved = np.linalg.norm(end - settled, axis=1)
    assert np.percentile(moved, 99) < 0.01 * 1.1, f"99th percentile moved {np.percentile(moved, 99):.4f} m"
    assert moved.max() < 0.03, f"a particle moved {moved.max():.3f} m"


def test_resting_column_keeps_its_wall_layers(resting_column):
    """The layer touching the floor and the side walls stays where the fill put it, half a
    plane step out (solver/lattice.py: 0.77-0.83 r on this column's fcc lattice, r on the cubic
    one), within 15 % (measured 1.06-1.13 of it on the fcc lattice, where the wall's mirror
    images continue the planes but not their checkerboard; 0.996-1.018 on the cubic). With the
    walls as tabulated boundary samples it sank to about half a radius as a sparse layer (0.56 r
    in this column, 0.54 r in bench/pool_volume.py's pool), the mesh lost that volume, and the
    squeezed-out particles rose up the walls; mirrored in the walls (dfsph.k_density_factor) a
    sparse layer reads sparse."""
    _, _, end, gap = resting_column
    r = 0.01
    for axis, lo, hi in ((1, 0.0, None), (0, 0.0, W), (2, 0.0, W)):
        x = end[:, axis]
        layers = [x[x - lo < 2 * r] - lo] + ([hi - x[hi - x < 2 * r]] if hi is not None else [])
        for d in layers:
            assert len(d) > 50 and abs(d.mean() / gap[axis] - 1.0) < 0.15, \
                f"axis {axis}: wall layer at {d.mean() / r:.2f} r, the fill put it at {gap[axis] / r:.2f} r"


# ------------------------------------------------------------------------------------ volume
def mesh_volume(d: dict, attrs_radius: float) -> float:
    """Volume of the surface mesh of a snapshot, as the surface stage makes it (iso 0.5)."""
    import pyvista as pv

    from surfacing.reconstruct import SurfaceParams, reconstruct

    vol = np.full(len(d["position"]), (2 * attrs_radius) ** 3, np.float32)   # lattice volume
    _field, mesh = reconstruct(d["position"], None, vol,
                               SurfaceParams(cell=0.75 * attrs_radius, kernel_radius=4 * attrs_radius))
    return float(pv.PolyData.from_regular_faces(mesh.points, mesh.faces).volume)


def test_a_small_dam_break_keeps_its_volume():
    """A 0.2 x 0.3 x 0.2 m column collapses across a 0.6 m tank: 1.5 s later, when the wave
    has run up the far wall and come back, the surface mesh holds the first frame's volume
    within 2 % (WCSPH gained 29 % on the example shot) and the interior is within 0.5 % of
    rest density."""
    r = 0.01
    spec, params, s = dfsph(tiny_spec(((0, 0, 0), (0.2, 0.3, 0.2)), ((0, 0, 0), (0.6, 0.4, 0.2)),
                                      fluid={"viscosity": 1.0}))
    first = s.snapshot()
    v0 = mesh_volume(first, r)
    s.advance_to(1.5)
    last = s.snapshot()
    v1 = mesh_volume(last, r)
    assert abs(v1 / v0 - 1.0) < 0.02, f"mesh volume {v0 * 1e3:.2f} L -> {v1 * 1e3:.2f} L"
    from scipy.spatial import cKDTree
    n = np.array([len(x) for x in cKDTree(last["position"]).query_ball_point(last["position"], params.h)])
    interior = n >= 0.9 * n.max()
    assert abs(np.median(last["density"][interior]) / 1000.0 - 1.0) < 0.005


def test_an_expanding_bulk_is_pulled_back():
    """A 0.2 m cube without gravity set expanding uniformly, v = 0.5 (x - c) /s: a one-sided
    solve lets the bulk thin out freely (its core's density falls to 0.59 of rest by 0.4 s, as
    the flow says: (1 + 0.5 t)^-3), the way a splash's churned bulk stays aerated. The
    divergence solve also acts where the fluid expands once it is LOOSE (0.5 %) under its
    target, at half weight, so the core stops there and holds (measured 0.982-0.985 of rest
    from 0.05 s to 0.4 s; bound 3 %), while the outer layers, with too few neighbours for the
    solve, fly on."""
    from pipeline.stages.sim import make_solver

    spec, params, s = dfsph(tiny_spec(((0.3, 0.3, 0.3), (0.5, 0.5, 0.5)), sim={"gravity": (0, 0, 0)},
                                      fluid={"viscosity": 0.0}))
    state = s.state()
    centre = state["position"].mean(axis=0)
    state["velocity"][:] = 0.5 * (state["position"] - centre)
    s = make_solver(spec, params, state)
    first = s.snapshot()["position"]
    for t in (0.1, 0.4):
        s.advance_to(t)
        d = s.snapshot()
        core = np.linalg.norm(d["position"] - d["position"].mean(axis=0), axis=1) < 0.05
        assert core.sum() > 40
        assert np.median(d["density"][core]) > 0.97 * 1000.0, (t, np.median(d["density"][core]))
    grown = np.ptp(d["position"], axis=0).mean() / np.ptp(first, axis=0).mean()
    assert grown > 1.1, f"the outer layers were held back too: the cube grew {grown:.3f}x"


def test_a_resting_pool_keeps_its_volume_and_its_flat_top():
    """A 0.4 x 0.12 x 0.2 m pool from the fill lattice, left alone 1.5 s. Its top layer misses
    the water above it (0.78 of rest on the lattice); pushing only over rest density, DFSPH let
    it sink into the layers below until its sum read rest (bench/pool_volume.py: the example's
    pool lost 1.94 % of its mesh volume in 2 s, its top sank 0.45 r). Each particle's own target
    (dfsph.SURFACE_FROM) holds it: the mesh keeps the first frame's volume within 0.5 % and the
    top (the heights' 99th percentile) does not sink 0.1 r. Measured at 0.5 / 1 / 1.5 s:
    +0.08 / +0.01 / -0.06 %, the top 0.15-0.22 r above its start as the pool sloshes (rms 29-35
    mm/s; this small pool starts from the lattice and rings); before: -0.45 / -0.60 / -0.63 %,
    sunk 0.17 / 0.33 / 0.33 r (rms 40-42 mm/s)."""
    r = 0.01
    spec, params, s = dfsph(tiny_spec(((0, 0, 0), (0.4, 0.12, 0.2)), ((0, 0, 0), (0.4, 0.3, 0.2))))
    first = s.snapshot()
    top0 = np.percentile(first["position"][:, 1], 99)
    s.advance_to(1.5)
    end = s.snapshot()
    change = mesh_volume(end, r) / mesh_volume(first, r) - 1.0
    sink = (top0 - np.percentile(end["position"][:, 1], 99)) / r
    assert abs(change) < 0.005 and sink < 0.1, f"mesh volume {100 * change:+.2f} %, top sank {sink:.2f} r"


def test_sweeps_gated_on_the_device_match_the_hosts_loop(monkeypatch):
    """Each solve's sweeps decide on the device whether they are done (dfsph.k_sweeps: one
    launch a sweep; on a GPU one read for several), and the lists are rebuilt in one launch. For
    a small dam break's first 0.1 s (a column falling onto the floor, with the density bound
    at 0.01 % so that the solves take several sweeps: 4.5-6.2 a step), with the sweeps run ahead of the reads as on a GPU: the same sweeps in every frame
    and the same state, bit for bit, as the separate launches and the host's loop, which reads
    every sweep's error (both add the chunk sums in the same order)."""
    from solver.dfsph import DFSPHSolver

    runs = []
    for fused in (False, True):
        monkeypatch.setattr(DFSPHSolver, "FUSED", fused)
        _, _, s = dfsph(tiny_spec(((0, 0, 0), (0.1, 0.2, 0.1)), ((0, 0, 0), (0.3, 0.3, 0.1)),
                                  fluid={"viscosity": 1.0}, sim={"max_density_error": 1e-4}))
        s.on_cpu = False        # sweeps launched ahead of the reads, as on a GPU
        frames = []
        for k in range(1, 4):
            s.advance_to(k / 30)
            frames.append((s.steps, s.frame_report(), s.state()))
        runs.append(frames)
    for (steps_a, report_a, a), (steps_b, report_b, b) in zip(*runs):
        assert steps_a == steps_b and report_a == report_b
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert runs[0][0][1]["density_iterations"] > 2
    # the column's fall takes the closing-speed step, and its density solve Chebyshev's sweeps
    assert sum(report["density_accelerated_steps"] for _, report, _ in runs[0]) > 0, [f[1] for f in runs[0]]


def test_a_solve_stopped_at_its_cap_is_counted_and_said(caplog):
    """A step whose solve runs out of sweeps (sim.max_iterations) with its error still above the
    bound is counted in the frame's report and said in one warning line naming the key. A small
    column falling for 0.1 s with a bound of 0.001 %: one sweep a solve leaves most steps above
    it; with the default cap of 100 none is."""
    import logging

    from pipeline.stages.sim import log_frame

    column = (((0, 0, 0), (0.1, 0.2, 0.1)), ((0, 0, 0), (0.3, 0.3, 0.1)))
    reports = {}
    for cap in (1, 100):
        _, _, s = dfsph(tiny_spec(*column, fluid={"viscosity": 1.0},
                                  sim={"max_density_error": 1e-5, "max_iterations": cap}))
        s.advance_to(0.1)
        reports[cap] = s.frame_report()
    capped = reports[1]
    assert capped["density_capped_steps"] > capped["dfsph_steps"] // 2, capped
    assert capped["density_error"] > 1e-5 and capped["max_iterations"] == 1
    assert reports[100]["density_capped_steps"] == reports[100]["divergence_capped_steps"] == 0, reports[100]
    with caplog.at_level(logging.INFO, logger="sphshot"):
        log_frame(3, capped)
        log_frame(4, reports[100])
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) >= 1 and all("frame 0003" in w and "sim.max_iterations" in w for w in warned), warned
    assert f"on {capped['density_capped_steps']} of {capped['dfsph_steps']} steps" in warned[0]


# ----------------------------------------------------------------------------------- layering
def two_layers(heavy_below: bool, viscosity: float = 1.0) -> dict:
    water = {"name": "water", "rest_density": 1000.0, "viscosity": viscosity}
    oil = {"name": "oil", "rest_density": 800.0, "viscosity": viscosity}
    lower, upper = (water, oil) if heavy_below else (oil, water)
    return {"shot": {"name": "t"}, "sim": {"particle_radius": 0.01},
            "domain": {"min": (0, 0, 0), "max": (0.2, 0.26, 0.1)},
            "fluids": ({**lower, "blocks": ({"min": (0, 0, 0), "max": (0.2, 0.1, 0.1)},)},
                       {**upper, "blocks": ({"min": (0, 0.1, 0), "max": (0.2, 0.2, 0.1)},)})}


def layering(s) -> tuple[float, float, float]:
    """For two_layers(True) now: the shares of oil more than two radii below the interface and of
    water more than two radii above it, and the rms speed (m/s)."""
    d = s.snapshot()
    y, f = d["position"][:, 1], d["fluid"]
    oil_sunk = ((f == 1) & (y < 0.1 - 0.02)).sum() / (f == 1).sum()
    water_up = ((f == 0) & (y > 0.1 + 0.02)).sum() / (f == 0).sum()
    return oil_sunk, water_up, float(np.sqrt((d["velocity"] ** 2).sum(axis=1).mean()))


def test_oil_on_water_stays_layered_and_still():
    """Oil (800 kg/m^3) resting on water, settled 1 s and left alone 1 s more: under 1 % of
    either fluid lies beyond two radii of the interface (the issue's bound; measured 0 %), and
    the rms speed, sampled every 1/8 s over that second, averages under the issue's 5 mm/s
    (measured 3.6 mm/s, and 3.6 again with the density bound 1 % tighter or looser; 3.2-4.6 over
    the four bounds before the thirty-eighth session's factor at sparse particles; 8.6 on the
    cubic fill). At rest the step is the CFL's floor here, about 8 ms (sim.max_dt, 1/120 s,
    does not bind), and the noise the density solve leaves is about its bound times h / dt:
    with the old cap of 1/240 s the same layers held 11.7 mm/s on average, single samples
    9.3-13.1 (bench/RESULTS.md, twenty-fifth session)."""
    spec, _params, s = dfsph(two_layers(True))
    rms = []
    for t in np.arange(1.0, 2.01, 0.125):
        s.advance_to(t)
        oil_sunk, water_up, speed = layering(s)
        rms.append(speed)
    assert oil_sunk < 0.01 and water_up < 0.01, (oil_sunk, water_up)
    assert np.mean(rms) < 0.005, f"rms speed {np.mean(rms) * 1000:.1f} mm/s on average"


def test_oil_on_water_comes_to_rest_with_a_tighter_density_bound():
    """The same layers with sim.max_density_error = 0.05 %: settled 1 s from the fill and left
    alone 1 s more, the rms speed is under the issue's 5 mm/s (measured 2.3 mm/s at 2 s, 3.7 at
    2.5 s, 21.5 density sweeps a step at rest against 15 at the default 0.1 %), and the layers
    stay sharp. With the old cap of 1/240 s this bound was what it took to get under 5 mm/s (2.4
    mm/s at 2 s, where 0.1 % gave 12.7); with steps of the CFL's floor (about 8 ms) it adds little."""
    job = two_layers(True)
    job["sim"]["max_density_error"] = 0.0005
    spec, _params, s = dfsph(job)
    s.advance_to(2.0)
    oil_sunk, water_up, rms = layering(s)
    assert oil_sunk < 0.01 and water_up < 0.01, (oil_sunk, water_up)
    assert rms < 0.005, f"rms speed {rms * 1000:.1f} mm/s"


def test_a_water_blob_sinks_through_oil():
    """A water blob dropped into a pool of oil (800 kg/m^3) goes to the bottom: 3.5 s later
    most of the water lies in the pool's lower half and below the oil's median height. At
    eight particles across the blob sinks at about 4 cm/s, slower than a resolved one would,
    and how it breaks up is chaotic: a change of round-off alone (1e-9 m in the first step's
    positions, from taking grad W from the density pass) moved the share at 2.5 s from 65 % to
    48 %. At 3.5 s the two runs had 81 % and 75 % down."""
    spec, _params, s = dfsph({
        "shot": {"name": "t"}, "sim": {"particle_radius": 0.01},
        "domain": {"min": (0, 0, 0), "max": (0.2, 0.4, 0.1)},
        "fluids": ({"name": "oil", "rest_density": 800.0, "viscosity": 0.05,
                    "blocks": ({"min": (0, 0, 0), "max": (0.2, 0.2, 0.1)},)},
                   {"name": "water", "rest_density": 1000.0, "viscosity": 0.05,
                    "blocks": ({"min": (0.06, 0.26, 0.02), "max": (0.14, 0.34, 0.08)},)})})
    s.advance_to(3.5)
    d = s.snapshot()
    y, f = d["position"][:, 1], d["fluid"]
    low = np.mean(y[f == 1] < 0.1)
    assert low > 0.6, f"only {low:.0%} of the water reached the pool's lower half"
    assert np.median(y[f == 1]) < np.median(y[f == 0])


# -------------------------------------------------------------------------------- experiment
# Martin & Moyce 1952's collapsing column (tests/experiments.py: the data, the set-up, the measures)


def test_surge_front_follows_martin_and_moyce():
    """A column a wide and 2a high (a = 0.1 m, 10 particles across) on a frictionless floor.
    The front leads the experiment: +12, +16, +16, +14, +11, +16, +9, +10 % at the eight times
    (mirrored walls, one thread and two, the fortieth session's sort by larger cells; +12, +16,
    +16, +14, +12, +17, +9, +9 % before it; +12, +18, +16, +13, +12, +16, +8, +8 % before the
    thirty-eighth session's factor at sparse particles; with the walls' tables +6 % to +15 %),
    so the bound is 20 % ahead and never behind by more than 2 %; the issue's 5 % is not met.
    SPlisHSPlasH's DFSPH leads it too (`bench/martin_moyce.py --splishsplash`, the column as its
    block sampling places it, 5-10 % narrower and starting 2r off the floor, both of which slow
    a front): +10, +13, +10, +9, +8, +12, +6, +7 % at r = 2.5 mm, +13, +15, +10, +8, +5, +11,
    +3, +2 % at 5 mm (bench/RESULTS.md, thirty-ninth session). The lead is not the
    experiment's clock: the column's top (next test) keeps it to 0.5 ms. It starts at the
    foot, which the experiment's release held, and later the front runs at Ritter's ideal
    speed where the experiment's runs 15 % below it on its dry floor (bench/martin_moyce.py;
    bench/RESULTS.md, thirty-first session). Half of that late lead is the experiment's size:
    its 57 mm column of water, run as it was with water's viscosity and surface tension and
    resolved (r = a / 80, `bench/martin_moyce.py --water`, 16,000 particles, 100 s), leads by
    6-8 % from T = 4.4 on; the early lead stays (thirty-second session). This column is
    Froude-scaled and inviscid, at the suite's cost."""
    a, r = 0.1, 0.005
    _params, s = mm.collapsing_column(0.8, a, r)
    for T, Z in mm.FRONT[:8]:                   # to Z = 7 (the 0.8 m tank)
        s.advance_to(mm.front_time(T, a))
        front = mm.front(s.position.to_numpy(), a, r)
        assert -0.02 < front / Z - 1 < 0.20, f"T = {T}: front at Z = {front:.2f}, experiment {Z}"


def test_the_collapsing_column_falls_as_martin_and_moyces():
    """The same column's height at the back wall (the second-highest particle within 2r of it,
    plus r) against Martin & Moyce's Table 6 while it falls from 0.94 to 0.56 of its first
    height. The column's top is far from the gate, so unlike the surge front it starts with the
    experiment: measured +0.3, -0.6, +0.4, +0.4, -0.4, -1.5, -1.1, -0.1 % (one thread and two;
    in a 1.6 m tank at r = 2.5 mm within 1.3 % too). Bound 3 %.
    Later the column drains too slowly (+6 % at H = 0.50, +23 % at 0.22; bench/RESULTS.md,
    thirtieth session), and that is not asserted."""
    a, r = 0.1, 0.005
    _params, s = mm.collapsing_column(0.8, a, r)
    for tau, H in mm.COLUMN[mm.COLUMN[:, 1] >= 0.56]:
        s.advance_to(mm.column_time(tau, a))
        height = mm.column_height(s.position.to_numpy(), a, r)
        assert abs(height / H - 1) < 0.03, f"tau = {tau}: column at H = {height:.3f}, experiment {H}"


def test_the_sheet_behind_the_surge_front_keeps_its_thickness():
    """The same column in a 1.6 m tank, at t sqrt(g / a) = 5.25: the water within 0.2 m of the
    back wall is a sheet two to four particles thick. Spread over the floor at its particles'
    rest volume (2r)^3 it would be 2.5 cm deep; its top (the mean over 2 cm bins of the 95th
    percentile height, plus r) stands 1.19 times that (measured; 1.22 before the thirty-eighth
    session's factor at sparse particles, 1.15 before the free-surface targets), and its median
    number density is 0.971 of rest (0.952; 0.979). Until the twenty-ninth
    session the density solve pushed such a sheet's one-sided particles towards their targets,
    7-10 % under rest, and only particles with 20 neighbours were pulled back when they
    overshot: the sheet stood 1.89 times its water's depth at 0.76 of rest, and boiled.
    Bounds: 1.4 and 0.9."""
    a, r = 0.1, 0.005
    params, s = mm.collapsing_column(1.6, a, r)
    s.advance_to(mm.column_time(5.25, a))
    p = s.position.to_numpy()
    near_wall = p[:, 0] < 0.2
    depth = near_wall.sum() * (2 * r) ** 3 / (0.2 * 0.05)
    bins = [near_wall & (p[:, 0] >= x) & (p[:, 0] < x + 0.02) for x in np.arange(0.0, 0.2, 0.02)]
    top = np.mean([np.percentile(p[b, 1], 95) for b in bins]) + r
    density = np.median(s.number_density.to_numpy()[near_wall]) / params.lattice_density
    assert top / depth < 1.4, f"the sheet stands {top / depth:.2f} times its water's depth"
    assert density > 0.9, f"the sheet's median number density is {density:.3f} of rest"


# ---------------------------------------------------------------------------------- viscosity
def shear_wave(eta: float, r: float, no_slip, mode):
    """(solver, amplitude(), analytic decay rate) for v_x = 0.02 f(y, z) in a 0.6 x 0.2 x 0.1 m
    tank without gravity, f = cos(pi y / L) (free-slip walls), sin(2 pi y / L) sin(pi z / D)
    (no-slip walls: zero at every wall, no net flow along the closed tank) or sin(2 pi y / L)
    (no slip at the y walls only; `no_slip`: domain.no_slip). The amplitude is
    the least-squares fit of f to v_x in the tank's middle third. Without gravity nothing caps
    the step but sim.max_dt: these waves were measured at 1/240 s (4.2 ms), the default until
    the twenty-fifth session, and keep it."""
    L, D = 0.2, 0.1
    job = tiny_spec(((0, 0, 0), (0.6, L, D)), ((0, 0, 0), (0.6, L, D)),
                    sim={"gravity": (0, 0, 0), "particle_radius": r, "max_dt": 1 / 240},
                    fluid={"dynamic_viscosity": eta})
    job["domain"]["no_slip"] = no_slip
    spec, params, s = dfsph(job)
    if mode == "cos":
        k2, f = (np.pi / L) ** 2, lambda p: np.cos(np.pi / L * p[:, 1])
    elif mode == "sin":
        k2, f = (2 * np.pi / L) ** 2, lambda p: np.sin(2 * np.pi / L * p[:, 1])
    else:
        k2 = (2 * np.pi / L) ** 2 + (np.pi / D) ** 2
        f = lambda p: np.sin(2 * np.pi / L * p[:, 1]) * np.sin(np.pi / D * p[:, 2])
    state = s.state()
    state["velocity"][:, 0] = 0.02 * f(state["position"])
    from pipeline.stages.sim import make_solver
    s = make_solver(spec, params, state)

    def amplitude():
        d = s.snapshot()
        mid = (d["position"][:, 0] > 0.2) & (d["position"][:, 0] < 0.4)
        c = f(d["position"][mid])
        return (d["velocity"][mid, 0] * c).sum() / (c * c).sum()

    return s, amplitude, eta / 1000.0 * k2


def test_viscosity_in_pascal_seconds_damps_a_shear_wave_at_the_analytic_rate():
    """v_x = A cos(pi y / L) between free-slip walls (fluid-fluid viscosity only) decays as
    exp(-nu (pi / L)^2 t). With honey's 10 Pa s (nu = 0.01 m^2/s, L = 0.2 m) the amplitude in the
    tank's middle after 0.4 s is the analytic one within 5 % (measured 0.382 against 0.373 on the
    fcc fill, whose lattice moment scales the viscosity, params.viscous_scale: 0.400 without it; the
    step, 4.2 ms, is within the explicit limit 5 ms, so this is the explicit path). (At 1 Pa s
    the decay rate is 30 % too high: the DFSPH solve's own velocity noise damps as much as such
    a viscosity does at 10 particles across.)"""
    s, amplitude, rate = shear_wave(10.0, 0.01, False, "cos")
    a0 = amplitude()
    s.advance_to(0.4)
    assert s.frame_report()["viscosity_steps"] == 0
    assert abs(amplitude() / a0 / np.exp(-rate * 0.4) - 1.0) < 0.05, (amplitude() / a0, np.exp(-rate * 0.4))


def test_implicit_viscosity_takes_steps_far_beyond_the_explicit_limit():
    """50 Pa s at r = 5 mm: the explicit limit is 0.25 ms; the solver takes 4.2 ms steps (17
    times longer) with the viscosity solved implicitly (solver.viscosity), and the cos wave's
    amplitude after 0.1 s is the analytic one within 8 % (measured -1.3 % on the fcc fill, +6 % on
    the cubic one: backward Euler at
    nu k^2 dt = 0.05 damps 3 % less than the exact decay over 24 steps; capped at the explicit
    limit the old way took 400 steps, 4x the time, and was within 0.3 %). Taken explicitly at the
    same step, the wave blows up within a frame: particles reach 2-3 m/s against the wave's 2
    cm/s by 0.02-0.04 s, and the solver stops the run near 0.08 s, or, where the divergence
    solve's pull on the expanding fluid holds the fastest under its limit, the speeds stay there."""
    s, amplitude, rate = shear_wave(50.0, 0.005, False, "cos")
    assert s.dt_eta < 3e-4
    a0 = amplitude()
    s.advance_to(0.1)
    report = s.frame_report()
    assert report["viscosity_steps"] == report["dfsph_steps"] <= 30, report
    assert report["viscosity_residual"] <= 1e-3
    assert abs(amplitude() / a0 / np.exp(-rate * 0.1) - 1.0) < 0.08, (amplitude() / a0, np.exp(-rate * 0.1))

    from solver.errors import Unstable
    s, _amplitude, _rate = shear_wave(50.0, 0.005, False, "cos")
    s.dt_eta = math.inf            # explicit at any step
    fastest = 0.0
    try:
        for t in (0.02, 0.04, 0.06, 0.08, 0.1):
            s.advance_to(t)
            fastest = max(fastest, float(np.linalg.norm(s.snapshot()["velocity"], axis=1).max()))
    except Unstable:
        fastest = math.inf
    assert fastest > 1.0, f"explicit at 17x its limit, the fastest particle moved at only {fastest:.3g} m/s"


def test_implicit_viscosity_starts_from_the_last_correction_and_ends_where_a_cold_start_does():
    """The implicit solve's warm start (solver.viscosity: from v* + the last step's correction,
    stopped at the same residual as a start from v*) changes how many CG iterations a step takes,
    not where it ends. The 50 Pa s wave after 0.1 s (24 steps), against the same run solved to
    1e-6 every step: started warm, 0.36 % off it; started cold, 0.53 % off (measured; both under
    the 1e-3 residual each step allows, which over 24 steps bounds neither tightly: 1 % here).
    The warm runs take fewer iterations (9.6 against 10.9 a step, measured), and nearly every
    solve starts warm; without the correction carried through the sort it would be a worse start
    than v* and fall back to it."""
    from solver.viscosity import ImplicitViscosity

    runs = {}
    for name, warm, tolerance in (("warm", True, 1e-3), ("cold", False, 1e-3), ("converged", False, 1e-6)):
        s, amplitude, _rate = shear_wave(50.0, 0.005, False, "cos")
        s.implicit = ImplicitViscosity(s.n, tolerance=tolerance, warm_start=warm)
        a0 = amplitude()
        s.advance_to(0.1)
        report = s.frame_report()
        assert report["viscosity_steps"] == report["dfsph_steps"], report
        assert report["viscosity_residual"] <= tolerance, report
        runs[name] = (amplitude() / a0, report["viscosity_iterations"], s.implicit.warm_starts,
                      report["viscosity_steps"])
    (warm_a, warm_it, warm_starts, steps), (cold_a, cold_it, cold_starts, _) = runs["warm"], runs["cold"]
    exact = runs["converged"][0]
    assert cold_starts == 0
    assert warm_starts >= 0.75 * steps, f"{warm_starts} of {steps} solves started warm"
    assert abs(warm_a / exact - 1.0) < 0.01 and abs(cold_a / exact - 1.0) < 0.01, (warm_a, cold_a, exact)
    assert warm_it < cold_it, f"warm start: {warm_it:.2f} iterations a step, cold: {cold_it:.2f}"


def test_no_slip_walls_hold_a_viscous_flow_at_the_analytic_rate():
    """v_x = A sin(2 pi y / L) sin(pi z / D), zero at the walls, decays as exp(-nu k^2 t) with
    k^2 = (2 pi / L)^2 + (pi / D)^2 when the walls hold the fluid (domain.no_slip, Morris et al.
    1997's extrapolated wall velocity). At 10 Pa s, r = 5 mm (10 particles across D) the
    measured rate over 0.1 s is 8.1 % under the analytic one on the fcc fill (9.6 % on the cubic
    one; 4 % of it backward Euler's at
    steps 3.3 times the explicit limit; explicit, capped at that limit, 5 % under): the bound is
    15 %. With free-slip walls the walls hold nothing: measured 7.5 /s against 19.7."""
    rates = {}
    for no_slip in (True, False):
        s, amplitude, rate = shear_wave(10.0, 0.005, no_slip, "sinsin")
        a0 = amplitude()
        s.advance_to(0.1)
        rates[no_slip] = -np.log(amplitude() / a0) / 0.1
    assert abs(rates[True] / rate - 1.0) < 0.15, (rates, rate)
    assert rates[False] < 0.8 * rate, (rates, rate)


def test_the_spec_and_the_solver_name_the_same_no_slip_walls():
    """domain.no_slip's names (pipeline.spec, which must not import Taichi) and the rows of the
    solver's wall table (solver.params) are two lists of one vocabulary: the stage passes the
    names through, and the solver holds a wall where its row's name is among them, so a name
    in one and not the other would leave that wall silently free-slip."""
    from pipeline.spec import NO_SLIP_ALL
    from solver.params import NO_SLIP_ROWS

    assert sorted(NO_SLIP_ALL) == sorted(NO_SLIP_ROWS)


def test_no_slip_on_the_faces_named_holds_the_fluid_there_only():
    """domain.no_slip as a list of faces. v_x = A sin(2 pi y / L), the same across z, is the mode
    of a slice of a wide channel: its y walls hold the fluid, its z sides are free. With
    no_slip = ["-y", "+y"] it decays at nu (2 pi / L)^2 (measured 9.02 /s against 9.87, 8.6 %
    under, as the all-walls mode above: bound 15 %); with every wall holding, the z sides drag
    it too (20.2 /s: bound above 1.5 times the analytic rate); with none, nothing holds it (5.5:
    bound 0.8 times)."""
    rates = {}
    for no_slip in (("-y", "+y"), True, False):
        s, amplitude, rate = shear_wave(10.0, 0.005, no_slip, "sin")
        a0 = amplitude()
        s.advance_to(0.1)
        rates[no_slip] = -np.log(amplitude() / a0) / 0.1
    assert abs(rates[("-y", "+y")] / rate - 1.0) < 0.15, (rates, rate)
    assert rates[True] > 1.5 * rate, (rates, rate)
    assert rates[False] < 0.8 * rate, (rates, rate)


# ---------------------------------------------------------------------------- surface tension
def test_akinci_surface_tension_pulls_a_cube_into_a_drop_and_keeps_it():
    """Without gravity, a 10 cm cube (r = 5 mm, 13 fcc planes a side) under Akinci et al. 2013's
    tension (gamma 0.5) is a drop by 0.2 s, stays one, and loses no particle. Roundness: max /
    rms radius about the centre, 1.57 for the cube, sqrt(5/3) = 1.29 for a ball (R the radius of
    the ball of the particles' volume, 6.4 cm: the fcc fill puts 1,099 particles of (2r)^3 in the
    1 L cube). The cube overshoots into a drop that rings; a real drop this size would ring for
    about a minute (Rayleigh's l = 2 mode decays in R^2 / (5 nu) = 80 s at this 0.01 Pa s), so
    the solver's own damping sets how soon it looks round, and the drop is judged over its
    ringing, sampled every 20 ms:
    - from 0.2 s its mean roundness within a quarter of the way from the ball's to the cube's,
      under 1.36 (measured 1.34; 1.31 before the twenty-ninth session's pull on thinned surface
      particles, which damps the ringing less: 1.35-1.39 from 0.2 to 0.36 s, then 1.31-1.34);
    - it settles: the mean from 0.4 to 0.6 s under that from 0.2 to 0.4 s and under a ball's
      with its outermost particle half a radius beyond R, (R + r / 2) / (sqrt(3 / 5) R) = 1.34
      (measured 1.32 against 1.36 and 1.34), and no sample from 0.4 s over 1.36 (measured at most
      1.34);
    - from 0.2 s no particle farther than 1.15 R from the centre (the cube's corners are at
      1.35 R; measured at most 1.08) or without a neighbour within h.
    Müller's color-field force (sigma 2) on the same cube fails all but the last: roundness
    1.32-1.65 from 0.2 s and 1.46-1.63 from 0.4 s, a particle at 1.34 R (with steps of 4.2 ms,
    the old default cap, it pushed particles off: 4.07 at 0.6 s)."""
    spec, params, s = dfsph(tiny_spec(((0.1, 0.1, 0.1), (0.2, 0.2, 0.2)), ((0, 0, 0), (0.3, 0.3, 0.3)),
                                      sim={"particle_radius": 0.005, "gravity": (0, 0, 0),
                                           "surface_tension_model": "akinci"},
                                      fluid={"surface_tension": 0.5, "dynamic_viscosity": 0.01}))
    r_p, h = params.particle_radius, params.h
    ball = (3 * s.n * (2 * r_p) ** 3 / (4 * np.pi)) ** (1 / 3)
    times, roundness, farthest, lonely = np.arange(1, 31) * 0.02, [], [], []
    for t in times:
        s.advance_to(t)
        p = s.snapshot()["position"]
        r = np.linalg.norm(p - p.mean(0), axis=1)
        roundness.append(r.max() / np.sqrt((r * r).mean()))
        farthest.append(r.max() / ball)
        d2 = ((p[:, None, :] - p[None, :, :]) ** 2).sum(-1)
        np.fill_diagonal(d2, np.inf)
        lonely.append(int((d2.min(1) >= h * h).sum()))
    roundness, farthest, lonely = np.array(roundness), np.array(farthest), np.array(lonely)
    ringing, settled, after = (times > 0.19) & (times < 0.41), times > 0.39, times > 0.19
    ball_roundness, cube_roundness = np.sqrt(5 / 3), 1.57
    assert roundness[after].mean() < ball_roundness + 0.25 * (cube_roundness - ball_roundness), \
        f"not a drop by 0.2 s: {np.round(roundness[after], 3)}"
    loose_ball = (ball + 0.5 * r_p) / (np.sqrt(0.6) * ball)
    assert roundness[settled].mean() < min(roundness[ringing].mean(), loose_ball), \
        f"not settling into a ball from 0.4 s: {np.round(roundness[after], 3)}"
    assert roundness[settled].max() < 1.36, f"not a ball from 0.4 s: {np.round(roundness[settled], 3)}"
    assert farthest[after].max() < 1.15, f"a particle at {farthest[after].max():.3f} of the ball's radius"
    assert lonely[after].max() == 0, f"particles left the drop: {lonely[after]}"


def test_a_drop_in_flight_does_not_set_the_step_and_lands_at_a_spacing():
    """Spray needs no CFL of its own: one particle thrown from 20 cm above a resting 10 cm pool
    at 6 m/s, alone in the air, steps as its clearance lets it (k_far_rate: nothing within 2h,
    so dt (|v_i| + v) <= 2h - 2r; measured 4.8-4.9 ms, where the CFL on its speed gave 0.67 ms and
    the old worst-case rule dt (v_lone + v) <= h - 2r 3.0 ms), comes within h of the pool no nearer
    than 2r (measured 3.56 r; 2.75 r on the old rule), and does not throw the pool's particles
    faster than it came (measured 1.6 m/s; 2.7). With the CFL's small steps it went on into the
    pool to 0.17 r of a particle."""
    from pipeline.stages.sim import initial_state, make_solver, solver_params

    spec = ShotSpec.model_validate(tiny_spec(((0, 0, 0), (0.3, 0.1, 0.3)), ((0, 0, 0), (0.3, 0.6, 0.3))))
    params = solver_params(spec)
    state = initial_state(spec, params)
    x = state["position"]
    k = int(np.argmax(x[:, 1] - 0.01 * np.abs(x[:, 0] - 0.15) - 0.01 * np.abs(x[:, 2] - 0.15)))
    x[k], state["velocity"][k] = (0.15, 0.3, 0.15), (0.0, -6.0, 0.0)
    s = make_solver(spec, params, state)
    r, h, cfl = params.particle_radius, params.h, spec.sim.cfl
    flying, entered, pool_speed = [], None, 0.0
    while s.time < 0.06:
        dt = s.step(0.06)
        p, v = s.position.to_numpy(), s.velocity.to_numpy()
        j = int(np.flatnonzero(s.id.to_numpy() == state["id"][k])[0])
        nearest = np.delete(np.linalg.norm(p - p[j], axis=1), j).min()
        pool_speed = max(pool_speed, np.delete(np.linalg.norm(v, axis=1), j).max())
        if nearest > h:
            flying.append(dt)
        elif entered is None:
            entered = nearest
    # (2h - 2r) / (2 x 6 m/s) = 5 ms less the speed it gains falling; 4 ms: the old rule's 3 fails
    assert len(flying) >= 5 and min(flying) > 0.8 * (2 * h - 2 * r) / 12.0, f"steps in flight: {flying}"
    assert entered is not None and entered >= 2 * r * (1 - 1e-4), f"came within h at {entered / r:.2f} r"
    assert pool_speed < 6.0, f"a pool particle thrown at {pool_speed:.2f} m/s"



def test_a_body_falling_as_one_takes_long_steps_and_meets_the_pool_and_the_floor_at_a_spacing():
    """Where the flow moves faster than it deforms the step is the closing-speed CFL's
    (DFSPHSolver.stable_dt): a 6 cm cube falling at 5 m/s as a body, its bottom 4.2 r above a
    resting pool (cfl 0.8), takes a first step of 4.54 ms where the speed CFL gives 1.57 ms. Its
    particles outrun their neighbourhoods, so they are searched (k_far_rate): the cube comes
    within h of the pool no nearer than 2r (measured 2.05 r; without the search the step was
    max_dt's 8.33 ms and it came to 0.79 r of the pool in one step), and, over a bare floor, no
    nearer than r to it (measured 1.21 r; without the search the first step put it on the
    walls' clamp, 0.5 r)."""
    from scipy.spatial import cKDTree

    from pipeline.stages.sim import initial_state, make_solver, solver_params

    for pool in (True, False):
        job = tiny_spec(((0.07, 0.2, 0.07), (0.13, 0.26, 0.13)), ((0, 0, 0), (0.2, 0.4, 0.2)), sim={"cfl": 0.8})
        if pool:
            job["fluids"][0]["blocks"] += ({"min": (0.0, 0.0, 0.0), "max": (0.2, 0.06, 0.2)},)
        spec = ShotSpec.model_validate(job)
        params = solver_params(spec)
        state = initial_state(spec, params)
        r, h = params.particle_radius, params.h
        x, v = state["position"], state["velocity"]
        cube = x[:, 1] > 0.15
        below = x[~cube, 1].max() if pool else 0.0
        x[cube, 1] += below + 4.2 * r - x[cube, 1].min()
        v[cube] = (0.0, -5.0, 0.0)
        s = make_solver(spec, params, state)
        dt = s.step(0.03)
        assert dt > 2.0 * s.dt_speed, (dt, s.dt_speed)
        p = s.position.to_numpy()
        in_cube = np.isin(s.id.to_numpy(), state["id"][cube])
        if pool:
            nearest = cKDTree(p[~in_cube]).query(p[in_cube])[0].min()
            assert nearest >= 2 * r * (1 - 1e-3), f"the cube came to {nearest / r:.3f} r of the pool in one step"
        else:
            lowest = p[:, 1].min()
            assert lowest >= r * (1 - 1e-3), f"the cube came to {lowest / r:.3f} r of the floor in one step"


def test_spray_does_not_step_through_a_thin_collider():
    """The lone particles' step (k_far_rate) moves a particle towards a collider no farther
    than it is from it (at least cfl r a step): drops falling free at 5 and 7 m/s onto a plate
    1.5 r thick come to rest on it. Without the collider's term the longer steps took both
    through the plate to the floor; the test's drops start where that happened."""
    from pipeline.stages.sim import initial_state, make_solver, solver_params

    plate = {"type": "box", "min": (0.1, 0.2, 0.1), "max": (0.3, 0.215, 0.3)}
    for speed in (5.0, 7.0):
        spec = ShotSpec.model_validate(tiny_spec(((0, 0, 0), (0.08, 0.04, 0.08)), ((0, 0, 0), (0.4, 0.6, 0.4)),
                                                 colliders=(plate,)))
        params = solver_params(spec)
        state = initial_state(spec, params)
        k = int(np.argmax(state["position"][:, 1]))
        state["position"][k], state["velocity"][k] = (0.2, 0.47, 0.2), (0.0, -speed, 0.0)
        s = make_solver(spec, params, state)
        lowest = np.inf
        while s.time < 0.08:
            s.step(0.08)
            j = int(np.flatnonzero(s.id.to_numpy() == state["id"][k])[0])
            lowest = min(lowest, float(s.position.to_numpy()[j, 1]))
        assert lowest >= 0.215, f"the drop at {speed} m/s went to y = {lowest:.4f} m, into or through the plate"

def test_the_walls_images_are_listed_as_the_mirror_makes_them():
    """The density pass lists, for the sweeps, every image j' of a particle and its neighbours
    in the walls within h (each wall, and the edges' and corner's pairs and triple) with its
    grad W_ij': against numpy mirroring every pair in every wall subset. A block in a box corner
    has particles near one, two and three walls; its ~16 images a floor particle outgrow the
    pool's first size (one entry a particle), so its growth is taken too."""
    _spec, params, s = dfsph(tiny_spec(((0, 0, 0), (0.12, 0.1, 0.12)), ((0, 0, 0), (0.3, 0.3, 0.3))))
    s.update_lists()
    s.compute_density()
    assert s.img.shape[0] > s.n, "the pool never grew: the growth path went untested"
    x, h = s.position.to_numpy().astype(np.float64), params.h
    img, grad, span = s.img.to_numpy(), s.img_g.to_numpy(), s.img_span.to_numpy()
    lo, hi = np.zeros(3), np.full(3, 0.3)
    listed_by_walls = np.zeros(4, int)
    for i in range(s.n):
        near = np.abs(x[i] - lo) < h                     # walls within h: the low ones only here
        assert not (np.abs(x[i] - hi) < h).any()
        expected = {}
        for sub in range(1, 8):
            axes = [a for a in range(3) if sub >> a & 1]
            if not all(near[a] for a in axes):
                continue
            mirrored = x.copy()
            mirrored[:, axes] = 2 * lo[axes] - x[:, axes]
            d = np.linalg.norm(x[i] - mirrored, axis=1)
            for j in np.flatnonzero((d < h) & (d > 1e-9)):
                expected[j * 8 + sub] = x[i] - mirrored[j]
        start, count = span[i]
        assert count == len(expected), f"particle {i}: {count} images listed, {len(expected)} within h"
        for e, g in zip(img[start:start + count], grad[start:start + count]):
            rv = expected.pop(int(e))                     # KeyError: an image listed twice or not there
            r = np.linalg.norm(rv)
            exact = K.dw_np(params.density_kind, r, h) / r * rv
            assert np.linalg.norm(g - exact) <= 1e-4 * np.linalg.norm(exact), f"particle {i}: {g} != {exact}"
        listed_by_walls[near.sum()] += count
    assert (listed_by_walls[1:] > 0).all(), f"images listed near 1, 2, 3 walls: {listed_by_walls[1:]}"


def sheet_into_an_edge():
    """(params, solver): a water sheet four particles thick (r = 6 mm) sliding at 1.6 m/s, at 45
    degrees, into the vertical edge of a frictionless box's two walls; the anchor's fluid
    (bench/solver.py's 10 Pa s, free slip)."""
    r = 0.006
    _spec, params, s = dfsph({
        "shot": {"name": "t"},
        "sim": {"particle_radius": r, "cfl": 0.8, "max_density_error": 0.0005, "max_dt": 0.005},
        "domain": {"min": (0, 0, 0), "max": (0.3, 0.5, 0.3), "no_slip": False, "friction": 0.0},
        "fluids": ({"name": "water", "dynamic_viscosity": 10.0,
                    "blocks": ({"min": (0.04, 0, 0.04), "max": (0.16, 8 * r, 0.16),
                                "velocity": (-1.6 / math.sqrt(2), 0, -1.6 / math.sqrt(2))},)},)})
    return params, s


def test_the_factor_is_a_sweeps_exact_diagonal_where_the_neighbourhood_is_sparse():
    """A sweep's kappa_i = alpha_i e_i / dt^k removes particle i's error e_i only if 1 / alpha_i is
    how i's rate answers its own kappa. Measured for each particle with a wall near and fewer than
    MIN_DIVERGENCE_NEIGHBOURS (the sheet's, as it meets the edge): kappa = 1 at i alone, applied by
    the sweeps' own apply pass from rest, and i's rate summed here in numpy over its neighbours and
    the images the density pass listed (velocities mirrored). Bound 1e-3: float32 round-off
    (measured within 2e-7). The lumped factor, each image a neighbour of its own, read up to twice
    the response there (bench/RESULTS.md, thirty-eighth session)."""
    from solver.dfsph import MIN_DIVERGENCE_NEIGHBOURS, k_apply_kappa
    import taichi as ti

    params, s = sheet_into_an_edge()
    s.advance_to(0.032)
    s.update_lists()
    s.compute_density()
    x, nc, span = s.position.to_numpy(), s.near_count.to_numpy(), s.img_span.to_numpy()
    near, gfac, (lx, ly) = s.near.to_numpy(), s.gfac.to_numpy(), s.near_lay
    img, img_g, wall_grad = s.img.to_numpy(), s.img_g.to_numpy(), s.wall_grad.to_numpy()
    alpha = s.alpha.to_numpy()

    def rate(i, v):
        slots = i * lx + np.arange(nc[i]) * ly
        js = near[slots]
        out = v[i] @ wall_grad[i] + np.sum((v[i] - v[js]) * gfac[slots, None] * (x[i] - x[js]))
        for e, g in zip(img[span[i, 0]:span[i, 0] + span[i, 1]], img_g[span[i, 0]:span[i, 0] + span[i, 1]]):
            mirrored = v[e >> 3] * np.where([(e & 7) >> a & 1 for a in range(3)], -1.0, 1.0)
            out += (v[i] - mirrored) @ g
        return out

    sparse = np.flatnonzero((nc < MIN_DIVERGENCE_NEIGHBOURS) & (span[:, 1] > 0))
    assert len(sparse) >= 20, f"only {len(sparse)} sparse particles near the walls"
    scratch = ti.ndarray(ti.f32, s.n)
    dt = 1e-3
    for i in sparse[:: max(1, len(sparse) // 40)]:
        unit = np.zeros(s.n, np.float32)
        unit[i] = 1.0
        s.xk.from_numpy(np.c_[x, unit].astype(np.float32))       # the sweeps' positions with kappa
        s.v4.from_numpy(np.zeros((s.n, 4), np.float32))
        k_apply_kappa(s.xk, s.v4, s.fluid, s.near, s.near_count, s.gfac, s.near_lay, s.rows, *s.images,
                      scratch, s.wall_grad, dt, s.ftab, s.delta, 0.0, False)
        answer = -rate(i, s.v4.to_numpy()[:, :3].astype(np.float64)) / dt
        assert abs(answer * alpha[i] - 1.0) < 1e-3, \
            f"particle {i} ({nc[i]} neighbours, {span[i, 1]} images): 1 / alpha {1 / alpha[i]:.4g}, answer {answer:.4g}"


def test_a_sheet_sliding_into_an_edge_is_not_thrown_up_it():
    """The sheet above meets the edge at 1.6 m/s; over 0.12 s its fastest particle reaches 6.1
    m/s up the edge (measured; SPlisHSPlasH's DFSPH on the same sheet: 3.3). With the lumped
    factor at its sparse particles it reached 9.4 m/s, and the CFL took 91 steps where it now
    takes 65 (SPlisHSPlasH 64). Bound 7.5 m/s."""
    _params, s = sheet_into_an_edge()
    fastest = 0.0
    while s.time < 0.12:
        s.step(0.12)
        fastest = max(fastest, float(np.linalg.norm(s.velocity.to_numpy(), axis=1).max()))
    assert fastest < 7.5, f"the fastest particle reached {fastest:.2f} m/s"


def akinci_box_accelerations(r: float):
    """(positions, accelerations), by particle id, of the fill lattice in a closed box's lower
    half, no gravity, Akinci's tension at the example's gamma 0.15, before any step (and in
    tests/test_gpu.py, on CUDA)."""
    _spec, _params, s = dfsph(tiny_spec(((0, 0, 0), (0.3, 0.2, 0.3)), ((0, 0, 0), (0.3, 0.4, 0.3)),
                                        sim={"particle_radius": r, "gravity": (0, 0, 0),
                                             "surface_tension_model": "akinci"},
                                        fluid={"surface_tension": 0.15}))
    s.update_lists()
    s.compute_density()
    s.nonpressure()
    order = np.argsort(s.id.to_numpy(), kind="stable")      # by particle id: the same on every backend
    return s.position.to_numpy()[order], s.acceleration.to_numpy()[order]


def test_akinci_tension_takes_a_wall_for_more_water_not_a_surface():
    """The walls mirror the fluid for its density and pressure, and Akinci's cohesion and
    normals take the same images: a block filling a closed box's lower half (no gravity, gamma
    0.15, the example's) pulls its top layer down at 6.3 m/s^2, and the layer along a side wall,
    away from the top, away from the wall at 1.6 m/s^2 (the mirrored fcc planes do not continue
    the lattice's stacking: the wall layer sits 1.6 r from its image, 2.2 r from its neighbours).
    Without the images that layer was pulled as hard as the free surface (6.2 m/s^2), and in the
    example the pool drew back from the walls in a rounded rim a radius or two wide."""
    r, h = 0.01, 0.04
    p, a = akinci_box_accelerations(r)
    top = p[:, 1].max()
    away = (p[:, 2] > h) & (p[:, 2] < 0.3 - h)
    wall = away & (p[:, 1] > h) & (p[:, 1] < top - h) & (p[:, 0] < r)
    surface = away & (p[:, 1] > top - r) & (p[:, 0] > h) & (p[:, 0] < 0.3 - h)
    pull_top, pull_wall = -a[surface, 1].mean(), a[wall, 0].mean()
    assert pull_top > 3.0, f"the top layer is pulled in at {pull_top:.2f} m/s^2 only"
    assert abs(pull_wall) < 0.3 * pull_top, f"the wall layer is pulled off the wall at {pull_wall:.2f} m/s^2"


def test_a_tall_column_at_high_resolution_does_not_blow_up():
    """The example's column (0.4 m, 80 particles deep at r = 2.5 mm) in a 5 cm deep slice of
    its tank: in its first 40 ms no particle may pass 2 m/s (measured 1.3 m/s: the front
    starting off; Ritter's dam-break front moves at 2 sqrt(g H) = 4 m/s only later). With
    steps of max_dt (4.2 ms) the floor layer was squeezed to the collision clamp and particles
    ran along the floor at 8-13 m/s within 25 ms; the CFL speed's floor (dfsph.SPEED_FLOOR)
    caps the step at 1.6 r / sqrt(2 g H) = 1.4 ms here."""
    _spec, _params, s = dfsph(tiny_spec(((0.0, 0.0, 0.0), (0.34, 0.4, 0.05)), ((0, 0, 0), (1.0, 0.6, 0.05)),
                                        sim={"solver": "dfsph", "particle_radius": 0.0025}))
    s.advance_to(0.04)
    speed = np.linalg.norm(s.velocity.to_numpy(), axis=1).max()
    assert speed < 2.0, f"fastest particle {speed:.2f} m/s after {s.time * 1000:.0f} ms"


# ---------------------------------------------------------------------------------- resume
@pytest.mark.parametrize("fluid", [{}, {"dynamic_viscosity": 20.0}], ids=["water", "honey"])
def test_a_stop_mid_frame_resumes_bit_identically(fluid):
    """A stop between two steps (SIGTERM: the sim stage writes the exact state mid-frame) and a
    solver rebuilt from that state carry on exactly as an uninterrupted run, bit for bit on one
    thread. (Without a Verlet skin, the rebuilt solver must list neighbours at the current
    positions, as the running one does every step, not at the checkpoint's reference positions.)
    A fluid of 20 Pa s is solved implicitly, warm-started from the last step's correction: that
    travels in the state too."""
    from pipeline.stages.sim import make_solver

    job = tiny_spec(((0, 0, 0), (0.2, 0.3, 0.2)), ((0, 0, 0), (0.6, 0.4, 0.2)), fluid=fluid)
    spec, params, whole = dfsph(job)
    whole.advance_to(0.2)
    _spec, _params, split = dfsph(job)
    steps = []
    assert not split.advance_to(0.2, should_stop=lambda: steps.append(1) or len(steps) > 17)
    if fluid:
        assert split.frame_report()["viscosity_steps"] > 0
    c = split.controller()
    resumed = make_solver(spec, params, split.state(), time_s=c["time"], step=c["step"], dt_prev=c["dt_prev"])
    assert resumed.advance_to(0.2)
    a, b = whole.snapshot(), resumed.snapshot()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
