"""Render stage: golden images of synthetic scenes, movie, contact sheet, flat memory.

Golden images are small (320x180) with everything pinned in the job (camera, lights,
background, no SSAA). Regenerate them after an intended look change with
    SPHSHOT_UPDATE_GOLDEN=1 .venv/bin/python -m pytest tests/test_render.py
and look at them before committing.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from conftest import tiny_spec, use_taichi_cpu
from pipeline.cache import ShotPaths
from pipeline.progress import Progress
from pipeline.spec import ShotSpec

GOLDEN = Path(__file__).parent / "golden"
# Mean absolute difference per channel (0-255) and the share of pixels off by more than 40:
# llvmpipe versions and GPU drivers differ in shading round-off and edge coverage, not in
# what is where; a moved camera, wrong color or missing object breaks both bounds by far.
MEAN_TOL = 3.0
OUTLIER_TOL = 0.01


def scene(tmp_path, look: str = "preview", surface: dict | None = None, color=None, **render):
    """The golden scene. With the preview look, its own background (as before looks existed);
    with another look, the look's background, ground and material. The water look's fluid is the
    preview's blue half way to clear water's: the color that look drew it in when its golden
    was made (it took every fluid's color half way there itself then)."""
    base = {"look": look, "resolution": (320, 180), "ssaa": False, "movie": True, "contact_sheet": True,
            "camera": {"position": (1.2, 0.8, 1.3), "focal_point": (0.3, 0.15, 0.2), "fov": 40.0},
            "lights": ({"position": (2.0, 3.0, 2.0), "intensity": 1.0},
                       {"position": (-2.0, 1.0, 1.0), "intensity": 0.4})}
    if look == "preview":
        base.update(background=(0.1, 0.1, 0.12), background_top=(0.3, 0.34, 0.4))
    base.update(render)
    return ShotSpec.model_validate(tiny_spec(
        ((0, 0, 0), (0.2, 0.2, 0.2)), ((0, 0, 0), (0.6, 0.4, 0.4)), name="golden", surface=surface or {},
        shot={"frame_start": 1, "frame_end": 3, "output": str(tmp_path)},
        fluid={"name": "water", "color": color or ((0.2, 0.45, 0.85) if look != "water" else (0.1, 0.375, 0.625))},
        colliders=({"type": "box", "min": (0.45, 0.0, 0.1), "max": (0.55, 0.1, 0.3)},), render=base))


def synthetic_meshes(spec, frames, velocity=(0.0, 0.0, 0.0)):
    """A sphere of water that moves along x, written where the surface stage would put it (its
    vertices carry `velocity`)."""
    import pyvista as pv

    from pipeline.formats import write_mesh
    from surfacing.mesh import Mesh
    from surfacing.reconstruct import vertex_normals

    use_taichi_cpu()                  # vertex_normals is a Taichi loop
    paths = ShotPaths.for_spec(spec)
    for f in frames:
        s = pv.Sphere(radius=0.1, center=(0.15 + 0.05 * f, 0.1, 0.2), theta_resolution=40, phi_resolution=40)
        pts = np.asarray(s.points, np.float32)
        faces = np.asarray(s.faces).reshape(-1, 4)[:, 1:].astype(np.int32)
        mesh = Mesh(pts, faces, vertex_normals(pts, faces), np.broadcast_to(np.float32(velocity), pts.shape).copy())
        path = paths.surface_meshes(f)[None]
        path.parent.mkdir(parents=True, exist_ok=True)
        write_mesh(path, mesh, "ply")
    return paths


def synthetic_particles(spec, frames):
    from pipeline.formats import write_frame

    paths = ShotPaths.for_spec(spec)
    ax = np.arange(0.02, 0.2, 0.02)
    p = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    for f in frames:
        v = np.zeros_like(p)
        v[:, 0] = p[:, 1] * 10 * f      # speed grows with height and frame
        write_frame(paths.sim_frame(f), {"position": p + [0.05 * f, 0, 0.1], "velocity": v,
                                         "density": np.full(len(p), 1000.0), "pressure": np.zeros(len(p)),
                                         "id": np.arange(len(p)), "fluid": np.zeros(len(p), int)},
                    {"frame": f, "time": 0.0, "particle_radius": 0.01})
    return paths


def with_level_set(paths, frame: int):
    """Write the level set of the frame's synthetic mesh where the surface stage puts its .vdb
    (the water look's depth tint reads it); returns the mesh."""
    import pyopenvdb as ov

    from pipeline.formats import read_mesh, write_vdb

    m = read_mesh(paths.surface_meshes(frame)[None])
    grid = ov.FloatGrid.createLevelSetFromPolygons(m.points.astype(np.float64), triangles=m.faces,
                                                   transform=ov.createLinearTransform(voxelSize=0.005),
                                                   halfWidth=3.0)
    grid.name = "surface"
    write_vdb(paths.surface_vdb(frame), [grid])
    return m


def facing_camera(spec, m) -> np.ndarray:
    """How squarely each vertex of mesh m faces the job's camera: -n . ray (1 head on, < 0
    turned away)."""
    ray = m.points - np.asarray(spec.render.camera.position)
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    return -np.einsum("ij,ij->i", m.normals, ray)


def quiet():
    return Progress(stream=open(os.devnull, "w"), interactive=False)


def compare(name: str, image_path: Path):
    got = np.asarray(Image.open(image_path).convert("RGB"), np.float64)
    golden = GOLDEN / f"{name}.png"
    if os.environ.get("SPHSHOT_UPDATE_GOLDEN") or not golden.exists():
        if not os.environ.get("SPHSHOT_UPDATE_GOLDEN"):
            pytest.fail(f"missing golden image {golden}; create it with SPHSHOT_UPDATE_GOLDEN=1")
        golden.parent.mkdir(exist_ok=True)
        Image.fromarray(got.astype(np.uint8)).save(golden)
    want = np.asarray(Image.open(golden).convert("RGB"), np.float64)
    assert got.shape == want.shape, f"{name}: size {got.shape} vs golden {want.shape}"
    diff = np.abs(got - want)
    mean, outliers = diff.mean(), (diff.max(axis=2) > 40).mean()
    assert mean < MEAN_TOL and outliers < OUTLIER_TOL, \
        f"{name}: mean abs diff {mean:.2f} (tol {MEAN_TOL}), {outliers:.2%} pixels off by >40 (tol {OUTLIER_TOL:.0%})"


def test_surface_golden_headless(tmp_path):
    from pipeline.stages import render

    assert "DISPLAY" not in os.environ, "renders must work with DISPLAY unset"
    spec = scene(tmp_path)
    paths = synthetic_meshes(spec, [1, 2, 3])
    render.run(spec, [1, 2, 3], paths, quiet())
    compare("surface_f2", paths.render_frame(2))
    img = np.asarray(Image.open(paths.render_frame(2)))
    assert img.shape == (180, 320, 3)


@pytest.mark.parametrize("look", ["water", "clay"])
def test_looks_golden(tmp_path, look, capfd):
    """Each render.look on the synthetic sphere, with spray points beside it (the surface
    stage's spray file): the look's own background, ground and material (the scene's background
    keys are dropped so the look sets them). The water look draws the sphere translucent: the
    box collider behind it shows through. VTK prints no warning (the water look's sky made one
    per frame, 70 in the example's log, until its spherical harmonics were turned off)."""
    from pipeline.formats import write_points
    from pipeline.stages import render

    spec = scene(tmp_path, look=look, surface={"spray": 25})
    paths = synthetic_meshes(spec, [2])
    rng = np.random.default_rng(2)
    write_points(paths.surface_spray(2), (rng.random((40, 3)) * [0.1, 0.1, 0.1] + [0.35, 0.25, 0.15]).astype(np.float32),
                 np.zeros((40, 3), np.float32), 0.004)
    render.run(spec, [2], paths, quiet())
    err = capfd.readouterr().err
    assert "WARN|" not in err and "ERR|" not in err, err     # vtkLogger's lines
    compare(f"look_{look}_f2", paths.render_frame(2))
    if look != "preview":
        # the ground has no edge in the frame: the top row is the fade's one color, where a plane
        # too small ended in the corners as a wedge of the background's top color (off by up to
        # 35 levels: inside the golden tolerance, so checked here)
        top = np.asarray(Image.open(paths.render_frame(2)).convert("RGB"), np.float64)[0]
        assert np.abs(top - top.mean(axis=0)).max() <= 2, "the ground ends inside the frame"


def test_water_look_draws_each_fluid_in_its_own_color(tmp_path):
    """The water look keeps a fluid's color (dimmed): the synthetic sphere as honey reads amber,
    red over green over blue at its middle (measured 135, 119, 83), and as the example's water
    blue. (Until 2026-11-26 the look took every color half way to clear water's: honey came out
    olive grey, 109, 111, 100.)"""
    from pipeline.stages import render

    middle = {}
    for name, color in (("honey", (0.85, 0.52, 0.1)), ("water", (0.11, 0.39, 0.61))):
        spec = scene(tmp_path / name, look="water", color=color)
        paths = synthetic_meshes(spec, [2])
        render.run(spec, [2], paths, quiet())
        img = np.asarray(Image.open(paths.render_frame(2)).convert("RGB"), np.float64)
        middle[name] = img[92:98, 149:155].reshape(-1, 3).mean(axis=0)
    r, g, b = middle["honey"]
    assert r > g + 10 and g > b + 10, middle
    r, g, b = middle["water"]
    assert b > g > r, middle


def test_sky_is_the_looks_colors_and_the_same_every_time():
    """The environment the water look reflects: the background's top color overhead, its
    bottom color at the horizon, the ground color below, white soft boxes, and no randomness."""
    from pipeline.stages.render import LOOKS, sky_faces

    look = LOOKS["water"]
    faces = sky_faces(look, n=64)
    assert all(np.array_equal(a, b) for a, b in zip(faces, sky_faces(look, n=64)))
    px, py, nx, ny = faces[0], faces[2], faces[1], faces[3]
    color = lambda c: np.round(np.asarray(c) * 255)   # noqa: E731
    assert np.abs(py[32, 32] - color(look["background_top"])).max() <= 1      # straight up
    bottom, top = color(look["background"]), color(look["background_top"])
    for side in (px, nx):   # the texel row just above the horizon (1/64 up): an eighth of the way up
        assert np.abs(side[31, 10] - bottom).max() <= 0.13 * np.abs(top - bottom).max() + 1
    assert np.abs(ny[32, 32] - color(look["ground_color"])).max() <= 1        # straight down
    white = (py == 255).all(axis=2).mean()
    assert 0.05 < white < 0.5, f"soft boxes cover {white:.0%} of the top face"


def test_contact_shadow_lies_under_what_casts_it():
    """A closed 0.2 m cube in a 1 m domain: straight down, its top and bottom each cover the
    texels under it once, so under its middle the opacity is strength * (1 - exp(-1)) (the
    blur, 4.5 cm: 3 % of the diagonal, takes 5 % off the middle of a 20 cm square); 15 cm
    beside it, nothing. The same under a closed upright cylinder of 12 cm radius (its side
    projects onto its outline; the blur takes 3 % off its middle)."""
    import pyvista as pv

    from pipeline.stages.render import ContactShadow

    shadow = ContactShadow(pv, (0, 0, 0), (1, 0.5, 1), strength=0.5)
    cube = pv.Box(bounds=(0.4, 0.6, 0.0, 0.2, 0.4, 0.6)).triangulate()
    # a cylinder's caps are polygons (as a capsule collider's drawing is), spray is points
    post = pv.Cylinder(center=(0.2, 0.1, 0.2), direction=(0, 1, 0), radius=0.12, height=0.2, resolution=48)
    shadow.cast([cube, post, pv.PolyData(np.full((3, 3), 0.8))])
    alpha = shadow.opacity
    x = shadow.origin[0] + shadow.texel * np.arange(shadow.shape[0])
    z = shadow.origin[1] + shadow.texel * np.arange(shadow.shape[1])
    at = lambda px, pz: alpha[np.abs(x - px).argmin(), np.abs(z - pz).argmin()]   # noqa: E731
    assert at(0.5, 0.5) == pytest.approx(0.5 * (1 - np.exp(-1)), abs=0.02)
    assert at(0.2, 0.2) == pytest.approx(0.5 * (1 - np.exp(-1)), abs=0.03)
    assert at(0.75, 0.5) < 0.01 and at(0.5, 0.25) < 0.01
    shadow.cast([])
    assert shadow.opacity.max() == 0 and (shadow.layer.point_data["rgb"] == round(0.5 * 255)).all()


def test_water_is_as_clear_as_it_is_shallow(tmp_path):
    """With the frame's level set beside its mesh, the water look gives each vertex the opacity
    of the water behind it along the camera's ray (Beer-Lambert): looking through the middle of
    the 0.2 m ball (1.6 absorption lengths: 0.15 of the scene's 0.82 m diagonal) more opaque
    than near its outline, a short chord (measured 0.79 against 0.39 on average); every vertex
    at least the floor (half the look's opacity); faces turned away clear. The frame is drawn
    with these opacities."""
    from pipeline.formats import read_level_set
    from pipeline.stages import render

    spec = scene(tmp_path, look="water")
    paths = synthetic_meshes(spec, [2])
    m = with_level_set(paths, 2)
    fr = render.FrameRenderer(spec)
    try:
        alpha = fr._water_alpha(2, m.points, m.normals, read_level_set(paths.surface_vdb(2)))
        facing = facing_camera(spec, m)
        look = fr.look
        assert (alpha[facing < 0] == 0).all()
        assert (alpha[facing > 0] >= 0.5 * look["opacity"] - 1e-9).all()
        assert alpha[facing > 0.95].mean() > alpha[(facing > 0) & (facing < 0.3)].mean() + 0.2
        fr.render(2, paths)
        drawn = [a for a in fr.fluid_actors if a.mapper.dataset.point_data.get("rgba") is not None]
        assert len(drawn) == 1
        np.testing.assert_array_equal(drawn[0].mapper.dataset.point_data["rgba"][:, 3], np.round(255 * alpha))
    finally:
        fr.close()


def test_a_colored_liquid_takes_its_color_at_its_transmission_depth(tmp_path):
    """fluids.transmission_depth (honey): light through a length d of the liquid keeps
    color^(d / depth) of each channel. Against the look's ground gray g each front vertex's
    color c and alpha blend to exactly g times that (alpha c + (1 - alpha) g = g T, where alpha
    is above its floor); the middle of the 0.2 m ball (about 4 depths of 5 cm behind it) is
    darker and redder than near its outline, and more opaque; faces turned away are clear. The
    frame matches its golden: an amber ball, deep orange-brown at its middle, gold at its rim."""
    from pipeline.formats import read_level_set
    from pipeline.stages import render

    honey = (0.8, 0.45, 0.08)
    spec = scene(tmp_path, look="water", color=honey)
    spec = spec.model_copy(update={"fluids": (spec.fluids[0].model_copy(update={"transmission_depth": 0.05}),)})
    paths = synthetic_meshes(spec, [2])
    m = with_level_set(paths, 2)
    fr = render.FrameRenderer(spec)
    try:
        level_set = read_level_set(paths.surface_vdb(2))
        rgb, alpha = fr._transmitted(2, m.points, m.normals, level_set, spec.fluids[0])
        front, water = fr._water_behind(2, m.points, m.normals, level_set, 0.05, 4.0)
        g = float(np.mean(fr.look["ground_color"]))
        through = np.asarray(honey) ** (water[:, None] / 0.05)
        above = alpha[front] > 0.5 * fr.look["opacity"] + 1e-6
        blended = alpha[front, None] * rgb[front] + (1 - alpha[front, None]) * g
        np.testing.assert_allclose(blended[above], g * through[above], atol=1e-9)
        assert (alpha[~front] == 0).all() and above.mean() > 0.5
        facing = facing_camera(spec, m)[front]          # the front vertices: middle and rim
        middle, rim = facing > 0.95, (facing > 0) & (facing < 0.3)
        assert water[middle].mean() > 2 * water[rim].mean()
        assert alpha[front][middle].mean() > alpha[front][rim].mean() + 0.2
        transmitted = g * through        # what the eye gets through the middle and the rim
        red_share = lambda c: c[:, 0] / c.sum(axis=1)      # noqa: E731
        mid, edge = transmitted[middle], transmitted[rim]
        assert mid.sum(axis=1).mean() < 0.6 * edge.sum(axis=1).mean()
        assert red_share(mid).mean() > red_share(edge).mean() + 0.1
    finally:
        fr.close()
    render.run(spec, [2], paths, quiet())
    compare("look_water_honey_f2", paths.render_frame(2))


def test_a_collider_has_its_form_under_the_water_look(tmp_path):
    """A grey sphere collider alone under the water look, with the default lights: from its lit
    side to its shadowed side its brightness spans (p90 - p10) / p50 = 0.45 (measured: 78,
    111, 128 of 255). With the PBR shading the colliders had before (the look's sky lights them
    from every side) it spanned 0.10 (165, 176, 182): the example's sphere and the boulder read
    as flat discs. Bound 0.3. The sphere's pixels are those its depth brings nearer."""
    from pipeline.stages import render

    def draw(colliders: bool):
        spec = ShotSpec.model_validate(tiny_spec(
            ((0, 0, 0), (0.1, 0.1, 0.1)), ((0, 0, 0), (0.6, 0.4, 0.4)), name="form",
            shot={"frame_start": 1, "frame_end": 1, "output": str(tmp_path)},
            colliders=({"type": "sphere", "center": (0.3, 0.1, 0.2), "radius": 0.1, "color": (0.6, 0.6, 0.6)},),
            render={"look": "water", "resolution": (320, 180), "ssaa": False, "colliders": colliders,
                    "camera": {"position": (1.2, 0.8, 1.3), "focal_point": (0.3, 0.15, 0.2), "fov": 40.0}}))
        fr = render.FrameRenderer(spec)
        try:
            fr.place_camera(1)
            return fr.pl.screenshot(return_img=True).astype(np.float64), fr.pl.get_image_depth(fill_value=np.inf)
        finally:
            fr.close()

    img, depth = draw(True)
    _img, bare = draw(False)
    sphere = np.isfinite(depth) & (~np.isfinite(bare) | (depth > bare + 1e-3))
    assert sphere.sum() > 300
    p10, p50, p90 = np.percentile(img[sphere] @ [0.2126, 0.7152, 0.0722], [10, 50, 90])
    assert (p90 - p10) / p50 > 0.3, (p10, p50, p90)


def ball_and_slab(tmp_path, name: str, slab_y: tuple, frames: tuple, **render_keys):
    """(spec, paths) of a shot under the water look: a grey ball of radius 0.08 m, its centre 0.1 m
    up in a 0.6 x 0.4 x 0.4 m domain, and as each of `frames`' surface mesh a slab of water from
    slab_y[0] to slab_y[1] high over most of the floor; frame 2 alone has its level set."""
    import pyvista as pv

    from pipeline.formats import write_mesh
    from surfacing.mesh import Mesh
    from surfacing.reconstruct import vertex_normals

    use_taichi_cpu()
    spec = ShotSpec.model_validate(tiny_spec(
        ((0, 0, 0), (0.1, 0.1, 0.1)), ((0, 0, 0), (0.6, 0.4, 0.4)), name=name,
        shot={"frame_start": 1, "frame_end": 3, "output": str(tmp_path)},
        fluid={"name": "water", "color": (0.1, 0.375, 0.625)},
        colliders=({"type": "sphere", "center": (0.3, 0.1, 0.2), "radius": 0.08, "color": (0.6, 0.6, 0.6)},),
        render={"look": "water", "ssaa": False, "movie": False, "contact_sheet": False, **render_keys}))
    paths = ShotPaths.for_spec(spec)
    slab = pv.Box(bounds=(0.1, 0.5, slab_y[0], slab_y[1], 0.05, 0.35), level=8, quads=False)
    pts, faces = np.asarray(slab.points, np.float32), np.asarray(slab.regular_faces, np.int32)
    for f in frames:
        path = paths.surface_meshes(f)[None]
        path.parent.mkdir(parents=True, exist_ok=True)
        write_mesh(path, Mesh(pts, faces, vertex_normals(pts, faces), np.zeros_like(pts)), "ply")
    with_level_set(paths, 2)
    return spec, paths


def test_a_collider_under_the_water_takes_the_light_that_reaches_it(tmp_path):
    """Under the water look a collider's color per vertex is its own times the transmission of
    the water straight above it (thickness.water_above; Beer-Lambert over the look's absorption
    length, each channel as the water's color absorbs it). A grey ball half in a slab of water
    0.1 m deep (0.8 absorption lengths at the ball's foot):
    - its dry top, a cell and more over the waterline, keeps its color exactly;
    - every wet vertex, a cell and more under it, takes its color times the transmission of its
      depth under the waterline, to within 3 of 255 (the depth within a cell);
    - the deepest third is darker than the shallowest third and bluer;
    - the frame with no .vdb draws the ball in its own color (the colors per vertex off);
    - the frame matches its golden: a ball whose foot turns dark blue-green under the water."""
    from pipeline.stages import render

    spec, paths = ball_and_slab(tmp_path, "waterline", (0.0, 0.1), (1, 2), resolution=(320, 180),
                                camera={"position": (0.55, 0.22, 0.75), "focal_point": (0.3, 0.08, 0.2), "fov": 35.0})
    grey = spec.colliders[0].color
    fr = render.FrameRenderer(spec)
    try:
        (actor, mesh, _col, _normals), = fr.solids
        fr.render(1, paths)
        assert not actor.mapper.GetScalarVisibility()
        fr.render(2, paths)
        assert actor.mapper.GetScalarVisibility()
        lit = np.asarray(mesh.point_data["lit"], np.float64)
        y = np.asarray(mesh.points)[:, 1]
        cell = 0.005                                           # with_level_set's voxel
        dry, wet = y > 0.1 + cell, y < 0.1 - cell
        assert dry.sum() > 100 and wet.sum() > 100
        np.testing.assert_array_equal(lit[dry], np.round(255 * np.array(grey))[None].repeat(dry.sum(), 0))
        want = 255 * np.array(grey) * fr._transmission(spec.fluids[0], 0.1 - y[wet])
        assert np.abs(lit[wet] - want).max() <= 3.0, np.abs(lit[wet] - want).max()
        depth = 0.1 - y[wet]
        deep, shallow = lit[wet][depth > np.percentile(depth, 67)], lit[wet][depth < np.percentile(depth, 33)]
        assert deep.sum(axis=1).mean() < 0.8 * shallow.sum(axis=1).mean()
        blue = lambda c: c[:, 2] / c.sum(axis=1)      # noqa: E731
        assert blue(deep).mean() > blue(shallow).mean() + 0.05
    finally:
        fr.close()
    render.run(spec, [2], paths, quiet())
    compare("look_water_waterline_f2", paths.render_frame(2))


def test_a_collider_under_liquid_overhead_takes_a_shadow_no_darker_than_the_floors(tmp_path):
    """A grey ball 6 cm under a slab of water 14 cm thick (1.1 absorption lengths: through it
    the red keeps 13 %), as under the two-fluid example's falling blocks: its dry top takes the
    light lost in the slab, each channel as the water takes it (the red most, the blue least)
    but no channel darker than the look's floor shadow under the liquid ("shadow", 0.45): the
    red of the vertices facing straight up loses that share to within 2 of 255, and no vertex
    loses more than that share of its facing up; a face turned down keeps its color. (Uncapped,
    the ball's top came out a saturated navy beside the floor's soft gray shadow.)"""
    from pipeline.stages import render

    spec, paths = ball_and_slab(tmp_path, "overhead", (0.24, 0.38), (2,), resolution=(160, 90))
    grey = spec.colliders[0].color
    fr = render.FrameRenderer(spec)
    try:
        (_actor, mesh, _col, normals), = fr.solids
        fr.render(2, paths)
        through = fr._transmission(spec.fluids[0], np.array([0.14]))[0]
        assert through[0] < 0.2 and through[2] > through[1] > through[0]      # the slab takes the red most
        lost = 255 * np.array(grey) - np.asarray(mesh.point_data["lit"], np.float64)
        shadow = fr.look["shadow"]
        top = normals[:, 1] > 0.98
        assert top.sum() > 5 and (normals[:, 1] < 0).sum() > 100
        np.testing.assert_allclose(lost[top, 0], 255 * 0.6 * shadow, atol=2.0)
        up = np.clip(normals[:, 1], 0.0, 1.0)[:, None]
        assert (lost <= 255 * 0.6 * shadow * up + 1.0).all()        # a face turned down loses nothing
        assert (lost[top, 0] > lost[top, 1] + 5).all() and (lost[top, 1] > lost[top, 2] + 5).all()
    finally:
        fr.close()


def test_colliders_under_the_water_look_are_cut_fine_within_a_budget(tmp_path):
    """For their colors per vertex to follow the water, colliders under the water look are cut
    into triangles of at most the edge asked for (the showcase's: 4 cells of 3 mm), their normals
    carried onto the new points; a box 100 m across (a floor wider than the domain) stops at
    UNDER_WATER_MOST_TRIANGLES, not tens of millions (VTK's adaptive subdivision, used first, took
    150 s over it)."""
    from pipeline.stages import render

    spec = ShotSpec.model_validate(tiny_spec(
        ((0, 0, 0), (0.1, 0.1, 0.1)), ((0, 0, 0), (0.6, 0.4, 0.4)), name="cut",
        shot={"frame_start": 1, "frame_end": 1, "output": str(tmp_path)},
        colliders=({"type": "box", "min": (0.45, 0.0, 0.1), "max": (0.55, 0.3, 0.2)},
                   {"type": "box", "min": (-50.0, -1.0, -50.0), "max": (50.0, 0.0, 50.0)}),
        render={"look": "water"}))
    (pillar, _), (floor, _) = render.collider_meshes(spec, 0.012)
    for m in (pillar, floor):
        assert m.point_data.active_normals is not None and m.is_all_triangles
    assert render.longest_edge(pillar) <= 0.012
    assert floor.n_cells <= render.UNDER_WATER_MOST_TRIANGLES
    np.testing.assert_allclose(pillar.area, 2 * (0.1 * 0.3 + 0.3 * 0.1 + 0.1 * 0.1), rtol=1e-6)   # (float32 points)


def test_a_floor_wider_than_the_contact_shadow_casts_it_whole(tmp_path):
    """A box collider 100 m across under the domain (a floor) casts the contact shadow over the
    whole layer, evenly, at what its top and bottom project on each texel: STILL (1 - exp(-1))
    (two faces, each a texel's area) within 0.01. Only its part over the layer is split into
    texel-sized triangles (split whole, it took minutes when the renderer was made; the part
    beyond the layer falls outside the shadow anyway)."""
    from pipeline.stages import render

    spec = ShotSpec.model_validate(tiny_spec(
        ((0, 0, 0), (0.1, 0.1, 0.1)), ((0, 0, 0), (0.6, 0.4, 0.4)), name="floor",
        shot={"frame_start": 1, "frame_end": 1, "output": str(tmp_path)},
        colliders=({"type": "box", "min": (-50.0, -1.0, -50.0), "max": (50.0, 0.0, 50.0)},),
        render={"look": "clay", "resolution": (320, 180), "ssaa": False}))
    fr = render.FrameRenderer(spec)
    try:
        inner = fr.shadow.still[20:-20, 20:-20]      # away from the blurred rim
        want = render.ContactShadow.STILL * (1 - np.exp(-1.0))
        assert np.abs(inner - want).max() < 0.01, (inner.min(), inner.max(), want)
    finally:
        fr.close()


def test_a_camera_near_the_domain_sees_the_front_of_what_it_looks_at(tmp_path):
    """A camera 0.35 m from a 0.6 m tank, looking at a ball 0.54 m off: the pixel at the middle
    of the frame is the ball's near side (its depth within 2 mm of 0.536 m). VTK put the near
    plane at a thousandth of the far one, 0.56 m with the ground's far plane, so the ball's
    front was cut away and its inside drawn (measured 0.696 m: the far side)."""
    from pipeline.stages import render

    spec = ShotSpec.model_validate(tiny_spec(
        ((0, 0, 0), (0.1, 0.1, 0.1)), ((0, 0, 0), (0.6, 0.4, 0.4)), name="near",
        shot={"frame_start": 1, "frame_end": 1, "output": str(tmp_path)},
        colliders=({"type": "sphere", "center": (0.3, 0.1, 0.2), "radius": 0.08},),
        render={"look": "clay", "resolution": (320, 180), "ssaa": False,
                "camera": {"position": (0.55, 0.22, 0.75), "focal_point": (0.3, 0.1, 0.2), "fov": 35.0}}))
    fr = render.FrameRenderer(spec)
    try:
        fr.place_camera(1)
        fr.pl.screenshot(return_img=True)
        depth = fr.pl.get_image_depth(fill_value=np.nan)
    finally:
        fr.close()
    front = np.linalg.norm(np.subtract((0.55, 0.22, 0.75), (0.3, 0.1, 0.2))) - 0.08
    assert abs(-depth[90, 160] - front) < 0.002, (-depth[90, 160], front)


def test_a_frame_is_the_same_drawn_first_or_after_another(tmp_path):
    """A renderer is kept across frames (and a Dask worker draws every other frame): a frame
    must not depend on what was drawn before it. (Casting the contact shadow after the fluid
    was added made a renderer's first frame differ by up to 3 levels from the same frame drawn
    later.)"""
    from pipeline.stages import render

    spec = scene(tmp_path, look="water")
    paths = synthetic_meshes(spec, [1, 2])
    first = render.FrameRenderer(spec)
    second = render.FrameRenderer(spec)
    try:
        a = first.render(2, paths)
        second.render(1, paths)
        b = second.render(2, paths)
    finally:
        first.close()
        second.close()
    assert np.array_equal(a, b)


def test_spray_is_white_where_it_flies_and_its_fluids_color_at_rest(tmp_path):
    """The water look's spray points: the spray color (white) at a quarter of the shot's
    expected largest speed and above, half way between it and the point's own fluid's color at
    rest (a droplet left on a stone is a bead, not foam; an oil droplet a golden one); opaque in
    flight, render.REST_OPACITY at rest (the beads the boulder example's stone keeps, drawn
    unlit, read as a grid of lamps at full opacity)."""
    from pipeline.formats import write_points
    from pipeline.stages import render

    spec = scene(tmp_path, look="water", surface={"spray": 25})
    oil = {"name": "oil", "rest_density": 850.0, "color": (0.85, 0.62, 0.15),
           "blocks": ({"min": (0.3, 0.0, 0.0), "max": (0.4, 0.1, 0.1)},)}
    spec = ShotSpec.model_validate({**spec.model_dump(), "fluids": (spec.fluids[0].model_dump(), oil)})
    paths = synthetic_meshes(spec, [2])
    fast = 0.25 * spec.expected_max_speed()
    velocity = np.array([[0, 0, 0], [fast, 0, 0], [0, -2 * fast, 0], [0, 0, 0]], np.float32)
    write_points(paths.surface_spray(2), np.full((4, 3), 0.3, np.float32), velocity, 0.004, np.array([0, 0, 1, 1]))
    fr = render.FrameRenderer(spec)
    try:
        clouds = [m for m, _kw in fr._fluid_meshes(2, paths, fr._level_set(2, paths)) if m.n_faces == 0]
    finally:
        fr.close()
    assert len(clouds) == 1
    rgba = clouds[0].point_data["rgba"] / 255.0
    rgb, alpha = rgba[:, :3], rgba[:, 3]
    white = np.asarray(fr.look["spray_color"])
    water, oil = (np.asarray(f.color) for f in spec.fluids)
    np.testing.assert_allclose(rgb[0], 0.5 * (white + water), atol=1 / 255)
    np.testing.assert_allclose(rgb[3], 0.5 * (white + oil), atol=1 / 255)
    np.testing.assert_allclose(rgb[1:3], [white, white], atol=1 / 255)
    np.testing.assert_allclose(alpha, [render.REST_OPACITY, 1, 1, render.REST_OPACITY], atol=1 / 255)


def test_spray_droplets_are_fine():
    """A spray point is the particle's diameter on screen, at least 2 px and at most 3 px per
    1080 lines: the showcase's 4 mm particles at 1080p stay as they are (3.1 -> 3 px), the
    two-fluid example's 8 mm ones at 960x540 (8.4 px, a cloud of hail over the impact) become 2."""
    from pipeline.stages.render import spray_point_size

    assert spray_point_size(3.1, 1080) == 3.0
    assert spray_point_size(2.5, 1080) == 2.5
    assert spray_point_size(8.4, 540) == 2.0
    assert spray_point_size(1.0, 2160) == 2.0
    assert spray_point_size(8.4, 2160) == 6.0


@pytest.mark.parametrize("look", ["water", "clay"])
def test_spray_shows_with_supersampling(tmp_path, look):
    """jobs/showcase.toml's camera, tank and colliders at 320x180 with render.ssaa on (the
    default; the goldens run without it), the synthetic sphere as its water, and 40 spray
    points flying over the run-up: with them at least 20 pixels are brighter by 60 levels than
    without them (measured 45 under the water look, 43 under clay; a few points lie behind the
    pillar or on each other), and the brightest of those is near the look's spray color. Lit
    sphere points with per-point colors, under the water look's image-based sky, with
    supersampling and the colliders' polygon offset (a global VTK mode), came out as nothing: 0
    pixels changed (bisected: from 952c67c, the spray's colors per point, to 2026-11-28), and
    every default frame with a collider lost its spray (the showcase's 19,000 droplets over the
    run-up at frame 24)."""
    from pipeline.formats import write_points
    from pipeline.spec import load_spec
    from pipeline.stages import render

    job = Path(__file__).resolve().parents[1] / "jobs" / "showcase.toml"
    spec = load_spec(job, [f"shot.output={str(tmp_path)!r}", "render.resolution=[320,180]", "render.ssaa=true",
                           f"render.look={look!r}"])
    paths = synthetic_meshes(spec, [2])
    rng = np.random.default_rng(3)
    where = (rng.random((40, 3)) * [0.6, 0.5, 0.6] + [1.6, 0.6, 0.2]).astype(np.float32)
    flying = np.tile(np.float32([0.0, 0.5 * spec.expected_max_speed(), 0.0]), (40, 1))       # white
    fr = render.FrameRenderer(spec)
    try:
        without = fr.render(2, paths).astype(np.int64)
        write_points(paths.surface_spray(2), where, flying, spec.sim.particle_radius)
        with_spray = fr.render(2, paths).astype(np.int64)
    finally:
        fr.close()
    brighter = (with_spray - without).sum(axis=2) > 60
    assert brighter.sum() >= 20, f"{brighter.sum()} pixels brighter with 40 spray points"
    # within 60 levels: supersampling averages a droplet 2 px across with the sky around it
    # (measured 42 levels under the water look's white, 27 under clay's grey)
    spray = np.asarray(fr.look["spray_color"]) * 255
    assert np.abs(with_spray[brighter].max(axis=0) - spray).max() < 60, with_spray[brighter].max(axis=0)


@pytest.mark.parametrize("opacity", [None, 1.0])
def test_the_water_look_reads_the_depth_only_for_a_translucent_fluid(tmp_path, monkeypatch, opacity):
    """With the look's own translucency the water's depth behind each vertex sets its opacity
    (the frame's level set is read); a job's opaque `material` (opacity 1) is drawn opaque, with
    no level set read (its depth alpha was 1 - exp(-inf * depth): nan where the depth was 0)."""
    from pipeline.stages import render

    spec = scene(tmp_path, look="water", **({"material": {"opacity": opacity}} if opacity else {}))
    paths = synthetic_meshes(spec, [2])
    paths.surface_vdb(2).write_bytes(b"")         # the frame has a .vdb
    read = []
    monkeypatch.setattr(render, "read_level_set", lambda path: read.append(path))    # (None: no level set)
    fr = render.FrameRenderer(spec)
    try:
        kw = [kw for m, kw in fr._fluid_meshes(2, paths, fr._level_set(2, paths)) if m.n_faces > 0][0]
    finally:
        fr.close()
    assert read == ([] if opacity == 1.0 else [paths.surface_vdb(2)])
    if opacity == 1.0:
        assert kw["opacity"] == 1.0 and "scalars" not in kw


def test_water_look_reflects_the_sky(tmp_path, monkeypatch):
    """The water look lights the fluid with the sky as well as the lamps: without the
    environment, the sphere's pixels change (its reflection and Fresnel rim go: measured 1,298
    pixels by more than 8 levels at 320x180), while with it two
    renders from fresh renderers are identical (the prefiltered environment is deterministic)."""
    from pipeline.stages import render

    def frame(name):
        spec = scene(tmp_path / name, look="water")
        paths = synthetic_meshes(spec, [2])
        render.run(spec, [2], paths, quiet())
        render.close_renderer()
        return np.asarray(Image.open(paths.render_frame(2)), np.float64)

    lit, again = frame("a"), frame("b")
    assert np.array_equal(lit, again)
    monkeypatch.setattr(render.FrameRenderer, "_environment", lambda self, pl: None)
    unlit = frame("c")
    changed = np.abs(lit - unlit).max(axis=2) > 8
    assert changed.sum() > 300, f"only {changed.sum()} pixels change without the sky"


def test_motion_blur_comes_from_the_velocity(tmp_path):
    """render.motion_blur = 8: the fluid is drawn at 8 instants of a half-frame shutter, moved
    along its velocity, and the renders averaged. A sphere at rest comes out as the sharp frame
    (to rounding); the same sphere moving at 3 m/s (6 cm of travel while the shutter is open)
    is smeared: pixels along its edges change (measured 217 by over 30 levels of 255 at 320x180),
    and the frame matches its golden."""
    from pipeline.stages import render

    def frame(name, velocity, **kw):
        spec = scene(tmp_path / name, **kw)
        paths = synthetic_meshes(spec, [2], velocity=velocity)
        render.run(spec, [2], paths, quiet())
        return np.asarray(Image.open(paths.render_frame(2)), np.float64), paths

    sharp, _ = frame("sharp", (3.0, 0.0, 0.0))
    still, _ = frame("still", (0.0, 0.0, 0.0), motion_blur=8)
    blur, paths = frame("blur", (3.0, 0.0, 0.0), motion_blur=8)
    assert np.abs(still - sharp).max() <= 1
    changed = (np.abs(blur - sharp).max(axis=2) > 30).sum()
    assert changed > 150, changed
    compare("motion_blur_f2", paths.render_frame(2))


def test_particles_golden_colored_by_speed(tmp_path):
    from pipeline.stages import render

    spec = scene(tmp_path, mode="particles", color_by="speed")
    paths = synthetic_particles(spec, [1, 2, 3])
    render.run(spec, [2], paths, quiet())
    compare("particles_speed_f2", paths.render_frame(2))


def test_kept_renderer_renders_as_a_new_one(tmp_path):
    """The render stage keeps its renderer open between calls (a Dask worker gets one frame a
    task). Frame 2 rendered after frames 3 and 1 in the kept renderer is the image a new
    renderer makes, pixel for pixel; another thread and another spec get renderers of their own."""
    from pipeline.stages import render

    spec = scene(tmp_path / "a")
    paths = synthetic_meshes(spec, [1, 2, 3])
    render.close_renderer()
    render.run(spec, [2], paths, quiet())
    new = np.asarray(Image.open(paths.render_frame(2)))
    kept = render.renderer_for(spec)
    for f in (3, 1, 2):
        render.run(spec, [f], paths, quiet())
    assert render.renderer_for(spec) is kept
    np.testing.assert_array_equal(np.asarray(Image.open(paths.render_frame(2))), new)
    # a GL context belongs to its thread: a Dask worker with several threads has one renderer each
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(1) as pool:
        assert pool.submit(lambda: (render.renderer_for(spec), render.close_renderer())[0]).result() is not kept

    other = scene(tmp_path / "b", resolution=(160, 90))
    other_paths = synthetic_meshes(other, [2])
    render.run(other, [2], other_paths, quiet())
    assert render.renderer_for(other) is not kept
    assert np.asarray(Image.open(other_paths.render_frame(2))).shape == (90, 160, 3)


def test_golden_catches_a_moved_camera(tmp_path, monkeypatch):
    """The tolerance is tight enough to see a real change (here: the camera 10 cm off). Never
    with SPHSHOT_UPDATE_GOLDEN set, which would write this image over surface_f2's golden."""
    from pipeline.stages import render

    monkeypatch.delenv("SPHSHOT_UPDATE_GOLDEN", raising=False)
    spec = scene(tmp_path, camera={"position": (1.3, 0.8, 1.3), "focal_point": (0.3, 0.15, 0.2), "fov": 40.0})
    paths = synthetic_meshes(spec, [2])
    render.run(spec, [2], paths, quiet())
    with pytest.raises(AssertionError, match="mean abs diff"):
        compare("surface_f2", paths.render_frame(2))


def test_movie_and_contact_sheet(tmp_path):
    import imageio_ffmpeg

    from pipeline.stages import render

    spec = scene(tmp_path, resolution=(161, 91))      # odd: the movie pads to even
    paths = synthetic_meshes(spec, [1, 2, 3])
    render.run(spec, [1, 2, 3], paths, quiet())
    written = render.finalize(spec, paths)
    assert written == [paths.movie, paths.contact_sheet]
    reader = imageio_ffmpeg.read_frames(str(paths.movie))
    meta = next(reader)
    frames = sum(1 for _ in reader)
    assert tuple(meta["size"]) == (162, 92)
    assert frames == 3
    sheet = Image.open(paths.contact_sheet)
    cols, rows = render.contact_sheet_grid(3)
    assert (cols, rows) == (2, 2)
    th = round(91 * 240 / 161)
    assert sheet.size == (cols * 244 + 4, rows * (th + 4) + 4)


def test_a_movie_cut_short_by_a_full_disk_is_not_published(tmp_path):
    """On a full disk ffmpeg only logs that it could not write the movie's trailer and
    imageio-ffmpeg returns as if done: the cut-short movie was published and never made again.
    write_movie counts the frames of what it wrote before publishing it: on a 64 kB disk (a real
    tmpfs; skipped where none can be mounted) 12 frames of noise are one clear OSError naming the
    movie, and nothing is left on the disk."""
    from conftest import mounted_tmpfs

    from pipeline.stages.render import write_movie

    rng = np.random.default_rng(5)
    frames = []
    for k in range(12):
        frames.append(tmp_path / f"f.{k:04d}.png")
        Image.fromarray(rng.integers(0, 255, (90, 160, 3), dtype=np.uint8)).save(frames[-1])
    assert write_movie(tmp_path / "whole.mp4", frames, 24.0).stat().st_size > 64 * 1024
    with mounted_tmpfs(tmp_path / "disk", "size=64k") as disk:
        with pytest.raises(OSError, match="the movie written could not be read, not 12 frames"):
            write_movie(disk / "m.mp4", frames, 24.0)
        assert list(disk.iterdir()) == []


def test_camera_keys_interpolate(tmp_path):
    from pipeline.stages.render import camera_at

    spec = scene(tmp_path, camera_keys=(
        {"frame": 1, "position": (1.0, 1.0, 1.0), "focal_point": (0, 0, 0), "fov": 30.0},
        {"frame": 3, "position": (3.0, 1.0, 1.0), "focal_point": (0, 0, 0), "fov": 50.0}))
    cam = camera_at(spec.render, 2)
    assert cam.position == pytest.approx((2.0, 1.0, 1.0)) and cam.fov == pytest.approx(40.0)
    assert camera_at(spec.render, 9).position == (3.0, 1.0, 1.0)


def test_memory_stays_flat_over_100_frames(tmp_path):
    """One plotter renders 100 frames; resident memory after frame 100 is within 30 MB of
    what it was after frame 20 (a leak of one mesh or image per frame would add > 30 MB)."""
    import psutil

    from pipeline.stages.render import FrameRenderer

    spec = scene(tmp_path, resolution=(160, 90))
    paths = synthetic_meshes(spec, [1, 2, 3])
    proc = psutil.Process()
    renderer = FrameRenderer(spec)
    try:
        rss = {}
        for k in range(1, 101):
            renderer.render(1 + k % 3, paths)
            if k in (20, 100):
                rss[k] = proc.memory_info().rss
    finally:
        renderer.close()
    growth = (rss[100] - rss[20]) / 2**20
    assert growth < 30, f"resident memory grew {growth:.1f} MB over 80 frames"


def test_depth_pass_png16(tmp_path):
    """The optional depth pass: 16-bit PNG, background 65535, the sphere nearer than the ground."""
    from pipeline.stages import render

    spec = scene(tmp_path, depth="png16", ground=False, domain=False, colliders=False, background_top=None)
    paths = synthetic_meshes(spec, [2])
    render.run(spec, [2], paths, quiet())
    depth = np.asarray(Image.open(paths.render_depth(2)))
    assert depth.dtype == np.uint16 and depth.shape == (180, 320)
    color = np.asarray(Image.open(paths.render_frame(2)).convert("RGB")).astype(int)
    background = color[0, 0]
    hit = np.abs(color - background).sum(axis=2) > 30          # pixels showing the sphere
    assert hit.mean() > 0.01
    assert (depth[~hit] == 65535).mean() > 0.95, "background must be 65535"
    # silhouette pixels are color-blended with the background but not depth-blended: allow 2%
    assert (depth[hit] < 65535).mean() > 0.98 and depth.min() == 0   # normalised: nearest hit is 0


@pytest.mark.parametrize("failure", ["black", "small"])
def test_a_failed_render_is_an_error_and_publishes_nothing(tmp_path, monkeypatch, failure):
    """Issue 19, item 6: at 8192 x 4320 VTK's off-screen framebuffer could not be made, every
    pixel came back black and the black PNGs were published as valid frames. A render of one
    flat color, or of another size than render.resolution, is a StageError naming the frame,
    and nothing is written for it."""
    from pipeline.errors import StageError
    from pipeline.stages import render

    spec = scene(tmp_path)
    paths = synthetic_meshes(spec, spec.frames)
    w, h = spec.render.resolution
    bad = np.zeros((h, w, 3), np.uint8) if failure == "black" else np.full((h // 2, w // 2, 3), 90, np.uint8)
    monkeypatch.setattr(render.FrameRenderer, "render", lambda self, frame, paths: bad)
    with pytest.raises(StageError, match="render: frame 0001 came out"):
        render.run(spec, [1], paths, quiet())
    assert not paths.render_frame(1).exists()


def test_an_empty_view_on_a_flat_background_is_a_frame(tmp_path):
    """A flat background (render.background_top unset) with nothing in view is one flat color
    too, and a legitimate frame."""
    from pipeline.stages import render

    spec = scene(tmp_path, background_top=None,
                 camera={"position": (0.3, 0.2, -3.0), "focal_point": (0.3, 0.2, -6.0), "fov": 30.0})
    paths = synthetic_meshes(spec, [1])
    render.run(spec, [1], paths, quiet())
    img = np.asarray(Image.open(paths.render_frame(1)))
    assert (img == img[0, 0]).all()
