"""What is on disk: the files the stages write and read, in one place.

- Sim frames and checkpoints (HDF5). Frame datasets: position (N,3) f32 m, velocity (N,3) f32
  m/s, density (N,) f32 kg/m^3, pressure (N,) f32 Pa, id (N,) i32, fluid (N,) i32. Attributes:
  frame, time (s), particle_radius (m), kernel_radius (m), fluid_names, fluid_rest_density
  (kg/m^3), fluid_mass (kg), plus the solver's counters. Checkpoints add the solver's exact
  state (half-step velocity, last acceleration, particle order) and its time-step controller.
- Surface meshes: PLY keeps normals (nx, ny, nz) and velocity (vx, vy, vz) as vertex
  properties; OBJ keeps normals; VTU keeps both as point arrays.
- OpenVDB files: the grids surfacing.vdb builds; spray as a PointDataGrid `spray` (attributes
  P, v, pscale, fluid), written by the sphshot-vdb-points tool that scripts/setup.sh builds from
  pipeline/native/vdb_points.cpp (pyopenvdb 10 has no point grids).

Every writer publishes atomically (cache.atomic_path): a file exists under its final name only
once it is complete. Every writer is reproducible: the same content gives the same bytes
(meshio's time of writing is blanked from PLY and OBJ headers, and an OpenVDB file's UUID is
derived from the rest of the file instead of drawn at random), so a frame computed again from
the same input leaves the frames made from it valid (cache.check_file compares digests). The
user's input meshes (mesh colliders) are read by pipeline/meshes.py.
"""
from __future__ import annotations

import hashlib
import json
import re
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import h5py
import numpy as np

from surfacing.mesh import Mesh

from .cache import atomic_path

FRAME_DATASETS = {"position": np.float32, "velocity": np.float32, "density": np.float32,
                  "pressure": np.float32, "id": np.int32, "fluid": np.int32}


# ---------------------------------------------------------------------------- sim frames (HDF5)
def write_h5(final: Path, datasets: dict[str, np.ndarray], attrs: dict) -> Path:
    """HDF5 builds the file in memory (its core driver, no backing store) and Python writes the
    image: a full disk is then one OSError from the write, naming the file (atomic_path). Written
    by HDF5 itself, a write that failed as the file closed came out as a RuntimeError ("Disable
    slist on flush dest failure failed (file write failed: ... errno = 28 ...)"), and its
    objects' finalisers printed tracebacks to stderr after it."""
    with h5py.File(final.name, "w", driver="core", backing_store=False) as f:
        for k, v in datasets.items():
            f.create_dataset(k, data=v)
        for k, v in attrs.items():
            f.attrs[k] = v
        f.flush()
        image = f.id.get_file_image()
    with atomic_path(final) as tmp:
        tmp.write_bytes(image)
    return final


def write_frame(final: Path, data: dict[str, np.ndarray], attrs: dict) -> Path:
    return write_h5(final, {k: np.asarray(data[k], dtype=t) for k, t in FRAME_DATASETS.items()}, attrs)


def read_h5(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    with h5py.File(path, "r") as f:
        data = {k: f[k][()] for k in f.keys()}
        attrs = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in f.attrs.items()}
    attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in attrs.items()}
    if "fluid_names" in attrs:
        attrs["fluid_names"] = [n.decode() if isinstance(n, bytes) else str(n) for n in attrs["fluid_names"]]
    return data, attrs


read_frame = read_h5


# ------------------------------------------------------------------------------ surface meshes
def write_mesh(final: Path, mesh: Mesh, fmt: str) -> Path:
    """Publish a Mesh as PLY, OBJ or VTU (see the module docstring)."""
    import meshio

    cells = [("triangle", mesh.faces.astype(np.int32))]
    if fmt == "ply":
        pd = {"nx": mesh.normals[:, 0], "ny": mesh.normals[:, 1], "nz": mesh.normals[:, 2],
              "vx": mesh.velocity[:, 0], "vy": mesh.velocity[:, 1], "vz": mesh.velocity[:, 2]}
    elif fmt == "obj":
        pd = {"obj:vn": mesh.normals}
    else:
        pd = {"Normals": mesh.normals, "velocity": mesh.velocity}
    with atomic_path(final) as tmp:
        meshio.write(str(tmp), meshio.Mesh(mesh.points, cells, point_data=pd), file_format=fmt)
        _blank_write_time(tmp)
    return final


def _blank_write_time(path: Path) -> None:
    """meshio heads a PLY or OBJ file with "Created by meshio vX, <the time of writing>": the
    time is overwritten with spaces in place (the header keeps its length), so the same mesh
    gives the same bytes."""
    with open(path, "r+b") as f:
        head = f.read(512)
        m = re.search(rb"Created by meshio v[^,\n]*(, [0-9T:.\-]+)\n", head)
        if m:
            f.seek(m.start(1))
            f.write(b" " * (m.end(1) - m.start(1)))


def write_points(final: Path, position: np.ndarray, velocity: np.ndarray, radius: float,
                 fluid: np.ndarray | None = None) -> Path:
    """Publish particles as PLY points (binary): x y z, velocity vx vy vz, pscale (the radius:
    Houdini's name for it; Blender reads the points and their attributes too) and, given, fluid
    (the index of each point's fluid in the job's `fluids`)."""
    import meshio

    n = len(position)
    cells = []                  # points only: one `vertex` element, no faces
    pd = {"vx": velocity[:, 0].astype(np.float32), "vy": velocity[:, 1].astype(np.float32),
          "vz": velocity[:, 2].astype(np.float32), "pscale": np.full(n, radius, np.float32)}
    if fluid is not None:
        pd["fluid"] = np.asarray(fluid, np.int32)
    with atomic_path(final) as tmp:
        meshio.write(str(tmp), meshio.Mesh(np.asarray(position, np.float32).reshape(-1, 3), cells, point_data=pd),
                     file_format="ply")
        _blank_write_time(tmp)
    return final


def read_points(path: Path) -> dict[str, np.ndarray]:
    """{position, velocity, pscale, fluid} from a file write_points wrote (fluid 0 where the file
    has none: written before 2026-11-26, or without it)."""
    import meshio

    m = meshio.read(str(path))
    pd = m.point_data
    return {"position": np.asarray(m.points, np.float32),
            "velocity": np.stack([pd["vx"], pd["vy"], pd["vz"]], 1) if len(m.points) else np.zeros((0, 3), np.float32),
            "pscale": np.asarray(pd.get("pscale", np.zeros(len(m.points))), np.float32),
            "fluid": np.asarray(pd.get("fluid", np.zeros(len(m.points))), np.int64)}


def read_mesh(path: Path) -> Mesh:
    """A Mesh from a file write_mesh wrote."""
    import meshio

    m = meshio.read(str(path))
    faces = m.cells_dict.get("triangle", np.zeros((0, 3), np.int32))
    pd = m.point_data
    if "nx" in pd:
        normals = np.stack([pd["nx"], pd["ny"], pd["nz"]], 1)
        vel = np.stack([pd["vx"], pd["vy"], pd["vz"]], 1)
    else:
        normals = pd.get("Normals", pd.get("obj:vn", np.zeros_like(m.points)))
        vel = pd.get("velocity", np.zeros_like(m.points))
    return Mesh(np.asarray(m.points, np.float32), np.asarray(faces, np.int32),
                np.asarray(normals, np.float32), np.asarray(vel, np.float32))


# ------------------------------------------------------------------------------------ OpenVDB
def write_vdb(final: Path, grids) -> Path:
    """Publish OpenVDB grids (pyopenvdb grid objects) as one .vdb file."""
    import pyopenvdb as vdb

    with atomic_path(final) as tmp:
        vdb.write(str(tmp), grids=grids)
        # pyopenvdb does not raise when the disk fills: check the file's layout, then read the
        # grid list back, before the file is published (a cut-short file fails here and is never
        # renamed into place). The layout comes first: OpenVDB reading a cut-short file took a
        # string length from past its end and built a 1.4 GB "grid type" (5.5 GB resident, 30 s)
        short = vdb_cut_short(tmp)
        if short:
            raise OSError(f"{final}: the OpenVDB file written could not be read back: {short}; {disk_left(tmp)}")
        content_uuid(tmp)
        try:
            names = [g["name"] for g in vdb.readAllGridMetadata(str(tmp))]
        except Exception as exc:          # OpenVDB's IoError and friends carry no common base
            detail = " ".join(str(exc).split())[:200]
            raise OSError(f"{final}: the OpenVDB file written could not be read back ({detail})") from None
        if sorted(names) != sorted(g.name for g in grids):
            raise OSError(f"{final}: the OpenVDB file written holds {names}, not {[g.name for g in grids]}")
    return final


VDB_UUID = slice(21, 57)     # the UUID's bytes in an OpenVDB file's header (see vdb_cut_short)


def content_uuid(path: Path) -> None:
    """Replace the random UUID OpenVDB writes into a file's header with one derived from the
    rest of the file (blake2b, as a UUID string): the same grids give the same bytes, and two
    files share a UUID only where their content is the same, which is what readers that cache
    by UUID (OpenVDB's delayed loading, Houdini) take it to mean. The file's layout must have
    been checked (vdb_cut_short)."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "r+b") as f:
        h.update(f.read(VDB_UUID.start))
        f.seek(VDB_UUID.stop)
        for piece in iter(lambda: f.read(1 << 20), b""):       # a showcase frame is ~100 MB
            h.update(piece)
        f.seek(VDB_UUID.start)
        f.write(str(uuid.UUID(bytes=h.digest())).encode())


def disk_left(path: Path) -> str:
    """How much room the disk holding `path` has left, for the message of a file written that
    did not read back whole (a full disk is the usual reason)."""
    return f"{shutil.disk_usage(path.parent).free / 2 ** 20:.1f} MB left on its disk"


def vdb_cut_short(path: Path) -> str | None:
    """Why a .vdb file does not hold together, or None if it does. OpenVDB's layout (io/Archive,
    io/GridDescriptor, file version 224): magic (int64), file version and library version
    (3 uint32), a grid-offsets flag (1 byte), a UUID (36 bytes), the file's metadata (int32
    count; per entry the name and type name as uint32-length strings, then a uint32 size and that
    many bytes), the grid count (int32), and per grid its name, type and instance parent
    (strings) and the stream positions of its start, its data and its end (3 int64): the next
    grid starts at that end, and the last ends at the end of the file. Every length and position
    is checked against the file's size before anything is read past it. sphshot-vdb-points runs
    the same check in C++ before it opens a file (pipeline/native/vdb_points.cpp, cut_short)."""
    import struct

    size = path.stat().st_size
    with open(path, "rb") as f:
        def take(n: int, what: str) -> bytes:
            if n < 0 or f.tell() + n > size:
                raise EOFError(f"{what} at byte {f.tell()} runs past the end ({size} bytes)")
            return f.read(n)

        def u32(what: str) -> int:
            return struct.unpack("<I", take(4, what))[0]

        def string(what: str) -> bytes:
            return take(u32(what), what)

        try:
            magic = struct.unpack("<q", take(8, "the magic number"))[0]
            if magic != 0x56444220:
                return f"no OpenVDB magic number (0x{magic & 0xFFFFFFFFFFFFFFFF:x})"
            take(12, "the versions")
            if take(1, "the grid-offsets flag") != b"\x01":
                return "written without grid offsets"
            take(36, "the UUID")
            for _ in range(u32("the metadata count")):
                string("a metadata name"), string("a metadata type")
                take(u32("a metadata value's size"), "a metadata value")
            count = u32("the grid count")
            end = f.tell()
            for k in range(count):
                string(f"grid {k}'s name"), string(f"grid {k}'s type"), string(f"grid {k}'s instance parent")
                start, data, end = struct.unpack("<qqq", take(24, f"grid {k}'s stream positions"))
                if not f.tell() <= start <= data <= end <= size:
                    return (f"grid {k}'s data (bytes {start} to {end}) does not lie within the file's "
                            f"{size} bytes")
                f.seek(end)
            if end != size:
                return f"{size - end} bytes after the last grid"
        except EOFError as exc:
            return str(exc)
    return None


VDB_POINTS_TOOL = "sphshot-vdb-points"


def vdb_points_tool() -> Path | None:
    """The sphshot-vdb-points executable: beside this interpreter (the venv setup.sh made), else
    on PATH; None if there is none."""
    here = Path(sys.prefix) / "bin" / VDB_POINTS_TOOL
    if here.is_file():
        return here
    found = shutil.which(VDB_POINTS_TOOL)
    return Path(found) if found else None


def _run_vdb_points(*args: str, data: bytes | None = None) -> str:
    tool = vdb_points_tool()
    if tool is None:
        raise OSError(f"{VDB_POINTS_TOOL} not found (scripts/setup.sh builds it; it needs g++ and libopenvdb-dev)")
    proc = subprocess.run([str(tool), *args], input=data, capture_output=True)
    if proc.returncode != 0:
        lines = proc.stderr.decode(errors="replace").strip().splitlines()
        raise OSError(lines[-1] if lines else f"{VDB_POINTS_TOOL} exited {proc.returncode}")
    return proc.stdout.decode()


def write_vdb_points(final: Path, position: np.ndarray, velocity: np.ndarray, radius: float,
                     fluid: np.ndarray) -> Path:
    """Publish particles as an OpenVDB PointDataGrid named `spray`: P, v (velocity), pscale (the
    radius) and fluid, the names Houdini and Blender read. The file is read back (point count and
    sums) before it is published."""
    n = len(position)
    arrays = (np.asarray(position, "<f4").reshape(n, 3), np.asarray(velocity, "<f4").reshape(n, 3),
              np.full(n, radius, "<f4"), np.asarray(fluid, "<i4").reshape(n))
    data = np.uint64(n).astype("<u8").tobytes() + b"".join(a.tobytes() for a in arrays)
    with atomic_path(final) as tmp:
        back = json.loads(_run_vdb_points("write", "-", str(tmp), data=data))    # the tool reads it back
        if back["count"] != n or abs(back["fluid_sum"] - float(arrays[3].sum())) > 0.5:
            raise OSError(f"{final}: the points written read back as {back['count']} (fluid indices summing to "
                          f"{back['fluid_sum']:g}), not {n} ({int(arrays[3].sum())})")
        content_uuid(tmp)             # (the tool checked the layout before reading it back)
    return final


def read_vdb_points(path: Path) -> dict:
    """A summary of the `spray` PointDataGrid of a .vdb (through sphshot-vdb-points): count, and
    position_sum, velocity_sum, position_min, position_max, pscale_sum, fluid_sum."""
    return json.loads(_run_vdb_points("read", str(path)))


def read_level_set(path: Path, name: str = "surface") -> tuple[np.ndarray, tuple[int, int, int], float] | None:
    """A level set grid of a .vdb as a dense array over its active bounding box (one voxel of
    margin), that box's lower index and the voxel size; None if the file has no such grid or
    it is empty."""
    import pyopenvdb as vdb

    try:
        grid = vdb.read(str(path), name)
    except (KeyError, ValueError, RuntimeError):
        return None
    if grid.activeVoxelCount() == 0:
        return None
    lo, hi = grid.evalActiveVoxelBoundingBox()
    lo = tuple(int(v) - 1 for v in lo)
    shape = tuple(int(b) - int(a) + 2 for a, b in zip(lo, hi))
    dense = np.full(shape, grid.background, np.float32)
    grid.copyToArray(dense, ijk=lo)
    return dense, lo, float(grid.transform.voxelSize()[0])
