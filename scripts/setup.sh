#!/usr/bin/env bash
# Sets up sphshot on a fresh Debian/Ubuntu machine: system packages, a virtual environment in
# .venv with the pinned Python packages, and Debian's pyopenvdb module made visible to it.
# Safe to run again: each step is skipped when already done.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

# 1. System packages: Python venv support, OpenVDB's Python module, Mesa EGL/OSMesa for
#    off-screen rendering with no display and no GPU, and OpenVDB's C++ headers with a compiler
#    for the one thing pyopenvdb cannot write, spray as VDB points (step 4); the Vulkan loader and
#    Mesa's Vulkan drivers, whose software device (lavapipe) lets the tests run the kernels through
#    Taichi's Vulkan backend on a machine with no GPU (tests/test_gpu.py).
APT_PKGS="python3-venv python3-openvdb libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 g++ libopenvdb-dev libboost-dev
          libvulkan1 mesa-vulkan-drivers"
missing=""
for p in $APT_PKGS; do dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"; done
if [ -n "$missing" ]; then
  echo "setup: installing system packages:$missing"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -q
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q $missing
fi

# 2. The venv uses the system interpreter, the one Debian's pyopenvdb is built for.
PY=/usr/bin/python3
VENV=.venv
if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating $VENV with $($PY --version)"
  $PY -m venv "$VENV"
fi
stamp="$VENV/.sphshot-lock-$(sha256sum requirements.lock pyproject.toml | sha256sum | cut -c1-16)"
if [ ! -e "$stamp" ]; then
  echo "setup: installing pinned packages (requirements.lock)"
  "$VENV/bin/python" -m pip install -q --upgrade pip
  "$VENV/bin/python" -m pip install -q -r requirements.lock
  "$VENV/bin/python" -m pip install -q --no-deps -e .
  rm -f "$VENV"/.sphshot-lock-*
  touch "$stamp"
fi

# 3. Let the venv see the pyopenvdb module alone (not Debian's NumPy from the same folder).
site=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["platlib"])')
so=$(ls /usr/lib/python3/dist-packages/pyopenvdb*.so 2>/dev/null | head -n1 || true)
if [ -z "$so" ]; then echo "setup: python3-openvdb installed but pyopenvdb*.so not found" >&2; exit 1; fi
ln -sf "$so" "$site/$(basename "$so")"

# 4. sphshot-vdb-points (pipeline/native/vdb_points.cpp): the surface stage's spray as an OpenVDB
#    PointDataGrid. Built into the venv, again whenever its source changes (about 40 s).
tool="$VENV/bin/sphshot-vdb-points"
src=pipeline/native/vdb_points.cpp
tool_stamp="$VENV/.sphshot-vdb-points-$(sha256sum "$src" | cut -c1-16)"
if [ ! -x "$tool" ] || [ ! -e "$tool_stamp" ]; then
  echo "setup: building $tool"
  g++ -O2 -std=c++17 "$src" -o "$tool.tmp" -lopenvdb -ltbb
  mv "$tool.tmp" "$tool"
  rm -f "$VENV"/.sphshot-vdb-points-*
  touch "$tool_stamp"
fi

# 5. Check that the pieces import together (NumPy 1.x next to pyopenvdb).
"$VENV/bin/python" - <<'PY'
import numpy, pyopenvdb, taichi, h5py, pyvista, meshio, skimage  # noqa: F401
assert numpy.__version__.startswith("1."), f"expected NumPy 1.x next to pyopenvdb, got {numpy.__version__}"
print(f"setup: ok (numpy {numpy.__version__}, taichi {'.'.join(map(str, taichi.__version__))}, "
      f"pyvista {pyvista.__version__}, OpenVDB {'.'.join(map(str, pyopenvdb.LIBRARY_VERSION))})")
PY
