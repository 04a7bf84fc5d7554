#!/usr/bin/env python3
"""Surfacing speed: sphshot vs splashsurf on the same particle frames, in one session.

Particles come from the anchor's generator (../shared/anchors/surface/bench_surface.py): a
dam-break-like jittered lattice with splash droplets, r = 0.01 m, about 50k and 500k particles.
Both sides use the same particle radius, a kernel support of 4 radii (splashsurf: smoothing
length 2 radii), cube size 0.75 radii and iso 0.6 (splashsurf's threshold convention; sphshot's
color field is normalised the same way, 1 inside the bulk).

sphshot's surfacer takes each particle's volume from the sim cache (m / rho); these frames have
no density, so it uses the lattice volume (2r)^3 — the density pass is the sim stage's work.
splashsurf computes its own densities (included in its time). splashsurf runs in its own venv
(its wheel wants NumPy 2; pyopenvdb needs NumPy 1) as a child process; sphshot also runs in a
child, so both peak memories are per process. Timings are medians of --repeat runs after a
warm-up; the two sides alternate for --rounds rounds and the ratio is the median round's.
sphshot runs three times: "mesh" makes what splashsurf makes (the mesh, no velocities; the
comparison); "aniso" the same with the anisotropic kernels and their centres smoothed (the surface stage's defaults;
splashsurf has none: target at most 2x splashsurf's isotropic time at 500k); "full" makes what
the surface stage makes with isotropic kernels (velocity field and vertex velocities too), then
times the VDB grids separately.

    .venv/bin/python bench/surface.py --sizes 50k          # ~1 min
    .venv/bin/python bench/surface.py --sizes 50k,500k     # ~4 min
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[0] = str(ROOT)
ANCHOR = ROOT.parent / "shared" / "anchors" / "surface" / "bench_surface.py"
SPLASH_VENV = Path(os.environ.get("SPLASH_VENV", Path(tempfile.gettempdir()) / "surfvenv"))
SIZES = {"50k": (50_000, 2_000), "500k": (500_000, 5_000)}
R, CUBE, SUPPORT, ISO = 0.01, 0.75, 4.0, 0.6


def particles(size: str, out: Path) -> Path:
    spec = importlib.util.spec_from_file_location("anchor_surface", ANCHOR)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    import numpy as np

    P, info = mod.make_particles(*SIZES[size], r=R)
    path = out / f"P_{size}.npy"
    np.save(path, P)
    return path


def child_sphshot(path: str, repeat: int, vdb_dir: str, mode: str) -> None:
    import numpy as np

    from pipeline.formats import write_vdb
    from solver.backend import init_taichi
    init_taichi("cpu", 0)
    from surfacing import vdb
    from pipeline.spec import Surface
    from surfacing.reconstruct import color_field, marching_cubes

    P = np.load(path).astype(np.float32)
    vel = np.random.default_rng(1).normal(size=P.shape).astype(np.float32)
    vol = np.full(len(P), (2 * R) ** 3, np.float32)
    # compile and warm up every Taichi kernel (splat and marching cubes) on a small frame, so
    # that neither the times nor the peak memory include the JIT compiler
    aniso = mode == "aniso"              # the anisotropic kernels (the surface stage's default), mesh alone
    iso = Surface.ISO["anisotropic"] if aniso else ISO
    marching_cubes(color_field(P[:2000], vel[:2000], vol[:2000], CUBE * R, SUPPORT * R, ISO), ISO)
    # the surface stage's default centre smoothing with the anisotropic kernels (two passes, Taubin's)
    smooth = {"center_smoothing": Surface().center_smoothing,
              "center_inflation": Surface().center_inflation} if aniso else {}
    marching_cubes(color_field(P[:2000], None, vol[:2000], CUBE * R, SUPPORT * R, iso, anisotropic=aniso, **smooth),
                   iso)

    def timed(v):
        times, field, mesh = [], None, None
        for _ in range(repeat):
            field = mesh = None          # peak memory is that of one reconstruction, not two
            t0 = time.perf_counter()
            field = color_field(P, v, vol, CUBE * R, SUPPORT * R, iso, anisotropic=aniso, **smooth)
            t1 = time.perf_counter()
            mesh = marching_cubes(field, iso)
            t2 = time.perf_counter()
            times.append((t2 - t0, t1 - t0, t2 - t1))
        return sorted(times)[len(times) // 2], field, mesh

    # "mesh": the mesh alone, what splashsurf makes. "full": what the surface stage makes, with
    # the velocity field, vertex velocities and the VDB grids (timed separately)
    (total, splat, mc), field, mesh = timed(vel if mode == "full" else None)
    t_vdb = None
    if mode == "full":
        t0 = time.perf_counter()
        write_vdb(Path(vdb_dir) / "bench.vdb", vdb.build_grids(field, mesh, 1, 0.0, 3.0))
        t_vdb = round(time.perf_counter() - t0, 3)
    f = np.asarray(mesh.faces)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, cnt = np.unique(e[:, 0].astype(np.int64) * (len(mesh.points) + 1) + e[:, 1], return_counts=True)
    print("RESULT " + json.dumps({
        "method": f"sphshot-{mode}", "particles": len(P), "mesh_s": round(total, 3), "splat_s": round(splat, 3),
        "marching_cubes_s": round(mc, 3), "vdb_s": t_vdb,
        "tris": len(f), "grid_nodes": field.n_blocks * 512, "closed": bool((cnt == 2).all())}), flush=True)


SPLASH_CHILD = r"""
import json, sys, time, numpy as np, pysplashsurf as ps
P = np.load(sys.argv[1]); repeat = int(sys.argv[2])
a = dict(particle_radius=%r, smoothing_length=%r, cube_size=%r, iso_surface_threshold=%r)
ps.reconstruct_surface(P[:2000], **a)
ts = []
rec = None
for _ in range(repeat):
    rec = None   # peak memory is that of one reconstruction, not two
    t = time.perf_counter(); rec = ps.reconstruct_surface(P, **a); ts.append(time.perf_counter() - t)
T = np.asarray(rec.mesh.triangles)
e = np.sort(np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]]), axis=1)
_, cnt = np.unique(e[:, 0].astype(np.int64) * (int(T.max()) + 1) + e[:, 1], return_counts=True)
print("RESULT " + json.dumps({"method": "splashsurf", "particles": len(P), "mesh_s": round(sorted(ts)[len(ts) // 2], 3),
      "tris": len(T), "closed": bool((cnt == 2).all())}), flush=True)
""" % (R, SUPPORT / 2, CUBE, ISO)


def ensure_splash_venv() -> Path:
    py = SPLASH_VENV / "bin" / "python"
    if not py.exists():
        subprocess.run(["/usr/bin/python3", "-m", "venv", str(SPLASH_VENV)], check=True)
    ok = subprocess.run([str(py), "-c", "import pysplashsurf"], capture_output=True).returncode == 0
    if not ok:
        subprocess.run([str(py), "-m", "pip", "install", "-q", "numpy", "pysplashsurf==0.14.1"], check=True)
    return py


def run_child(cmd, env=None) -> dict:
    proc = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True, env=env, cwd=ROOT)
    m = re.search(r"^RESULT (\{.*\})$", proc.stdout, re.M)
    if proc.returncode != 0 or not m:
        raise SystemExit(f"child failed: {cmd}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    r = json.loads(m.group(1))
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr)
    r["peak_rss_mb"] = round(int(rss.group(1)) / 1024, 1) if rss else None
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="50k,500k")
    ap.add_argument("--repeat", type=int, default=3, help="reconstructions per child process")
    ap.add_argument("--rounds", type=int, default=3, help="alternating sphshot/splashsurf rounds")
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child_sphshot(args.child[0], int(args.child[1]), args.child[2], args.child[3])
    load = os.getloadavg()[0]
    print(f"# {os.cpu_count()} cores, 1-min load {load:.2f}{'  (busy machine: numbers are noisy)' if load > 0.5 else ''}")
    print(f"# command: {' '.join([Path(sys.executable).name, *sys.argv])}")
    splash_py = ensure_splash_venv()
    work = Path(tempfile.mkdtemp(prefix="sphshot_surface_bench_"))
    for size in args.sizes.split(","):
        path = particles(size, work)
        # the comparison alternates the two sides, round after round, and takes the median of
        # the rounds' ratios: a host that slows down for a minute slows both sides of a round
        rounds = []
        for n in range(args.rounds):
            ours = run_child([sys.executable, __file__, "--child", str(path), str(args.repeat), str(work), "mesh"])
            ref = run_child([str(splash_py), "-c", SPLASH_CHILD, str(path), str(args.repeat)])
            aniso = run_child([sys.executable, __file__, "--child", str(path), str(args.repeat), str(work), "aniso"])
            rounds.append((ours, ref, aniso))
            print(f"{size:5s} round {n + 1}: sphshot {ours['mesh_s']} s (anisotropic {aniso['mesh_s']} s), "
                  f"splashsurf {ref['mesh_s']} s, x{ours['mesh_s'] / ref['mesh_s']:.2f} "
                  f"(anisotropic x{aniso['mesh_s'] / ref['mesh_s']:.2f})", flush=True)
        full = run_child([sys.executable, __file__, "--child", str(path), str(args.repeat), str(work), "full"])
        mid = sorted(range(len(rounds)), key=lambda n: rounds[n][0]["mesh_s"] / rounds[n][1]["mesh_s"])
        ours, ref, aniso = rounds[mid[len(mid) // 2]]                # the median round
        for r in (ours, aniso, full, ref):
            print(f"{size:5s} {r['method']:14s} " + " ".join(f"{k}={v}" for k, v in r.items() if k != "method"))
        print(f"RATIO {size}: sphshot mesh time x{ours['mesh_s'] / ref['mesh_s']:.2f} of splashsurf's "
              f"(>1 is slower; the median of {len(rounds)} rounds), peak memory "
              f"x{ours['peak_rss_mb'] / ref['peak_rss_mb']:.2f}, triangles x{ours['tris'] / ref['tris']:.2f}; "
              f"with velocities {full['mesh_s']} s (x{full['mesh_s'] / ref['mesh_s']:.2f}), "
              f"then VDB writing {full['vdb_s']} s; anisotropic kernels x{aniso['mesh_s'] / ref['mesh_s']:.2f} "
              f"(target <= x2), peak memory x{aniso['peak_rss_mb'] / ref['peak_rss_mb']:.2f}")


if __name__ == "__main__":
    main()
