"""Every example job in jobs/ runs through every stage with small overrides, so none rots."""
from __future__ import annotations

import shutil

import pytest

from conftest import JOBS, small, sphshot
from pipeline import cache
from pipeline.spec import load_spec

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("job_file", JOBS, ids=[j.stem for j in JOBS])
def test_example_job_runs_end_to_end(job_file, tmp_path):
    job = tmp_path / job_file.name
    job.write_text(job_file.read_text())
    shutil.copytree(job_file.parent / "assets", tmp_path / "assets")   # meshes the jobs refer to
    assert sphshot("validate", job).returncode == 0
    proc = sphshot("run", job, *small(), check=True)
    spec = load_spec(job, [s for s in small() if s != "--set"])
    paths = cache.ShotPaths.for_spec(spec)
    for stage in cache.STAGES:
        assert cache.scan(spec, paths, stage, spec.frames).valid == tuple(spec.frames), stage
    assert paths.movie.stat().st_size > 0
    assert "Traceback" not in proc.stderr


def test_there_are_example_jobs():
    assert len(JOBS) >= 2
