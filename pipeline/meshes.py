"""Mesh files that jobs refer to (mesh colliders): read once, checked, placed in the world.

Any format meshio reads (OBJ, PLY, STL, OFF, VTK, VTU, ...). Triangles and quads are kept (quads
split in two), other cells ignored. A collider mesh must be closed: every edge shared by at
least two faces, or inside and outside are not defined.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import math
from pathlib import Path

import numpy as np


class MeshFileError(ValueError):
    """The file is missing, unreadable, has no faces or is not closed; the message says which."""


def read_closed_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3) float64, triangles (m, 3) int64) of a closed surface mesh, read-only."""
    import meshio

    if not Path(path).is_file():
        raise MeshFileError(f"mesh file {str(path)!r} not found")
    path = str(path)
    chatter = io.StringIO()
    try:
        # meshio prints its readers' complaints and ends a failed read with sys.exit(1)
        with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
            mesh = meshio.read(path)
    except (Exception, SystemExit) as exc:   # an unknown format, or a bad file of a known one
        why = " ".join(chatter.getvalue().split()) or _reason(exc)
        raise MeshFileError(f"cannot read mesh file {path!r}: {why[:200]}") from None
    faces = []
    for block in mesh.cells:
        if block.type == "triangle":
            faces.append(np.asarray(block.data, np.int64))
        elif block.type == "quad":
            q = np.asarray(block.data, np.int64)
            faces += [q[:, [0, 1, 2]], q[:, [0, 2, 3]]]
    if not faces:
        raise MeshFileError(f"mesh file {path!r} has no triangles or quads")
    tris = np.concatenate(faces)
    verts = np.asarray(mesh.points, np.float64)
    if verts.ndim != 2 or verts.shape[1] != 3 or not np.isfinite(verts).all() or tris.max() >= len(verts):
        raise MeshFileError(f"mesh file {path!r} has non-3D, non-finite or missing vertices")
    # weld vertices at the same position (STL repeats them per triangle, other writers at seams)
    verts, inverse = np.unique(verts, axis=0, return_inverse=True)
    tris = inverse.reshape(-1)[tris]
    open_edges = count_open_edges(tris)
    if open_edges:
        raise MeshFileError(f"mesh file {path!r} is not closed ({open_edges} edges belong to one face "
                            f"only); a mesh collider needs a watertight surface")
    verts.flags.writeable = False
    tris.flags.writeable = False
    return verts, tris


def _reason(exc: BaseException) -> str:
    """A reader's exception as the user's reason. meshio parses a known format's numbers with
    NumPy, whose ValueErrors (a number cut in half, a last line with too few values) speak of
    arrays; they mean the file is malformed or cut short."""
    text = str(exc)
    if isinstance(exc, ValueError) and ("inhomogeneous" in text or "could not convert" in text):
        detail = "rows of different lengths" if "inhomogeneous" in text else text
        return f"it is malformed or cut short ({detail}); is the file complete?"
    return f"{exc.__class__.__name__}: {text}"


def count_open_edges(tris: np.ndarray) -> int:
    """Edges used by exactly one triangle (vertices matched by index)."""
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int((counts == 1).sum())


def file_sha256(path: Path) -> str:
    """sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def placement(scale: float, rotate_deg, translate) -> tuple[np.ndarray, np.ndarray]:
    """(3x3 matrix, offset): scale, then rotate about x, then y, then z (degrees), then translate."""
    ax, ay, az = (math.radians(a) for a in rotate_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx * scale, np.asarray(translate, np.float64)
