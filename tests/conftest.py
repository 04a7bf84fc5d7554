"""Shared fixtures: small copies of the example jobs, run in a temporary folder."""
from __future__ import annotations

import contextlib

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
JOBS = sorted((ROOT / "jobs").glob("*.toml"))

# Small overrides that turn any example job into a seconds-long test shot.
SMALL = ["sim.particle_radius=0.02", "shot.frame_end=6", "shot.checkpoint_every=2",
         "render.resolution=[160,90]", "render.ssaa=false", "sim.threads=1"]

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")
os.environ.pop("DISPLAY", None)   # every test renders headless, as on a farm node


@pytest.fixture
def job_copy(tmp_path):
    """Copy a job file from jobs/ into tmp_path (small() points its output at tmp_path/out)."""
    def make(name: str = "dambreak.toml") -> Path:
        dst = tmp_path / name
        text = (ROOT / "jobs" / name).read_text()
        dst.write_text(text)
        return dst
    return make


def sphshot(*args, check=False, timeout=600, env=None) -> subprocess.CompletedProcess:
    """Run the real console entry point in a subprocess (what a farm node runs)."""
    cmd = [sys.executable, "-m", "pipeline.cli", *map(str, args)]
    e = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=e)
    if check and proc.returncode != 0:
        raise AssertionError(f"{cmd} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


def small(*extra: str) -> list[str]:
    out = []
    for kv in [*SMALL, "shot.output=\"out\"", *extra]:
        out += ["--set", kv]
    return out


def tiny_spec(block=((0.0, 0.0, 0.0), (0.1, 0.1, 0.1)), domain=((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)), *,
              sim=None, fluid=None, velocity=(0.0, 0.0, 0.0), colliders=(), name="t", **sections) -> dict:
    """A job as a dict: one fluid "w" filling `block` inside `domain`. `sim` and `fluid` add keys
    to those sections (particle_radius is 0.01 unless given); other sections go in as given."""
    return {"shot": {"name": name, **sections.pop("shot", {})},
            "sim": {"particle_radius": 0.01, **(sim or {})},
            "domain": {"min": domain[0], "max": domain[1]},
            "fluids": ({"name": "w", **(fluid or {}),
                        "blocks": ({"min": block[0], "max": block[1], "velocity": velocity},)},),
            "colliders": tuple(colliders), **sections}


def use_taichi_cpu() -> None:
    """Taichi on the CPU with one thread: the particle order, and so every sum, is the same on
    every run (tests compare states bit for bit). A no-op when already so."""
    from solver.backend import init_taichi
    init_taichi("cpu", 1)


@pytest.fixture(scope="module")
def taichi_cpu():
    use_taichi_cpu()


def spec_of(job, args):
    """The ShotSpec a `sphshot` call with these `--set` arguments sees."""
    from pipeline.spec import load_spec
    return load_spec(job, [s for s in args if s != "--set"])


@contextlib.contextmanager
def mounted_tmpfs(folder: Path, options: str):
    """A tmpfs mounted at `folder` (created) with mount options `options` for the block; the
    test is skipped, with the reason, where this machine cannot mount one."""
    folder.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.strip() or mounted.returncode}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=False)
