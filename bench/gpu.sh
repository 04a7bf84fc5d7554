#!/usr/bin/env bash
# Every GPU test and benchmark in one call, for a lent GPU machine (see bench/RESULTS.md).
#
#   bash bench/gpu.sh prepare     # here, once: the Python packages the GPU machine lacks, built by
#                                 # ../shared/gpu/make_site.sh into .gpu/ (git-ignored, ~33 MB), meshio,
#                                 # and the mesh colliders' level sets (no OpenVDB there: bench/gpu_site)
#   bash bench/gpu.sh             # there, from the repository root (carry .gpu): the GPU tests,
#                                 # then bench/gpu.py; about 5 minutes; ends with one table
#   bash bench/gpu.sh --dry       # here: the same script on the CPU at 1/200 of the sizes
#   SHOWCASE_S=300 SHOWCASE_PACK=$OUT GPU_PY_LIMIT=440 bash bench/gpu.sh --only dambreak,showcase
#                                 # there: the GPU tests, the 1M dam break, then the showcase's sim
#                                 # for 300 s and a few of its frames packed into $OUT
#
# The GPU machine has Python 3.12 with pytest, h5py and rich but no package index, no pyopenvdb
# and no VTK (over the upload limit), so the solver, the surfacer's kernels and the sim stage run
# there (mesh colliders through bench/gpu_site's stand-in for pyopenvdb); the VDB and render
# paths do not.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
export PYTHONUNBUFFERED=1 ENABLE_TAICHI_HEADER_PRINT=0

if [ "${1:-}" = prepare ]; then
  site=../shared/gpu/make_site.sh
  [ -f "$site" ] || { echo "gpu.sh: $site not found (the leads' GPU folder beside the checkout)" >&2; exit 2; }
  bash "$site" .gpu
  # meshio (pure Python) reads the mesh colliders' files: the sim stage of jobs/showcase.toml needs it
  python3 -m pip download -q --no-deps --only-binary=:all: -d .gpu meshio==5.3.5 || exit 3
  # OpenVDB is not there either: the mesh colliders' level sets, made here, for bench/gpu_site's stand-in
  .venv/bin/python bench/gpu_levelsets.py jobs/showcase.toml || exit 3
  exit
fi

PY=python3
if [ "${1:-}" = --dry ]; then
  PY=.venv/bin/python
elif [ -f .gpu/site312.tar.xz ] && ! python3 -c "import taichi" 2>/dev/null; then
  python3 -c "import tarfile; tarfile.open('.gpu/site312.tar.xz').extractall('/tmp')" || exit 3
  export PYTHONPATH=/tmp/site312
  for w in .gpu/*.whl; do [ -f "$w" ] && python3 -m zipfile -e "$w" /tmp/site312; done
fi
if ! $PY -c "import pyopenvdb" 2>/dev/null; then      # mesh colliders: level sets made by 'prepare'
  export PYTHONPATH="${PYTHONPATH:+$PYTHONPATH:}$PWD/bench/gpu_site"
fi
$PY -c "import taichi, numpy, pydantic, h5py" || { echo "gpu.sh: packages missing: run 'bash bench/gpu.sh prepare' here and carry .gpu" >&2; exit 3; }

# The tree that ran: the device's copy carries the working tree, but its git HEAD may be an older
# commit's, so the header names the working tree's own tree hash (here: `git add -A` into a
# scratch index, then `git write-tree`; compare with `git rev-parse --short HEAD^{tree}`).
tree() {
  local index; index=$(mktemp -u) || return
  GIT_INDEX_FILE=$index git add -A 2>/dev/null && GIT_INDEX_FILE=$index git write-tree 2>/dev/null | cut -c1-7
  rm -f "$index"
}
echo "# $(date -u +%Y-%m-%dT%H:%MZ) $(nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || echo 'no nvidia-smi') tree $(tree) (HEAD $(git rev-parse --short HEAD 2>/dev/null))"
if [ "${1:-}" != --dry ]; then
  echo "## GPU tests"
  # 10 CUDA tests: the nine of the twenty-fifth session took 100 s on the H200. The Vulkan ones
  # run on every machine (Mesa's software device); here they would spend the GPU's minutes.
  timeout 150 $PY -m pytest -q -p no:cacheprovider --tb=short -W ignore -m gpu -k "not vulkan" tests/test_gpu.py 2>&1 | tail -n 80
fi
timeout "${GPU_PY_LIMIT:-440}" $PY bench/gpu.py "$@"
