"""Mesh colliders at the pipeline's edges: reading, checking and placing the file, its errors,
the cache's view of it, and drawing it."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline import cache
from pipeline.cli import main
from pipeline.meshes import read_closed_mesh
from pipeline.spec import load_spec
from test_spec_errors import GOOD

JOB = GOOD + """
[[colliders]]
type = "mesh"
path = "{path}"
scale = 0.1
translate = [0.6, 0.1, 0.2]
"""


def write_cube(path, quads=True):
    """A unit cube [0, 1]^3 through meshio; quads or, split, triangles."""
    import meshio

    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    q = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
    cells = [("quad", q)] if quads else [("triangle", np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]]))]
    meshio.write(path, meshio.Mesh(v, cells))
    return path


def test_placement_scales_then_rotates_about_x_y_z_then_translates(tmp_path):
    write_cube(tmp_path / "cube.obj")
    job = tmp_path / "job.toml"
    job.write_text(JOB.format(path="cube.obj").replace("scale = 0.1", "scale = 0.1\nrotate = [90.0, 0.0, 90.0]"))
    spec = load_spec(job)
    verts, tris = spec.collider_mesh(0)
    file_verts, _ = read_closed_mesh(tmp_path / "cube.obj")
    # x -> (about x) x -> (about z) y;  y -> z -> z;  z -> -y -> x
    expect = 0.1 * file_verts[:, [2, 0, 1]] + [0.6, 0.1, 0.2]
    np.testing.assert_allclose(verts, expect, atol=1e-12)
    assert len(tris) == 12                       # six quads, split


def test_stl_triangles_are_welded_into_a_closed_mesh(tmp_path):
    """STL stores three vertices per triangle: closedness is judged after welding them."""
    import meshio

    write_cube(tmp_path / "cube.obj", quads=False)
    v, t = read_closed_mesh(tmp_path / "cube.obj")
    meshio.write(tmp_path / "cube.stl", meshio.Mesh(v[t].reshape(-1, 3), [("triangle", np.arange(36).reshape(-1, 3))]))
    sv, st = read_closed_mesh(tmp_path / "cube.stl")
    assert len(sv) == 8 and len(st) == 12


def bad_mesh(tmp_path, kind):
    import meshio

    if kind == "missing":
        return "nope.obj"
    if kind == "open":                       # the cube without its top
        v, t = read_closed_mesh(write_cube(tmp_path / "cube.obj", quads=False))
        top = (v[t][:, :, 1] == 1).all(1)
        meshio.write(tmp_path / "open.obj", meshio.Mesh(v, [("triangle", t[~top])]))
        return "open.obj"
    if kind == "garbage":
        (tmp_path / "junk.ply").write_bytes(b"this is not a ply file\n")
        return "junk.ply"
    if kind in ("cut", "cut_row"):           # a copy that stopped mid-number, or mid-line
        text = write_cube(tmp_path / "cube.obj").read_text()
        last_vertex = text.rindex("\nv ") + 1
        (tmp_path / f"{kind}.obj").write_text(text[:last_vertex] + ("v 1.0 1.0 -" if kind == "cut" else "v 1.0 1.0"))
        return f"{kind}.obj"
    if kind == "lines":                      # cells, but no faces
        meshio.write(tmp_path / "lines.vtu", meshio.Mesh(np.eye(3), [("line", np.array([[0, 1], [1, 2]]))]))
        return "lines.vtu"
    raise KeyError(kind)


@pytest.mark.parametrize("kind,expect", [
    ("missing", "colliders[0].path: mesh file '{dir}/nope.obj' not found"),
    ("open", "is not closed (4 edges belong to one face only)"),
    ("garbage", "colliders[0].path: cannot read mesh file"),
    ("lines", "has no triangles or quads"),
    ("cut", "cannot read mesh file '{dir}/cut.obj': it is malformed or cut short (could not convert"),
    ("cut_row", "cannot read mesh file '{dir}/cut_row.obj': it is malformed or cut short (rows of different"),
])
@pytest.mark.parametrize("command", ["validate", "run"])
def test_bad_mesh_file_is_one_clear_line(tmp_path, capsys, kind, expect, command):
    job = tmp_path / "job.toml"
    job.write_text(JOB.format(path=bad_mesh(tmp_path, kind)))
    code = main([command, str(job)])
    out, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and "Traceback" not in out + err, (code, err)
    assert lines[0].startswith(f"sphshot: error: {job}:") and expect.format(dir=tmp_path) in lines[0], lines[0]
    assert not (tmp_path / "out").exists()


def test_mesh_too_fine_for_its_distance_grid_is_refused(tmp_path, capsys):
    write_cube(tmp_path / "cube.obj")
    job = tmp_path / "job.toml"
    job.write_text(JOB.format(path="cube.obj").replace("scale = 0.1", "scale = 0.9\nvoxel_size = 0.25")
                   .replace("particle_radius = 0.02", "particle_radius = 0.002"))
    assert main(["validate", str(job)]) == 2
    assert "colliders[0].voxel_size: the mesh colliders' distance grids would have" in capsys.readouterr().err


def test_mesh_colliders_share_one_distance_grid_budget(tmp_path, capsys):
    """Each grid fits alone, two do not: offsets into them must stay exact in float32."""
    write_cube(tmp_path / "cube.obj")
    job = tmp_path / "job.toml"
    one = JOB.format(path="cube.obj").replace("scale = 0.1", "scale = 0.17\nvoxel_size = 0.25")
    job.write_text(one.replace("particle_radius = 0.02", "particle_radius = 0.004"))
    assert main(["validate", str(job)]) == 0
    second = one[one.index("[[colliders]]"):]
    job.write_text(one.replace("particle_radius = 0.02", "particle_radius = 0.004") + second)
    assert main(["validate", str(job)]) == 2
    assert "colliders[1].voxel_size: the mesh colliders' distance grids would have" in capsys.readouterr().err


def test_editing_the_mesh_file_invalidates_the_sim(tmp_path):
    write_cube(tmp_path / "cube.obj")
    job = tmp_path / "job.toml"
    job.write_text(JOB.format(path="cube.obj"))
    before = cache.stage_hashes(load_spec(job))
    assert cache.stage_hashes(load_spec(job)) == before           # reading is repeatable
    write_cube(tmp_path / "cube.obj", quads=False)                # same shape, another file
    after = cache.stage_hashes(load_spec(job))
    assert all(after[s] != before[s] for s in cache.STAGES)       # sim, and all that follows


def test_render_draws_the_placed_mesh(tmp_path):
    from pipeline.stages.render import collider_meshes

    write_cube(tmp_path / "cube.obj")
    job = tmp_path / "job.toml"
    job.write_text(JOB.format(path="cube.obj"))
    spec = load_spec(job)
    (mesh, col), = collider_meshes(spec)
    assert col is spec.colliders[0]
    np.testing.assert_allclose(mesh.bounds, (0.6, 0.7, 0.1, 0.2, 0.2, 0.3), atol=1e-9)
    assert mesh.n_cells == 12
