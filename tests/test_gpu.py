"""The device backends against the CPU: CUDA where an NVIDIA GPU is (bench/gpu.sh runs these on a
lent GPU machine), Vulkan wherever Taichi can start a Vulkan device, Mesa's software one
(lavapipe, which scripts/setup.sh installs) included: its kernels go through Taichi's SPIR-V
code generator, as on an AMD or Intel GPU, so this machine checks that path without a GPU."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import tiny_spec
from pipeline.spec import ShotSpec
from solver.backend import nvidia_present, vulkan_starts

pytestmark = [pytest.mark.gpu]


NVIDIA = nvidia_present()
ONLY_CUDA = pytest.mark.skipif(not NVIDIA, reason="no NVIDIA GPU on this machine")
ONLY_VULKAN = pytest.mark.skipif(not vulkan_starts(software=True), reason="no Vulkan device here")
DEVICES = [pytest.param("cuda", marks=ONLY_CUDA), pytest.param("vulkan", marks=ONLY_VULKAN)]


BOULDER = Path(__file__).resolve().parents[1] / "jobs" / "assets" / "boulder.obj"


def small_dambreak(mesh: bool = False, solver: str = "dfsph"):
    colliders = ({"type": "mesh", "path": str(BOULDER), "scale": 0.1, "translate": (0.3, 0.03, 0.15)},) if mesh else ()
    return ShotSpec.model_validate(tiny_spec(((0, 0, 0), (0.2, 0.3, 0.3)), ((0, 0, 0), (0.6, 0.4, 0.3)),
                                             name="g", colliders=colliders, sim={"solver": solver}))


def run_on(backend: str, t_end: float, mesh: bool = False, solver: str = "dfsph", spec=None):
    """The snapshot after t_end of `spec` (default: small_dambreak) on `backend`. The solver
    goes with this call, before the next ti.init: a device array freed after it is freed through
    the new program (see solver.backend.init_taichi), which crashed lavapipe in 3 of 8 runs when
    a test kept its last solver alive across it."""
    from solver.backend import init_taichi
    init_taichi(backend, 1 if backend == "cpu" else 0)
    from pipeline.stages.sim import fresh_solver
    _params, s = fresh_solver(spec or small_dambreak(mesh, solver))
    s.advance_to(t_end)
    return s.snapshot()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("solver", ["dfsph", "wcsph"])
def test_device_matches_cpu_early_on(solver, device):
    """Before the flow turns chaotic (first 20 ms), CUDA and CPU agree: WCSPH to float32
    round-off amplified over about 100 steps (positions within 1e-6 m); DFSPH within a twentieth
    of a radius (see below)."""
    gpu = run_on(device, 0.02, solver=solver)
    cpu = run_on("cpu", 0.02, solver=solver)
    # WCSPH: float32 round-off only. DFSPH's solves stop at an error bound, so round-off can
    # change a step's sweep count and the velocities by one sweep's correction: on the H200
    # positions differed by up to 1e-4 m (a hundredth of a radius) after 0.02 s
    np.testing.assert_allclose(gpu["position"], cpu["position"], atol=1e-6 if solver == "wcsph" else 5e-4)
    np.testing.assert_allclose(gpu["density"], cpu["density"], rtol=1e-3 if solver == "wcsph" else 1e-2)


@pytest.mark.parametrize("device", DEVICES)
def test_device_two_fluids_match_cpu_early_on(device):
    """Water (1000 kg/m^3) and oil (800) side by side collapsing together, DFSPH with the
    multi-phase density (each particle's own mass over the neighbours' volumes): the same
    first 20 ms on the device as on the CPU, within test_device_matches_cpu_early_on's DFSPH
    bounds (a solve's sweep count may differ by one through round-off), and each fluid's mean
    density within 0.05 % of the CPU's, so the device sees the same contrast. Measured on
    lavapipe: positions within 6e-8 m, densities within 3e-6; it passed on an H200 (2026-11-28)."""
    job = tiny_spec(((0, 0, 0), (0.1, 0.3, 0.3)), ((0, 0, 0), (0.6, 0.4, 0.3)), name="g",
                    fluid={"rest_density": 1000.0})
    job["fluids"] = (job["fluids"][0], {"name": "oil", "rest_density": 800.0,
                                         "blocks": ({"min": (0.1, 0, 0), "max": (0.2, 0.3, 0.3)},)})
    spec = ShotSpec.model_validate(job)
    gpu, cpu = run_on(device, 0.02, spec=spec), run_on("cpu", 0.02, spec=spec)
    np.testing.assert_array_equal(gpu["fluid"], cpu["fluid"])
    np.testing.assert_allclose(gpu["position"], cpu["position"], atol=5e-4)
    np.testing.assert_allclose(gpu["density"], cpu["density"], rtol=1e-2)
    for k, rest in ((0, 1000.0), (1, 800.0)):
        mine = cpu["fluid"] == k
        assert abs(np.median(cpu["density"][mine]) / rest - 1) < 0.02, (k, np.median(cpu["density"][mine]))
        assert abs(gpu["density"][mine].mean() / cpu["density"][mine].mean() - 1) < 5e-4, k


@pytest.mark.parametrize("device", DEVICES)
def test_device_mesh_collider_matches_cpu(device):
    """The mesh collider's distance grid on CUDA: the block has reached the boulder by 0.15 s;
    no particle is inside it on either backend, and the mean positions agree within a radius
    (the flow is chaotic by then, so particle by particle they do not)."""
    pytest.importorskip("meshio", reason="the OBJ reader is not installed on this GPU machine")
    pytest.importorskip("pyopenvdb", reason="OpenVDB (the mesh's distance grid) is not installed on this GPU machine")
    from pipeline.stages.sim import solver_params
    from solver.boundaries import collider_clearance
    out = {b: run_on(b, 0.15, mesh=True) for b in (device, "cpu")}
    params = solver_params(small_dambreak(True))
    for b, snap in out.items():
        assert collider_clearance(params, snap["position"]).min() > 0, b
    np.testing.assert_allclose(out[device]["position"].mean(0), out["cpu"]["position"].mean(0), atol=0.01)


@pytest.mark.parametrize("device", DEVICES)
def test_device_mesh_collider_normals_match_the_trilinear_field(device):
    """tests/test_solver.py's check of a mesh collider's distance and normal, on CUDA (a distance
    grid made in NumPy: no OpenVDB needed). Before the tolerance in boundaries.mesh_sdf, 86 % of
    the points near the showcase's boulder had a normal unlike the CPU's on the H200."""
    from solver.backend import init_taichi
    init_taichi(device, 0)
    from test_solver import test_mesh_collider_normals_match_the_trilinear_field as check
    check()


@pytest.mark.parametrize("device", DEVICES)
def test_device_analytic_colliders_match_cpu(device):
    """Sphere, box and capsule colliders' distance and normal on CUDA against the CPU's at points
    around each (the mesh collider's normals were once wrong on CUDA alone; these have no test
    of their own there). Float32 on both: within 1e-6 m and 1e-5."""
    import dataclasses

    from pipeline.stages.sim import solver_params
    from solver.backend import init_taichi
    from test_solver import collider_probe

    spec = ShotSpec.model_validate(tiny_spec(((0.1, 0.1, 0.1), (0.2, 0.2, 0.2)), ((0, 0, 0), (1.0, 0.6, 0.4)),
        colliders=({"type": "sphere", "center": (0.45, 0.25, 0.2), "radius": 0.08},
                   {"type": "box", "min": (0.7, 0.0, 0.1), "max": (0.74, 0.3, 0.3)},
                   {"type": "capsule", "a": (0.3, 0.05, 0.05), "b": (0.3, 0.05, 0.35), "radius": 0.03})))
    params = solver_params(spec)
    pts = (np.random.default_rng(4).random((6000, 3)) * [1.0, 0.6, 0.4]).astype(np.float32)
    for k in range(3):
        one = dataclasses.replace(params, colliders=(params.colliders[k],))
        got = {}
        for backend in (device, "cpu"):
            init_taichi(backend, 1 if backend == "cpu" else 0)
            got[backend] = collider_probe(one, pts)
        np.testing.assert_allclose(got[device][0], got["cpu"][0], atol=1e-6, err_msg=str(k))
        np.testing.assert_allclose(got[device][1], got["cpu"][1], atol=1e-5, err_msg=str(k))


@pytest.mark.parametrize("device", DEVICES)
def test_device_implicit_viscosity_matches_cpu(device):
    """A viscosity solved implicitly (solver.viscosity's conjugate gradients) with no-slip walls,
    on CUDA: tests/test_dfsph.py's channel mode at 10 Pa s, r = 5 mm, where every step is past
    the explicit limit; after 0.05 s its amplitude agrees with the CPU's within 1 % (the CG stops
    at a relative residual of 1e-3, so round-off may change its sweep count by one)."""
    from solver.backend import init_taichi
    from test_dfsph import shear_wave
    decay = {}
    for backend in (device, "cpu"):
        init_taichi(backend, 1 if backend == "cpu" else 0)
        s, amplitude, _rate = shear_wave(10.0, 0.005, True, "sinsin")
        a0 = amplitude()
        s.advance_to(0.05)
        assert s.frame_report()["viscosity_steps"] > 0, backend
        decay[backend] = amplitude() / a0
        del s, amplitude            # before the next ti.init (see run_on)
    assert abs(decay[device] / decay["cpu"] - 1.0) < 0.01, decay


@pytest.mark.parametrize("device", DEVICES)
def test_device_akinci_tension_with_the_walls_images_matches_cpu(device):
    """Akinci's cohesion and curvature with the walls' images (dfsph.image_tension) on CUDA:
    tests/test_dfsph.py's lattice in a closed box, accelerations before any step, against the
    CPU's, particle by particle; float32 sums in another order: within 1e-3 m/s^2 of
    accelerations up to about 10 m/s^2."""
    from solver.backend import init_taichi
    from test_dfsph import akinci_box_accelerations
    got = {}
    for backend in (device, "cpu"):
        init_taichi(backend, 1 if backend == "cpu" else 0)
        got[backend] = akinci_box_accelerations(0.01)
    np.testing.assert_allclose(got[device][0], got["cpu"][0], atol=1e-7)
    np.testing.assert_allclose(got[device][1], got["cpu"][1], atol=1e-3)


@ONLY_VULKAN
@pytest.mark.skipif(NVIDIA or vulkan_starts(), reason="a GPU here: auto takes it")
def test_auto_leaves_the_software_vulkan_device_to_an_explicit_ask(monkeypatch):
    """With a render node (as in a VM) but no GPU's Vulkan driver, "auto" must not land on
    Mesa's software device, several times slower than Taichi's CPU backend; "vulkan" may."""
    from solver import backend
    monkeypatch.setattr(backend, "_render_node_present", lambda: True)
    assert backend.init_taichi("auto", 1) == "cpu"
    assert backend.init_taichi("vulkan", 0) == "vulkan"


@ONLY_CUDA
def test_auto_backend_picks_cuda():
    from solver.backend import init_taichi
    assert init_taichi("auto", 0) == "cuda"


def _surface(backend: str, anisotropic: bool = False):
    from solver.backend import init_taichi
    init_taichi(backend, 1 if backend == "cpu" else 0)
    from surfacing.reconstruct import color_field, marching_cubes
    rng = np.random.default_rng(5)
    ax = np.arange(24) * 0.01
    pos = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    pos = (pos + rng.uniform(-0.002, 0.002, pos.shape)).astype(np.float32)
    vel = rng.normal(size=pos.shape).astype(np.float32)
    vol = np.full(len(pos), 0.01 ** 3, np.float32)
    iso = 0.2 if anisotropic else 0.5
    # anisotropic: with the surface stage's default centre smoothing (both passes: anisotropy.k_inflate)
    from pipeline.spec import Surface
    stage = Surface()
    smooth = ({"center_smoothing": stage.center_smoothing, "center_inflation": stage.center_inflation}
              if anisotropic else {})
    field = color_field(pos, vel, vol, 0.00375, 0.02, iso, anisotropic=anisotropic, spray_below=25 if anisotropic else 0,
                        **smooth)
    mesh = marching_cubes(field, iso)
    return field.color.copy(), field.velocity.copy(), field.velocity_ids, mesh


@pytest.mark.parametrize("device", DEVICES)
def test_device_surfacer_matches_cpu(device):
    """The surfacer on CUDA (fixed-point atomic scatter, device-resident arrays, parallel
    normals) against the CPU's (phased float scatter): the color within 2e-5 (float32 round-off
    of sums of ~50 terms), so the same blocks and, but for vertices on edges whose ends sit within
    that of the iso value, the same mesh (vertex counts within 0.1 %); velocities where the color
    is over 1e-3 within 1e-4 m/s; CUDA twice gives the same bits."""
    gpu_color, gpu_vel, gpu_ids, gpu_mesh = _surface(device)
    again_color, _v, _i, again_mesh = _surface(device)
    cpu_color, cpu_vel, cpu_ids, cpu_mesh = _surface("cpu")
    np.testing.assert_array_equal(gpu_color, again_color)
    np.testing.assert_array_equal(gpu_mesh.normals, again_mesh.normals)
    np.testing.assert_allclose(gpu_color, cpu_color, atol=2e-5)
    assert abs(len(gpu_mesh.points) - len(cpu_mesh.points)) <= 1e-3 * len(cpu_mesh.points)
    if len(gpu_mesh.points) == len(cpu_mesh.points):
        # a vertex's place along its edge is (iso - c0) / (c1 - c0): where c1 - c0 is small, the
        # colors' 1e-6 differences move it further (on the H200: 1 of 80,490 by 2.5e-5 m)
        err = np.abs(gpu_mesh.points - cpu_mesh.points).max(1)
        assert (err < 1e-5).mean() > 0.999 and err.max() < 0.00375 / 10, err.max()
    np.testing.assert_array_equal(gpu_ids, cpu_ids)
    solid = cpu_color[cpu_ids] > 1e-3
    np.testing.assert_allclose(gpu_vel[:-1][solid], cpu_vel[:-1][solid], atol=1e-4)   # speeds ~1 m/s


@pytest.mark.parametrize("device", DEVICES)
def test_device_anisotropic_surfacer_matches_cpu(device):
    """The anisotropic kernels (surfacing/anisotropy.py: covariance and SVD per particle, the
    centres smoothed in two passes, then the stretched splat) on CUDA against the CPU: the
    kernel shapes come from float32 SVDs that may round differently, so the color within 2e-4
    (not 2e-5), the same blocks, vertex counts within 0.5 %."""
    gpu_color, _gv, gpu_ids, gpu_mesh = _surface(device, anisotropic=True)
    cpu_color, _cv, cpu_ids, cpu_mesh = _surface("cpu", anisotropic=True)
    assert gpu_color.shape == cpu_color.shape
    np.testing.assert_allclose(gpu_color, cpu_color, atol=2e-4)
    assert abs(len(gpu_mesh.points) - len(cpu_mesh.points)) <= 5e-3 * len(cpu_mesh.points)
