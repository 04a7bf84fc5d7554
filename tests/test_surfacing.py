"""Surfacing against an analytic sphere of particles, and the VDB/mesh files it writes."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import tiny_spec

R_PART = 0.005           # particle radius, m
CELL = 0.75 * R_PART     # grid cell, m
SUPPORT = 4.0 * R_PART
CENTRE = np.array([0.31, 0.22, 0.17])


@pytest.fixture(scope="module", autouse=True)
def _taichi(taichi_cpu):
    pass


def ball(radius=0.06, velocity=(1.0, -2.0, 0.5)):
    """Particles on the fill lattice (spacing 2r) inside a ball; each carries volume (2r)^3.
    The equal-volume radius of the particles is the surface we expect."""
    d = 2 * R_PART
    ax = np.arange(-radius, radius + d, d)
    p = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    p = p[np.linalg.norm(p, axis=1) <= radius - R_PART] + CENTRE
    n = len(p)
    r_eq = (3 * n * d ** 3 / (4 * np.pi)) ** (1 / 3)
    vel = np.broadcast_to(np.array(velocity, np.float32), p.shape).copy()
    return p.astype(np.float32), vel, np.full(n, d ** 3, np.float32), r_eq


@pytest.fixture(scope="module")
def sphere_mesh():
    from surfacing.reconstruct import color_field, marching_cubes

    pos, vel, vol, r_eq = ball()
    field = color_field(pos, vel, vol, CELL, SUPPORT)
    return field, marching_cubes(field, 0.5), r_eq


def test_sphere_vertices_within_one_cell_of_radius(sphere_mesh):
    _field, mesh, r_eq = sphere_mesh
    r = np.linalg.norm(mesh.points - CENTRE, axis=1)
    err = np.abs(r - r_eq)
    assert len(mesh.points) > 1000
    assert err.max() < CELL, f"max radial error {err.max() / CELL:.2f} cells (radius {r_eq:.4f} m)"


def test_sphere_mesh_is_closed_manifold_with_outward_normals(sphere_mesh):
    import pyvista as pv

    _field, mesh, _ = sphere_mesh
    poly = pv.PolyData.from_regular_faces(mesh.points, mesh.faces)
    assert poly.n_open_edges == 0, "the mesh has boundary edges"
    assert poly.is_manifold
    edges = poly.extract_all_edges()
    euler = poly.n_points - edges.n_cells + poly.n_cells
    assert euler == 2, f"Euler characteristic {euler}, a sphere has 2"
    outward = np.einsum("ij,ij->i", mesh.normals, mesh.points - CENTRE)
    assert (outward > 0).all(), "vertex normals must point out of the fluid"
    assert poly.volume > 0


def test_vertex_normals_are_float64_area_weighted_normals(sphere_mesh):
    """The float32 Taichi normals against a float64 numpy reference (the sum over each vertex's
    faces of e1 x e2, normalised): within 0.05 degrees (float32 edges of one cell, 3.75 mm, at
    coordinates near 0.3 m: relative error ~1e-5, more at the tiny triangles marching cubes
    makes where the surface passes close to a node)."""
    from surfacing.reconstruct import vertex_normals

    _field, mesh, _ = sphere_mesh
    p, f = mesh.points.astype(np.float64), mesh.faces
    fn = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    want = np.zeros_like(p)
    for c in range(3):
        np.add.at(want, f[:, c], fn)
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    got = vertex_normals(mesh.points, mesh.faces)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", got, want), -1.0, 1.0)))
    assert angle.max() < 0.05, f"largest angle to the float64 normals {angle.max():.3f} degrees"
    np.testing.assert_array_equal(vertex_normals(mesh.points, mesh.faces), got)   # run to run


def test_vertex_velocity_is_interpolated_from_particles(sphere_mesh):
    _field, mesh, _ = sphere_mesh
    np.testing.assert_allclose(mesh.velocity, np.broadcast_to([1.0, -2.0, 0.5], mesh.velocity.shape),
                               atol=1e-4, err_msg="a uniform particle velocity must reach every vertex")


def _clump_and_stray(seed=3):
    """A jittered clump of particles and one droplet far away (a dense box over both would be
    mostly empty)."""
    rng = np.random.default_rng(seed)
    d = 2 * R_PART
    ax = np.arange(0, 8) * d
    p = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    p = p + rng.uniform(-0.3, 0.3, p.shape) * d + CENTRE
    p = np.vstack([p, CENTRE + [1.0, 0.3, -0.15]]).astype(np.float32)
    vel = rng.normal(size=p.shape).astype(np.float32)
    return p, vel, np.full(len(p), d ** 3, np.float32)


@pytest.mark.parametrize("kernel", ["cubic", "poly6", "wendland"])
def test_vector_kernel_shape_is_the_kernel(kernel):
    """The splat evaluates W for a row of 8 nodes at once as sigma * kernels.shape(s) on a
    vector of s = r^2 / h^2. Against the float64 kernel at 80,000 radii out to 1.2 h, in rows of
    8: within 2e-6 W(0) (float32 round-off of s, a square root and a cubic: a few 1e-7), and
    exactly 0 from r = h on."""
    import taichi as ti

    from solver import kernels as K

    kind = K.DENSITY_KERNELS[kernel]
    r = np.linspace(0.0, 1.2 * SUPPORT, 80_000)
    s = (r / SUPPORT) ** 2
    rows = ti.Vector.ndarray(8, ti.f32, len(s) // 8)
    rows.from_numpy(s.reshape(-1, 8).astype(np.float32))

    def evaluate(v):
        for n in v:
            v[n] = K.shape(kind, v[n])

    # (this module's annotations are strings, which Taichi does not read)
    evaluate.__annotations__ = {"v": ti.types.ndarray(dtype=ti.types.vector(8, ti.f32), ndim=1)}
    ti.kernel(evaluate)(rows)
    got = K.sigma(kind, SUPPORT) * rows.to_numpy().reshape(-1).astype(np.float64)
    want = K.w_np(kind, r, SUPPORT)
    assert np.abs(got - want).max() <= 2e-6 * want[0]
    assert (got[r >= SUPPORT] == 0).all()


@pytest.mark.parametrize("method", ["phased", "atomic"])
@pytest.mark.parametrize("kernel", ["cubic", "poly6", "wendland"])
def test_sparse_field_is_the_sph_sum_at_every_node(kernel, method):
    """Every node of the blocks' bounding box equals the brute-force sum over all particles
    (nodes of blocks that were not allocated must be zero), and only the blocks near particles
    are allocated; both scatters (the CPU's phased float sums, CUDA's fixed-point atomics, which
    run on the CPU too), each the same from run to run."""
    from solver.kernels import DENSITY_KERNELS as KERNELS, w_np
    from surfacing.reconstruct import color_field

    pos, vel, vol = _clump_and_stray()
    field = color_field(pos, vel, vol, CELL, SUPPORT, kernel=kernel, method=method)
    dense, index0 = field.dense()
    expect = np.zeros(dense.shape)             # numpy scatter, in float64, over each support cube
    reach = int(np.ceil(SUPPORT / CELL))
    for p, v in zip(pos.astype(np.float64), vol):
        lo = np.floor(p / CELL).astype(int) - reach
        ax = [np.arange(lo[a], lo[a] + 2 * reach + 2) for a in range(3)]
        node = np.stack(np.meshgrid(*ax, indexing="ij"), -1)
        wgt = v * w_np(KERNELS[kernel], np.linalg.norm(node * CELL - p, axis=-1), SUPPORT)
        at = lo - index0
        assert (at >= 0).all() and (at + 2 * reach + 2 <= dense.shape).all(), "support outside the blocks"
        expect[at[0]:at[0] + 2 * reach + 2, at[1]:at[1] + 2 * reach + 2, at[2]:at[2] + 2 * reach + 2] += wgt
    # float32 sums of ~50 terms of size <= 0.32: round-off well under 1e-5; the float32 kernel
    # adds at most 2e-6 W(0) V per term (test above), and only the few nearest terms come close
    np.testing.assert_allclose(dense, expect, atol=2e-5)
    box_blocks = np.prod(field.blocks.max(0) - field.blocks.min(0) + 1)
    assert field.n_blocks < box_blocks / 20, f"{field.n_blocks} blocks of a {box_blocks}-block box"
    again = color_field(pos, vel, vol, CELL, SUPPORT, kernel=kernel, method=method)
    assert np.array_equal(again.color, field.color), "the scatter must not depend on thread timing"
    assert np.array_equal(again.velocity, field.velocity)


def test_atomic_and_phased_velocity_fields_agree():
    """The velocity band from CUDA's fixed-point scatter against the CPU's phased one, on the
    CPU: where the color is over 1e-3 (the band the mesh and the VDB vel grid use), within
    1e-5 m/s of speeds of order 1 m/s (float32 round-off of sums of ~50 terms, divided by the
    color)."""
    from surfacing.reconstruct import color_field

    pos, vel, vol = _clump_and_stray()
    a = color_field(pos, vel, vol, CELL, SUPPORT, iso=0.5, method="phased")
    b = color_field(pos, vel, vol, CELL, SUPPORT, iso=0.5, method="atomic")
    np.testing.assert_array_equal(a.velocity_ids, b.velocity_ids)
    solid = (a.color[a.velocity_ids] > 1e-3)[..., None] & np.ones(3, bool)
    assert solid.sum() > 10_000
    np.testing.assert_allclose(a.velocity[:-1][solid], b.velocity[:-1][solid], atol=1e-5)


@pytest.mark.parametrize("iso", [0.3, 0.5])
def test_block_marching_cubes_equals_marching_cubes_on_the_dense_grid(sphere_mesh, iso):
    """Our block-sparse marching cubes makes the vertices and as many triangles as
    scikit-image's (Lewiner) on the dense array (these fields have no ambiguous faces)."""
    from skimage.measure import marching_cubes as mc

    from surfacing.reconstruct import color_field, marching_cubes

    for field in (sphere_mesh[0], color_field(*_clump_and_stray(), CELL, SUPPORT)):
        dense, index0 = field.dense()
        verts, faces, _n, _v = mc(np.pad(dense, 1), level=iso, allow_degenerate=True)
        ref = np.round((verts - 1 + index0) * CELL, 6)
        mesh = marching_cubes(field, iso)
        got = np.round(mesh.points.astype(np.float64), 6)
        assert len(mesh.faces) == len(faces) and len(got) == len(ref)
        np.testing.assert_allclose(np.sort(got, axis=0), np.sort(ref, axis=0), atol=2e-6)


def test_an_anisotropic_field_is_interpolated_through_its_cube_root():
    """An anisotropic color field tells marching cubes to place each vertex where the cube root
    of the color, linear along the edge, reaches the iso's (surfacing/mc.py): the vertices are
    scikit-image's on the dense array of color^(1/3) at iso^(1/3). An isotropic field keeps
    linear interpolation (the test above)."""
    from skimage.measure import marching_cubes as mc

    from surfacing.reconstruct import ANISOTROPIC_EDGE_POWER, color_field, marching_cubes

    assert ANISOTROPIC_EDGE_POWER == pytest.approx(1 / 3)
    field = color_field(*_clump_and_stray(), CELL, SUPPORT, anisotropic=True)
    assert field.edge_power == ANISOTROPIC_EDGE_POWER
    iso = 0.14
    dense, index0 = field.dense()
    verts, faces, _n, _v = mc(np.cbrt(np.pad(dense, 1).astype(np.float64)), level=np.cbrt(iso),
                              allow_degenerate=True)
    ref = (verts - 1 + index0) * CELL
    mesh = marching_cubes(field, iso)
    assert len(mesh.faces) == len(faces) > 1000 and len(mesh.points) == len(ref)
    np.testing.assert_allclose(np.sort(mesh.points.astype(np.float64), axis=0), np.sort(ref, axis=0), atol=2e-6)
    linear = mc(np.pad(dense, 1), level=iso, allow_degenerate=True)[0]
    assert np.abs(np.sort((linear - 1 + index0) * CELL, axis=0) - np.sort(ref, axis=0)).max() > 1e-4


def _closed_and_oriented(faces: np.ndarray) -> None:
    """Every directed edge of the faces occurs once and its reverse once: the surface has no
    boundary, no edge with more than two faces, and its faces agree on which side is out."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    pairs, count = np.unique(directed, axis=0, return_counts=True)
    assert (count == 1).all(), f"{(count > 1).sum()} directed edges used twice"
    key = {(int(a), int(b)) for a, b in pairs}
    missing = sum((int(b), int(a)) not in key for a, b in pairs)
    assert missing == 0, f"{missing} edges without a face on their other side"


def _dense_marching_cubes(f: np.ndarray, iso: float) -> np.ndarray:
    """The case table applied cell by cell (numpy; vertex id = lower node, axis)."""
    from surfacing.mc_table import CORNER, EDGE_AXIS, EDGE_CORNER, table

    tri_edges, tri_count = table()
    inside = f > iso
    n = np.array(f.shape)
    tris = []
    for cell in np.ndindex(*(n - 1)):
        case = sum(int(inside[tuple(np.add(cell, CORNER[v]))]) << v for v in range(8))
        for t in tri_edges[case, :tri_count[case]]:
            lo = np.add(cell, CORNER[EDGE_CORNER[t]])
            tris.append(np.ravel_multi_index(lo.T, n) * 3 + EDGE_AXIS[t])
    return np.array(tris).reshape(-1, 3)


def test_case_table_closes_every_case():
    """Each of the 256 cases alone in a cell (the rest of the grid outside), and random fields
    full of ambiguous faces, give closed surfaces whose faces agree on their orientation."""
    from surfacing.mc_table import CORNER, table

    tri_edges, tri_count = table()
    assert tri_count[0] == tri_count[255] == 0 and tri_count.max() <= tri_edges.shape[1]
    for case in range(1, 255):
        f = np.zeros((4, 4, 4))
        for v in range(8):
            f[tuple(CORNER[v] + 1)] = case >> v & 1
        _closed_and_oriented(_dense_marching_cubes(f, 0.5))
    rng = np.random.default_rng(3)
    for _ in range(5):
        f = np.pad(rng.random((5, 5, 5)), 1)
        _closed_and_oriented(_dense_marching_cubes(f, 0.5))


def test_marching_cubes_on_noise():
    """A field of random values (most cells ambiguous) on 27 blocks: the Taichi marching cubes
    is closed, consistently oriented with the outside below iso (positive volume), one vertex
    per crossed grid edge at scikit-image's positions (scikit-image's Lewiner variant also puts
    vertices inside some ambiguous cells; those are left out of the comparison)."""
    import pyvista as pv
    from skimage.measure import marching_cubes as mc

    from surfacing.grid import B, Field
    from surfacing.reconstruct import marching_cubes

    rng = np.random.default_rng(7)
    blocks = np.argwhere(np.ones((3, 3, 3), bool)) + [5, -2, 0]
    dense = np.zeros((3 * B,) * 3, np.float32)          # a zero rim: the blocks hold the surface
    dense[1:-1, 1:-1, 1:-1] = rng.random((3 * B - 2,) * 3)
    color = np.zeros((len(blocks) + 1, B, B, B), np.float32)
    for n, b in enumerate(blocks - blocks.min(0)):
        color[n] = dense[b[0] * B:(b[0] + 1) * B, b[1] * B:(b[1] + 1) * B, b[2] * B:(b[2] + 1) * B]
    lookup = np.arange(len(blocks), dtype=np.int32).reshape(3, 3, 3)
    field = Field(color, blocks, lookup, blocks.min(0), CELL)
    got, dense0 = field.dense()
    np.testing.assert_array_equal(got, dense)

    mesh = marching_cubes(field, 0.5)
    assert len(mesh.faces) > 10_000
    _closed_and_oriented(mesh.faces)
    assert pv.PolyData.from_regular_faces(mesh.points, mesh.faces).volume > 0
    verts, _f, _n, _v = mc(dense, level=0.5)
    on_edge = (np.abs(verts - np.round(verts)) < 1e-6).sum(1) >= 2   # Lewiner adds cell centres
    ref = np.sort(np.round((verts[on_edge] + dense0) * CELL, 6), axis=0)
    assert len(mesh.points) == len(ref)
    np.testing.assert_allclose(np.sort(mesh.points.astype(np.float64), axis=0), ref, atol=2e-6)


def test_velocity_band_is_the_full_velocity_field_there():
    """Velocities are splatted only into the band of blocks the surface crosses, from only the
    particles that reach it; there they equal the velocity field computed from all particles
    on all blocks."""
    from surfacing.reconstruct import color_field
    from surfacing.splat import Splat

    pos, vel, vol = _clump_and_stray()
    field = color_field(pos, vel, vol, CELL, SUPPORT, iso=0.5)
    assert 0 < len(field.velocity_ids) < field.n_blocks
    full = Splat(pos, vol, CELL, SUPPORT).velocity(vel, np.arange(field.n_blocks), field.rows)
    full = np.asarray(full).reshape(-1, 8, 8, 8, 3)       # numpy on the CPU
    np.testing.assert_allclose(field.velocity[:-1], full[field.velocity_ids], rtol=1e-5, atol=1e-6)
    assert np.abs(full[field.velocity_ids]).max() > 0.1


def test_particles_spread_too_far_is_one_clear_error():
    from surfacing.grid import GridTooLarge
    from surfacing.reconstruct import color_field

    pos = np.array([[0.0, 0.0, 0.0], [400.0, 400.0, 400.0]], np.float32)
    with pytest.raises(GridTooLarge, match="surface.cell_size"):
        color_field(pos, None, np.full(2, 1e-6, np.float32), CELL, SUPPORT)


def test_field_without_velocity():
    from surfacing import vdb
    from surfacing.reconstruct import color_field, marching_cubes

    pos, _vel, vol, _ = ball(radius=0.03)
    field = color_field(pos, None, vol, CELL, SUPPORT)
    mesh = marching_cubes(field, 0.5)
    assert field.velocity is None and len(mesh.faces) > 0 and not mesh.velocity.any()
    grids = {g.name: g for g in vdb.build_grids(field, mesh, 1, 0.0, 3.0)}
    assert grids["vel"].activeVoxelCount() == 0 and grids["density"].activeVoxelCount() > 0


def _trilinear(acc, xform, points):
    """Sample a FloatGrid at world points (index-space trilinear interpolation)."""
    out = np.empty(len(points))
    for n, p in enumerate(points):
        ijk = np.array(xform.worldToIndex(tuple(map(float, p))))
        base = np.floor(ijk).astype(int)
        f = ijk - base
        v = 0.0
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    w = (f[0] if dx else 1 - f[0]) * (f[1] if dy else 1 - f[1]) * (f[2] if dz else 1 - f[2])
                    v += w * acc.getValue((int(base[0] + dx), int(base[1] + dy), int(base[2] + dz)))
        out[n] = v
    return out


@pytest.fixture(scope="module")
def vdb_file(sphere_mesh, tmp_path_factory):
    from pipeline.formats import write_vdb
    from surfacing import vdb

    field, mesh, _ = sphere_mesh
    path = tmp_path_factory.mktemp("vdb") / "ball.0007.vdb"
    grids = vdb.build_grids(field, mesh, frame=7, time_s=0.25, half_width=3.0)
    write_vdb(path, grids)
    return path, grids


def test_vdb_round_trip(vdb_file):
    import pyopenvdb as ov

    path, written = vdb_file
    grids, _meta = ov.readAll(str(path))
    by_name = {g.name: g for g in grids}
    assert set(by_name) == {"surface", "density", "vel"}     # `vel`: Houdini's and Blender's name
    assert by_name["surface"].gridClass == ov.GridClass.LEVEL_SET
    assert by_name["density"].gridClass == ov.GridClass.FOG_VOLUME
    for g0 in written:
        g1 = by_name[g0.name]
        assert g1.transform.voxelSize() == pytest.approx((CELL,) * 3, rel=1e-6)
        for ijk in [(0, 0, 0), (10, -3, 7)]:
            assert g1.transform.indexToWorld(ijk) == pytest.approx(g0.transform.indexToWorld(ijk))
        assert g1.activeVoxelCount() == g0.activeVoxelCount() > 0
        assert g1.evalActiveVoxelBoundingBox() == g0.evalActiveVoxelBoundingBox()
        assert g1["frame"] == 7 and g1["time"] == pytest.approx(0.25)
        a0, a1 = g0.getConstAccessor(), g1.getConstAccessor()
        for k, item in enumerate(g0.citerOnValues()):
            if k > 2000:
                break
            ijk = item["min"]
            np.testing.assert_allclose(a1.getValue(ijk), a0.getValue(ijk), rtol=1e-6)


def test_a_cut_short_vdb_is_told_from_its_layout_alone(vdb_file, tmp_path):
    """pyopenvdb leaves a file cut short, without an error, when the disk fills, and OpenVDB
    reading such a file back took a string length from past its end: a 1.4 GB error line and a
    5.5 GB process on a full 3 MB disk. So write_vdb first checks the file's layout against its
    size (formats.vdb_cut_short): the whole file (three grids, and file metadata) holds
    together; every cut of it, from inside the magic number to its last byte, does not."""
    import pyopenvdb as ov

    from pipeline.formats import vdb_cut_short

    _path, grids = vdb_file
    whole = tmp_path / "whole.vdb"
    ov.write(str(whole), grids=grids, metadata={"creator": "sphshot", "frame": 7})
    assert vdb_cut_short(whole) is None
    data = whole.read_bytes()
    cut = tmp_path / "cut.vdb"
    for n in sorted({*range(0, 300), *np.linspace(300, len(data) - 1, 200).astype(int)}):
        cut.write_bytes(data[:n])
        assert vdb_cut_short(cut), f"cut at {n} of {len(data)} bytes passed"
    cut.write_bytes(data + b"\0")
    assert vdb_cut_short(cut) == "1 bytes after the last grid"


def test_level_set_agrees_with_mesh_and_radius(sphere_mesh, vdb_file):
    import pyopenvdb as ov

    _field, mesh, r_eq = sphere_mesh
    path, _ = vdb_file
    ls = [g for g in ov.readAll(str(path))[0] if g.name == "surface"][0]
    acc, xform = ls.getConstAccessor(), ls.transform
    sample = mesh.points[:: max(1, len(mesh.points) // 800)]
    phi = _trilinear(acc, xform, sample)
    assert np.abs(phi).max() < CELL, f"|phi| at mesh vertices up to {np.abs(phi).max() / CELL:.2f} voxels"
    # the zero crossing sits at the sphere's radius: inside one cell in, outside one cell out
    dirs = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0.6, 0.8, 0], [0, -0.6, -0.8]])
    inner = _trilinear(acc, xform, CENTRE + (r_eq - CELL) * dirs)
    outer = _trilinear(acc, xform, CENTRE + (r_eq + CELL) * dirs)
    assert (inner < 0).all() and (outer > 0).all(), f"inner {inner}, outer {outer}"


def test_water_along_a_view_ray_is_the_chord_of_the_sphere(sphere_mesh, vdb_file):
    """The render's depth tint measures the water behind a surface point along the view ray
    (surfacing.thickness, on the .vdb's level set read back densely).
    - Against the same level set sampled every 1/100 cell along 200 chords of the ball (up to
      0.95 of its radius off centre, starting on the mesh's mean sphere as rays start on a
      mesh's vertices): the entry is found within a quarter cell and the exit within half a
      cell, so within 0.75 cells.
    - Through the centre: the ball's diameter, within 1.5 cells (the lattice ball's mesh is
      lumpy by up to 0.7 cells in radius, at each end).
    - A ray that starts in air, more than two cells from the water, measures none.
    - With a longer least step, the exit is found within that step (never before it)."""
    from pipeline.formats import read_level_set
    from surfacing.thickness import ray_thickness, sample

    _field, mesh, _r = sphere_mesh
    r = np.linalg.norm(mesh.points - CENTRE, axis=1).mean()
    sdf, index_min, cell = read_level_set(vdb_file[0])
    assert cell == pytest.approx(CELL)
    rng = np.random.default_rng(5)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    side = np.cross(d, rng.normal(size=(200, 3)))
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    b = r * np.sqrt(rng.random(200)) * 0.95
    start = CENTRE + b[:, None] * side - np.sqrt(r * r - b * b)[:, None] * d
    got = ray_thickness(sdf, index_min, cell, start, d, max_length=1.0)
    s = np.arange(0.0, 2.2 * r, 0.01 * cell)        # brute force: inside at every 1/100 cell
    inside = np.stack([sample(sdf, index_min, cell, start + t * d, 1.0) < 0 for t in s], 1)
    first = inside.argmax(axis=1)
    last = len(s) - 1 - inside[:, ::-1].argmax(axis=1)
    ref = s[last] - s[first]
    assert np.abs(got - ref).max() < 0.75 * CELL, np.abs(got - ref).max() / CELL
    # with a coarser tolerance (the render's 1/32 of an absorption length) the exit is found
    # within that step instead: against the brute force, short by at most the quarter-cell
    # entry search, long by at most the step
    coarse = ray_thickness(sdf, index_min, cell, start, d, max_length=1.0, min_step=4 * CELL)
    assert (coarse - ref).min() > -0.25 * CELL and (coarse - ref).max() < 4.25 * CELL, \
        ((coarse - ref).min() / CELL, (coarse - ref).max() / CELL)
    through = ray_thickness(sdf, index_min, cell, CENTRE - r * d[:50], d[:50], max_length=1.0)
    assert np.abs(through - 2 * r).max() < 1.5 * CELL, np.abs(through - 2 * r).max() / CELL
    air = ray_thickness(sdf, index_min, cell, CENTRE + 2 * r * d[:5], d[:5], max_length=1.0)
    np.testing.assert_array_equal(air, 0.0)


def test_water_above_a_point_is_the_balls_column(sphere_mesh, vdb_file):
    """The render's light under the water (thickness.water_above): the water straight above a
    point, on the .vdb's level set read back densely.
    - On the vertical through the ball's centre, from under the ball to over it: the ball's
      diameter below it, top - y inside it, none above it, within a cell (the lattice ball's
      mesh is lumpy by up to 0.7 cells; the occupancy ramp adds nothing on average).
    - It has no steps: 0.05 cells apart along that line, neighbours differ by at most 0.1 cell
      more than the 0.05 cells the water itself changes by (the column sums looked up at the
      nearest sample, not interpolated, would jump by a cell).
    - Beside the ball (1.3 radii off its axis) and below the grid there: none; below the grid
      under the ball: the whole diameter."""
    from pipeline.formats import read_level_set
    from surfacing.thickness import water_above

    _field, mesh, _r = sphere_mesh
    r = np.linalg.norm(mesh.points - CENTRE, axis=1).mean()
    sdf, index_min, cell = read_level_set(vdb_file[0])
    y = np.arange(-1.5 * r, 1.5 * r, 0.05 * cell)
    line = CENTRE + np.outer(y, [0.0, 1.0, 0.0])
    got = water_above(sdf, index_min, cell, line)
    want = np.clip(r - y, 0.0, 2 * r)
    assert np.abs(got - want).max() < cell, np.abs(got - want).max() / cell
    assert np.abs(np.diff(got)).max() < 0.15 * cell, np.abs(np.diff(got)).max() / cell
    beside = CENTRE + [1.3 * r, 0.0, 0.0] + np.outer(y, [0.0, 1.0, 0.0])
    np.testing.assert_array_equal(water_above(sdf, index_min, cell, beside), 0.0)
    far_below = water_above(sdf, index_min, cell, CENTRE[None] - [0.0, 10 * r, 0.0])
    assert abs(far_below[0] - 2 * r) < cell


def test_empty_frame_writes_empty_mesh_and_grids(tmp_path, caplog):
    import pyopenvdb as ov

    from pipeline.spec import ShotSpec
    from surfacing import vdb
    from pipeline.formats import read_mesh, write_mesh, write_vdb
    from pipeline.stages.surface import surface_frame

    spec = ShotSpec.model_validate(tiny_spec(sim={"particle_radius": 0.01}))
    data = {k: np.zeros((0, 3) if k in ("position", "velocity") else 0, np.float32)
            for k in ("position", "velocity", "density", "pressure")}
    data.update(id=np.zeros(0, np.int32), fluid=np.zeros(0, np.int32))
    with caplog.at_level("WARNING", logger="sphshot"):
        field, mesh, _, _ = surface_frame(spec, data, {"particle_radius": 0.01}, 12)
    assert "frame 0012: surfacing: no particles" in caplog.text
    write_vdb(tmp_path / "e.vdb", vdb.build_grids(field, mesh, 12, 0.5, 3.0))
    write_vdb(tmp_path / "again.vdb", vdb.build_grids(field, mesh, 12, 0.5, 3.0))
    assert (tmp_path / "e.vdb").read_bytes() == (tmp_path / "again.vdb").read_bytes()   # the UUID from the content
    grids, _ = ov.readAll(str(tmp_path / "e.vdb"))
    assert {g.name for g in grids} == {"surface", "density", "vel"}
    assert all(g.activeVoxelCount() == 0 for g in grids)
    write_mesh(tmp_path / "e.ply", mesh, "ply")
    assert len(read_mesh(tmp_path / "e.ply").faces) == 0


@pytest.mark.parametrize("fmt,keeps_velocity", [("ply", True), ("obj", False), ("vtu", True)])
def test_mesh_formats_keep_normals(sphere_mesh, tmp_path, fmt, keeps_velocity):
    """Written twice, a mesh is the same bytes (meshio's time of writing blanked): a frame
    computed again leaves what was made from it valid."""
    import time

    from pipeline.formats import read_mesh, write_mesh

    _field, mesh, _ = sphere_mesh
    path = tmp_path / f"m.{fmt}"
    write_mesh(path, mesh, fmt)
    time.sleep(0.01)
    write_mesh(tmp_path / f"again.{fmt}", mesh, fmt)
    assert path.read_bytes() == (tmp_path / f"again.{fmt}").read_bytes()
    back = read_mesh(path)
    np.testing.assert_allclose(back.points, mesh.points, atol=1e-6)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_allclose(back.normals, mesh.normals, atol=1e-6)
    if keeps_velocity:
        np.testing.assert_allclose(back.velocity, mesh.velocity, atol=1e-6)


@pytest.mark.parametrize("smoothing, decimate", [(0, 0.0), (20, 0.0), (5, 0.5)])
def test_surface_mesh_is_marching_cubes_then_postprocess(sphere_mesh, smoothing, decimate):
    """The stage's one call (normals computed once, at the end) makes exactly the mesh of the
    two steps, each with its own normals."""
    from surfacing.reconstruct import marching_cubes, postprocess, surface_mesh

    field, _mesh, _r = sphere_mesh
    want = postprocess(marching_cubes(field, 0.5), smoothing, decimate)
    got = surface_mesh(field, 0.5, smoothing, decimate)
    for name in ("points", "faces", "normals", "velocity"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)


def test_taubin_smoothing_keeps_the_sphere(sphere_mesh):
    from surfacing.reconstruct import postprocess

    _field, mesh, r_eq = sphere_mesh
    smooth = postprocess(mesh, smoothing_iterations=20, decimate=0.5)
    assert 0.4 * len(mesh.faces) < len(smooth.faces) < 0.6 * len(mesh.faces)
    r = np.linalg.norm(smooth.points - CENTRE, axis=1)
    assert np.abs(r - r_eq).max() < 1.5 * CELL


# --------------------------------------------------------------------- anisotropic kernels, spray
def lattice_block(lo, hi, r=R_PART):
    """Particles on the fill lattice (spacing 2r) filling the box [lo, hi]."""
    ax = [np.arange(a + r, b - r + 1e-9, 2 * r) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)


def surfaced(pos, method, **kw):
    """(field, mesh, pyvista mesh) with the stage's iso for `method`, volumes (2r)^3."""
    import pyvista as pv

    from pipeline.spec import Surface
    from surfacing.reconstruct import SurfaceParams, reconstruct

    params = SurfaceParams(cell=CELL, kernel_radius=SUPPORT, iso=Surface.ISO[method], method=method, **kw)
    field, mesh = reconstruct(pos, None, np.full(len(pos), (2 * R_PART) ** 3, np.float32), params)
    return field, mesh, pv.PolyData.from_regular_faces(mesh.points, mesh.faces)


def test_anisotropic_kernel_table_matches_numpy():
    """Per particle: the weighted covariance over R = 2h, its eigen-decomposition, the axes
    s_1 / max(s_k, s_1 / KR) and det A, against numpy on a block's corner, edge, face and
    inner particles (float32 sums of ~250 terms: within 2e-4)."""
    from surfacing import anisotropy as A
    from surfacing import device as D
    from surfacing.splat import Splat

    pos = lattice_block((0, 0, 0), (0.1, 0.06, 0.1))
    sp = Splat(pos, np.full(len(pos), 1e-6, np.float32), CELL, SUPPORT, anisotropic=True)
    got_pos, table = D.host(sp.pos), D.host(sp.shape)
    R = A.RADIUS * SUPPORT
    for target in ((0.005, 0.005, 0.005), (0.005, 0.005, 0.045), (0.045, 0.055, 0.045), (0.045, 0.025, 0.045)):
        i = int(np.argmin(np.linalg.norm(got_pos - target, axis=1)))
        d = (pos - got_pos[i]) / R
        s = (d * d).sum(1)
        w = 1 - np.sqrt(s[s < 1]) ** 3
        dm = d[s < 1]
        mean = (w[:, None] * dm).sum(0) / w.sum()
        cov = np.einsum("n,ni,nj->ij", w, dm, dm) / w.sum() - np.outer(mean, mean)
        ev, u = np.linalg.eigh(cov)
        inv_axis = ev.max() / np.maximum(ev, ev.max() / A.KR)
        a = u @ np.diag(inv_axis) @ u.T
        m = a.T @ a
        want = [m[0, 0], m[1, 1], m[2, 2], m[0, 1], m[0, 2], m[1, 2], np.linalg.det(a)]
        np.testing.assert_allclose(table[i], want, atol=2e-4, err_msg=str(target))


def pool_top(mesh) -> np.ndarray:
    """The heights of the top-facing vertices over the middle of test_anisotropic_flattens_a_
    jittered_pool's pool (0.2 x 0.06 x 0.2 m)."""
    p, n = mesh.points, mesh.normals
    mid = (np.abs(p[:, 0] - 0.1) < 0.05) & (np.abs(p[:, 2] - 0.1) < 0.05)
    return p[mid & (n[:, 1] > 0.95) & (p[:, 1] > 0.03), 1]


def test_anisotropic_flattens_a_jittered_pool():
    """A pool 6 particles deep: on the exact lattice both methods give a flat top (the top-facing
    vertices' heights span under 0.01 r: issue 20's flat resting pool). With every particle
    moved by 0.1 r (rms) at random, three draws, the anisotropic top with the surface stage's
    centre smoothing (lambda 0.5, then Taubin's mu 0.53) is flatter than the isotropic: rms
    0.054, 0.050, 0.052 r against 0.059, 0.053, 0.062 r (asserted: each under the isotropic's,
    and together under 0.95 of it). The surface itself is that much flatter, not its sampling:
    on a grid four times finer the same three are 0.050, 0.048, 0.047 r against 0.063, 0.056,
    0.066 r. The smoothing keeps the mesh volume within 2 % of the exact pool's unsmoothed
    (measured 0.985-0.986; the exact pool smoothed so: 0.983, its edges rounded); its first
    pass alone (Yu & Turk's) loses 10 %.

    Until 2026-11-28 this test measured 0.028 r against 0.059 r, and a span under 0.1 r with the
    example's 60 mesh passes: marching cubes interpolated the anisotropic color linearly, which
    drew its surface towards the grid's planes, so a pool lying along them came out flatter than
    its field and a surface tilted against them in terraces (test_a_tilted_top_has_no_terraces).
    Measured through the cube root, the 60 passes leave both methods' jittered tops 0.22-0.31 r
    from lowest to highest."""
    pool = lattice_block((0, 0, 0), (0.2, 0.06, 0.2))
    for method in ("isotropic", "anisotropic"):
        _f, mesh, _p = surfaced(pool, method)
        top = pool_top(mesh)
        assert len(top) > 300 and np.ptp(top) < 0.01 * R_PART, (method, np.ptp(top) / R_PART)

    from pipeline.spec import Surface
    stage = {"center_smoothing": Surface().center_smoothing, "center_inflation": Surface().center_inflation}
    _f, _m, exact = surfaced(pool, "anisotropic")
    rms = {}
    for seed in (1, 2, 3):
        jittered = pool + np.random.default_rng(seed).normal(0, 0.1 * R_PART, pool.shape).astype(np.float32)
        for name, method, kw in (("isotropic", "isotropic", {}), ("anisotropic", "anisotropic", stage)):
            _f, mesh, poly = surfaced(jittered, method, **kw)
            rms[name, seed] = pool_top(mesh).std() / R_PART
            if name == "anisotropic":
                assert abs(abs(poly.volume) / abs(exact.volume) - 1) < 0.02, poly.volume / exact.volume
        assert rms["anisotropic", seed] < rms["isotropic", seed], rms
        if seed == 1:
            _f, _m, first_pass = surfaced(jittered, "anisotropic", **{**stage, "center_inflation": 0.0})
            assert abs(first_pass.volume) / abs(exact.volume) < 0.95     # what the second pass gives back
    together = [sum(rms[name, s] for s in (1, 2, 3)) for name in ("anisotropic", "isotropic")]
    assert together[0] < 0.95 * together[1], rms


def test_a_tilted_top_has_no_terraces(monkeypatch):
    """The pool's lattice sheared so that its top falls 0.09 m a metre along x (5 degrees against
    the grid, as the example's collapsing column tilts): the top-facing vertices lie on their
    straight line within 0.03 r rms and 0.1 r from lowest to highest (measured 0.019 r and
    0.069 r; isotropic 0.006 r). Interpolated linearly along the edges, as until 2026-11-28,
    the anisotropic color made terraces a cell apart in height, each cell / 0.09 long along x:
    0.102 r rms, 0.35 r span (asserted over 0.08 r, so the check can fail)."""
    import surfacing.reconstruct as RC

    pool = lattice_block((0, 0, 0), (0.2, 0.06, 0.2)).astype(np.float64)
    pool[:, 1] *= 1 - 0.09 * pool[:, 0] / 0.06             # the top: y = 0.06 - 0.09 x, less r

    def off_the_line():
        _f, mesh, _p = surfaced(pool.astype(np.float32), "anisotropic")
        p, n = mesh.points, mesh.normals
        top = p[(n[:, 1] > 0.9) & (np.abs(p[:, 2] - 0.1) < 0.05) & (p[:, 0] > 0.03) & (p[:, 0] < 0.17)]
        assert len(top) > 500
        res = top[:, 1] - np.polyval(np.polyfit(top[:, 0], top[:, 1], 1), top[:, 0])
        return res.std() / R_PART, np.ptp(res) / R_PART

    rms, span = off_the_line()
    assert rms < 0.03 and span < 0.1, (rms, span)
    monkeypatch.setattr(RC, "ANISOTROPIC_EDGE_POWER", 1.0)
    assert off_the_line()[0] > 0.08


def test_a_sheet_stays_a_sheet_and_a_lone_particle_a_droplet():
    """A sheet one particle thick: one connected surface under 3 r thick (measured 1.48 r; the
    field's own iso surface, on a grid four times finer, 1.35 r: the squashed kernels hold a
    sheet to about 0.7 of its particles' volume), not a string of beads. A lone particle (spray
    off): a droplet of about its own volume (measured 1.18 (2r)^3), where the isotropic kernel
    at its iso leaves nothing at all. (Interpolated linearly, as until 2026-11-28, the sheet
    measured 1.9 r at iso 0.2, as much the grid's doing as the field's: 1.31 r converged.)"""
    sheet = lattice_block((0, 0.1 - R_PART, 0), (0.2, 0.1 + R_PART, 0.2))
    _f, mesh, poly = surfaced(sheet, "anisotropic")
    assert poly.connectivity("all")["RegionId"].max() == 0
    mid = (np.abs(mesh.points[:, 0] - 0.1) < 0.03) & (np.abs(mesh.points[:, 2] - 0.1) < 0.03)
    assert np.ptp(mesh.points[mid, 1]) < 3 * R_PART
    one = np.array([[0.1, 0.1, 0.1]], np.float32)
    _f, _m, poly = surfaced(one, "anisotropic")
    assert 0.8 < abs(poly.volume) / (2 * R_PART) ** 3 < 1.5
    _f, mesh, _p = surfaced(one, "isotropic")
    assert len(mesh.faces) == 0


@pytest.mark.parametrize("method", ["isotropic", "anisotropic"])
def test_a_resting_block_keeps_its_volume_inside_the_domain(method):
    """A block in the domain's corner, as the stage surfaces it (the mesh kept inside the
    domain): no vertex outside, and the mesh volume within 3 % of the particles' (isotropic,
    iso 0.5: measured -2.6 %) and within 2 % with the anisotropic kernels (iso 0.14: -0.2 %).
    The anisotropic iso is where the example's frames 1-48 come out at 0.990-1.021 of their
    particles' volume (bench/RESULTS.md, 2026-11-28; 0.2 until the color was interpolated
    through its cube root, when it gave +1.0 % here)."""
    block = lattice_block((0, 0, 0), (0.1, 0.1, 0.1))
    _f, mesh, poly = surfaced(block, method, inside=((0, 0, 0), (0.3, 0.3, 0.3)))
    assert mesh.points.min() >= 0.0
    ratio = abs(poly.volume) / (len(block) * (2 * R_PART) ** 3)
    assert abs(ratio - 1) < (0.02 if method == "anisotropic" else 0.03), ratio


def test_particle_volumes_read_a_free_surface_as_rest():
    """V = m / max(rho, rho0): a particle short of neighbours (at a face, edge or corner) has
    its rest volume, a compressed one its smaller volume, and a frame without rest densities in
    its attributes (written before they were) keeps m / rho."""
    from surfacing.reconstruct import particle_volumes

    data = {"position": np.zeros((4, 3), np.float32), "fluid": np.array([0, 0, 1, 1]),
            "density": np.array([850.0, 1010.0, 400.0, 800.0], np.float32)}
    attrs = {"particle_radius": 0.01, "fluid_mass": [8e-3, 6.8e-3], "fluid_rest_density": [1000.0, 850.0]}
    np.testing.assert_allclose(particle_volumes(data, attrs), [8e-6, 8e-3 / 1010.0, 8e-6, 8e-6], rtol=1e-6)
    del attrs["fluid_rest_density"]
    np.testing.assert_allclose(particle_volumes(data, attrs), [8e-3 / 850, 8e-3 / 1010, 6.8e-3 / 400, 6.8e-3 / 800],
                               rtol=1e-6)


@pytest.mark.parametrize("fill", ["cubic", "fcc"])
def test_a_block_from_the_solver_keeps_its_volume_and_its_corners(fill):
    """A 0.1 m block of about 1,000 particles in mid-air, as the sim stage writes it (DFSPH's
    densities: 0.85 of rest on its faces, 0.61 at its corners) and the surface stage surfaces
    it: the mesh holds the particles' volume within 2.5 % on the cubic fill (measured +0.3 %,
    ten particles a side: its edges and corners are a large share; with V = m / rho +2.1 %) and
    within 5 % on the fcc fill (+3.5 %, 13 planes a side; with m / rho +6.0 %). The mesh reaches
    at most 1.8 r beyond the outermost particles anywhere (measured 1.73 r cubic, 1.67 r fcc, at
    the corners; with m / rho they stand out 1.96 r and 2.03 r). The middle of the top face lies
    within 0.1 r (cubic) or 0.15 r (fcc) of half a plane step above the top plane, where the
    lattice's cells end (measured -0.09 r cubic, +0.01 r fcc). (Until 2026-11-28, with the
    anisotropic color interpolated linearly along the grid's edges at iso 0.2: +1.7 % and
    +3.8 %, 1.55 r and 1.50 r, -0.03 r and +0.09 r.)"""
    from pipeline.stages.sim import frame_attrs, fresh_solver
    from pipeline.stages.surface import surface_frame
    from pipeline.spec import ShotSpec
    import pyvista as pv

    spec = ShotSpec.model_validate(tiny_spec(((0.1, 0.1, 0.1), (0.2, 0.2, 0.2)), ((0, 0, 0), (0.3, 0.3, 0.3)),
                                             sim={"particle_radius": R_PART, "fill": fill}, surface={"grids": ()}))
    params, s = fresh_solver(spec)
    data = s.snapshot()
    p = data["position"]
    assert data["density"].min() < 0.65 * 1000.0        # the corners' SPH density (0.61 of rest)
    _f, mesh, _per, _spray = surface_frame(spec, data, frame_attrs(spec, params, 1, s, {}), 1)
    poly = pv.PolyData.from_regular_faces(mesh.points, mesh.faces)
    ratio = abs(poly.volume) / (len(p) * (2 * R_PART) ** 3)
    q = mesh.points
    reach = max((p.min(0) - q.min(0)).max(), (q.max(0) - p.max(0)).max()) / R_PART
    face = q[(np.abs(q[:, 0] - 0.15) < 0.01) & (np.abs(q[:, 2] - 0.15) < 0.01) & (q[:, 1] > 0.15), 1]
    top = p[:, 1].max() + 0.5 * params.fill_domain.step[1]      # r above the top plane on the cubic fill
    assert abs(ratio - 1) < (0.025 if fill == "cubic" else 0.05) and reach < 1.8, (ratio, reach)
    assert abs(face.mean() - top) < (0.1 if fill == "cubic" else 0.15) * R_PART, (face.mean() - top) / R_PART


def test_spray_is_the_isolated_particles():
    """A clump and a few scattered particles: the scattered ones (fewer than 25 neighbours within
    2h) are spray, in input order, and add nothing to the field; the clump is not spray."""
    from surfacing.reconstruct import color_field

    clump = lattice_block((0.1, 0.1, 0.1), (0.16, 0.16, 0.16))
    stray = np.array([[0.3, 0.3, 0.3], [0.3, 0.32, 0.3], [0.02, 0.25, 0.05]], np.float32)
    pos = np.concatenate([stray[:2], clump, stray[2:]])
    vol = np.full(len(pos), (2 * R_PART) ** 3, np.float32)
    for aniso in (False, True):
        field = color_field(pos, None, vol, CELL, SUPPORT, iso=0.2, anisotropic=aniso, spray_below=25)
        want = np.zeros(len(pos), bool)
        want[[0, 1, len(pos) - 1]] = True
        np.testing.assert_array_equal(field.spray, want)
        alone = color_field(clump, None, vol[:len(clump)], CELL, SUPPORT, iso=0.2, anisotropic=aniso)
        assert abs(field.color.sum() - alone.color.sum()) < 1e-3 * alone.color.sum()


def test_surface_stage_writes_the_spray_as_points(tmp_path):
    """The surface stage on a sim frame of a clump and three stray particles: the frame's spray
    file holds exactly the strays, with their velocities, the particle radius (pscale) and their
    fluid's index, is one of the frame's files (the cache checks it with the others) and the
    mesh is the clump's."""
    from pipeline.cache import ShotPaths
    from pipeline.formats import read_mesh, read_points, write_frame
    from pipeline.spec import ShotSpec
    from pipeline.stages import STAGES
    from pipeline.stages.surface import _write_frame

    spec = ShotSpec.model_validate(tiny_spec(sim={"particle_radius": R_PART}, surface={"grids": ()},
                                             shot={"output": str(tmp_path)}))
    clump = lattice_block((0.1, 0.1, 0.1), (0.16, 0.16, 0.16))
    stray = np.array([[0.3, 0.3, 0.3], [0.3, 0.32, 0.3], [0.02, 0.25, 0.05]], np.float32)
    pos = np.concatenate([clump, stray])
    vel = np.zeros_like(pos)
    vel[-3:] = [[1.0, 2.0, 3.0], [0.0, -1.0, 0.0], [0.5, 0.0, 0.0]]
    n = len(pos)
    paths = ShotPaths.for_spec(spec)
    write_frame(paths.sim_frame(4), {"position": pos, "velocity": vel, "density": np.full(n, 1000.0),
                                     "pressure": np.zeros(n), "id": np.arange(n), "fluid": np.zeros(n, int)},
                {"frame": 4, "time": 0.1, "particle_radius": R_PART})
    written = _write_frame(spec, 4, paths)
    assert paths.surface_spray(4) in written and paths.surface_spray(4) in STAGES["surface"].frame_files(paths, 4)
    spray = read_points(paths.surface_spray(4))
    order = np.argsort(spray["position"][:, 0] + spray["position"][:, 1])
    np.testing.assert_array_equal(spray["position"][order], stray[[2, 0, 1]])
    np.testing.assert_array_equal(spray["velocity"][order], vel[-3:][[2, 0, 1]])
    import meshio
    assert "fluid" in meshio.read(str(paths.surface_spray(4))).point_data      # each point's fluid index
    np.testing.assert_array_equal(spray["fluid"], 0)
    assert (spray["pscale"] == np.float32(R_PART)).all()
    mesh = read_mesh(paths.surface_meshes(4)[None])
    assert mesh.points.max() < 0.2
    assert not paths.surface_spray_vdb(4).exists()        # no grids asked for: no VDB points either


def test_surface_stage_writes_the_spray_as_vdb_points_too(tmp_path):
    """With grids (the default) the spray also goes to surface/<name>.0004.spray.vdb, an OpenVDB
    PointDataGrid `spray` (P, v, pscale, fluid) that pyopenvdb cannot write, through
    sphshot-vdb-points: the same points as the PLY (count, sums and extremes read back from the
    file within float32 round-off, 1e-6 m), a file of the frame the cache checks."""
    from pipeline.cache import ShotPaths
    from pipeline.formats import read_vdb_points, write_frame
    from pipeline.spec import ShotSpec
    from pipeline.stages import STAGES
    from pipeline.stages.surface import _write_frame

    spec = ShotSpec.model_validate({**tiny_spec(sim={"particle_radius": R_PART}, shot={"output": str(tmp_path)}),
                                    "fluids": ({"name": "a", "blocks": ({"min": (0.1, 0.1, 0.1), "max": (0.16, 0.16, 0.16)},)},
                                               {"name": "b", "blocks": ({"min": (0.3, 0.3, 0.3), "max": (0.31, 0.31, 0.31)},)})})
    clump = lattice_block((0.1, 0.1, 0.1), (0.16, 0.16, 0.16))
    stray = np.array([[0.3, 0.3, 0.3], [0.3, 0.32, 0.3], [0.02, 0.25, 0.05]], np.float32)
    pos = np.concatenate([clump, stray])
    vel = np.zeros_like(pos)
    vel[-3:] = [[1.0, 2.0, 3.0], [0.0, -1.0, 0.0], [0.5, 0.0, 0.0]]
    fluid = np.zeros(len(pos), int)
    fluid[-2:] = 1
    n = len(pos)
    paths = ShotPaths.for_spec(spec)
    write_frame(paths.sim_frame(4), {"position": pos, "velocity": vel, "density": np.full(n, 1000.0),
                                     "pressure": np.zeros(n), "id": np.arange(n), "fluid": fluid},
                {"frame": 4, "time": 0.1, "particle_radius": R_PART})
    written = _write_frame(spec, 4, paths)
    target = paths.surface_spray_vdb(4)
    assert target in written and target in STAGES["surface"].frame_files(paths, 4)
    got = read_vdb_points(target)
    assert got["count"] == 3
    np.testing.assert_allclose(got["position_sum"], stray.astype(float).sum(0), atol=1e-6)
    np.testing.assert_allclose(got["position_min"], stray.min(0), atol=1e-6)
    np.testing.assert_allclose(got["position_max"], stray.max(0), atol=1e-6)
    np.testing.assert_allclose(got["velocity_sum"], vel[-3:].sum(0), atol=1e-6)
    assert got["pscale_sum"] == pytest.approx(3 * R_PART, rel=1e-6)
    assert got["fluid_sum"] == 2


def test_vdb_points_round_trip_and_no_points():
    """write_vdb_points publishes what read_vdb_points reads back (500 random points, two
    fluids); a frame without spray gives a valid file with an empty grid."""
    import tempfile
    from pathlib import Path

    from pipeline.formats import read_vdb_points, write_vdb_points

    rng = np.random.default_rng(3)
    pos = rng.uniform(-1, 2, (500, 3)).astype(np.float32)
    vel = rng.normal(0, 2, (500, 3)).astype(np.float32)
    fluid = rng.integers(0, 2, 500)
    with tempfile.TemporaryDirectory() as d:
        path = write_vdb_points(Path(d) / "a.spray.vdb", pos, vel, 0.004, fluid)
        got = read_vdb_points(path)
        assert got["count"] == 500 and got["fluid_sum"] == fluid.sum()
        np.testing.assert_allclose(got["position_sum"], pos.astype(float).sum(0), atol=1e-4)   # 500 float32s
        np.testing.assert_allclose(got["velocity_sum"], vel.astype(float).sum(0), atol=1e-4)
        assert got["pscale_sum"] == pytest.approx(500 * 0.004, rel=1e-6)
        empty = write_vdb_points(Path(d) / "b.spray.vdb", np.zeros((0, 3)), np.zeros((0, 3)), 0.004, np.zeros(0))
        assert read_vdb_points(empty)["count"] == 0
        assert sorted(p.name for p in Path(d).iterdir()) == ["a.spray.vdb", "b.spray.vdb"]    # no temporaries
        # the tool checks a file's layout before OpenVDB reads it (what a full disk leaves when
        # the tool writes): every cut is refused in one short line
        data = path.read_bytes()
        cut = Path(d) / "cut.vdb"
        for n in (0, 20, 57, 70, 130, len(data) // 2, len(data) - 1):
            cut.write_bytes(data[:n])
            with pytest.raises(OSError, match="does not hold together") as refused:
                read_vdb_points(cut)
            assert len(str(refused.value)) < 300, n


def test_spray_vdb_without_its_tool_is_one_clear_error(tmp_path, monkeypatch):
    """Where sphshot-vdb-points was not built, a run that would write VDB points stops before
    any stage starts (the sim included: nothing is written, no version folder is left) with one
    line naming the keys and the way out; so does the surface stage called on its own."""
    from pipeline.cache import ShotPaths
    from pipeline.errors import StageError
    from pipeline.runner import run_stages
    from pipeline.spec import ShotSpec
    from pipeline.stages import surface

    spec = ShotSpec.model_validate(tiny_spec(shot={"output": str(tmp_path), "frame_end": 2}))
    monkeypatch.setattr(surface, "vdb_points_tool", lambda: None)
    line = r"surface\.spray and surface\.grids: .*scripts/setup\.sh.*surface\.spray = 0"
    with pytest.raises(StageError, match=line):
        run_stages(spec, ["sim", "surface"], spec.frames)
    assert [p for p in tmp_path.rglob("*") if not p.is_dir()] == []
    assert not ShotPaths.for_spec(spec).root.exists()
    with pytest.raises(StageError, match=line):
        surface.run(spec, [1], ShotPaths.for_spec(spec), None)
    ok = ShotSpec.model_validate(tiny_spec(shot={"output": str(tmp_path)}, surface={"grids": ()}))
    surface.ready(ok, ShotPaths.for_spec(ok))            # no VDB asked for: the tool is not needed


@pytest.mark.parametrize("anisotropic", [False, True])
def test_device_arrays_as_on_a_gpu_give_the_same_field(monkeypatch, anisotropic):
    """On a GPU the surfacer's arrays are Taichi ndarrays (vectors where numpy has a last axis),
    on the CPU numpy arrays. The ndarray path forced on the CPU (both scatters) gives the same
    color bit for bit and the same spray: what caught a kernel argument typed for numpy's 2-D
    table that a GPU's vector ndarray does not match (H200, twelfth session). The anisotropic
    case smooths the centres in both passes, as the surface stage does."""
    from surfacing import device as D
    from surfacing.reconstruct import color_field

    pos, _vel, vol = _clump_and_stray()
    iso = 0.2 if anisotropic else 0.5
    from pipeline.spec import Surface
    stage = Surface()           # the surface stage's centre smoothing, both passes
    smooth = ({"center_smoothing": stage.center_smoothing, "center_inflation": stage.center_inflation}
              if anisotropic else {})
    want = color_field(pos, None, vol, CELL, SUPPORT, iso, anisotropic=anisotropic, spray_below=25, **smooth)
    monkeypatch.setattr(D, "on_cpu", lambda: False)
    for method in ("phased", "atomic"):
        got = color_field(pos, None, vol, CELL, SUPPORT, iso, method=method, anisotropic=anisotropic, spray_below=25,
                          **smooth)
        np.testing.assert_array_equal(got.spray, want.spray)
        if method == "phased":
            np.testing.assert_array_equal(got.color, want.color)
        else:           # fixed-point sums: the same to float32 round-off
            np.testing.assert_allclose(got.color, want.color, atol=2e-5)


def test_the_mesh_stays_inside_the_domain_and_out_of_colliders():
    """Water resting against a sphere obstacle (the particles' centres down to half a radius
    from its surface) and the domain's walls, as the surface stage makes its mesh: no vertex outside the
    domain or inside the sphere (float32 round-off: within 1e-6 m). Without keeping it out, the
    kernels carried the surface 1.6 mm into the sphere and 3.7 mm past the walls (asserted, so
    the check can fail). With the particles one radius further from the sphere the raw surface
    stops 0.5 mm short of it (it went 0.09 mm in while the anisotropic color was interpolated
    linearly, before 2026-11-28)."""
    from pipeline.spec import ShotSpec
    from pipeline.stages.sim import solver_params
    from pipeline.stages.surface import surface_frame
    from solver.boundaries import collider_clearance
    from surfacing.reconstruct import SurfaceParams, reconstruct

    centre, radius = np.array([0.1, 0.05, 0.1]), 0.04
    spec = ShotSpec.model_validate(tiny_spec(((0, 0, 0), (0.2, 0.1, 0.2)), ((0, 0, 0), (0.2, 0.3, 0.2)),
                                             sim={"particle_radius": R_PART},
                                             colliders=({"type": "sphere", "center": tuple(centre), "radius": radius},)))
    pos = lattice_block((0, 0, 0), (0.2, 0.1, 0.2))
    pos = pos[np.linalg.norm(pos - centre, axis=1) > radius + 0.5 * R_PART]
    n = len(pos)
    data = {"position": pos, "velocity": np.zeros_like(pos), "density": np.full(n, 1000.0, np.float32),
            "fluid": np.zeros(n, np.int32)}
    _field, mesh, _pf, _spray = surface_frame(spec, data, {"particle_radius": R_PART}, 1)
    clearance = collider_clearance(solver_params(spec), mesh.points)
    assert clearance.min() > -1e-6 and mesh.points.min() >= 0 and mesh.points.max() <= 0.2 + 1e-6
    raw = reconstruct(pos, None, np.full(n, (2 * R_PART) ** 3, np.float32),
                      SurfaceParams(cell=CELL, kernel_radius=SUPPORT, iso=spec.surface.iso_value, method="anisotropic"))[1]
    assert collider_clearance(solver_params(spec), raw.points).min() < -5e-5 and raw.points.min() < -1e-3
