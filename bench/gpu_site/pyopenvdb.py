"""A stand-in for pyopenvdb on the lent GPU machine (no OpenVDB there), for mesh colliders
only: bench/gpu.sh puts this folder on the path there when the real module is missing. It serves
the level sets that the real OpenVDB made on this machine for the same mesh, voxel and band
(`bash bench/gpu.sh prepare` runs bench/gpu_levelsets.py), found by a hash of them in
$SPHSHOT_LEVELSETS (default .gpu/levelsets), and fails for any other. Not part of the product: a
GPU farm node has OpenVDB installed like any other."""
import hashlib
import os
from pathlib import Path

import numpy as np

STORE = Path(os.environ.get("SPHSHOT_LEVELSETS", Path(__file__).resolve().parents[2] / ".gpu" / "levelsets"))


def key(verts, tris, voxel, half_width) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(verts, np.float32).tobytes())
    h.update(np.ascontiguousarray(tris, np.int32).tobytes())
    h.update(repr((float(voxel), float(half_width))).encode())
    return h.hexdigest()[:20]


def file_name(k: str, ijk, shape) -> str:
    return f"sdf_{k}_{'_'.join(str(int(i)) for i in ijk)}_{'x'.join(str(int(n)) for n in shape)}.npy"


def createLinearTransform(voxelSize):
    return float(voxelSize)


class _Grid:
    def __init__(self, k):
        self.k = k

    def copyToArray(self, phi, ijk):
        f = STORE / file_name(self.k, ijk, phi.shape)
        if not f.is_file():
            raise RuntimeError(f"pyopenvdb stand-in: no level set {f.name} in {STORE} (run 'bash bench/gpu.sh "
                               f"prepare' on a machine with OpenVDB)")
        phi[...] = np.load(f)


class FloatGrid:
    @staticmethod
    def createLevelSetFromPolygons(verts, triangles, transform, halfWidth):
        return _Grid(key(verts, triangles, transform, halfWidth))
