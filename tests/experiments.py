"""Published experiments the solver is measured against: their data, set-up and measures, once.

Read by tests/test_dfsph.py (which asserts) and bench/martin_moyce.py (which prints the whole
comparison and probes explanations), so that both measure the same thing the same way.

Martin & Moyce 1952, "An experimental study of the collapse of liquid columns on a rigid
horizontal plane", Phil. Trans. R. Soc. A 244, 312-324: the n^2 = 2, a = 2.25 in column, a
wide and 2a high, released on a dry horizontal floor.
"""
from __future__ import annotations

import numpy as np

G = 9.81
A_EXPERIMENT = 2.25 * 0.0254                # m: the column's width a in the runs below
# water as the experiment had it (about 20 C): Pa s and N/m
WATER = {"dynamic_viscosity": 1.0e-3, "surface_tension": 0.0728}

# Fig. 3: the surge front Z = z / a against T = t sqrt(2 g / a), as digitised in PySPH
# (pysph/examples/db_exp_data.py).
FRONT = np.array([(0.832, 1.217), (1.219, 1.474), (1.997, 2.292), (2.547, 2.995), (3.345, 4.134),
                  (4.034, 4.944), (4.418, 5.881), (5.091, 6.980), (5.685, 7.945), (6.306, 8.966),
                  (6.822, 9.986), (7.439, 10.963), (8.031, 11.977), (8.633, 13.005), (9.237, 13.970)])

# Table 6: the residual column's height at the back wall H / (n^2 a) against tau = t sqrt(g / a).
COLUMN = np.array([(0.56, 0.94), (0.77, 0.89), (0.93, 0.83), (1.08, 0.78), (1.28, 0.72), (1.46, 0.67),
                   (1.66, 0.61), (1.84, 0.56), (2.00, 0.50), (2.21, 0.44), (2.45, 0.39), (2.70, 0.33),
                   (3.06, 0.28), (3.44, 0.22), (4.20, 0.17), (5.25, 0.11)])


def front_time(T: float, a: float) -> float:
    """Seconds at Fig. 3's T for a column a wide."""
    return T / np.sqrt(2 * G / a)


def column_time(tau: float, a: float) -> float:
    """Seconds at Table 6's tau for a column a wide."""
    return tau / np.sqrt(G / a)


def collapsing_column(tank_length: float, a: float = 0.1, r: float = 0.005, depth: float = 0.05, *,
                      sim: dict | None = None, fluid: dict | None = None, domain: dict | None = None):
    """(params, solver) for the column, a wide and 2a high, inviscid, in a slice `depth` deep of
    a tank `tank_length` long and 2.5a high with frictionless walls: the pipeline's DFSPH solver,
    started as the sim stage starts it. `sim`, `fluid` and `domain` add job keys (a viscosity, a
    surface tension, the walls that hold it)."""
    from pipeline.spec import ShotSpec
    from pipeline.stages.sim import fresh_solver

    spec = ShotSpec.model_validate({
        "shot": {"name": "martin_moyce"}, "sim": {"particle_radius": r, **(sim or {})},
        "domain": {"min": (0, 0, 0), "max": (tank_length, 2.5 * a, depth), "friction": 0.0, **(domain or {})},
        "fluids": ({"name": "water", **(fluid or {"viscosity": 0.0}),
                    "blocks": ({"min": (0, 0, 0), "max": (a, 2 * a, depth)},)},)})
    return fresh_solver(spec)


def front(position: np.ndarray, a: float, r: float) -> float:
    """The surge front's Z: the leading edge (the third particle from the front, so that two
    stray particles ahead of the sheet do not count, plus its radius) over a."""
    return (np.sort(position[:, 0])[-3] + r) / a


def column_height(position: np.ndarray, a: float, r: float) -> float:
    """The column's H at the back wall: the second-highest particle within 2r of it, plus its
    radius, over the first height 2a."""
    return (np.sort(position[position[:, 0] < 2 * r, 1])[-2] + r) / (2 * a)
