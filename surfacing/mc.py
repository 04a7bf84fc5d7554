"""Marching cubes over the block-sparse color field, in Taichi (see surfacing/mc_table.py).

One vertex per grid edge the iso level crosses, owned by the edge's lower node: the vertices
come out welded (no sort, no hashing), numbered block by block, and the triangles refer to
them directly. Four kernels, each parallel over blocks and serial inside one:

1. count_vertices: per block of the band (the blocks whose cells cross the level and their
   upper neighbours: every crossed edge's lower node lies in one), each node's crossed edges
   (3 bits) and how many the nodes before it own (node_first);
2. place_vertices: the vertex on each such edge, by linear interpolation, in node units from
   its block's first node (numpy then adds the block's place, in float64);
3. count_triangles: per block whose cells cross the level, each cell's case and the block's
   triangle count;
4. emit_triangles: each cell's triangles from the table, a vertex id being node_first of the
   edge's owner node plus its crossed edges along lower axes.

Block-level offsets between the passes are numpy prefix sums over a few thousand numbers.
vertex_normals, for any triangle mesh, is here too: a Taichi loop, like the rest of the mesh's
making.
"""
import numpy as np
import taichi as ti

from .mc_table import CORNER, EDGE_AXIS, EDGE_CORNER, table
from .grid import B

B3 = B * B * B
F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
I2 = ti.types.ndarray(dtype=ti.i32, ndim=2)
I3 = ti.types.ndarray(dtype=ti.i32, ndim=3)
F2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
U2 = ti.types.ndarray(dtype=ti.u8, ndim=2)
V3 = ti.types.ndarray(dtype=ti.math.vec3, ndim=1)
T3 = ti.types.ndarray(dtype=ti.types.vector(3, ti.i32), ndim=1)


@ti.func
def _value(color: ti.template(), nbr: ti.template(), s, x, y, z):
    """The color at node (x, y, z), each in 0..8, of block row s of `nbr` (column 0: the block
    itself; column bx + 2 by + 4 bz: the upper neighbour the node falls in, the zero block if
    none)."""
    blk = nbr[s, (x >> 3) + 2 * (y >> 3) + 4 * (z >> 3)]
    return color[blk * B3 + ((x & 7) * B + (y & 7)) * B + (z & 7)]


@ti.func
def _edges(color: ti.template(), nbr: ti.template(), s, n, iso):
    """The crossed edges of node n of block row s, as bits (1: +x, 2: +y, 4: +z)."""
    x, y, z = n >> 6, (n >> 3) & 7, n & 7
    base = nbr[s, 0] * B3
    inside = color[base + n] > iso
    bits = 0
    # the node one step up each axis: in the block, or at the bottom of the upper neighbour
    ox = base + n + B * B if x < 7 else nbr[s, 1] * B3 + n - 7 * B * B
    oy = base + n + B if y < 7 else nbr[s, 2] * B3 + n - 7 * B
    oz = base + n + 1 if z < 7 else nbr[s, 4] * B3 + n - 7
    if (color[ox] > iso) != inside:
        bits |= 1
    if (color[oy] > iso) != inside:
        bits |= 2
    if (color[oz] > iso) != inside:
        bits |= 4
    return bits


@ti.kernel
def count_vertices(color: F1, nbr: I2, iso: ti.f32, edges: U2, node_first: I2, count: I1):
    """edges[s, n]: node n's crossed edges (bits, see _edges) in band block row s;
    node_first[s, n]: the crossed edges of the nodes before it; count[s]: all of the row's."""
    for s in count:
        c = 0
        for n in range(B3):
            bits = _edges(color, nbr, s, n, iso)
            edges[s, n] = ti.cast(bits, ti.u8)
            node_first[s, n] = c
            c += (bits & 1) + (bits >> 1 & 1) + (bits >> 2)
        count[s] = c


@ti.kernel
def place_vertices(color: F1, nbr: I2, iso: ti.f32, offset: I1, edges: U2, node_first: I2,
                   local: F2):
    """local[v]: vertex v in node units from its block's first node (linear interpolation along
    its edge); node_first becomes global (adds offset[s])."""
    for s in offset:
        for n in range(B3):
            v = offset[s] + node_first[s, n]
            node_first[s, n] = v
            bits = ti.cast(edges[s, n], ti.i32)
            if bits:
                x, y, z = n >> 6, (n >> 3) & 7, n & 7
                c0 = _value(color, nbr, s, x, y, z)
                for a in ti.static(range(3)):
                    if bits >> a & 1:
                        c1 = _value(color, nbr, s, x + int(a == 0), y + int(a == 1), z + int(a == 2))
                        local[v, 0] = ti.cast(x, ti.f32)
                        local[v, 1] = ti.cast(y, ti.f32)
                        local[v, 2] = ti.cast(z, ti.f32)
                        local[v, a] += (iso - c0) / (c1 - c0)
                        v += 1


@ti.func
def _case(color: ti.template(), nbr: ti.template(), s, n, iso):
    """The case (bit v: corner v above iso) of the cell whose lowest corner is node n."""
    i, j, k = n >> 6, (n >> 3) & 7, n & 7
    case = 0
    if i < 7 and j < 7 and k < 7:                       # all eight corners in the block
        base = nbr[s, 0] * B3 + n
        for v in ti.static(range(8)):
            if color[base + (v & 1) * B * B + (v >> 1 & 1) * B + (v >> 2 & 1)] > iso:
                case |= 1 << v
    else:
        for v in ti.static(range(8)):
            if _value(color, nbr, s, i + (v & 1), j + (v >> 1 & 1), k + (v >> 2 & 1)) > iso:
                case |= 1 << v
    return case


@ti.kernel
def count_triangles(color: F1, nbr: I2, iso: ti.f32, tri_count: I1, cases: U2, count: I1):
    """cases[s, n]: the case of cell n of block row s; count[s]: the row's triangles."""
    for s in count:
        c = 0
        for n in range(B3):
            case = _case(color, nbr, s, n, iso)
            cases[s, n] = ti.cast(case, ti.u8)
            c += tri_count[case]
        count[s] = c


@ti.kernel
def emit_triangles(cases: U2, slot: I2, tri_edges: I3, tri_count: I1, edge_corner: I1,
                   edge_axis: I1, offset: I1, edges: U2, node_first: I2, faces: I2):
    """faces[offset[s]:]: the triangles of block row s's cells as vertex ids. slot[s, col]: the
    band row of the block in column col (as nbr). A vertex is node_first[owner row, owner node]
    plus the owner node's crossed edges along lower axes."""
    for s in offset:
        f = offset[s]
        for n in range(B3):
            case = ti.cast(cases[s, n], ti.i32)
            if tri_count[case]:
                i, j, k = n >> 6, (n >> 3) & 7, n & 7
                for t in range(tri_count[case]):
                    for q in ti.static(range(3)):
                        e = tri_edges[case, t, q]
                        lo = edge_corner[e]
                        x, y, z = i + (lo & 1), j + (lo >> 1 & 1), k + (lo >> 2 & 1)
                        owner = slot[s, (x >> 3) + 2 * (y >> 3) + 4 * (z >> 3)]
                        m = ((x & 7) * B + (y & 7)) * B + (z & 7)
                        below = ti.cast(edges[owner, m], ti.i32) & ((1 << edge_axis[e]) - 1)
                        faces[f, q] = node_first[owner, m] + (below & 1) + (below >> 1)
                    f += 1


@ti.kernel
def k_vertex_normals(points: V3, faces: T3, out: V3):
    """out[v] = the unit sum of the (area-weighted) normals e1 x e2 of the faces at v. One
    thread, in face order: the sums are the same on every run (10 ms for 800k faces, against
    120 ms for float64 numpy bincounts), and the float32 cross products of one-cell edges are
    within 0.05 degrees of float64 ones (tests/test_surfacing.py)."""
    ti.loop_config(serialize=True)
    for f in range(faces.shape[0]):
        a, b, c = faces[f][0], faces[f][1], faces[f][2]
        p = points[a]
        n = (points[b] - p).cross(points[c] - p)
        out[a] = out[a] + n
        out[b] = out[b] + n
        out[c] = out[c] + n
    for v in out:
        out[v] = out[v] / ti.max(out[v].norm(), 1e-30)


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 outward unit vertex normals from the faces' winding (area-weighted)."""
    out = np.zeros((len(points), 3), np.float32)
    if len(faces):
        k_vertex_normals(np.ascontiguousarray(points, np.float32), np.ascontiguousarray(faces, np.int32), out)
    return out


def marching_cubes(color: np.ndarray, blocks: np.ndarray, todo: np.ndarray, upper: np.ndarray,
                   neighbour, iso: float):
    """(g, faces): the `iso` surface of a block-sparse field as vertices in global node
    coordinates (float64) and triangles (int32) counter-clockwise seen from the side below
    `iso` (outward for a fluid whose color is above it).

    color: (nb + 1, 8, 8, 8), the last block all zero; blocks: (nb, 3) block coordinates;
    todo: the blocks that own a cell crossing `iso` (a superset will do); upper: (len(todo), 7)
    their upper neighbours at block offsets CORNER[1:] (nb where missing); neighbour(offset,
    ids): the same for any blocks (Field.neighbour)."""
    nb = len(blocks)
    tri_edges, tri_count = table()
    flat = color.reshape(-1)
    up = np.c_[todo, upper]                                             # 8 columns
    band = np.unique(up[up < nb])
    band_nbr = np.stack([band] + [neighbour(o, band) for o in CORNER[1:]], 1).astype(np.int32)
    row = np.full(nb + 1, 0, np.int32)        # the zero block owns no vertex: any row will do
    row[band] = np.arange(len(band), dtype=np.int32)

    node_first = np.empty((len(band), B3), np.int32)
    edges = np.empty((len(band), B3), np.uint8)
    n_vert = np.empty(len(band), np.int32)
    count_vertices(flat, band_nbr, iso, edges, node_first, n_vert)
    local = np.empty((int(n_vert.sum()), 3), np.float32)
    place_vertices(flat, band_nbr, iso, _exclusive_sum(n_vert), edges, node_first, local)
    # vertices are numbered block by block: add each one's block origin, in float64 (a grid far
    # from the origin keeps its precision; the kernels need no 64-bit floats, which some
    # Vulkan devices lack)
    g = np.repeat(blocks[band] * B, n_vert, axis=0).astype(np.float64)
    g += local
    del local

    cases = np.empty((len(todo), B3), np.uint8)
    n_tri = np.empty(len(todo), np.int32)
    count_triangles(flat, up.astype(np.int32), iso, tri_count, cases, n_tri)
    faces = np.empty((int(n_tri.sum()), 3), np.int32)
    emit_triangles(cases, row[up], tri_edges, tri_count, EDGE_CORNER.astype(np.int32),
                   EDGE_AXIS.astype(np.int32), _exclusive_sum(n_tri), edges, node_first, faces)
    return g, faces


def _exclusive_sum(n: np.ndarray) -> np.ndarray:
    return (np.cumsum(n, dtype=np.int64) - n).astype(np.int32)
