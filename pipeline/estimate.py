"""Pre-flight estimate of a shot's memory and disk, from the spec alone (nothing allocated).

Figures per unit, measured (bench/RESULTS.md, eleventh session):
- solver: about 1,000 bytes a particle on the compute device (973 WCSPH, 1,025 DFSPH on the
  H200; the two neighbour lists are ~800 of it; DFSPH keeps one list on a GPU since the
  thirteenth session, and two again on the CPU since the forty-second, a copy in narrower
  rows: 246 MB peak resident for the CPU bench's 50,622 particles, 234 with one), plus host
  copies of the state for frames and checkpoints: SIM_BYTES per particle in all. A DFSPH shot
  whose viscosity can pass its explicit limit within sim.max_dt solves it implicitly
  (solver.viscosity), and from the first such step holds the CG's six arrays (48 bytes a
  particle) and each list slot's pair weight (4 bytes, 64 slots on the CPU bench): VISCOUS_BYTES
  more (forty-third session: the bench's peak 238.7 MB against 232.7);
- surfacing: about 36 grid nodes a particle at the default 0.75 r cell (18.0M nodes for 502,606
  particles) and about 26 bytes a node at the peak (color, velocity band, marching cubes'
  arrays: 720 MB for the 500k frame with velocities, 250 MB of it Python and Taichi). A splash
  spreads the blocks (thirty-sixth session, jobs/showcase.toml's surface stage: 2.0 GB peak
  resident at its splashiest frame 24, 1.31 GB at the calm frame 120, against 1.5 GB
  estimated at 26 bytes a node): counted as 38, a few per cent over it;
- a mesh collider's distance grid: OpenVDB voxelises the whole mesh, not only the part inside
  the domain: 12 bytes a voxel over the mesh's own box;
- rendering (twenty-second session, the example's render stage alone, peak resident): 512, 573
  and 708 MB at 480x270, 960x540 and 1920x1080 with SSAA: VTK, PyVista and Mesa's llvmpipe
  about 490 MB over Python's own, and about 110 bytes an output pixel; counted as RENDER_BYTES
  over BASE_BYTES and 120 a pixel. The frame's fluid mesh and, under the water look, its level
  set read densely come on top (thirty-sixth session, jobs/showcase.toml at 1920x1080: 1.17,
  1.79 and 1.20 GB peak resident at frames 12, 24 and 120, meshes of 0.99, 2.17 and 0.92 M
  vertices; frame 24 under the clay look, no level set read, 1.54 GB): about 340 bytes a mesh
  vertex, counted at PEAK_VERTICES vertices a cell^2 of the fluid blocks' starting surface (the
  showcase's frame 24: 4.35; the example jobs' splashiest frames 2.1-3.3), and 4 bytes a cell
  of the domain for the level set (its box, at most the domain's: 0.25 GB for that frame).
  Until then the showcase's rendering was estimated at 0.67 GB. The example end to end in one process peaked at 738 MB
  (sim alone 215, surface alone 408: OpenVDB, scikit-image and the meshes' arrays about 110 MB
  over Python and Taichi, counted as SURFACE_BYTES);
- what every run holds: Python, NumPy and the pipeline (BASE_BYTES), and Taichi once a sim or
  surface stage has initialised it (TAICHI_BYTES; the render stage never loads it). Twenty-third
  session, the example's 4 frames of one stage a process: sim 177, surface 380, render 553 MB
  resident (960x540), against 308, 426 and 609 MB estimated; until then the render alone was
  charged for Taichi as well (809 MB);
- disk (the example jobs' full runs, twenty-second session): a sim frame is 41-43 bytes a
  particle (position, velocity, density, pressure, id, fluid), a checkpoint 65. A surface frame
  grows with the water's surface, not its particles: over a whole shot 296-329 bytes a frame per
  cell^2 of the fluid blocks' starting surface (dambreak, two_fluids, boulder: the surface
  spreads, splashes and ripples), of which the binary PLY mesh is about 40 % (OBJ, ASCII, 2.5
  times that), the `vel` grid 33 %, `surface` and `density` 14 % each; counted here with a
  quarter more. A rendered PNG is 0.33-0.36 bytes a pixel (counted as 0.5), a 16-bit depth
  PNG at most 2.
"""
from __future__ import annotations

import contextlib
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from solver.lattice import Domain, site_count
from solver.stability import explicit_viscous_limit

from .stages import STAGES

SIM_BYTES = 1_200              # per particle: device arrays and host copies
VISCOUS_BYTES = 320            # per particle, where DFSPH may solve viscosity implicitly (docstring)
NODE_BYTES = 38                # per surfacing grid node, at the peak of one frame (module docstring)
NODES_PER_CELL_VOLUME = 1.9    # blocks reach a support beyond the fluid: 36 nodes/particle at 0.75 r
VOXEL_BYTES = 12               # per collider distance-grid voxel while OpenVDB builds it
BASE_BYTES = 100 * 2 ** 20     # Python, NumPy and the pipeline loaded
TAICHI_BYTES = 200 * 2 ** 20   # Taichi loaded and initialised (the sim and surface stages)
RENDER_BYTES = 450 * 2 ** 20   # VTK, PyVista and Mesa loaded, while rendering
SURFACE_BYTES = 120 * 2 ** 20  # OpenVDB and scikit-image loaded, while surfacing
PIXEL_BYTES = 120              # per output pixel, while rendering
RENDER_VERTEX_BYTES = 340      # per vertex of the frame's fluid mesh, while rendering
PEAK_VERTICES = 4.4            # the splashiest frame's mesh vertices per cell^2 of the starting surface
LEVEL_SET_BYTES = 4            # per cell of the domain: the frame's level set, read densely (water look)
FRAME_BYTES, CHECKPOINT_BYTES = 44, 66        # on disk, per particle
# a surface frame, per cell^2 of the fluid blocks' starting surface (module docstring)
MESH_BYTES = {"ply": 150.0, "vtu": 150.0, "obj": 375.0}
GRID_BYTES = {"surface": 55.0, "density": 55.0, "velocity": 125.0}
PNG_BYTES, DEPTH_BYTES = 0.5, 2.0              # a rendered frame, per pixel


@dataclass(frozen=True)
class Estimate:
    particles: float
    sim: float                 # bytes while the sim stage runs
    colliders: float           # bytes while the mesh colliders' distance grids are built
    surface: float             # bytes while one frame is surfaced (its libraries included)
    render: float              # bytes while a frame is rendered (its libraries included)
    disk: float                # bytes the whole shot writes

    @property
    def memory(self) -> float:
        return self.memory_for(STAGES)

    def parts(self, stages) -> dict[str, float]:
        """What each of these stages holds at its peak beyond BASE_BYTES and Taichi (the
        colliders' grids are built as the sim starts)."""
        every = {"sim": self.sim + self.colliders, "surface": self.surface, "render": self.render}
        return {stage: every[stage] for stage in stages}

    def memory_for(self, stages) -> float:
        """The peak of a run of these stages: they run one after another, in one process that
        keeps Taichi once a stage has loaded it."""
        taichi = TAICHI_BYTES if {"sim", "surface"} & set(stages) else 0.0
        return BASE_BYTES + taichi + max(self.parts(stages).values(), default=0.0)

    def line(self, stages=STAGES) -> str:
        """The estimate in words: the peak of these stages, then what each holds at its own
        (they run in turn, so the peak is not their sum)."""
        each = {"sim": f"sim {_gb(self.sim)}, collider grids {_gb(self.colliders)}",
                "surface": f"surfacing {_gb(self.surface)}", "render": f"rendering {_gb(self.render)}"}
        return (f"{_count(self.particles)} particles; memory {_gb(self.memory_for(stages))} at the peak (the "
                f"stages run in turn: {', '.join(each[s] for s in stages)}); disk {_gb(self.disk)}")


def estimate(spec) -> Estimate:
    r = spec.sim.particle_radius
    d = 2.0 * r
    particles = area = 0.0
    blocks = [b for f in spec.fluids for b in f.blocks]
    domain = Domain(spec.domain.min, spec.domain.max, spec.domain.open, d, spec.sim.fill_lattice,
                    [(b.min, b.max) for b in blocks])
    for bi, b in enumerate(blocks):
        particles += site_count(domain, bi)                         # solver/fill.py's count
        x, y, z = (max(hi - lo, d) for lo, hi in zip(b.min, b.max))
        area += 2.0 * (x * y + y * z + x * z)
    cell = spec.surface_cell_m
    nodes = particles * (d / cell) ** 3 * NODES_PER_CELL_VOLUME
    voxels = 0.0
    for ci, col in enumerate(spec.colliders):
        if col.type == "mesh":
            verts, _tris = spec.collider_mesh(ci)
            pad = spec.sdf_pad(col)
            extent = verts.max(0) - verts.min(0) + 2 * pad
            voxels += math.prod(float(e) / spec.collider_voxel_m(col) + 2 for e in extent)
    frames = len(spec.frames)
    checkpoints = frames / max(spec.shot.checkpoint_every, 1) + 2
    surface_frame = area / cell / cell * (MESH_BYTES[spec.surface.format]
                                        + sum(GRID_BYTES[g] for g in spec.surface.grids))
    w, h = spec.render.resolution
    render_frame = w * h * (PNG_BYTES + (DEPTH_BYTES if spec.render.depth != "none" else 0.0))
    disk = (particles * (frames * FRAME_BYTES + checkpoints * CHECKPOINT_BYTES)
            + frames * (surface_frame + render_frame))
    render = RENDER_BYTES + w * h * PIXEL_BYTES
    if spec.render.mode == "surface":
        render += PEAK_VERTICES * area / cell / cell * RENDER_VERTEX_BYTES
        if _reads_level_set(spec):
            volume = math.prod(hi - lo for lo, hi in zip(spec.domain.min, spec.domain.max))
            render += LEVEL_SET_BYTES * volume / cell / cell / cell
    sim = particles * (SIM_BYTES + (VISCOUS_BYTES if _implicit_viscosity(spec) else 0))
    return Estimate(particles, sim=sim, colliders=voxels * VOXEL_BYTES,
                    surface=SURFACE_BYTES + nodes * NODE_BYTES, render=render, disk=disk)


def _implicit_viscosity(spec) -> bool:
    """Whether a DFSPH step can pass Morris's explicit limit (the solver then takes viscosity
    implicitly, solver.dfsph.kick): its steps are never longer than sim.max_dt. (The solver's
    limit takes eta times the fill lattice's viscous_scale, within a few per cent of 1.)"""
    if spec.sim.solver != "dfsph":
        return False
    nu = [spec.fluid_viscosity(fi)[1] / f.rest_density for fi, f in enumerate(spec.fluids)]
    return explicit_viscous_limit(spec.sim.kernel_radius * spec.sim.particle_radius, nu) < spec.sim.max_dt


def _reads_level_set(spec) -> bool:
    """Whether the render stage reads each frame's level set (FrameRenderer._level_set): a look
    that draws the water by its depth, with a translucent material, and a `surface` grid."""
    from .stages.render import draws_depth, look_of

    return draws_depth(look_of(spec.render)) and "surface" in spec.surface.grids


def available_memory() -> float:
    """Bytes this machine can give now (MemAvailable), or its physical memory."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return float(line.split()[1]) * 1024
    except OSError:
        pass
    return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def free_disk(path: Path) -> float:
    """Free bytes where `path` will be (its nearest existing folder)."""
    p = Path(path)
    while not p.exists() and p != p.parent:
        p = p.parent
    return float(shutil.disk_usage(p).free)


def used_disk(path: Path) -> float:
    """Bytes already under `path` (a resumed shot's frames: they are not written again)."""
    total = 0
    for folder, _dirs, files in os.walk(path):
        for name in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(folder, name)).st_size
    return float(total)


def too_big(spec, est: Estimate, max_memory: float | None = None, stages=tuple(STAGES)) -> str | None:
    """One line saying why a run of these stages of the shot cannot run here, or None."""
    limit = max_memory if max_memory is not None else available_memory()
    where = "--max-memory" if max_memory is not None else "available on this machine"
    if BASE_BYTES > limit:
        return f"--max-memory {_gb(limit, '')} is less than Python and the libraries take ({_gb(BASE_BYTES)})"
    if est.memory_for(stages) > limit:
        parts = est.parts(stages)
        largest = max(parts, key=parts.get)
        if largest == "render":
            culprit = "render.resolution (or render on a larger machine: --stage render)"
        elif largest == "sim" and est.colliders > est.sim:
            culprit = "the mesh colliders' voxel_size (or their scale)"
        else:
            culprit = f"sim.particle_radius = {spec.sim.particle_radius:g} m (a larger radius or smaller fluid blocks)"
        return f"the shot needs {est.line(stages)}: over the {_gb(limit, '')} {where}; change {culprit}"
    free, written = free_disk(spec.output_root), used_disk(spec.output_root)
    if est.disk - written > free:
        more = f" more (of {_gb(est.disk, '')} in all)" if written else ""
        return (f"the shot would write {_gb(est.disk - written)}{more} to {spec.output_root}, which has "
                f"{_gb(free, '')} free; use a larger sim.particle_radius, fewer frames or another shot.output")
    return None


def _gb(n: float, about: str = "about ") -> str:
    if not math.isfinite(n) or n >= 1e15:
        return "over a petabyte"
    return f"{about}{n / 2 ** 30:.3g} GB" if n >= 2 ** 30 / 10 else f"{about}{n / 2 ** 20:.3g} MB"


def _count(n: float) -> str:
    return "over 1e15" if not math.isfinite(n) or n >= 1e15 else f"about {n:,.0f}"
