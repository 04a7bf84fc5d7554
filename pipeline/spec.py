"""The shot job spec: one TOML file, validated once into one frozen object.

Units: SI throughout (metres, seconds, kg/m^3, Pa s, N/m). The few lengths given in particle
radii say so in their name's documentation and are converted once, in the properties at the
bottom of :class:`ShotSpec`. Axes: y is up (Houdini's convention), so the default gravity is
(0, -9.81, 0).

Every key is documented in docs/jobspec.md.
"""
from __future__ import annotations

import difflib
import math
import os
import re
import tomllib
import typing
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, field_validator, model_validator

from .errors import SpecError

Vec3 = tuple[float, float, float]
Color = tuple[
    Annotated[float, Field(ge=0, le=1)],
    Annotated[float, Field(ge=0, le=1)],
    Annotated[float, Field(ge=0, le=1)],
]
Pos = Annotated[float, Field(gt=0)]
NonNeg = Annotated[float, Field(ge=0)]
Unit = Annotated[float, Field(ge=0, le=1)]


def _check_extent(lo, hi) -> None:
    for axis, a, b in zip("xyz", lo, hi):
        if not b > a:
            raise ValueError(f"max.{axis} must be > min.{axis}, got {b} <= {a}")


class Strict(BaseModel):
    """Unknown keys rejected, no type coercion (an int is accepted where a float is asked),
    no NaN or infinity anywhere (TOML has them: `nan`, `inf`)."""
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


# --------------------------------------------------------------------------------------- shot
class Shot(Strict):
    name: Annotated[str, Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]*$", max_length=64)]
    frame_start: Annotated[int, Field(ge=0, le=99999)] = 1
    frame_end: Annotated[int, Field(ge=0, le=99999)] = 48
    fps: Pos = 24.0
    output: str = "shots"          # folder; relative paths are relative to the job file
    version: Annotated[int, Field(ge=1, le=999)] = 1
    checkpoint_every: Annotated[int, Field(ge=1)] = 10   # frames between full-state checkpoints

    @field_validator("output")
    @classmethod
    def _variables_set(cls, output):
        expanded = os.path.expandvars(os.path.expanduser(output))
        if "$" in expanded:
            unset = sorted(set(re.findall(r"\$\{?([A-Za-z_][A-Za-z0-9_]*)", expanded)))
            raise ValueError(f"expected environment variables that are set, got {', '.join('$' + v for v in unset)} unset")
        return output

    @model_validator(mode="after")
    def _range(self):
        if self.frame_end < self.frame_start:
            raise ValueError(f"frame_end must be >= frame_start, got {self.frame_end} < {self.frame_start}")
        return self


# ---------------------------------------------------------------------------------------- sim
class Kernels(Strict):
    """Which smoothing kernel serves which term. Unset: the solver's own (WCSPH: Müller et al.
    2003's poly6 and spiky; DFSPH: the cubic spline for both, as it needs one kernel for the
    density and its gradient)."""
    density: Literal["poly6", "cubic", "wendland"] | None = None
    pressure: Literal["spiky", "cubic", "wendland"] | None = None
    viscosity: Literal["viscosity"] = "viscosity"
    surface_tension: Literal["poly6"] = "poly6"


class Sim(Strict):
    solver: Literal["dfsph", "wcsph"] = "dfsph"      # Bender & Koschier 2017, or Müller 2003
    backend: Literal["auto", "cpu", "cuda", "vulkan"] = "auto"
    threads: Annotated[int, Field(ge=0)] = 0          # CPU threads, 0 = every allowed core
    particle_radius: Pos = 0.01                      # m; lattice spacing is 2 radii
    kernel_radius: Annotated[float, Field(gt=1, le=8)] = 4.0  # support h, in particle radii
    gravity: Vec3 = (0.0, -9.81, 0.0)                # m/s^2, any constant acceleration
    speed_of_sound: Annotated[float, Field(ge=0)] = 0.0  # m/s (wcsph); 0 = 10x expected max speed
    max_speed: Annotated[float, Field(ge=0)] = 0.0    # m/s expected; 0 = sqrt(2 g H) of the fluid
    gamma: Pos = 7.0                                 # Tait exponent (wcsph)
    cfl: Annotated[float, Field(gt=0, le=1)] = 0.4    # wcsph: of h/2 at sound speed; dfsph: radii a step
    max_density_error: Annotated[float, Field(gt=0, le=0.1)] = 0.001     # dfsph: mean compression
    max_divergence_error: Annotated[float, Field(gt=0, le=0.1)] = 0.001  # dfsph: mean rate x dt
    max_iterations: Annotated[int, Field(ge=1, le=10000)] = 100          # dfsph: per solve and step
    max_dt: Pos = 1.0 / 120.0                        # s
    surface_threshold: Pos = 0.4                     # |grad c| * h above which tension acts (mueller)
    # mueller: Müller et al. 2003's color-field force; akinci: Akinci et al. 2013's cohesion and
    # curvature (dfsph only), which holds drops together instead of pushing surface particles off
    surface_tension_model: Literal["mueller", "akinci"] = "mueller"
    max_density_ratio: Annotated[float, Field(gt=1)] = 1.5  # instability guard on rho/rho0
    kernels: Kernels = Kernels()
    # the blocks' starting lattice (solver/lattice.py): "fcc" (dfsph's default) starts no rows
    # that a collapsing column keeps as ribs; "cubic" (wcsph's, the only one it takes)
    fill: Literal["fcc", "cubic"] | None = None

    @model_validator(mode="after")
    def _one_kernel_for_dfsph(self):
        k = self.kernels
        given = {v for v in (k.density, k.pressure) if v is not None}
        if self.solver == "dfsph" and (given - {"cubic", "wendland"} or len(given) > 1):
            raise ValueError(f"kernels: dfsph takes one kernel, \"cubic\" or \"wendland\", for the density and "
                             f"its gradient; got density = {k.density!r}, pressure = {k.pressure!r}")
        return self

    @model_validator(mode="after")
    def _akinci_needs_dfsph(self):
        if self.surface_tension_model == "akinci" and self.solver != "dfsph":
            raise ValueError("surface_tension_model: \"akinci\" needs solver = \"dfsph\"")
        return self

    @model_validator(mode="after")
    def _fcc_needs_dfsph(self):
        if self.fill == "fcc" and self.solver != "dfsph":
            raise ValueError("fill: \"fcc\" needs solver = \"dfsph\" (wcsph's wall samples and hydrostatic "
                             "start are built for the \"cubic\" lattice)")
        return self

    @property
    def fill_lattice(self) -> str:
        """The fill's lattice: as given, else fcc for dfsph and cubic for wcsph."""
        return self.fill or ("fcc" if self.solver == "dfsph" else "cubic")

    @property
    def density_kernel(self) -> str:
        return self._kernel(self.kernels.density, self.kernels.pressure, "poly6")

    @property
    def pressure_kernel(self) -> str:
        return self._kernel(self.kernels.pressure, self.kernels.density, "spiky")

    def _kernel(self, given: str | None, other: str | None, wcsph_default: str) -> str:
        """dfsph: one kernel for both terms (either key names it; cubic by default)."""
        if self.solver == "dfsph":
            return given or other or "cubic"
        return given or wcsph_default


Face = Literal["-x", "+x", "-y", "+y", "-z", "+z"]          # a face of the domain's box
NoSlipWall = Literal[Face, "colliders"]
NO_SLIP_ALL: tuple[str, ...] = NoSlipWall.__args__


class Domain(Strict):
    min: Vec3 = (0.0, 0.0, 0.0)
    max: Vec3 = (1.0, 1.0, 1.0)
    restitution: Unit = 0.0
    friction: Unit = 0.1
    # dfsph: the walls and colliders that hold a fluid's dynamic viscosity by no slip (honey
    # clings): true all, false none (free slip: viscosity acts between particles only), or a
    # list of the box's faces and "colliders" (a slice of a wide channel: its sides free)
    no_slip: bool | tuple[NoSlipWall, ...] = True
    # faces with no wall: particles that leave through one are removed (and counted in the log)
    open: tuple[Face, ...] = ()

    @field_validator("no_slip", mode="before")
    @classmethod
    def _walls(cls, value):
        """One line for a bad value (pydantic would report each branch of the union)."""
        names = ", ".join(f'"{w}"' for w in NO_SLIP_ALL)
        if isinstance(value, bool):
            return value
        if not isinstance(value, (tuple, list)) or not all(isinstance(w, str) and w in NO_SLIP_ALL for w in value):
            raise ValueError(f"expected true, false or a list of {names}, got {value!r}")
        return tuple(value)

    @model_validator(mode="after")
    def _extent(self):
        _check_extent(self.min, self.max)
        if len(set(self.open)) != len(self.open):
            raise ValueError(f"open: each face at most once, got {list(self.open)}")
        if not isinstance(self.no_slip, bool):
            if len(set(self.no_slip)) != len(self.no_slip):
                raise ValueError(f"no_slip: each face at most once, got {list(self.no_slip)}")
            if set(self.no_slip) & set(self.open):
                face = sorted(set(self.no_slip) & set(self.open))[0]
                raise ValueError(f'no_slip: "{face}" is open (domain.open), there is no wall there to hold the fluid')
        return self

    @property
    def no_slip_walls(self) -> tuple[str, ...]:
        """The faces (and "colliders") that hold the fluid: no_slip as a list."""
        if isinstance(self.no_slip, bool):
            return NO_SLIP_ALL if self.no_slip else ()
        return tuple(self.no_slip)


class Block(Strict):
    min: Vec3
    max: Vec3
    velocity: Vec3 = (0.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _extent(self):
        _check_extent(self.min, self.max)
        return self


class Fluid(Strict):
    name: Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]+$")]
    rest_density: Pos = 1000.0        # kg/m^3
    # Pa s, physical (Morris et al. 1997), dfsph: water 0.001, olive oil 0.08, honey about 10.
    # Unset: water's, unless the old `viscosity` is given.
    dynamic_viscosity: NonNeg | None = None
    xsph: Unit = 0.0                  # dfsph: artist smoothing, share of the neighbours' mean velocity a step
    # Müller et al. 2003's particle-scale viscosity: wcsph's (default 1.0); kept for old job files
    viscosity: NonNeg | None = None
    surface_tension: NonNeg = 0.0     # N/m
    color: Color = (0.125, 0.4, 0.625)   # clear water's blue (the water look dims it)
    # m, water look: the depth of this liquid through which what lies behind it takes `color`
    # (Beer-Lambert per channel, as Arnold's transmission_depth): honey, tea, wine. Unset: a
    # clear liquid, `color` dimmed as its body and more opaque where deeper
    transmission_depth: Pos | None = None
    blocks: Annotated[tuple[Block, ...], Field(min_length=1)]


class Collider(Strict):
    restitution: Unit = 0.0
    friction: Unit = 0.2
    mode: Literal["obstacle", "container"] = "obstacle"
    color: Color = (0.6, 0.6, 0.6)


class SphereCollider(Collider):
    type: Literal["sphere"]
    center: Vec3
    radius: Pos


class BoxCollider(Collider):
    type: Literal["box"]
    min: Vec3
    max: Vec3

    @model_validator(mode="after")
    def _extent(self):
        _check_extent(self.min, self.max)
        return self


class CapsuleCollider(Collider):
    type: Literal["capsule"]
    a: Vec3
    b: Vec3
    radius: Pos


class MeshCollider(Collider):
    """A closed triangle mesh from a file (path relative to the job file), placed by scaling,
    then rotating about x, y and z (degrees), then translating. The solver samples its signed
    distance on a grid of `voxel_size` particle radii (OpenVDB mesh to level set)."""
    type: Literal["mesh"]
    path: Annotated[str, Field(min_length=1)]
    scale: Pos = 1.0
    rotate: Vec3 = (0.0, 0.0, 0.0)
    translate: Vec3 = (0.0, 0.0, 0.0)
    voxel_size: Annotated[float, Field(ge=0.25, le=8)] = 1.0


AnyCollider = Annotated[Union[SphereCollider, BoxCollider, CapsuleCollider, MeshCollider],
                        Field(discriminator="type")]
# all mesh colliders' distance grids together: 64 MB of float32, and every offset into them
# exact in the solver's float32 collider table
MAX_SDF_VOXELS = 1 << 24


# ------------------------------------------------------------------------------------ surface
class Surface(Strict):
    # anisotropic: Yu & Turk 2013's stretched kernels (surfacing/anisotropy.py); isotropic: spheres
    method: Literal["anisotropic", "isotropic"] = "anisotropic"
    cell_size: Annotated[float, Field(gt=0.1, le=4)] = 0.75   # grid spacing, in particle radii
    kernel_radius: Annotated[float, Field(gt=1, le=8)] = 4.0  # splat support, in particle radii
    kernel: Literal["cubic", "poly6", "wendland"] = "cubic"   # splat kernel
    # color-field iso value; unset: the method's (ISO), where a resting block's mesh keeps its volume
    iso: Annotated[float | None, Field(gt=0, lt=1)] = None
    # particles with fewer neighbours than this within two kernel radii (itself counted) are spray:
    # written as points (<shot>.<frame>.spray.ply, and .spray.vdb with grids), left out of the mesh;
    # 0: no spray file. The default is the anisotropic kernels' N_EPS: fewer than that have no
    # shape to stretch
    spray: Annotated[int, Field(ge=0, le=1000)] = 25
    # anisotropic: Laplacian smoothing of the kernel centres (Yu & Turk's lambda, 0.9 in the paper),
    # then Taubin's second pass pushing them back out by center_inflation of their own Laplacian
    # (his -mu): particle-scale bumps damped, faces kept where they were (surfacing/anisotropy.py).
    # center_inflation = 0 is Yu & Turk's smoothing alone, which pulls every face in
    center_smoothing: Unit = 0.5
    center_inflation: Unit = 0.53
    format: Literal["ply", "obj", "vtu"] = "ply"
    per_fluid: bool = False               # one mesh per fluid instead of one for all
    smoothing_iterations: Annotated[int, Field(ge=0, le=200)] = 0   # Taubin smoothing
    decimate: Annotated[float, Field(ge=0, lt=1)] = 0.0           # fraction of triangles removed
    half_width: Annotated[float, Field(ge=1, le=10)] = 3.0         # level-set narrow band, voxels
    # OpenVDB grids written per frame; none: no .vdb at all (the level set is most of a frame's time)
    grids: tuple[Literal["surface", "density", "velocity"], ...] = ("surface", "density", "velocity")

    ISO: ClassVar[dict[str, float]] = {"isotropic": 0.5, "anisotropic": 0.14}

    @property
    def iso_value(self) -> float:
        return self.ISO[self.method] if self.iso is None else self.iso

    @field_validator("grids")
    @classmethod
    def _grids_once(cls, grids):
        twice = sorted({g for g in grids if grids.count(g) > 1})
        if twice:
            raise ValueError(f"each grid at most once, got {', '.join(map(repr, twice))} twice")
        return grids


# ------------------------------------------------------------------------------------- render
class Camera(Strict):
    position: Vec3 = (2.6, 1.6, 2.4)
    focal_point: Vec3 = (0.8, 0.2, 0.0)
    up: Vec3 = (0.0, 1.0, 0.0)
    fov: Annotated[float, Field(gt=1, lt=179)] = 35.0   # vertical field of view, degrees

    @model_validator(mode="after")
    def _not_degenerate(self):
        view = np.subtract(self.focal_point, self.position)
        up = np.asarray(self.up, float)
        if not np.linalg.norm(view) > 0:
            raise ValueError("position and focal_point must differ, got the same point")
        if not np.linalg.norm(up) > 0:
            raise ValueError(f"up must be a direction, got {list(self.up)}")
        if np.linalg.norm(np.cross(view / np.linalg.norm(view), up / np.linalg.norm(up))) < 1e-6:
            raise ValueError(f"up must not be along the view direction, got up = {list(self.up)}")
        return self


class CameraKey(Camera):
    frame: int


class Light(Strict):
    position: Vec3
    intensity: Annotated[float, Field(ge=0)] = 1.0
    color: Color = (1.0, 1.0, 1.0)


class Material(Strict):
    color: Color | None = None    # None: each fluid's own color
    roughness: Unit = 0.15
    metallic: Unit = 0.0
    opacity: Unit = 1.0


class Render(Strict):
    # a preset for the keys below that the job leaves unset (render.LOOKS): "water" translucent
    # and reflecting a studio sky, "clay" matte grey for reading form, "preview" the opaque blue of old
    look: Literal["water", "clay", "preview"] = "water"
    mode: Literal["surface", "particles"] = "surface"
    color_by: Literal["fluid", "speed"] = "fluid"
    resolution: tuple[Annotated[int, Field(ge=16, le=8192)], Annotated[int, Field(ge=16, le=8192)]] = (1280, 720)
    camera: Camera = Camera()
    camera_keys: tuple[CameraKey, ...] = ()     # optional keyframes, linearly interpolated
    lights: tuple[Light, ...] = ()              # empty: a default three-point rig
    material: Material = Material()
    background: Color = (0.08, 0.09, 0.11)
    background_top: Color | None = (0.32, 0.36, 0.42)   # None: flat background
    ground: bool = True
    domain: bool = True                         # draw the domain box as a thin outline
    colliders: bool = True
    ssaa: bool = True
    # motion blur: renders of the frame averaged, the fluid moved along its velocity to each of
    # this many instants while the shutter is open (0 or 1: none); shutter: the open share of a
    # frame, centred on it (0.5: a 180-degree shutter)
    motion_blur: Annotated[int, Field(ge=0, le=64)] = 0
    shutter: Annotated[float, Field(gt=0, le=1)] = 0.5
    depth: Literal["none", "png16"] = "none"
    movie: bool = True
    contact_sheet: bool = True


# --------------------------------------------------------------------------------------- shot
class ShotSpec(Strict):
    shot: Shot
    sim: Sim = Sim()
    domain: Domain = Domain()
    fluids: Annotated[tuple[Fluid, ...], Field(min_length=1)]
    colliders: tuple[AnyCollider, ...] = ()
    surface: Surface = Surface()
    render: Render = Render()
    # Filled in by load_spec, not by users: where the job file lives, for relative paths.
    job_dir: str = "."
    # Resolved at validation: each mesh collider's (world vertices, triangles, file sha256)
    _meshes: dict = PrivateAttr(default_factory=dict)

    @model_validator(mode="after")
    def _cross_checks(self):
        lo, hi = self.domain.min, self.domain.max
        r = self.sim.particle_radius
        for fi, fluid in enumerate(self.fluids):
            for bi, block in enumerate(fluid.blocks):
                for axis, a, b, dlo, dhi in zip("xyz", block.min, block.max, lo, hi):
                    if a < dlo or b > dhi:
                        raise ValueError(
                            f"fluids[{fi}].blocks[{bi}]: block {axis} range [{a}, {b}] lies outside "
                            f"the domain [{dlo}, {dhi}]")
                    if b - a < 2 * r:
                        raise ValueError(
                            f"fluids[{fi}].blocks[{bi}]: block is thinner along {axis} ({b - a:g} m) than "
                            f"one particle (2 x particle_radius = {2 * r:g} m)")
        names = [f.name for f in self.fluids]
        if len(set(names)) != len(names):
            raise ValueError(f"fluids: names must be unique, got {names}")
        h = self.sim.kernel_radius * r
        for axis, a, b in zip("xyz", lo, hi):
            if b - a < 2 * h:
                raise ValueError(f"domain: extent along {axis} ({b - a:g} m) must be at least two kernel "
                                 f"radii ({2 * h:g} m)")
        voxels = 0
        for ci, col in enumerate(self.colliders):
            if col.type == "mesh":
                voxels += self._check_mesh(ci, col, voxels)
        keys = [k.frame for k in self.render.camera_keys]
        if keys != sorted(set(keys)):
            raise ValueError(f"render.camera_keys: frames must be strictly increasing, got {keys}")
        return self

    def _check_mesh(self, ci: int, col: MeshCollider, before: int) -> int:
        """Mesh collider ci's file and box are sound; returns (an upper bound of) the voxels of
        its distance grid, which with those of the mesh colliders `before` it must fit."""
        from .meshes import MeshFileError

        from .meshes import file_sha256, placement, read_closed_mesh

        where = f"colliders[{ci}]"
        try:
            verts, tris = read_closed_mesh(self.mesh_path(ci))
            sha = file_sha256(self.mesh_path(ci))
        except MeshFileError as exc:
            raise ValueError(f"{where}.path: {exc}") from None
        matrix, offset = placement(col.scale, col.rotate, col.translate)
        verts = verts @ matrix.T + offset
        verts.flags.writeable = False
        self._meshes[ci] = (verts, tris, sha)   # the spec is a value: the file is read once
        lo, hi = self.sdf_box(verts, col)
        if np.any(hi <= lo):
            raise ValueError(f"{where}: the mesh lies entirely outside the domain")
        # nodes on multiples of the voxel covering [lo, hi]: at most ceil(extent / voxel) + 2 a side
        voxels = math.prod(int(v) for v in np.ceil((hi - lo) / self.collider_voxel_m(col)) + 2)
        if before + voxels > MAX_SDF_VOXELS:
            raise ValueError(f"{where}.voxel_size: the mesh colliders' distance grids would have "
                             f"{before + voxels:,} voxels (at most {MAX_SDF_VOXELS:,}); raise voxel_size "
                             f"or shrink the mesh")
        return voxels

    # ----------------------------------------------------------------- derived, converted once
    def mesh_path(self, ci: int) -> Path:
        path = Path(self.colliders[ci].path)
        return path if path.is_absolute() else Path(self.job_dir) / path

    def collider_mesh(self, ci: int) -> tuple[np.ndarray, np.ndarray]:
        """(vertices in world space, triangles) of mesh collider ci, as read at validation."""
        verts, tris, _sha = self._meshes[ci]
        return verts, tris

    def sdf_pad(self, col: MeshCollider) -> float:
        """How far a mesh collider's distance grid reaches beyond the mesh, and is exact inside
        it: one kernel radius (the reach of the collider's forces) and two voxels."""
        return self.kernel_radius_m + 2 * col.voxel_size * self.sim.particle_radius

    def sdf_box(self, verts: np.ndarray, col: MeshCollider) -> tuple[np.ndarray, np.ndarray]:
        """World box of a mesh collider's distance grid: its bounds plus sdf_pad, clipped to the
        domain grown by as much (nothing beyond can meet a particle)."""
        pad = self.sdf_pad(col)
        lo = np.maximum(verts.min(0) - pad, np.array(self.domain.min) - pad)
        hi = np.minimum(verts.max(0) + pad, np.array(self.domain.max) + pad)
        return lo, hi

    @property
    def frames(self) -> range:
        return range(self.shot.frame_start, self.shot.frame_end + 1)

    @property
    def output_root(self) -> Path:
        """<output>/<name>/v### — every file of this shot version lives below it. `~` and
        $VARIABLES in shot.output are expanded (validation checks they are set)."""
        out = Path(os.path.expandvars(os.path.expanduser(self.shot.output)))
        if not out.is_absolute():
            out = Path(self.job_dir) / out
        # normalised but not resolved: symlinks of a farm's shared folder stay as written
        return Path(os.path.normpath(out / self.shot.name / f"v{self.shot.version:03d}"))

    def frame_time(self, frame: int) -> float:
        """Simulated time (s) of a frame; frame_start is t = 0."""
        return (frame - self.shot.frame_start) / self.shot.fps

    # Lengths the job file gives in particle radii, in metres: the one place they are converted.
    @property
    def kernel_radius_m(self) -> float:
        """The solver's kernel support h (sim.kernel_radius particle radii)."""
        return self.sim.kernel_radius * self.sim.particle_radius

    @property
    def surface_cell_m(self) -> float:
        """The surfacing grid's node spacing (surface.cell_size particle radii)."""
        return self.surface.cell_size * self.sim.particle_radius

    @property
    def surface_kernel_radius_m(self) -> float:
        """The surfacing splat kernel's support (surface.kernel_radius particle radii)."""
        return self.surface.kernel_radius * self.sim.particle_radius

    def collider_voxel_m(self, col: MeshCollider) -> float:
        """A mesh collider's distance-grid voxel (voxel_size particle radii)."""
        return col.voxel_size * self.sim.particle_radius

    def fluid_viscosity(self, fi: int) -> tuple[float, float]:
        """(Müller's particle-scale viscosity, dynamic viscosity in Pa s) of fluid fi, defaults
        resolved. Given keys win. With neither: wcsph takes Müller's at 1.0, dfsph water's
        0.001 Pa s; an old job file's `viscosity` alone replaces water's."""
        f = self.fluids[fi]
        if f.viscosity is None and f.dynamic_viscosity is None:
            return (1.0, 0.0) if self.sim.solver == "wcsph" else (0.0, 0.001)
        return (f.viscosity or 0.0), (f.dynamic_viscosity or 0.0)

    def warnings(self) -> list[str]:
        """Keys that validate but mean something the user may not expect: one line each."""
        out = []
        for fi, f in enumerate(self.fluids):
            if f.viscosity is not None and self.sim.solver == "dfsph":
                out.append(f"fluids[{fi}].viscosity: Müller's particle-scale viscosity, kept for old job files; "
                           f"give dynamic_viscosity in Pa s (water 0.001, honey about 10) and xsph for smoothing")
            if f.xsph and self.sim.solver == "wcsph":
                out.append(f"fluids[{fi}].xsph: ignored by sim.solver = \"wcsph\" (dfsph only)")
        r = self.render
        if (not self.surface.per_fluid and len({f.color for f in self.fluids}) > 1 and r.mode == "surface"
                and r.look != "clay" and r.material.color is None):
            out.append(f"surface.per_fluid: false with {len(self.fluids)} fluids of different colors: one mesh "
                       f"for all of them, drawn in fluids[0]'s color (\"{self.fluids[0].name}\"); true meshes "
                       f"and draws each fluid in its own")
        return out

    def mesh_hashes(self) -> dict[int, str]:
        """sha256 of each mesh collider's file (read at validation): editing the mesh invalidates
        the sim."""
        return {ci: sha for ci, (_v, _t, sha) in sorted(self._meshes.items())}

    def expected_max_speed(self) -> float:
        """sqrt(2 g H) over the tallest fluid column, plus the fastest initial block speed."""
        if self.sim.max_speed > 0:
            return self.sim.max_speed
        g = math.sqrt(sum(c * c for c in self.sim.gravity))
        up = [-c / g for c in self.sim.gravity] if g > 0 else [0.0, 1.0, 0.0]
        floor = sum(u * m for u, m in zip(up, self.domain.min))
        top = max(sum(u * m for u, m in zip(up, b.max)) for f in self.fluids for b in f.blocks)
        v0 = max(math.sqrt(sum(c * c for c in b.velocity)) for f in self.fluids for b in f.blocks)
        return max(math.sqrt(2 * g * max(top - floor, 0.0)) + v0, 0.5)


# ------------------------------------------------------------------------------------ loading
def _tuples(value: Any) -> Any:
    """TOML arrays become tuples, so the frozen model holds only immutable values."""
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    if isinstance(value, dict):
        return {k: _tuples(v) for k, v in value.items()}
    return value


def _dotted(loc: tuple) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in ("sphere", "box", "capsule", "mesh") and out.startswith("colliders"):
            continue  # pydantic's discriminator tag, not a key the user wrote
        else:
            out += ("." if out else "") + str(part)
    return out or "<root>"


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    """The models a field's annotation holds: itself, or inside a tuple, union or Annotated."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models_in(arg)]


def _keys_beside(loc: tuple) -> set[str]:
    """The keys the table holding loc's last key takes (the union's, for a collider whose
    type pydantic names in loc)."""
    models: list[type[BaseModel]] = [ShotSpec]
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        fields = [m.model_fields[part] for m in models if part in m.model_fields]
        if fields:
            models = [m for f in fields for m in _models_in(f.annotation)]
        else:       # pydantic's tag of a union member (a collider's type): that member
            models = [m for m in models if "type" in m.model_fields
                      and part in typing.get_args(m.model_fields["type"].annotation)]
    return {f.alias or name for m in models for name, f in m.model_fields.items()} - {"job_dir"}


def _meant(err: dict) -> str | None:
    """For an unknown key, the known key of the same table it is most likely a misspelling of."""
    close = difflib.get_close_matches(str(err["loc"][-1]), sorted(_keys_beside(tuple(err["loc"]))), n=1,
                                      cutoff=0.7)
    return close[0] if close else None


def _describe(err: dict, near: str | None = None) -> str:
    """One line for a validation error; `near`: for an unknown key, the key it likely misspells."""
    where = _dotted(err["loc"])
    got = err.get("input")
    msg = err["msg"]
    if err["type"] == "extra_forbidden":
        return f"{where}: unknown key" + (f" (did you mean {near!r}?)" if near else "")
    if err["type"] == "missing":
        return f"{where}: required key is missing"
    if err["type"] == "value_error":
        msg = msg.removeprefix("Value error, ")
        return f"{where}: {msg}" if where != "<root>" else msg
    if isinstance(got, (dict, tuple)) and len(repr(got)) > 60:
        got_s = type(got).__name__
    else:
        got_s = repr(got)
    expected = msg.removeprefix("Input should be ").rstrip(".").replace("a valid tuple", "an array")
    return f"{where}: expected {expected}, got {got_s}"


def parse_override(text: str) -> tuple[list[str], Any]:
    """`key.path=value` with a TOML value (numbers, strings in quotes, arrays, booleans)."""
    if "=" not in text:
        raise SpecError("--set", [f"{text!r}: expected key.path=value"])
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise SpecError("--set", [f"{text!r}: expected key.path=value"])
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        # A bare word is taken as a string (--set render.mode=particles).
        if raw.strip() and all(ch.isalnum() or ch in "_-./" for ch in raw.strip()):
            value = raw.strip()
        else:
            raise SpecError("--set", [f"{key}: expected a TOML value, got {raw!r}"]) from None
    return key.split("."), value


def apply_override(data: dict, path: list[str], value: Any, text: str) -> None:
    node: Any = data
    for i, part in enumerate(path[:-1]):
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise SpecError("--set", [f"{'.'.join(path)}: index {part!r} out of range in {text!r}"])
            node = node[int(part)]
        else:
            node = node.setdefault(part, {})
        if not isinstance(node, (dict, list)):
            raise SpecError("--set", [f"{'.'.join(path[:i + 1])}: is not a table in {text!r}"])
    last = path[-1]
    if isinstance(node, list):
        if not last.isdigit() or int(last) >= len(node):
            raise SpecError("--set", [f"{'.'.join(path)}: index {last!r} out of range in {text!r}"])
        node[int(last)] = value
    else:
        node[last] = value


def load_spec(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> ShotSpec:
    """Read, override and validate a job file. Raises SpecError with one line per problem."""
    path = Path(path)
    source = str(path)
    try:
        text = path.read_text(encoding="utf-8-sig")      # a byte-order mark is no error
    except FileNotFoundError:
        raise SpecError(source, ["job file not found"]) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(source, [f"cannot read job file: {exc.__class__.__name__}: {exc}"]) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(source, [f"not valid TOML: {exc}"]) from None
    if "job_dir" in data:
        raise SpecError(source, ["job_dir: unknown key"])
    for text_ in overrides:
        keys, value = parse_override(text_)
        apply_override(data, keys, value, text_)
    data["job_dir"] = str(path.resolve().parent)
    try:
        return ShotSpec.model_validate(_tuples(data))
    except ValidationError as exc:
        errs = exc.errors()
        # a failed item also fails its parent's length check; report the item only
        locs = [tuple(e["loc"]) for e in errs]
        errs = [e for e in errs if not any(len(o) > len(e["loc"]) and o[:len(e["loc"])] == tuple(e["loc"])
                                           for o in locs)]
        # a required key spelt wrong is one mistake: the unknown key's line names the key meant
        near = {id(e): _meant(e) for e in errs if e["type"] == "extra_forbidden"}
        meant = {tuple(e["loc"][:-1]) + (near[id(e)],) for e in errs if id(e) in near}
        errs = [e for e in errs if not (e["type"] == "missing" and tuple(e["loc"]) in meant)]
        raise SpecError(source, list(dict.fromkeys(_describe(e, near.get(id(e))) for e in errs))) from None
