"""The render stage: off-screen PyVista images of the surface meshes (or particles).

No display is needed: VTK renders through EGL (Mesa's llvmpipe on a CPU machine, the GPU's EGL
where there is one) or OSMesa. One plotter serves every frame a process renders of a shot,
across calls (renderer_for): static actors (ground, colliders, lights) are built once and only
the fluid actors change per frame.
"""
from __future__ import annotations

import atexit
import logging
import math
import os
import threading
from pathlib import Path

import numpy as np

from ..cache import atomic_path
from ..errors import StageError
from ..formats import disk_left, read_frame, read_level_set, read_mesh, read_points

log = logging.getLogger("sphshot")

# zlib level for every PNG written. Lossless at any level; Pillow's default (6) took 77 ms for a
# 960x540 frame of the example shot and 3 takes 38 ms for a file 14% larger (1: 31 ms, +24%).
PNG_LEVEL = 3
# the water look's spray droplets at rest: this opaque (in flight: fully)
REST_OPACITY = 0.3
# spray droplets are drawn at most this many pixels across per 1080 lines of the frame: a spray
# particle stands for droplets finer than the sim's particles, and drawn at its own diameter the
# two-fluid example's (r = 8 mm, 8 px at 960x540) flew up from the impact as a cloud of hail
SPRAY_MOST_PX = 3.0
# colliders under the water look are drawn in triangles at most this many surface cells long
# (and at least a 400th of the domain's diagonal, against millions of them for a big collider
# at a fine cell): their colors follow the water above them per vertex, and a waterline is
# this sharp
UNDER_WATER_EDGE = 4.0
# ... and in at most this many triangles each (a box collider wider than the domain, a floor
# 100 m across, would be cut into tens of millions)
UNDER_WATER_MOST_TRIANGLES = 250_000


def spray_point_size(diameter_px: float, lines: int) -> float:
    """The spray's point size in pixels: the particle's diameter on screen, at least 2 px and at
    most SPRAY_MOST_PX per 1080 lines."""
    return max(2.0, min(diameter_px, SPRAY_MOST_PX * lines / 1080))


# What a look sets, where the job leaves the key unset (render.look). Shading "ibl": VTK's PBR
# lit by a procedural studio sky (sky_faces) as well as the lights, so the water reflects the
# sky and two soft boxes with a Fresnel rise at grazing angles; "phong": a plain highlight;
# "pbr": as before. Translucency without depth peeling: with Mesa's llvmpipe, peeling left a
# translucent mesh out of the image altogether (measured), and plain alpha blending draws it;
# with "absorption" (water, where the frame has a level set) each vertex is as opaque as the
# water behind it is deep (Beer-Lambert, _water_alpha), in lengths of that share of the domain's
# diagonal. "shadow": the contact shadow's strength under the fluid (ContactShadow). "body": each
# fluid's color times this, since a clear liquid sends little of the sky's diffuse light back: at
# 1 the example's water read as pale blue jelly (until 2026-11-26 a fluid's color was also taken
# half way to clear water's, 0, 0.3, 0.4, which turned honey and oil olive grey). "lamps": the
# default light rig's intensity, as a share (the sky lights the scene too). "solids": how the
# colliders are shaded: "phong", by the lamps alone with an ambient share for the sky (under
# the sky's image-based light a collider took nearly the same light from every side and read
# as a flat disc: the example's sphere, the boulder, the showcase's rock; Lambert's falloff
# from the key light gives it its form), or "pbr" with the look's lights and sky. Under the
# water look's liquid a collider also takes only the light that comes through the liquid above
# it (FrameRenderer._light_under_water).
LOOKS = {
    "water": {"background": (0.66, 0.73, 0.80), "background_top": (0.52, 0.63, 0.77), "domain": False,
              "ground_color": (0.50, 0.52, 0.54), "ground_size": 30.0, "shading": "ibl", "opacity": 0.55,
              "roughness": 0.05, "metallic": 0.0,
              "body": 0.35, "lamps": 0.6, "solids": "phong",
              "spray_color": (0.93, 0.97, 1.0), "shadow": 0.45, "absorption": 0.15},
    "clay": {"background": (0.55, 0.55, 0.56), "background_top": (0.45, 0.46, 0.48), "domain": False,
             "ground_color": (0.42, 0.42, 0.43), "ground_size": 30.0, "shading": "phong", "opacity": 1.0,
             "specular": 0.08, "specular_power": 10.0, "ambient": 0.25, "diffuse": 0.8,
             "color": (0.80, 0.78, 0.74), "spray_color": (0.80, 0.78, 0.74), "shadow": 0.5, "solids": "phong"},
    "preview": {"background": (0.08, 0.09, 0.11), "background_top": (0.32, 0.36, 0.42), "domain": True,
                "ground_color": (0.42, 0.42, 0.44), "ground_size": 3.0, "shading": "pbr", "opacity": None,
                "spray_color": (0.85, 0.9, 1.0)},
}


def look_of(render) -> dict:
    """The look's settings, with the job's own keys (background, background_top, domain,
    material) where it sets them."""
    look = dict(LOOKS[render.look])
    for key in ("background", "background_top", "domain"):
        if key in render.model_fields_set:
            look[key] = getattr(render, key)
    mat = render.material
    if "material" in render.model_fields_set or look["shading"] == "pbr":
        look.update(shading="ibl" if look["shading"] == "ibl" else "pbr", color=mat.color, opacity=mat.opacity,
                    roughness=mat.roughness, metallic=mat.metallic)
    return look


def draws_depth(look: dict) -> bool:
    """Whether the look draws the liquid by its depth (an absorption length and a translucent
    material), so that the render stage reads each frame's level set (FrameRenderer._level_set)."""
    return bool(look.get("absorption")) and look["opacity"] is not None and look["opacity"] < 1.0


def longest_edge(mesh) -> float:
    """The longest edge of a triangle mesh's triangles (0 for none)."""
    tri = np.asarray(mesh.points, np.float64)[mesh.regular_faces]
    return float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max()) if len(tri) else 0.0


def _offscreen_env() -> None:
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def camera_at(render, frame: int):
    """The camera for a frame: the fixed camera, or keyframes interpolated linearly."""
    keys = render.camera_keys
    if not keys:
        return render.camera
    if frame <= keys[0].frame:
        return keys[0]
    if frame >= keys[-1].frame:
        return keys[-1]
    for a, b in zip(keys, keys[1:]):
        if a.frame <= frame <= b.frame:
            t = (frame - a.frame) / (b.frame - a.frame)
            lerp = lambda u, v: tuple(float(x + t * (y - x)) for x, y in zip(u, v))  # noqa: E731
            return type(render.camera)(position=lerp(a.position, b.position),
                                       focal_point=lerp(a.focal_point, b.focal_point),
                                       up=lerp(a.up, b.up), fov=a.fov + t * (b.fov - a.fov))
    return keys[-1]


class FrameRenderer:
    """A plotter with the shot's static scene; render(frame) swaps in that frame's fluid."""

    def __init__(self, spec):
        _offscreen_env()
        import pyvista as pv

        self.pv = pv
        self.spec = spec
        r = spec.render
        self.look = look = look_of(r)
        pl = pv.Plotter(off_screen=True, window_size=list(r.resolution), lighting="none")
        if look["background_top"] is not None:
            pl.set_background(look["background"], top=look["background_top"])
        else:
            pl.set_background(look["background"])
        self._lights(pl)
        if look["shading"] == "ibl":
            self._environment(pl)
        self.shadow = None
        if r.ground:
            self._ground(pl)
            if look.get("shadow"):
                self.shadow = ContactShadow(pv, spec.domain.min, spec.domain.max, look["shadow"], self._ground_rgb)
                pl.add_mesh(self.shadow.layer, scalars="rgb", rgb=True, lighting=False)
        if look["domain"]:
            lo, hi = spec.domain.min, spec.domain.max
            box = pv.Box(bounds=(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])).outline()
            pl.add_mesh(box, color=(0.78, 0.8, 0.84), line_width=1.5, lighting=False)
        # in the water look the colliders' colors follow the water above them, per vertex (not
        # with an opaque material: no level set is read, and they need not be cut)
        self.under_water = draws_depth(look) and look.get("solids") == "phong"
        diagonal = float(np.linalg.norm(np.subtract(spec.domain.max, spec.domain.min)))
        edge = max(UNDER_WATER_EDGE * spec.surface_cell_m, diagonal / 400) if self.under_water else None
        colliders = collider_meshes(spec, edge) if r.colliders else []
        if look.get("solids") == "phong":
            solid = dict(ambient=0.35, diffuse=0.8, specular=0.08, specular_power=12.0)
        else:
            solid = dict(pbr=True, metallic=0.0, roughness=0.6)
        self.solids = []                 # (actor, mesh, collider, its unit normals under water)
        for mesh, col in colliders:      # (a box keeps its hard edges)
            actor = pl.add_mesh(mesh, color=col.color, smooth_shading=col.type != "box", **solid)
            normals = None
            if self.under_water:        # (the cut interpolates its normals: not of unit length)
                normals = np.asarray(mesh.point_data["Normals"], np.float64)
                normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
            self.solids.append((actor, mesh, col, normals))
            # drawn a little nearer than it is: the water's mesh hugs a submerged collider, and
            # where the two coincide their depths fought, speckling the collider. (The mode is
            # VTK's one global setting, off by default; the offset is this mapper's own.)
            actor.mapper.SetResolveCoincidentTopologyToPolygonOffset()
            actor.mapper.SetRelativeCoincidentTopologyPolygonOffsetParameters(-4.0, -4.0)
        if self.shadow is not None:
            self.shadow.cast_still([m for m, _col in colliders])
        if r.ssaa:
            pl.enable_anti_aliasing("ssaa")
        self.pl = pl
        self.fluid_actors = []

    def _lights(self, pl) -> None:
        pv, r = self.pv, self.spec.render
        lo, hi = np.array(self.spec.domain.min), np.array(self.spec.domain.max)
        centre, size = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
        from ..spec import Light

        # key, fill and rim around the domain; under the water look's sky (which lights too) at
        # the look's "lamps" share, so that a pale collider is not burnt white
        k = self.look.get("lamps", 1.0)
        rig = r.lights or (
            Light(position=tuple(centre + size * np.array([1.2, 2.0, 1.5])), intensity=0.9 * k, color=(1.0, 0.97, 0.92)),
            Light(position=tuple(centre + size * np.array([-1.5, 0.8, 1.0])), intensity=0.35 * k, color=(0.85, 0.9, 1.0)),
            Light(position=tuple(centre + size * np.array([0.0, 1.5, -2.0])), intensity=0.5 * k),
        )
        for L in rig:
            light = pv.Light(position=tuple(map(float, L.position)), focal_point=tuple(map(float, centre)),
                             color=tuple(L.color), intensity=float(L.intensity), light_type="scene light")
            pl.add_light(light)

    def _environment(self, pl) -> None:
        """Image-based lighting from sky_faces as a cube map. VTK prefilters it on the GL
        device once per renderer: with its default 256-texel irradiance map and 512-texel BRDF
        table that took 48 s with Mesa's llvmpipe; with 16 texels (enough for the diffuse light
        of a smooth sky) and 128 (the frame differs by at most 2 of 255) it takes 2 s."""
        import vtk

        tex = vtk.vtkTexture()
        tex.CubeMapOn()
        tex.MipmapOn()
        tex.InterpolateOn()
        for i, face in enumerate(sky_faces(self.look)):
            img = self.pv.ImageData(dimensions=(face.shape[1], face.shape[0], 1))
            img.point_data["rgb"] = np.ascontiguousarray(face[::-1]).reshape(-1, 3)
            tex.SetInputDataObject(i, img)
        ren = pl.renderer
        ren.UseImageBasedLightingOn()
        # diffuse light from the prefiltered irradiance cube map: VTK's spherical harmonics take
        # an equirectangular image only; for a cube map it warned on every frame (70 lines in the
        # example's log) and the sky's diffuse light was missing from the picture
        ren.UseSphericalHarmonicsOff()
        ren.SetEnvironmentTexture(tex, False)
        ren.GetEnvMapIrradiance().SetIrradianceSize(16)
        ren.GetEnvMapLookupTable().SetLUTSize(128)
        self._sky = tex          # VTK keeps only a reference

    def _ground(self, pl) -> None:
        """A floor under the domain. With the water and clay looks it has no edge in the frame:
        unlit, fading from the ground color around the domain to the background's bottom color
        (a studio cyclorama), so it meets the background without a seam, and going on in that
        color to the horizon (a plane ground_size times the domain across ended in the frame at
        its sides: a wedge of the background's top color in the showcase's upper left)."""
        lo, hi = np.array(self.spec.domain.min), np.array(self.spec.domain.max)
        centre = 0.5 * (lo + hi)
        look = self.look
        if look["shading"] == "pbr":
            size = (hi - lo) * look["ground_size"]
            plane = self.pv.Plane(center=(centre[0], lo[1] - 1e-4, centre[2]), direction=(0, 1, 0),
                                  i_size=size[0], j_size=size[2])
            pl.add_mesh(plane, color=look["ground_color"], pbr=True, roughness=0.9, metallic=0.0)
            return
        reach = float(np.linalg.norm(hi - lo))
        flat, width = self._fade()
        fade = 2 * (flat + width)                # the fade, finely; beyond it the background's color
        plane = self.pv.Plane(center=(centre[0], lo[1] - 1e-4, centre[2]), direction=(0, 1, 0),
                              i_size=fade, j_size=fade, i_resolution=96, j_resolution=96)
        plane.point_data["rgb"] = np.round(self._ground_rgb(plane.points) * 255).astype(np.uint8)
        pl.add_mesh(plane, scalars="rgb", rgb=True, lighting=False)
        far = self.pv.Plane(center=(centre[0], lo[1] - 1e-3 * reach, centre[2]), direction=(0, 1, 0),
                            i_size=look["ground_size"] * 20 * reach, j_size=look["ground_size"] * 20 * reach)
        pl.add_mesh(far, color=look["background"], lighting=False)

    def _fade(self) -> tuple[float, float]:
        """(flat, width): the ground keeps its color out to `flat` from the domain's centre (in x
        and z), then fades to the background's over `width`."""
        lo, hi = np.array(self.spec.domain.min), np.array(self.spec.domain.max)
        reach = float(np.linalg.norm(hi - lo))
        return max(0.6 * reach, ContactShadow.corner(lo, hi)), 2.5 * reach

    def _ground_rgb(self, points) -> np.ndarray:
        """The unlit ground's color at these points: the ground color out to 0.6 of the
        domain's diagonal from its centre (or to the contact shadow's corners), then fading
        to the background's bottom color."""
        lo, hi = np.array(self.spec.domain.min), np.array(self.spec.domain.max)
        flat, width = self._fade()
        dist = np.linalg.norm((np.asarray(points) - 0.5 * (lo + hi))[:, [0, 2]], axis=1)
        t = np.clip((dist - flat) / width, 0.0, 1.0)[:, None] ** 0.7
        return (1 - t) * np.asarray(self.look["ground_color"]) + t * np.asarray(self.look["background"])

    def _level_set(self, frame: int, paths):
        """The frame's `surface` level set (formats.read_level_set) where the look draws the
        water by its depth (look "absorption", a translucent material) and the frame has one;
        else None."""
        if draws_depth(self.look) and paths.vdb and paths.surface_vdb(frame).exists():     # (an opaque material: none)
            return read_level_set(paths.surface_vdb(frame))
        return None

    def _fluid_meshes(self, frame: int, paths, level_set):
        """(mesh, add_mesh keywords) for the frame's fluid and spray; `level_set` as
        _level_set gives it."""
        pv, spec = self.pv, self.spec
        out = []
        if spec.render.mode == "particles":
            data, attrs = read_frame(paths.sim_frame(frame))
            cloud = pv.PolyData(data["position"].astype(np.float32))
            cloud.point_data["motion"] = np.asarray(data["velocity"], np.float32)
            if spec.render.color_by == "speed":
                cloud["speed"] = np.linalg.norm(data["velocity"], axis=1)
                out.append((cloud, dict(scalars="speed", cmap="viridis", clim=(0.0, spec.expected_max_speed()),
                                        show_scalar_bar=False)))
            else:
                colors = np.array([f.color for f in spec.fluids], np.float32)[data["fluid"]]
                cloud["rgb"] = (colors * 255).astype(np.uint8)
                out.append((cloud, dict(scalars="rgb", rgb=True)))
            for mesh, kw in out:
                kw.update(render_points_as_spheres=True,
                          point_size=max(2.0, self._pixels_per_metre() * 2 * spec.sim.particle_radius))
            return out

        look = self.look
        for key, path in paths.surface_meshes(frame).items():
            m = read_mesh(path)
            if len(m.faces) == 0:
                continue
            poly = pv.PolyData.from_regular_faces(m.points, m.faces)
            poly.point_data["Normals"] = m.normals
            poly.point_data.active_normals_name = "Normals"
            poly.point_data["motion"] = np.asarray(m.velocity, np.float32)
            fluid = spec.fluids[[f.name for f in spec.fluids].index(key)] if key is not None else spec.fluids[0]
            color = look.get("color") or fluid.color
            tinted = level_set is not None and fluid.transmission_depth is not None and not look.get("color")
            if "body" in look and not tinted:      # water: the fluid's color as dim as the little
                # light that a clear liquid scatters back (look "body")
                color = tuple(look["body"] * a for a in color)
            if look["shading"] in ("pbr", "ibl"):
                kw = dict(pbr=True, metallic=look["metallic"], roughness=look["roughness"])
            else:
                kw = {k: look[k] for k in ("specular", "specular_power", "ambient", "diffuse")}
            if level_set is not None:     # depth tint: each point as clear as the water behind it
                if tinted:
                    rgb, alpha = self._transmitted(frame, m.points, m.normals, level_set, fluid)
                else:
                    alpha = self._water_alpha(frame, m.points, m.normals, level_set)
                    rgb = np.tile(np.asarray(color, np.float64), (len(alpha), 1))
                # (VTK's PBR decodes vertex colors as sRGB and takes a property's color as
                # linear: encoded, the two paths give the same color)
                srgb = rgb ** (1 / 2.2)
                poly.point_data["rgba"] = np.column_stack([np.round(255 * srgb), np.round(255 * alpha)]).astype(np.uint8)
                kw.update(scalars="rgba", rgba=True)
            else:
                kw.update(color=color, opacity=look["opacity"])
            out.append((poly, dict(smooth_shading=True, **kw)))
        spray = paths.surface_spray(frame)
        if spray.exists():
            points = read_points(spray)
            pts = points["position"]
            if len(pts):            # fine droplets: a particle's diameter on screen, 2 px at least
                # and SPRAY_MOST_PX per 1080 lines at most
                size = spray_point_size(0.8 * self._pixels_per_metre() * 2 * spec.sim.particle_radius,
                                        spec.render.resolution[1])
                cloud = pv.PolyData(pts)
                cloud.point_data["motion"] = points["velocity"]
                kw = dict(color=look["spray_color"])
                if "body" in look:      # water: white where it flies (aerated spray), its fluid's
                    # color half way to white where it has come to rest (a droplet left on a stone
                    # is a bead, not foam), and there faint (REST_OPACITY: drawn unlit, the beads a
                    # stone keeps read as a grid of lamps at full opacity)
                    fast = np.clip(np.linalg.norm(points["velocity"], axis=1) / (0.25 * spec.expected_max_speed()),
                                   0.0, 1.0)[:, None]
                    white = np.asarray(look["spray_color"])
                    own = np.array([f.color for f in spec.fluids], np.float64)[
                        np.clip(points["fluid"], 0, len(spec.fluids) - 1)]
                    rgb = (1 - fast) * 0.5 * (own + white) + fast * white
                    alpha = REST_OPACITY + (1 - REST_OPACITY) * fast
                    cloud.point_data["rgba"] = np.round(255 * np.column_stack([rgb, alpha])).astype(np.uint8)
                    kw = dict(scalars="rgba", rgba=True)
                if look["shading"] == "ibl":
                    # unlit, in their own color: lit sphere points with per-point colors, under
                    # the sky's image-based light, with supersampling on (render.ssaa, the
                    # default) and a collider's polygon offset, came out as nothing in VTK, and
                    # from 952c67c (the colors per point) every water-look frame with a collider
                    # lost its spray (the showcase's 19,000 droplets over the run-up at frame 24).
                    # At a few pixels across, a droplet's shading does not show.
                    kw["lighting"] = False
                else:
                    kw["ambient"] = 0.5     # lit: a sphere's dark side is not black
                out.append((cloud, dict(render_points_as_spheres=True, point_size=size, **kw)))
        return out

    def _light_under_water(self, frame: int, paths, level_set) -> None:
        """Colliders under the liquid get the light that reaches them through it: each vertex's
        color times the transmission of the liquid straight above it (thickness.water_above,
        Beer-Lambert as for the view), so that a submerged rock darkens and takes the water's
        hue with depth, up to a waterline, instead of reading as a flat disc through the
        surface. Each fluid absorbs as its own color does, over its own level set where the
        frame has one per fluid (surface.per_fluid; else all of the liquid as the first fluid).
        Without a level set (no .vdb, an opaque material) the colliders keep their color."""
        if not self.solids:
            return
        if level_set is None or not self.under_water:
            for actor, *_ in self.solids:
                actor.mapper.SetScalarVisibility(False)
            return
        from surfacing.thickness import sample, water_above

        layers = [(level_set, self.spec.fluids[0])]
        if self.spec.surface.per_fluid and len(self.spec.fluids) > 1:
            own = [(read_level_set(paths.surface_vdb(frame), f"surface_{f.name}"), f) for f in self.spec.fluids]
            layers = [(ls, f) for ls, f in own if ls is not None]
        shadow = self.look.get("shadow") or 0.0
        for actor, mesh, col, normals in self.solids:
            points = np.asarray(mesh.points, np.float64)
            facing_up = np.clip(normals[:, 1], 0.0, 1.0)[:, None]
            light = np.ones((len(points), 3))
            for (sdf, index_min, cell), fluid in layers:
                through = self._transmission(fluid, water_above(sdf, index_min, cell, points))
                # wet (the liquid a cell and a half off the face): all its light came through the
                # liquid above. Dry, under a sheet or a block of it overhead: on a face turned up
                # (the share of the sky's light from above) the light lost in it, each channel
                # as the liquid takes it but no channel darker than the floor's shadow under the
                # liquid (the look's "shadow"); none on a face turned sideways or down. (Uncapped,
                # a grey capsule under the two-fluid example's falling blocks, 20 cm of liquid
                # 10 cm above it, came out painted navy and orange beside the floor's soft gray
                # shadow under the same blocks.)
                wet = sample(sdf, index_min, cell, points + 1.5 * cell * normals, 1.0)[:, None] < 0
                lost = 1.0 - through
                shade = lost * np.minimum(1.0, shadow / np.maximum(lost.max(axis=1, keepdims=True), 1e-12))
                light *= np.where(wet, through, 1.0 - facing_up * shade)
            rgb = np.asarray(col.color, np.float64) * light
            mesh.point_data["lit"] = np.round(255 * np.clip(rgb, 0, 1)).astype(np.uint8)   # (the last frame's goes)
            actor.mapper.SetScalarModeToUsePointFieldData()
            actor.mapper.SelectColorArray("lit")
            actor.mapper.SetColorModeToDirectScalars()
            actor.mapper.SetScalarVisibility(True)

    def _absorption_length(self) -> float:
        """The water look's absorption length, m: its share ("absorption") of the domain's diagonal."""
        lo, hi = np.array(self.spec.domain.min), np.array(self.spec.domain.max)
        return self.look["absorption"] * float(np.linalg.norm(hi - lo))

    def _transmission(self, fluid, depth: np.ndarray) -> np.ndarray:
        """Per channel, the share of light left after `depth` m of `fluid`: its color^(depth /
        transmission_depth) where it has one (as _transmitted); else exp(-a depth / L), L the
        look's absorption length and a the channels' absorbances -ln(color) scaled to a mean of
        1 (water's blue: the red goes first)."""
        color = np.clip(np.asarray(fluid.color, np.float64), 1e-3, 1.0)
        if fluid.transmission_depth is not None:
            return color[None, :] ** (depth[:, None] / fluid.transmission_depth)
        a = -np.log(color)
        a = a / a.mean() if a.mean() > 0 else np.ones(3)
        return np.exp(-a[None, :] * depth[:, None] / self._absorption_length())

    def _water_behind(self, frame: int, points, normals, level_set, length: float, lengths: float):
        """(front, water): which vertices face the camera, and for those the length of liquid
        behind each along the ray from the camera, to within 1/32 of `length` and up to
        `lengths` of it (the march through 1.3 M vertices of the showcase took 8.5 s in steps
        of half a cell up to 4 lengths)."""
        from surfacing.thickness import ray_thickness

        eye = np.asarray(camera_at(self.spec.render, frame).position, np.float64)
        ray = np.asarray(points, np.float64) - eye
        ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
        front = np.einsum("ij,ij->i", np.asarray(normals, np.float64), ray) < 0
        sdf, index_min, cell = level_set
        water = ray_thickness(sdf, index_min, cell, points[front], ray[front], max_length=lengths * length,
                              min_step=length / 32)
        return front, water

    def _water_alpha(self, frame: int, points, normals, level_set) -> np.ndarray:
        """Opacity per vertex from Beer-Lambert absorption over the water behind it, along the
        ray from the camera: the look's `opacity` where the water is one absorption length
        (look `absorption` times the domain's diagonal) deep, half that for the thinnest sheet
        (so that it still shows); zero on faces turned away (the front face carries the
        water's whole depth, and a blob no longer reads as a ball drawn twice)."""
        look = self.look
        depth = self._absorption_length()
        # up to 3 lengths: 91 % of the way to opaque
        front, water = self._water_behind(frame, points, normals, level_set, depth, 3.0)
        # opacity at one absorption length is look["opacity"]: 1 - exp(-k) = opacity
        k = -np.log(1 - look["opacity"])
        least = 0.5 * look["opacity"]
        alpha = np.zeros(len(points))
        alpha[front] = least + (1 - least) * (1 - np.exp(-k * water / depth))
        return alpha

    def _transmitted(self, frame: int, points, normals, level_set, fluid):
        """(rgb, alpha) per vertex for a colored liquid (fluids.transmission_depth): light
        through a length d of it keeps T = color^(d / depth) of each channel (Beer-Lambert, the
        color reached at `depth`: _transmission). One alpha cannot filter the channels apart,
        so against the look's ground (a gray g, what most of the frame shows through the
        liquid) alpha = 1 - min(T) and the vertex color c = g (T - (1 - alpha)) / alpha blend
        to g T: thin runs clear and golden, deep pools dark and saturated. Alpha is at least half the look's
        opacity, as for the water's thinnest sheet, so that a thin coat still shows its gloss
        (c is then clipped at 0); faces turned away are clear."""
        front, water = self._water_behind(frame, points, normals, level_set, fluid.transmission_depth, 4.0)
        gray = float(np.mean(self.look["ground_color"]))
        through = self._transmission(fluid, water)
        least = 0.5 * self.look["opacity"]
        alpha = np.zeros(len(points))
        alpha[front] = np.maximum(1.0 - through.min(axis=1), least)
        rgb = np.tile(np.asarray(fluid.color, np.float64), (len(points), 1))
        rgb[front] = gray * (through - (1.0 - alpha[front, None])) / alpha[front, None]
        return np.clip(rgb, 0.0, 1.0), alpha

    def _pixels_per_metre(self) -> float:
        cam = self.spec.render.camera
        dist = float(np.linalg.norm(np.subtract(cam.position, cam.focal_point)))
        return self.spec.render.resolution[1] / (2 * dist * np.tan(np.radians(cam.fov) / 2))

    def render(self, frame: int, paths) -> np.ndarray:
        pl, r = self.pl, self.spec.render
        for actor in self.fluid_actors:
            pl.remove_actor(actor, render=False)
        level_set = self._level_set(frame, paths)
        meshes = self._fluid_meshes(frame, paths, level_set)
        self._light_under_water(frame, paths, level_set)
        del level_set       # a dense grid (450 MB for the showcase): gone before the render's own peak
        if self.shadow is not None:   # before the meshes are added: cast after add_mesh, the
            # first frame a renderer drew came out up to 3 levels off the same frame drawn later
            self.shadow.cast([m for m, _kw in meshes])
        self.fluid_actors = [pl.add_mesh(mesh, **kw) for mesh, kw in meshes]
        self.place_camera(frame)
        if r.motion_blur < 2:
            return pl.screenshot(return_img=True)
        return self._motion_blurred([m for m, _kw in meshes], r.motion_blur, r.shutter / self.spec.shot.fps)

    def place_camera(self, frame: int) -> None:
        """The plotter's camera where the job puts it at this frame."""
        cam, pl = camera_at(self.spec.render, frame), self.pl
        pl.camera.position = cam.position
        pl.camera.focal_point = cam.focal_point
        pl.camera.up = cam.up
        pl.camera.view_angle = cam.fov
        # VTK puts the near plane at a thousandth of the far one (its tolerance 0: its default),
        # which the ground's far plane sets some hundreds of metres off: a camera nearer the
        # domain than that (0.56 m for a 0.8 m tank) lost the fronts of what it looked at. The
        # tolerance brings it in to half the camera's distance from the domain (a
        # hundred-thousandth of the far plane at least), and holds for every later reset (a
        # depth read makes one).
        pl.renderer.SetNearClippingPlaneTolerance(0.0)
        pl.reset_camera_clipping_range()
        near, far = pl.camera.clipping_range
        lo, hi = np.array(self.spec.domain.min), np.array(self.spec.domain.max)
        gap = float(np.linalg.norm(np.maximum(np.maximum(lo - cam.position, np.asarray(cam.position) - hi), 0.0)))
        if 0.5 * gap < near:
            pl.renderer.SetNearClippingPlaneTolerance(max(0.5 * gap / far, 1e-5))
            pl.reset_camera_clipping_range()

    def _motion_blurred(self, meshes, samples: int, open_s: float) -> np.ndarray:
        """The mean of `samples` renders, each with the fluid moved along its velocity to an
        instant of the open shutter (open_s seconds, centred on the frame's time)."""
        base = [np.array(m.points) for m in meshes]
        total = None
        for k in range(samples):
            t = ((k + 0.5) / samples - 0.5) * open_s
            for m, p in zip(meshes, base):
                m.points = p + t * m.point_data["motion"]
            img = self.pl.screenshot(return_img=True).astype(np.float64)
            total = img if total is None else total + img
        for m, p in zip(meshes, base):
            m.points = p
        return np.clip(np.rint(total / samples), 0, 255).astype(np.uint8)

    def depth(self) -> np.ndarray:
        return self.pl.get_image_depth(fill_value=np.nan)

    def close(self) -> None:
        self.pl.close()


class ContactShadow:
    """A soft contact shadow on the floor where the floor is unlit (the water and clay looks),
    as the sky's soft boxes overhead would cast it: every triangle's area projected straight
    down, summed per texel, blurred, and drawn as an opaque layer just above the ground in the
    ground's own color darkened by that opacity. (Cast along the key light, which stands by the
    camera, it fell behind the water, out of sight; as a translucent black layer it was not
    drawn at all without SSAA: VTK's order-independent translucency.) Colliders cast theirs once
    (cast_still), the fluid each frame (cast); a translucent fluid casts a lighter one."""

    TEXELS = 192            # along the layer's longer side
    STILL = 0.65            # opacity under a deep opaque collider

    MARGIN = 0.15           # of the domain's diagonal, around it: room for the blur

    @classmethod
    def corner(cls, lo, hi) -> float:
        """How far the layer reaches from the domain's centre, across the floor."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        return float(np.hypot(*(0.5 * (hi - lo)[[0, 2]] + cls.MARGIN * np.linalg.norm(hi - lo))))

    def __init__(self, pv, lo, hi, strength: float, ground_rgb=lambda points: np.full((len(points), 3), 0.5)):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        self.floor, self.strength = lo[1], strength
        reach = self.MARGIN * float(np.linalg.norm(hi - lo))
        self.origin = np.array([lo[0] - reach, lo[2] - reach])
        extent = np.array([hi[0] - lo[0], hi[2] - lo[2]]) + 2 * reach
        self.texel = float(extent.max()) / self.TEXELS
        self.shape = tuple(np.ceil(extent / self.texel).astype(int) + 1)
        self.blur = 0.03 * float(np.linalg.norm(hi - lo)) / self.texel
        gx, gz = np.meshgrid(*(self.origin[k] + self.texel * np.arange(self.shape[k]) for k in (0, 1)),
                             indexing="ij")
        points = np.column_stack([gx.ravel(), np.full(gx.size, self.floor - 0.5e-4), gz.ravel()])
        nx, nz = self.shape
        i, k = np.meshgrid(np.arange(nx - 1), np.arange(nz - 1), indexing="ij")
        a = (i * nz + k).ravel()
        quads = np.column_stack([np.full(a.size, 4), a, a + 1, a + nz + 1, a + nz])
        self.layer = pv.PolyData(points, faces=quads.ravel())
        self.ground = np.asarray(ground_rgb(points), float)
        self.layer.point_data["rgb"] = np.round(self.ground * 255).astype(np.uint8)
        self.still = np.zeros(self.shape)

    def _opacity(self, meshes) -> np.ndarray:
        """1 - exp(-projected area / texel area / 2): a closed surface projects twice."""
        total = np.zeros(self.shape)
        for m in meshes:
            if m.n_faces == 0:
                continue            # points (spray) cast none
            if not m.is_all_triangles:
                m = m.triangulate()     # a capsule's or a cylinder's polygon caps
            x0, z0 = self.origin - self.texel
            x1, z1 = self.origin + self.texel * np.array(self.shape)
            if m.bounds[0] < x0 or m.bounds[1] > x1 or m.bounds[4] < z0 or m.bounds[5] > z1:
                # the part over the layer only: a floor 100 m across, split to texels whole, took
                # minutes when the renderer was made
                m = m.clip_box((x0, x1, m.bounds[2] - 1.0, m.bounds[3] + 1.0, z0, z1), invert=False)
                m = m.extract_surface(algorithm="dataset_surface").triangulate()
                if m.n_faces == 0:
                    continue
            if longest_edge(m) > 4 * self.texel:
                # each triangle counts at its centre, a texel or two off under the blur (about 5
                # texels): split large ones (a box collider's), not the fluid's
                m = m.subdivide_adaptive(max_edge_len=self.texel)
            tri = np.asarray(m.points, np.float64)[m.regular_faces]
            area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
            c = tri.mean(axis=1)
            hist, _, _ = np.histogram2d(
                c[:, 0], c[:, 2], bins=self.shape, weights=area,
                range=[(self.origin[k] - 0.5 * self.texel, self.origin[k] + (self.shape[k] - 0.5) * self.texel)
                       for k in (0, 1)])
            total += hist
        from scipy.ndimage import gaussian_filter

        return gaussian_filter(1.0 - np.exp(-0.5 * total / self.texel ** 2), self.blur)

    def cast_still(self, meshes) -> None:
        self.still = self.STILL * self._opacity(meshes)
        self._show(self.still)

    def cast(self, meshes) -> None:
        self._show(1.0 - (1.0 - self.still) * (1.0 - self.strength * self._opacity(meshes)))

    def _show(self, opacity: np.ndarray) -> None:
        self.opacity = np.clip(opacity, 0, 1)
        rgb = self.layer.point_data["rgb"]
        rgb[:] = np.round(255 * self.ground * (1 - self.opacity.reshape(-1, 1)))
        self.layer.GetPointData().GetArray("rgb").Modified()
        self.layer.Modified()


SKY_TEXELS = 64     # a cube face's side: the soft boxes' edges stay sharp in a calm surface


def sky_faces(look: dict, n: int = SKY_TEXELS) -> list[np.ndarray]:
    """A studio sky as six n x n RGB cube faces (+x, -x, +y, -y, +z, -z; y up), made from the
    look's colors so that what the water reflects matches what is behind it: the background's
    bottom color at the horizon, its top color overhead, the ground color below, and two soft
    boxes overhead whose reflections read as a wet surface. Pure numpy: the same on every
    machine, nothing read from disk."""
    u = (np.arange(n) + 0.5) / n * 2 - 1
    a, b = np.meshgrid(u, -u)
    one = np.ones_like(a)
    horizon = np.asarray(look["background"], float)
    zenith = np.asarray(look["background_top"] if look["background_top"] is not None else horizon, float)
    ground = np.asarray(look["ground_color"], float)
    faces = []
    for d in ((one, b, -a), (-one, b, a), (a, one, -b), (a, -one, b), (a, b, one), (-a, b, -one)):
        d = np.stack(d, -1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        y = d[..., 1:2]
        up = np.sqrt(np.clip(y, 0, 1))
        rgb = np.where(y > 0, (1 - up) * horizon + up * zenith, ground + (horizon - ground) * np.exp(12 * y))
        lift = np.maximum(y[..., 0], 1e-3)     # where the ray meets a ceiling at height 1
        for cx, cz, w, l in ((0.45, 0.35, 0.30, 0.14), (-0.5, -0.15, 0.22, 0.10)):
            box = (np.abs(d[..., 0] / lift - cx) < w) & (np.abs(d[..., 2] / lift - cz) < l) & (y[..., 0] > 0.3)
            rgb = np.where(box[..., None], 1.0, rgb)
        faces.append(np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8))
    return faces


def collider_meshes(spec, edge: float | None = None):
    """(mesh, collider) for each collider drawn. With `edge` (m), each mesh is cut into
    triangles no longer than that, its point normals computed first and carried onto the new
    points (so that it shades as before): colors per vertex then follow the water above it
    (FrameRenderer._light_under_water), a waterline included."""
    import pyvista as pv

    out = []
    for ci, col in enumerate(spec.colliders):
        if col.mode == "container":
            continue      # the inside of a container would hide the fluid
        if col.type == "mesh":
            verts, tris = spec.collider_mesh(ci)
            m = pv.PolyData.from_regular_faces(verts, tris)
            m = m.compute_normals(auto_orient_normals=True, split_vertices=True, feature_angle=60.0)
        elif col.type == "sphere":
            m = pv.Sphere(radius=col.radius, center=col.center, theta_resolution=48, phi_resolution=48)
        elif col.type == "box":
            m = pv.Box(bounds=(col.min[0], col.max[0], col.min[1], col.max[1], col.min[2], col.max[2]))
        else:
            a, b = np.array(col.a), np.array(col.b)
            axis = b - a
            length = float(np.linalg.norm(axis))
            parts = [pv.Sphere(radius=col.radius, center=tuple(a)), pv.Sphere(radius=col.radius, center=tuple(b))]
            if length > 0:
                parts.append(pv.Cylinder(center=tuple(0.5 * (a + b)), direction=tuple(axis / length),
                                         radius=col.radius, height=length, resolution=48))
            m = parts[0].merge(parts[1:])
        if edge is not None:
            if col.type == "box":        # a normal per face
                m = m.compute_normals(cell_normals=False, split_vertices=True)
            elif col.type != "mesh":     # (a mesh's normals, split at its edges, are already there)
                m = m.compute_normals(cell_normals=False)
            m = m.triangulate()
            # each level halves every edge (4 triangles for 1; VTK's adaptive subdivision took
            # 150 s to cut a 100 m floor into 2.5 M triangles)
            longest = longest_edge(m)
            levels = math.ceil(math.log2(longest / edge)) if longest > edge else 0
            budget = int(math.log(max(UNDER_WATER_MOST_TRIANGLES / max(m.n_cells, 1), 1.0), 4))
            if min(levels, budget) > 0:
                m = m.subdivide(min(levels, budget), subfilter="linear")
        out.append((m, col))
    return out


def check_image(spec, frame: int, image: np.ndarray) -> np.ndarray:
    """The rendered frame, or a StageError when it cannot be what was asked for: another size,
    or one flat color other than a flat background's (the default background is a gradient, so
    a flat image is a render that failed: at 8192 x 4320 VTK's off-screen framebuffer could not
    be made and every pixel came back black, with no error)."""
    w, h = spec.render.resolution
    where = f"render: frame {frame:04d}"
    if image.shape[:2] != (h, w):
        raise StageError(f"{where} came out {image.shape[1]}x{image.shape[0]}, not the {w}x{h} of "
                         f"render.resolution: the off-screen framebuffer cannot be that large here")
    flat = (image == image.reshape(-1, image.shape[2])[0]).all()
    look = look_of(spec.render)            # the background drawn: the look's, or the job's own
    empty_view = look["background_top"] is None and \
        np.abs(image[0, 0, :3].astype(float) - 255 * np.asarray(look["background"])).max() <= 2
    if flat and not empty_view:       # (a flat background and nothing in view is a flat image)
        raise StageError(f"{where} came out one flat color at {w}x{h}: the off-screen render failed "
                         f"(a framebuffer this large may not be possible here); lower render.resolution")
    return image


def save_png(final: Path, image: np.ndarray) -> Path:
    from PIL import Image

    with atomic_path(final) as tmp:
        Image.fromarray(image).save(tmp, format="PNG", compress_level=PNG_LEVEL)
    return final


def save_depth_png16(final: Path, depth: np.ndarray) -> Path:
    """Depth pass as 16-bit PNG: 0 = near plane, 65534 = farthest hit, 65535 = background."""
    from PIL import Image

    d = np.asarray(depth, np.float64)
    finite = np.isfinite(d)
    out = np.full(d.shape, 65535, np.uint16)
    if finite.any():
        lo, hi = d[finite].min(), d[finite].max()
        out[finite] = np.round((d[finite] - lo) / max(hi - lo, 1e-12) * 65534).astype(np.uint16)
    with atomic_path(final) as tmp:
        Image.fromarray(out).save(tmp, format="PNG", compress_level=PNG_LEVEL)
    return final


_local = threading.local()      # a renderer per thread: VTK's GL context belongs to the thread that made it


def renderer_for(spec) -> FrameRenderer:
    """This thread's renderer of the shot, kept open between calls. A Dask worker gets one
    frame a task; with a new window and static scene each time, a 960x540 frame of the example
    took 0.38 s on one core instead of 0.26 s (the first render in a new window is the slow one)."""
    kept = getattr(_local, "renderer", None)
    if kept is not None and kept.spec == spec:
        return kept
    close_renderer()
    try:
        _local.renderer = FrameRenderer(spec)
    except Exception as exc:  # VTK raises plain RuntimeErrors for missing GL
        raise StageError(f"render: cannot open an off-screen render window: {exc}") from None
    return _local.renderer


def close_renderer() -> None:
    """Close this thread's renderer, if it has one."""
    kept = getattr(_local, "renderer", None)
    _local.renderer = None
    if kept is not None:
        kept.close()


# the main thread's renderer (serial runs) closes before the interpreter tears VTK down; a Dask
# worker's task threads leave theirs to the end of the process
atexit.register(close_renderer)


def run(spec, frames, paths, progress) -> None:
    renderer = renderer_for(spec)
    try:
        for frame in frames:
            image = check_image(spec, frame, renderer.render(frame, paths))
            written = [save_png(paths.render_frame(frame), image)]
            if spec.render.depth == "png16":
                written.append(save_depth_png16(paths.render_depth(frame), renderer.depth()))
            progress.frame_done(frame, written)
    except BaseException:
        close_renderer()          # whatever state a failed render left, the next call starts clean
        raise


def finalize(spec, paths, force: bool = False) -> list[Path]:
    """Preview movie and contact sheet, once every frame of the shot is rendered."""
    frames = list(spec.frames)
    written = []
    if spec.render.movie and (force or not paths.movie.exists()):
        written.append(write_movie(paths.movie, [paths.render_frame(f) for f in frames], spec.shot.fps))
    if spec.render.contact_sheet and (force or not paths.contact_sheet.exists()):
        written.append(write_contact_sheet(paths.contact_sheet, [(f, paths.render_frame(f)) for f in frames]))
    return written


def write_movie(final: Path, images: list[Path], fps: float) -> Path:
    """H.264 MP4 (yuv420p); odd widths or heights are padded by one pixel to be even. The movie
    is read back (its frames counted, without decoding) before it is published: on a full disk
    ffmpeg only logs that it could not write the trailer, and imageio-ffmpeg returns as if done."""
    import imageio_ffmpeg
    from PIL import Image

    first = Image.open(images[0])
    w, h = first.size
    W, H = w + (w % 2), h + (h % 2)
    with atomic_path(final) as tmp:
        writer = imageio_ffmpeg.write_frames(str(tmp), (W, H), fps=fps, codec="libx264",
                                             pix_fmt_out="yuv420p", macro_block_size=1, ffmpeg_log_level="quiet",
                                             output_params=["-f", "mp4", "-crf", "20"])
        writer.send(None)
        for p in images:
            img = np.asarray(Image.open(p).convert("RGB"))
            if (W, H) != (w, h):
                img = np.pad(img, ((0, H - h), (0, W - w), (0, 0)), mode="edge")
            writer.send(np.ascontiguousarray(img))
        writer.close()
        try:
            frames = imageio_ffmpeg.count_frames_and_secs(str(tmp))[0]
        except RuntimeError:
            frames = None
        if frames != len(images):
            got = "could not be read" if frames is None else f"holds {frames} frames"
            raise OSError(f"{final}: the movie written {got}, not {len(images)} frames; {disk_left(tmp)}")
    return final


def contact_sheet_grid(n: int) -> tuple[int, int]:
    """Columns and rows for n thumbnails: about 16:9 overall for 16:9 frames."""
    cols = max(1, int(np.ceil(np.sqrt(n))))
    rows = int(np.ceil(n / cols))
    return cols, rows


def write_contact_sheet(final: Path, frames: list[tuple[int, Path]], thumb_width: int = 240) -> Path:
    from PIL import Image, ImageDraw

    first = Image.open(frames[0][1])
    tw = thumb_width
    th = max(1, round(first.height * tw / first.width))
    cols, rows = contact_sheet_grid(len(frames))
    pad = 4
    sheet = Image.new("RGB", (cols * (tw + pad) + pad, rows * (th + pad) + pad), (20, 20, 22))
    draw = ImageDraw.Draw(sheet)
    for k, (frame, path) in enumerate(frames):
        x, y = pad + (k % cols) * (tw + pad), pad + (k // cols) * (th + pad)
        sheet.paste(Image.open(path).convert("RGB").resize((tw, th), Image.LANCZOS), (x, y))
        draw.rectangle((x, y, x + 34, y + 13), fill=(0, 0, 0))
        draw.text((x + 3, y + 1), f"{frame:04d}", fill=(255, 255, 255))
    with atomic_path(final) as tmp:
        sheet.save(tmp, format="PNG", compress_level=PNG_LEVEL)
    return final
